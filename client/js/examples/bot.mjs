#!/usr/bin/env node
// A headless posecast user in Node, on the SDK: joins a room, publishes a scripted
// head-and-hands motion at 30 Hz, receives everyone else, and prints ONE JSON report.
//
//   node examples/bot.mjs --url ws://127.0.0.1:8765 --room lab --seconds 5 [--codec compact|raw]
//
// Options: --url (several: comma-separated, tried in order), --room, --seconds,
// --codec (default compact), --rate (snapshot rate asked, Hz, default 15; or
// "auto": the relay chooses, --max-rate its ceiling),
// --label (default "js-bot:sway"), --token, --keyframes (add every received
// keyframe to the report).
//
// The scripted motion, a function of the server clock t (seconds), so that anyone
// can check what arrived against it (tests/client/test_js.py does):
//   head   position (0.4 sin(w t), 1.6 + 0.05 sin(2 w t), 0.4 cos(w t)), w = 0.8 rad/s,
//          turning about +y by the angle w t  (quaternion (cos(w t / 2), 0, sin(w t / 2), 0))
//   left   head position + (-0.25, -0.45, -0.2), rotated about +x by 0.6 sin(3 w t)
//   right  head position + ( 0.25, -0.45, -0.2), rotated about +z by 0.6 sin(3 w t)
// Poses are [px, py, pz, qw, qx, qy, qz]: metres, unit quaternion, w first.
//
// Report: {user, codec, seconds, peers: [{user, label, streams: {name: poses received}},
// poses, keyframes?}], granted_rate, rates (each rate the relay chose, --rate auto),
// current_rate, decode_errors, bytes_per_pose: {up, down}, poses_sent, ...}.
import { spawnSync } from "node:child_process";
import { existsSync } from "node:fs";
import { fileURLToPath, pathToFileURL } from "node:url";
import { dirname, join } from "node:path";

if (!globalThis.WebSocket) {
  // Node 20 has its WebSocket behind a flag: run again with it.
  const again = spawnSync(process.execPath, ["--experimental-websocket", "--no-warnings", ...process.argv.slice(1)], { stdio: "inherit" });
  process.exit(again.status ?? 1);
}

const here = dirname(fileURLToPath(import.meta.url));
const sdkPath = join(here, "..", "dist", "posecast.js");
if (!existsSync(sdkPath)) {
  console.error(`bot.mjs: ${sdkPath} is missing: run "npm run build" in client/js first`);
  process.exit(2);
}
const { PosecastClient } = await import(pathToFileURL(sdkPath).href);

function parseArgs(argv) {
  const opts = { codec: "compact", rate: 15, label: "js-bot:sway", token: null, keyframes: false };
  for (let i = 0; i < argv.length; i++) {
    const arg = argv[i];
    const value = () => {
      const v = argv[++i];
      if (v === undefined) throw new Error(`${arg} needs a value`);
      return v;
    };
    if (arg === "--url") opts.url = value();
    else if (arg === "--room") opts.room = value();
    else if (arg === "--seconds") opts.seconds = Number(value());
    else if (arg === "--codec") opts.codec = value();
    else if (arg === "--rate") {
      const v = value();
      opts.rate = v === "auto" ? v : Number(v);
    }
    else if (arg === "--max-rate") opts.maxRate = Number(value());
    else if (arg === "--label") opts.label = value();
    else if (arg === "--token") opts.token = value();
    else if (arg === "--keyframes") opts.keyframes = true;
    else throw new Error(`unknown option ${arg}`);
  }
  if (!opts.url || !opts.room || !(opts.seconds > 0)) throw new Error("usage: bot.mjs --url URL --room R --seconds S [--codec compact|raw]");
  if (opts.codec !== "compact" && opts.codec !== "raw") throw new Error(`--codec must be compact or raw, got ${opts.codec}`);
  return opts;
}

const W = 0.8;

/** The scripted pose of stream `name` at server time `t` (see the header). */
export function scriptedPose(name, t) {
  const a = W * t;
  const head = [0.4 * Math.sin(a), 1.6 + 0.05 * Math.sin(2 * a), 0.4 * Math.cos(a)];
  if (name === "head") return [...head, Math.cos(a / 2), 0, Math.sin(a / 2), 0];
  const side = name === "left" ? -1 : 1;
  const half = (0.6 * Math.sin(3 * a)) / 2;
  const q = name === "left" ? [Math.cos(half), Math.sin(half), 0, 0] : [Math.cos(half), 0, 0, Math.sin(half)];
  return [head[0] + 0.25 * side, head[1] - 0.45, head[2] - 0.2, ...q];
}

