// The session logic of PosecastClient over a scripted in-memory websocket (the
// transport is the one thing faked: tests/client/test_js.py runs a real relay).
import { test } from "node:test";
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { PosecastClient } from "../src/client.js";
import { DecodeError, JoinRefused } from "../src/errors.js";
import { decodeMessage, encodeControl } from "../src/messages.js";
import type { ControlMessage, Message } from "../src/messages.js";

type Handler = (m: Message | { type: "compact"; data: Uint8Array }, ws: FakeSocket) => void;

class FakeSocket {
  static handler: Handler = () => {};
  static sockets: FakeSocket[] = [];
  static refuse = 0; // the next n connections fail
  binaryType = "blob";
  bufferedAmount = 0;
  readyState = 0;
  onopen: (() => void) | null = null;
  onmessage: ((ev: { data: ArrayBuffer }) => void) | null = null;
  onclose: ((ev: { code: number; reason: string }) => void) | null = null;
  onerror: (() => void) | null = null;
  sent: Uint8Array[] = [];
  closedWith: number | null = null;

  constructor(readonly url: string) {
    FakeSocket.sockets.push(this);
    setTimeout(() => {
      if (FakeSocket.refuse > 0) {
        FakeSocket.refuse--;
        this.onerror?.();
        return;
      }
      this.readyState = 1;
      this.onopen?.();
    }, 0);
  }

  send(data: Uint8Array): void {
    const copy = new Uint8Array(data);
    this.sent.push(copy);
    const m = copy[0] === 0xc1 ? { type: "compact" as const, data: copy } : decodeMessage(copy);
    queueMicrotask(() => FakeSocket.handler(m, this));
  }

  close(code = 1000): void {
    if (this.readyState === 3) return;
    this.closedWith = code;
    this.readyState = 3;
  }

  /** The server sends a frame. */
  deliver(m: ControlMessage | Uint8Array): void {
    const bytes = m instanceof Uint8Array ? m : encodeControl(m);
    this.onmessage?.({ data: bytes.slice().buffer });
  }

  /** The connection ends from the server's side (or breaks: 1006). */
  drop(code: number, reason = ""): void {
    this.readyState = 3;
    this.onclose?.({ code, reason });
  }
}

function sentTypes(ws: FakeSocket): string[] {
  return ws.sent.map((b) => (b[0] === 0xc1 ? "compact" : decodeMessage(b).type));
}

const JOINED = { type: "joined", room: "lab", streams: { head: 6, left: 7, right: 8 }, rate: 20, objects: {} } as const;

/** A relay that welcomes (resuming `resumed` tokens), answers pings and accepts joins. */
function relay(opts: { resumed?: string; refuseJoin?: string } = {}): Handler {
  return (m, ws) => {
    if (m.type === "hello") {
      const resumed = opts.resumed !== undefined && m.resume === opts.resumed;
      ws.deliver({ type: "welcome", user: resumed ? 4 : 9 + FakeSocket.sockets.length, server_time: 50, version: 1, min_rate: 5, max_rate: 30, max_streams: 16, volume: [-8, -2, -8, 8, 4, 8], resume: `tok${FakeSocket.sockets.length}`, resumed });
    } else if (m.type === "ping") {
      ws.deliver({ type: "pong", seq: m.seq, ping_time: m.time, recv_time: 1000, send_time: 1000 });
    } else if (m.type === "join") {
      if (opts.refuseJoin) ws.deliver({ type: "error", code: opts.refuseJoin, message: "no", fatal: false, in_reply_to: "join" });
      else ws.deliver({ ...JOINED, streams: { ...JOINED.streams }, objects: {} });
    }
  };
}

function client(extra: Partial<ConstructorParameters<typeof PosecastClient>[0]> = {}): PosecastClient {
  FakeSocket.sockets = [];
  FakeSocket.refuse = 0;
  return new PosecastClient({
    url: "ws://relay.test:8765",
    room: "lab",
    rate: 20,
    label: "unit",
    initialPings: 2,
    pingInterval: 60,
    resumeWindow: 2,
    WebSocket: FakeSocket as unknown as typeof WebSocket,
    ...extra,
  });
}

