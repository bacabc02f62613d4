import { test } from "node:test";
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { RoomPlayoutDelay, StreamBuffer, percentile } from "../src/buffers.js";
import { ClockEstimator, pongOffset, pongRoundTrip } from "../src/clock.js";
import { Receiver } from "../src/receiver.js";
import { soa } from "../src/interp.js";
import type { Pose, Pong } from "../src/messages.js";

const doc = JSON.parse(readFileSync(new URL("../test/receiver-vectors.json", import.meta.url), "utf8")) as {
  playout: { interval: number; steps: { now: number; observe: [number, number][]; room: number; own: Record<string, number> }[] };
  buffer: { capacity: number; ops: Record<string, unknown>[] };
};

test("RoomPlayoutDelay follows Python's scenarios.receiver step for step (a late user shown alone)", () => {
  const d = new RoomPlayoutDelay(doc.playout.interval);
  let lateSteps = 0;
  for (const step of doc.playout.steps) {
    for (const [user, age] of step.observe) d.observe(user, age);
    const room = d.update(step.now);
    assert.ok(Math.abs(room - step.room) < 1e-12, `t=${step.now}: room D ${room} != ${step.room}`);
    const own = Object.fromEntries([...d.own].map(([u, v]) => [String(u), v]));
    assert.deepEqual(Object.keys(own).sort(), Object.keys(step.own).sort(), `t=${step.now}: own`);
    for (const [u, v] of Object.entries(step.own)) assert.ok(Math.abs(own[u]! - v) < 1e-12);
    if (Object.keys(step.own).length) lateSteps++;
  }
  assert.ok(lateSteps > 100, "the script has a late user");
});

test("StreamBuffer keeps, refuses and brackets as Python's StreamBuffer", () => {
  const buf = new StreamBuffer(doc.buffer.capacity);
  let refused = 0;
  for (const op of doc.buffer.ops) {
    if ("capture" in op) {
      const took = buf.push(op.capture as number, op.pose as number[], (op.floor as number | null) ?? -Infinity);
      assert.equal(took, op.took, `push ${op.capture}`);
      if (!took) refused++;
    } else {
      assert.deepEqual(buf.times, op.times);
      const br = buf.bracket(op.t as number);
      assert.deepEqual([br.lo, br.hi, br.stalled], [op.lo, op.hi, op.stalled], `bracket ${op.t}`);
      assert.ok(Math.abs(br.s - (op.s as number)) < 1e-12);
    }
  }
  assert.ok(refused > 3, "the script refuses duplicates and stale keyframes");
});

test("percentile is numpy's linear one", () => {
  assert.equal(percentile([1, 2, 3, 4], 50), 2.5);
  assert.equal(percentile([5], 95), 5);
  assert.ok(Math.abs(percentile([0, 10, 20, 30, 40], 95) - 38) < 1e-12);
});

test("the clock estimate keeps the lowest round trip of its window", () => {
  const c = new ClockEstimator(3);
  assert.equal(c.offset, 0);
  assert.ok(Number.isNaN(c.rtt));
  const pong: Pong = { type: "pong", seq: 1, ping_time: 10, recv_time: 110.02, send_time: 110.03 };
  // sent at 10 (ours), answered at 110.02-110.03 (theirs), back at 10.05 (ours)
  assert.ok(Math.abs(pongOffset(pong, 10.05) - 100) < 1e-9);
  assert.ok(Math.abs(pongRoundTrip(pong, 10.05) - 0.04) < 1e-9);
  c.add(1.0, 0.05);
  c.add(2.0, 0.01);
  c.add(3.0, 0.03);
  assert.equal(c.offset, 2.0);
  c.add(4.0, 0.02); // the 0.05 sample leaves; 0.01 is still the best
  assert.equal(c.offset, 2.0);
  c.add(5.0, 0.04); // now 0.01 left the window of 3
  assert.equal(c.offset, 4.0);
  assert.equal(c.rtt, 0.02);
});

