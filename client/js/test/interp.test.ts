import { test } from "node:test";
import assert from "node:assert/strict";
import { readFileSync } from "node:fs";
import { dqSlerp, interpolator, motorLerp, soa } from "../src/interp.js";

interface Case {
  name: string;
  a: number[];
  b: number[];
  s: number;
  soa: number[];
  "dq-slerp": number[];
  "motor-lerp": number[];
}

const doc = JSON.parse(readFileSync(new URL("../test/interp-vectors.json", import.meta.url), "utf8")) as { cases: Case[] };

// Sign-insensitive for the quaternion (q and -q are one rotation), exact per component otherwise.
function maxDiff(got: number[], want: number[]): number {
  let pos = 0;
  for (let i = 0; i < 3; i++) pos = Math.max(pos, Math.abs(got[i]! - want[i]!));
  let same = 0;
  let flip = 0;
  for (let i = 3; i < 7; i++) {
    same = Math.max(same, Math.abs(got[i]! - want[i]!));
    flip = Math.max(flip, Math.abs(got[i]! + want[i]!));
  }
  return Math.max(pos, Math.min(same, flip));
}

for (const method of ["soa", "dq-slerp", "motor-lerp"] as const) {
  test(`${method} agrees with Python interp/ to 1e-9 on every shared vector`, () => {
    const fn = interpolator(method);
    assert.ok(doc.cases.length > 300);
    let worst = 0;
    for (const c of doc.cases) {
      const d = maxDiff(fn(c.a, c.b, c.s), c[method]);
      assert.ok(d <= 1e-9, `${c.name} s=${c.s}: off by ${d}`);
      worst = Math.max(worst, d);
    }
    assert.ok(Number.isFinite(worst));
  });
}

test("every method gives the keyframes exactly at s = 0 and s = 1", () => {
  const a = [0.1, 1.5, -0.2, 0.9238795325112867, 0, 0.3826834323650898, 0];
  const b = [0.4, 1.4, 0.1, -0.7071067811865476, 0, 0, -0.7071067811865476];
  for (const fn of [soa, dqSlerp, motorLerp]) {
    assert.deepEqual(fn(a, b, 0), a);
    assert.deepEqual(fn(a, b, 1), b);
  }
});

test("q and -q interpolate alike, and results have unit quaternions", () => {
  const a = [0, 1, 0, 1, 0, 0, 0];
  const b = [1, 1, 0, 0.8, 0.6, 0, 0];
  const nb = [1, 1, 0, -0.8, -0.6, 0, 0];
  for (const fn of [soa, dqSlerp, motorLerp]) {
    const x = fn(a, b, 0.3);
    const y = fn(a, nb, 0.3);
    for (let i = 0; i < 7; i++) assert.ok(Math.abs(x[i]! - y[i]!) < 1e-15);
    assert.ok(Math.abs(Math.hypot(x[3], x[4], x[5], x[6]) - 1) < 1e-12);
  }
});

test("an unknown method name is a clear error", () => {
  assert.throws(() => interpolator("cubic-spline"), /unknown interpolator 'cubic-spline'/);
});