test("connect: hello (resumable), clock sync pings, join, joined", async () => {
  FakeSocket.handler = relay();
  const c = client({ codec: "compact" });
  const joined = await c.connect();
  assert.deepEqual(joined.streams, { head: 6, left: 7, right: 8 });
  const ws = FakeSocket.sockets[0]!;
  assert.deepEqual(sentTypes(ws), ["hello", "ping", "ping", "join"]);
  const hello = decodeMessage(ws.sent[0]!);
  assert.ok(hello.type === "hello" && hello.resumable === true && hello.agent === "posecast-js");
  const join = decodeMessage(ws.sent[3]!);
  assert.ok(join.type === "join");
  assert.deepEqual([join.room, join.streams, join.rate, join.label, join.codec], ["lab", ["head", "left", "right"], 20, "unit", "compact"]);
  assert.ok(Math.abs(c.serverNow() - 1000) < 1, "the server clock comes from the pongs");
  // A compact update goes out as a codec frame.
  assert.ok(c.publish({ head: [0, 1.6, 0, 1, 0, 0, 0] }) > 0);
  assert.equal(sentTypes(ws).at(-1), "compact");
  c.close("done");
  assert.equal(sentTypes(ws).at(-1), "bye");
  assert.equal(ws.closedWith, 1000);
  assert.equal(c.state, "closed");
});

test("a rate outside the welcome's range is refused before the join is sent", async () => {
  FakeSocket.handler = relay();
  const c = client({ rate: 45 });
  await assert.rejects(c.connect(), (e: unknown) => e instanceof JoinRefused && e.code === "bad-rate" && e.rateRange?.[1] === 30);
  assert.ok(!sentTypes(FakeSocket.sockets[0]!).includes("join"));
});

test("a refused join rejects connect() with the server's code", async () => {
  FakeSocket.handler = relay({ refuseJoin: "room-full" });
  await assert.rejects(client().connect(), (e: unknown) => e instanceof JoinRefused && e.code === "room-full");
});

test("a dropped connection (1006) resumes with the welcome's token: same user, same streams", async () => {
  FakeSocket.handler = relay({ resumed: "tok1" });
  const c = client();
  await c.connect();
  const resumed = c.once("resumed");
  FakeSocket.sockets[0]!.drop(1006);
  await resumed;
  const second = FakeSocket.sockets[1]!;
  const hello = decodeMessage(second.sent[0]!);
  assert.ok(hello.type === "hello" && hello.resume === "tok1");
  assert.equal(c.user, 4);
  assert.equal(c.state, "joined");
  c.close();
});

test("a relay going away (1001) with no other relay ends the session", async () => {
  FakeSocket.handler = relay();
  const c = client();
  await c.connect();
  const closed = c.once("closed");
  FakeSocket.sockets[0]!.drop(1001, "going away");
  const [end] = await closed;
  assert.equal(end.closeCode, 1001);
  assert.equal(FakeSocket.sockets.length, 1);
});

test("1001 with several relays fails over to the next one, cycling past one that is down", async () => {
  FakeSocket.handler = relay();
  const c = client({ url: undefined, urls: ["ws://a.test", "ws://b.test", "ws://c.test"] });
  await c.connect();
  const back = c.once("rejoined");
  FakeSocket.refuse = 1; // a.test (the one it was on) is down
  FakeSocket.sockets[0]!.drop(1001);
  await back;
  assert.deepEqual(FakeSocket.sockets.map((s) => s.url), ["ws://a.test", "ws://a.test", "ws://b.test"]);
  assert.equal(c.relay, 1);
  c.close();
});

test("a compact snapshot against baselines the client lacks: bad-baseline, error sent, reconnect", async () => {
  FakeSocket.handler = relay();
  const c = client({ codec: "compact" });
  await c.connect();
  const errors: string[] = [];
  c.on("error", (e) => errors.push(e.code));
  const back = c.once("rejoined");
  const delta = JSON.parse(readFileSync(new URL("../../../protocol/vectors/snapshot-delta.json", import.meta.url), "utf8")) as { hex: string };
  const first = FakeSocket.sockets[0]!;
  first.deliver(new Uint8Array(Buffer.from(delta.hex, "hex")));
  assert.deepEqual(errors, ["bad-baseline"]);
  assert.equal(c.decodeErrors, 1);
  const err = decodeMessage(first.sent.at(-1)!);
  assert.ok(err.type === "error" && err.code === "bad-baseline" && err.fatal);
  assert.equal(first.closedWith, 1002);
  await back;
  assert.equal(c.state, "joined");
  c.close();
});