async function main() {
  let opts;
  try {
    opts = parseArgs(process.argv.slice(2));
  } catch (err) {
    console.error(`bot.mjs: ${err.message}`);
    return 2;
  }
  const client = new PosecastClient({
    urls: opts.url.split(",").map((u) => u.trim()),
    room: opts.room,
    rate: opts.rate,
    ...(opts.maxRate !== undefined ? { maxRate: opts.maxRate } : {}),
    codec: opts.codec,
    label: opts.label,
    token: opts.token,
    agent: "posecast-js-bot",
  });
  const errors = [];
  client.on("error", (e) => errors.push(`${e.code}: ${e.message}`));
  let ended = null;
  client.on("closed", (c) => (ended ??= { code: c.closeCode, reason: c.reason }));
  const resumes = { resumed: 0, rejoined: 0 };
  client.on("resumed", () => resumes.resumed++);
  client.on("rejoined", () => resumes.rejoined++);
  const rates = []; // each rate the relay chose (rate "auto")
  client.on("rate", (hz) => rates.push(hz));
  try {
    await client.connect();
  } catch (err) {
    console.error(`bot.mjs: could not join: ${err.message}`);
    return 1;
  }
  // Peers' streams as received, kept when they leave (their buffers go with them).
  const peers = new Map();
  const note = (user) => {
    for (const rs of client.receiver.streams.values()) {
      if (user !== undefined && rs.user !== user) continue;
      let peer = peers.get(rs.user);
      if (!peer) {
        peer = { user: rs.user, label: null, streams: {}, poses: 0 };
        if (opts.keyframes) peer.keyframes = {};
        peers.set(rs.user, peer);
      }
      peer.label = rs.label ?? client.receiver.peers.get(rs.user)?.label ?? peer.label;
      peer.streams[rs.name] = rs.received;
      peer.poses = Object.values(peer.streams).reduce((a, b) => a + b, 0);
      if (opts.keyframes) {
        const kf = (peer.keyframes[rs.name] ??= new Map());
        rs.buffer.times.forEach((c, i) => kf.set(c, [c, ...rs.buffer.poses[i]]));
      }
    }
  };
  client.on("peer_left", (user) => note(user));
  const start = client.clock();
  const period = 1 / 30;
  let renderFrames = 0;
  // Publish on a 30 Hz grid of the local clock, never in bursts; render at 30 Hz too.
  await new Promise((resolve) => {
    let k = 0;
    const tick = () => {
      const now = client.clock();
      if (now - start >= opts.seconds || client.state === "closed") {
        resolve();
        return;
      }
      const t = client.serverNow();
      client.publish({ head: scriptedPose("head", t), left: scriptedPose("left", t), right: scriptedPose("right", t) }, { capture: t });
      client.render("soa");
      renderFrames++;
      if (opts.keyframes) note();
      k = Math.max(k + 1, Math.floor((now - start) / period) + 1);
      setTimeout(tick, Math.max(0, (start + k * period - client.clock()) * 1000));
    };
    tick();
  });
  note();
  client.close("done");
  if (opts.keyframes) {
    for (const peer of peers.values()) {
      for (const [name, kf] of Object.entries(peer.keyframes)) peer.keyframes[name] = [...kf.values()].sort((a, b) => a[0] - b[0]);
    }
  }
  const received = client.receiver.posesReceived;
  const report = {
    user: client.user,
    codec: opts.codec,
    seconds: client.clock() - start,
    granted_rate: client.grantedRate ?? null,
    rates,
    current_rate: client.currentRate ?? null,
    playout_interval: client.receiver.delay.interval,
    peers: [...peers.values()],
    decode_errors: client.decodeErrors,
    errors,
    bytes_per_pose: {
      up: client.posesSent ? client.updateBytes / client.posesSent : null,
      down: received ? client.snapshotBytes / received : null,
    },
    poses_sent: client.posesSent,
    poses_received: received,
    snapshots: client.snapshotsIn,
    render_frames: renderFrames,
    clock_rtt_ms: client.clockSync.rtt * 1000,
    ending: ended,
    ...resumes,
  };
  process.stdout.write(JSON.stringify(report) + "\n");
  return 0;
}

process.exitCode = await main();
