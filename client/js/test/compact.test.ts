import { test } from "node:test";
import assert from "node:assert/strict";
import {
  CompactSession,
  Volume,
  bestOrder,
  codesToPose,
  crc32,
  decodeUpdateFrame,
  poseCodes,
  predict,
  roundHalfEven,
} from "../src/compact.js";
import { UsageError } from "../src/errors.js";
import type { Pose, PoseEntry } from "../src/messages.js";

const DEFAULT = new Volume([-8, -2, -8, 8, 4, 8]);

test("primitives: round half to even, CRC-32 check value, Exp-Golomb order choice", () => {
  assert.deepEqual([0.5, 1.5, 2.5, -0.5, -1.5, 2.4999].map(roundHalfEven), [0, 2, 2, -0, -2, 2]);
  assert.equal(crc32(new TextEncoder().encode("123456789")), 0xcbf43926);
  assert.equal(bestOrder([]), 0);
  assert.equal(bestOrder([0, 0, 1]), 0);
  assert.equal(bestOrder([300, 280, 310]), 8);
});

test("the default volume quantises to 15, 14, 15 bits (docs/protocol.md 11.2)", () => {
  assert.deepEqual(DEFAULT.bits, [15, 14, 15]);
  assert.ok(Math.abs(DEFAULT.step[0] - 0.00048829615) < 1e-11);
  assert.ok(Math.abs(DEFAULT.step[1] - 0.00036623329) < 1e-11);
});

test("the worked example's codes (12) come out of its poses", () => {
  const head = poseCodes([0.1, 1.6, -0.2, 0.9238795, 0, 0.3826834, 0], DEFAULT);
  const left = poseCodes([-0.25, 1.2, -0.4, 0.7071068, 0.7071068, 0, 0], DEFAULT);
  const right = poseCodes([0.25, 1.2, -0.4, 0, 0, 0, 1], DEFAULT);
  assert.deepEqual(head, [0, 0, 2216, 0, 16588, 9830, 15974]);
  assert.deepEqual(left, [0, 4095, 0, 0, 15872, 8738, 15564]);
  assert.deepEqual(right, [3, 0, 0, 0, 16895, 8738, 15564]);
  assert.deepEqual(predict(left, 1), [4095, 0, 0]);
});

test("codes round-trip within the codec's bounds, q and -q alike", () => {
  let worstPos = 0;
  let worstDeg = 0;
  for (let i = 0; i < 2000; i++) {
    const a = i * 0.37;
    const q = [Math.cos(a), Math.sin(a) * 0.6, Math.sin(a) * 0.48, Math.sin(a) * 0.64];
    const sign = i % 2 ? -1 : 1;
    const pose = [Math.sin(i) * 7.9, 1 + Math.cos(i) * 2.9, Math.sin(2 * i) * 7.9, ...q.map((x) => sign * x)] as Pose;
    const back = codesToPose(poseCodes(pose, DEFAULT), DEFAULT).pose;
    for (let k = 0; k < 3; k++) worstPos = Math.max(worstPos, Math.abs(back[k]! - pose[k]!));
    const dot = Math.abs(back[3] * pose[3] + back[4] * pose[4] + back[5] * pose[5] + back[6] * pose[6]);
    worstDeg = Math.max(worstDeg, (2 * Math.acos(Math.min(1, dot)) * 180) / Math.PI);
  }
  assert.ok(worstPos <= DEFAULT.step[0] / 2 + 1e-6, `position off by ${worstPos}`);
  assert.ok(worstDeg < 0.04, `rotation off by ${worstDeg} degrees`);
});

test("a position outside the volume is a bad-pose, never clamped", () => {
  assert.throws(() => poseCodes([8.01, 1, 0, 1, 0, 0, 0], DEFAULT), (e: unknown) => e instanceof UsageError && e.code === "bad-pose");
  const s = new CompactSession([-1, 0, -1, 1, 2, 1], false);
  assert.throws(() => s.checkVolume("head", [0, 2.5, 0, 1, 0, 0, 0]), /outside the room volume/);
});

test("a session's updates decode on the relay's side: key first, then deltas with a relative header", () => {
  const s = new CompactSession([-8, -2, -8, 8, 4, 8], true);
  const relay = new Map<number, number[]>();
  let previous: { number: number; baseUs: number } | null = null;
  const volume = new Volume([-8, -2, -8, 8, 4, 8]);
  for (let seq = 1; seq <= 30; seq++) {
    const t = 100 + seq / 30;
    const entries: PoseEntry[] = [0, 1, 2].map((stream) => ({
      user: -1,
      stream,
      capture: t - stream * 0.004,
      pose: [0.3 * Math.sin(t + stream), 1.5, 0.3 * Math.cos(t), Math.cos(t / 2), 0, Math.sin(t / 2), 0],
      velocity: [0.1, 0, -0.2, 0, 0.8, 0],
    }));
    const frame = s.encodeUpdate(seq, t, entries);
    assert.equal(frame[1]! & 0x08 ? "relative" : "absolute", seq === 1 ? "absolute" : "relative");
    const got = decodeUpdateFrame(frame, volume, relay, previous);
    assert.equal(got.number, seq);
    assert.equal(got.entries.every((e) => e.delta), seq > 1);
    for (const e of got.entries) {
      relay.set(e.stream, e.codes);
      assert.deepEqual(e.codes, s.up.get(e.stream));
      const pose = codesToPose(e.codes, volume);
      assert.ok(Math.abs(pose.pose[0] - entries[e.stream]!.pose[0]) < 0.0003);
      assert.deepEqual(pose.velocity, [0.099609375, 0, -0.19921875, 0, 0.80078125, 0]);
    }
    previous = { number: got.number, baseUs: got.baseUs };
  }
});