test("in a browser, the page going hidden sends bye and closes", async () => {
  const g = globalThis as unknown as { document?: unknown; addEventListener?: unknown; removeEventListener?: unknown };
  const doc = Object.assign(new EventTarget(), { visibilityState: "visible" });
  const win = new EventTarget();
  g.document = doc;
  g.addEventListener = win.addEventListener.bind(win);
  g.removeEventListener = win.removeEventListener.bind(win);
  try {
    FakeSocket.handler = relay();
    const c = client();
    await c.connect();
    doc.visibilityState = "hidden";
    doc.dispatchEvent(new Event("visibilitychange"));
    const ws = FakeSocket.sockets[0]!;
    assert.equal(sentTypes(ws).at(-1), "bye");
    assert.equal(ws.closedWith, 1000);
    assert.equal(c.state, "closed");
  } finally {
    delete g.document;
    delete g.addEventListener;
    delete g.removeEventListener;
  }
});

test("publish skips updates while the socket holds 64 KiB unsent (latest wins, no backlog)", async () => {
  FakeSocket.handler = relay();
  const c = client();
  await c.connect();
  const ws = FakeSocket.sockets[0]!;
  const pose: [number, number, number, number, number, number, number] = [0, 1.6, 0, 1, 0, 0, 0];
  assert.ok(c.publish({ head: pose }) > 0);
  ws.bufferedAmount = 70 * 1024;
  assert.equal(c.publish({ head: pose }), 0);
  assert.equal(c.updatesSkipped, 1);
  ws.bufferedAmount = 0;
  assert.ok(c.publish({ head: pose }) > 0);
  assert.equal(c.updatesSent, 2);
  c.close();
});

test("a welcome of another protocol version fails connect() with version-mismatch at once", async () => {
  FakeSocket.handler = (m, ws) => {
    if (m.type === "hello") ws.deliver({ type: "welcome", user: 1, server_time: 5, version: 2, min_rate: 5, max_rate: 30, max_streams: 16, volume: [-8, -2, -8, 8, 4, 8], resume: null, resumed: false });
  };
  const c = client();
  await assert.rejects(c.connect(), (e: unknown) => e instanceof DecodeError && e.code === "version-mismatch");
  const ws = FakeSocket.sockets[0]!;
  const err = decodeMessage(ws.sent.at(-1)!);
  assert.ok(err.type === "error" && err.code === "version-mismatch" && err.fatal);
  assert.equal(ws.closedWith, 1002);
});

test("an undecodable frame while joined: fatal error sent, closed with its code, back as a new member", async () => {
  FakeSocket.handler = relay();
  const c = client();
  await c.connect();
  const back = c.once("rejoined");
  const first = FakeSocket.sockets[0]!;
  first.deliver(new Uint8Array([0x81, 0xa4, 0x74, 0x79, 0x70, 0x65, 0xa3, 0x66, 0x6f, 0x6f])); // {"type": "foo"}
  assert.equal(c.decodeErrors, 1);
  const err = decodeMessage(first.sent.at(-1)!);
  assert.ok(err.type === "error" && err.code === "unknown-type" && err.fatal);
  assert.equal(first.closedWith, 1002);
  await back;
  c.close();
});

/** A relay serving auto rates: joined at the join's max_rate (or the welcome's 30). */
function autoRelay(): Handler {
  const base = relay();
  return (m, ws) => {
    if (m.type === "join" && m.rate === "auto") ws.deliver({ ...JOINED, rate: m.max_rate ?? 30, streams: { ...JOINED.streams }, objects: {} });
    else base(m, ws);
  };
}

