// Shared objects through a real relay, on the SDK (run by tests/client/test_js.py):
// a thrower creates `object:ball` held, carries it, throws it; a catcher watches
// its flight from the relay's keyframes and catches it. Prints one JSON report.
//   node test/live/objects.mjs --url ws://127.0.0.1:8765 --room R [--codec compact|raw]
if (!globalThis.WebSocket) {
  const { spawnSync } = await import("node:child_process");
  const again = spawnSync(process.execPath, ["--experimental-websocket", "--no-warnings", ...process.argv.slice(1)], { stdio: "inherit" });
  process.exit(again.status ?? 1);
}
const { PosecastClient, ROOM_USER } = await import("../../dist/posecast.js");

const args = Object.fromEntries(process.argv.slice(2).reduce((acc, a, i, all) => (a.startsWith("--") ? [...acc, [a.slice(2), all[i + 1]]] : acc), []));
const sleep = (s) => new Promise((r) => setTimeout(r, s * 1000));
const common = { url: args.url, room: args.room, rate: 30, codec: args.codec ?? "compact", initialPings: 4 };

const thrower = new PosecastClient({ ...common, label: "thrower" });
const catcher = new PosecastClient({ ...common, label: "catcher" });
const reasons = [];
const errors = [];
for (const c of [thrower, catcher]) c.on("error", (e) => errors.push(`${e.code}: ${e.message}`));
catcher.on("owner", (o) => reasons.push([o.reason, o.owner, o.velocity]));
await thrower.connect();
await catcher.connect();

const created = new Promise((resolve) => catcher.on("object", (o) => o.name === "object:ball" && resolve(o)));
thrower.createObject("object:ball", [0, 1, 0, 1, 0, 0, 0], { hold: true, steal: true, time: thrower.serverNow() });
const info = await created;

// Carry it 0.4 s at 30 Hz along +x, then throw it up and along +x.
for (let k = 1; k <= 12; k++) {
  await sleep(1 / 30);
  thrower.publish({ "object:ball": [0.05 * k, 1, 0, 1, 0, 0, 0] });
}
await sleep(0.2);
const throwAt = catcher.serverNow();
thrower.release(info.stream, [1.0, 5.0, 0.0], [0, 0, 2.0]);

// Watch the flight for 0.4 s of its 1.2 s (the relay's keyframes, rendered at the
// playout time), then catch it in the air.
const rendered = [];
const until = catcher.clock() + 0.4;
while (catcher.clock() < until) {
  await sleep(1 / 60);
  const ball = catcher.render("soa").poses.find((p) => p.user === ROOM_USER && p.stream === info.stream);
  if (ball) rendered.push([ball.time, ...ball.pose]);
}
catcher.requestOwnership(info.stream);
await sleep(0.3);
const rs = [...catcher.receiver.streams.values()].find((s) => s.user === ROOM_USER && s.stream === info.stream);
const keyframes = rs ? rs.buffer.times.map((t, i) => [t, ...rs.buffer.poses[i]]) : [];
const flight = keyframes.filter((k) => k[0] > throwAt);
thrower.close("done");
catcher.close("done");
const object = catcher.objects.get(info.stream);
process.stdout.write(JSON.stringify({
  stream: info.stream,
  name: rs?.name ?? null,
  reasons,
  owner: object?.owner ?? null,
  catcher: catcher.user,
  thrower: thrower.user,
  flight_keyframes: flight.length,
  flight_max_y: Math.max(...flight.map((k) => k[2])),
  flight_max_x: Math.max(...flight.map((k) => k[1])),
  rendered: rendered.length,
  rendered_max_y: Math.max(...rendered.map((r) => r[2])),
  errors,
}) + "\n");