test("render returns every remote stream at now minus the playout delay, skipping its own", () => {
  const r = new Receiver({ rate: 10 });
  r.me = 1;
  r.peerJoined({ type: "peer_joined", user: 2, streams: { head: 0, left: 1 }, label: "orbit", velocities: false });
  const p0: Pose = [0, 1.5, 0, 1, 0, 0, 0];
  const p1: Pose = [1, 1.5, 0, 0.7071067811865476, 0, 0.7071067811865476, 0];
  r.snapshot({ type: "snapshot", tick: 1, time: 10, entries: [
    { user: 2, stream: 0, capture: 10.0, pose: p0 },
    { user: 1, stream: 0, capture: 10.0, pose: p0 },
  ] }, 10.02);
  r.snapshot({ type: "snapshot", tick: 2, time: 10.1, entries: [{ user: 2, stream: 0, capture: 10.1, pose: p1 }] }, 10.12);
  const d = r.delay.update(10.13);
  const frame = r.render(10.05 + d, "soa");
  assert.equal(frame.poses.length, 1);
  const [only] = frame.poses;
  assert.equal(only!.name, "head");
  assert.equal(only!.label, "orbit");
  assert.equal(only!.stalled, false);
  const want = soa(p0, p1, 0.5);
  for (let i = 0; i < 7; i++) assert.ok(Math.abs(only!.pose[i]! - want[i]!) < 1e-9);
  // long after the newest keyframe: held, stalled
  const late = r.render(20, "dq-slerp").poses[0]!;
  assert.deepEqual(late.pose, p1);
  assert.equal(late.stalled, true);
  r.peerLeft(2);
  assert.equal(r.render(20).poses.length, 0);
});

test("a key snapshot's resend of an unchanged keyframe is no new keyframe", () => {
  const r = new Receiver({ rate: 10 });
  const p: Pose = [0, 1, 0, 1, 0, 0, 0];
  r.snapshot({ type: "snapshot", tick: 1, time: 5, entries: [{ user: 65535, stream: 4, capture: 5.0, pose: p }] }, 5);
  r.snapshot({ type: "snapshot", tick: 2, time: 7, entries: [{ user: 65535, stream: 4, capture: 5.0008, pose: p }] }, 7);
  assert.equal(r.posesReceived, 1);
  assert.equal([...r.streams.values()][0]!.buffer.length, 1);
});

test("a peer announced again with the same streams keeps its buffers; a reused id starts afresh", () => {
  const r = new Receiver({ rate: 10 });
  const p: Pose = [0, 1, 0, 1, 0, 0, 0];
  // A snapshot before the announcement: kept, named once announced.
  r.snapshot({ type: "snapshot", tick: 1, time: 5, entries: [{ user: 3, stream: 0, capture: 5.0, pose: p }] }, 5);
  assert.equal([...r.streams.values()][0]!.name, "stream0");
  r.peerJoined({ type: "peer_joined", user: 3, streams: { head: 0 }, label: "a", velocities: false });
  assert.equal([...r.streams.values()][0]!.name, "head");
  r.snapshot({ type: "snapshot", tick: 2, time: 5.1, entries: [{ user: 3, stream: 0, capture: 5.1, pose: p }] }, 5.1);
  r.peerJoined({ type: "peer_joined", user: 3, streams: { head: 0 }, label: "a", velocities: false }); // after a resume
  assert.equal([...r.streams.values()][0]!.buffer.length, 2);
  r.peerJoined({ type: "peer_joined", user: 3, streams: { head: 4 }, label: "b", velocities: false }); // another member
  assert.equal(r.streams.size, 0);
});

test("RoomPlayoutDelay.retime: the interval follows the rate, the ages stay, D slews to the new target", () => {
  const d = new RoomPlayoutDelay(1 / 30);
  for (let i = 0; i < 20; i++) {
    d.observe(1, 0.01 + 0.001 * (i % 5));
    d.observe(2, 0.012 + 0.001 * (i % 3));
  }
  let t = 0;
  for (; t < 10; t += 0.1) d.update(t);
  const before = d.room.value;
  d.retime(10);
  assert.ok(Math.abs(d.interval - 0.1) < 1e-15 && Math.abs(d.room.interval - 0.1) < 1e-15);
  const target = before + (0.1 - 1 / 30); // same ages, a longer interval to bridge
  const next = d.update(t + 0.1);
  assert.ok(next > before && next < target - 1e-3, `slews (${before} -> ${next}), no jump to ${target}`);
  for (let k = 1; k < 200; k++) d.update(t + 0.1 * (k + 1));
  assert.ok(Math.abs(d.room.value - target) < 1e-6, `settles at ${target}: ${d.room.value}`);
  d.retime(0); // not a rate: ignored
  assert.ok(Math.abs(d.interval - 0.1) < 1e-15);
});