test('rate "auto": the join asks it with max_rate; each rate notice moves currentRate and the playout delay', async () => {
  FakeSocket.handler = autoRelay();
  const c = client({ rate: "auto", maxRate: 24 });
  const joined = await c.connect();
  const ws = FakeSocket.sockets[0]!;
  const join = decodeMessage(ws.sent.find((b) => decodeMessage(b).type === "join")!);
  assert.ok(join.type === "join" && join.rate === "auto" && join.max_rate === 24);
  assert.equal(joined.rate, 24);
  assert.equal(c.currentRate, 24);
  assert.ok(c.autoRate);
  assert.ok(Math.abs(c.receiver.delay.interval - 1 / 24) < 1e-12);
  const heard: number[] = [];
  c.on("rate", (r) => heard.push(r));
  ws.deliver({ type: "rate", rate: 12 });
  assert.deepEqual(heard, [12]);
  assert.equal(c.currentRate, 12);
  assert.ok(Math.abs(c.receiver.delay.interval - 1 / 12) < 1e-12, "D now bridges a 1/12 s interval");
  // set_rate ends the auto rate: a number from now on.
  c.setRate(15);
  assert.equal(c.currentRate, 15);
  assert.ok(!c.autoRate);
  const setRate = decodeMessage(ws.sent.at(-1)!);
  assert.ok(setRate.type === "set_rate" && setRate.rate === 15);
  c.close();
});

test('rate "auto" without maxRate sends no max_rate; a maxRate out of range or without auto is refused', async () => {
  FakeSocket.handler = autoRelay();
  const c = client({ rate: "auto" });
  await c.connect();
  const bytes = FakeSocket.sockets[0]!.sent.find((b) => decodeMessage(b).type === "join")!;
  const join = decodeMessage(bytes);
  assert.ok(join.type === "join" && join.rate === "auto" && join.max_rate === null);
  assert.ok(!Buffer.from(bytes).includes(Buffer.from("max_rate")), "max_rate is omitted at its default");
  assert.equal(c.currentRate, 30);
  c.close();
  const high = client({ rate: "auto", maxRate: 45 });
  await assert.rejects(high.connect(), (e: unknown) => e instanceof JoinRefused && e.code === "bad-rate" && /max_rate 45/.test(e.message));
  assert.ok(!sentTypes(FakeSocket.sockets[0]!).includes("join"));
  assert.throws(() => client({ rate: 20, maxRate: 25 }), /maxRate is only allowed with rate "auto"/);
});

test("budgetDeg: the join asks it and the receiver sizes each peer's playout delay per peer, across a rate change", async () => {
  FakeSocket.handler = relay();
  const c = client({ budgetDeg: 1.5 });
  await c.connect();
  const join = FakeSocket.sockets[0]!.sent.filter((b) => b[0] !== 0xc1).map((b) => decodeMessage(b) as ControlMessage).find((m) => m.type === "join") as unknown as { budget_deg: number };
  assert.equal(join.budget_deg, 1.5);
  assert.equal(c.receiver.perPeer, true);
  assert.equal(c.receiver.delay.perPeer, true);
  c.receiver.setRate(15);
  assert.equal(c.receiver.delay.perPeer, true);
  c.close();
  const plain = client();
  assert.equal(plain.receiver.perPeer, false);
  assert.equal(plain.receiver.delay.perPeer, false);
});

test("a spectator with a token: the join carries both; renew and setRate send their messages", async () => {
  FakeSocket.handler = relay();
  const c = client({ spectator: true, token: "v1.abc.def" });
  await c.connect();
  const ws = FakeSocket.sockets[0]!;
  const join = decodeMessage(ws.sent[3]!);
  assert.ok(join.type === "join");
  assert.deepEqual([join.spectator, join.token, join.label], [true, "v1.abc.def", "unit"]);
  c.renew("v1.new.sig");
  const renew = decodeMessage(ws.sent.at(-1)!);
  assert.ok(renew.type === "renew" && renew.token === "v1.new.sig");
  c.setRate(12);
  const setRate = decodeMessage(ws.sent.at(-1)!);
  assert.ok(setRate.type === "set_rate" && setRate.rate === 12);
  assert.equal(c.currentRate, 12);
  c.close("done");
});