const perPeer = (doc as unknown as {
  per_peer: {
    rate: number;
    steps: { now: number; observe: [number, number, number][]; room: number; own: Record<string, number>; delay: Record<string, number> }[];
  };
}).per_peer;

test("per peer: RoomPlayoutDelay gives each user Python's D step for step (slower peers later, the rest as before)", () => {
  const d = new RoomPlayoutDelay(1 / perPeer.rate);
  d.perPeer = true;
  let apart = 0;
  for (const step of perPeer.steps) {
    for (const [user, age, sent] of step.observe) d.observe(user, age, sent);
    const room = d.update(step.now);
    assert.ok(Math.abs(room - step.room) < 1e-12, `t=${step.now}: room D ${room} != ${step.room}`);
    for (const [u, v] of Object.entries(step.delay)) {
      assert.ok(Math.abs(d.delay(Number(u)) - v) < 1e-12, `t=${step.now}: user ${u} D ${d.delay(Number(u))} != ${v}`);
    }
    const own = d.ownDelays();
    assert.deepEqual([...own.keys()].map(String).sort(), Object.keys(step.own).sort(), `t=${step.now}: own`);
    if (own.has(3)) apart++;
  }
  assert.equal(d.divisor(3), 4);
  assert.equal(d.divisor(1), 1);
  assert.ok(apart > 400, "the every-4th peer is shown at its own D");
});

test("per peer off: observe with a send time changes nothing (a client without a budget)", () => {
  const on = new RoomPlayoutDelay(1 / 30);
  const off = new RoomPlayoutDelay(1 / 30);
  for (let i = 0; i < 120; i++) {
    const sent = i / 30;
    off.observe(1, 0.01 + (i % 7) * 0.001, sent);
    on.observe(1, 0.01 + (i % 7) * 0.001);
    if (i % 4 === 0) {
      off.observe(2, 0.012, sent);
      on.observe(2, 0.012);
    }
    assert.equal(off.update(sent), on.update(sent));
    assert.equal(off.delay(2), on.delay(2));
  }
  assert.equal(off.divisor(2), 1);
});

function stallsOfPeers(perPeer: boolean): { far: number; near: number; farDelay: number; nearDelay: number } {
  // 30 Hz snapshots: peer 2 in every one, peer 3 in every 5th (6 Hz); frames at 90 Hz.
  const r = new Receiver({ rate: 30, perPeer });
  r.me = 1;
  for (const u of [2, 3]) r.peerJoined({ type: "peer_joined", user: u, streams: { head: 0 }, label: null, velocities: false });
  let far = 0;
  let near = 0;
  let frame = 0;
  let last = { far: 0, near: 0 };
  for (let tick = 0; tick < 180; tick++) {
    const t = tick / 30;
    const pose: Pose = [t, 1.5, 0, 1, 0, 0, 0];
    const entries = [{ user: 2, stream: 0, capture: t, pose }];
    if (tick % 5 === 0) entries.push({ user: 3, stream: 0, capture: t, pose });
    r.snapshot({ type: "snapshot", tick, time: t, entries }, t + 0.01);
    while (frame <= t + 0.01) {
      const f = r.render(frame);
      if (frame > 3) {
        for (const p of f.poses) if (p.stalled) p.user === 3 ? far++ : near++;
        last = { far: f.poses.find((p) => p.user === 3)!.delay, near: f.poses.find((p) => p.user === 2)!.delay };
      }
      frame += 1 / 90;
    }
  }
  return { far, near, farDelay: last.far, nearDelay: last.near };
}

test("per peer: a Receiver bridges a peer sent at 6 Hz without stalls, the 30 Hz peer at the room's D", () => {
  const on = stallsOfPeers(true);
  assert.equal(on.far, 0);
  assert.equal(on.near, 0);
  assert.ok(Math.abs(on.farDelay - on.nearDelay - 4 / 30) < 0.01, `${on.farDelay} vs ${on.nearDelay}`);
  const off = stallsOfPeers(false);
  assert.ok(off.far > 100, `without per peer the far peer stalls (${off.far})`);
  assert.equal(off.farDelay, off.nearDelay);
});
