// Speed of the SDK's codecs per pose in Node, and the bundle's size.
//   npm run bench
// Prints figures only; nothing here passes or fails on time.
import { readFileSync } from "node:fs";
import { gzipSync } from "node:zlib";
import { fileURLToPath } from "node:url";
import { dirname, join } from "node:path";
import * as sdk from "../dist/posecast.js";

const root = join(dirname(fileURLToPath(import.meta.url)), "..");
const POSES = 3 * 8; // a snapshot of 8 users' head and hands

function poses(t, n) {
  const out = [];
  for (let i = 0; i < n; i++) {
    const a = 0.8 * t + i;
    const h = a / 2;
    out.push({ user: 1 + Math.floor(i / 3), stream: i % 3, capture: t - 0.001 * (i % 3), pose: [0.4 * Math.sin(a), 1.6, 0.4 * Math.cos(a), Math.cos(h), 0, Math.sin(h), 0] });
  }
  return out;
}

function time(label, fn, perCall) {
  for (let i = 0; i < 2000; i++) fn(i); // warm up
  let n = 0;
  const start = process.hrtime.bigint();
  let elapsed = 0n;
  while (elapsed < 1_000_000_000n) {
    for (let i = 0; i < 1000; i++) fn(n++);
    elapsed = process.hrtime.bigint() - start;
  }
  const ns = Number(elapsed) / (n * perCall);
  console.log(`${label.padEnd(44)} ${(ns / 1000).toFixed(3)} us/pose   (${n} calls of ${perCall} poses)`);
  return ns;
}

const report = {};
const updateEntries = poses(100, 3).map((e) => ({ ...e, user: -1 }));
report.raw_update_encode_us = time("raw update encode (3 poses)", (i) => sdk.encodeUpdate(i, 100 + i / 30, updateEntries), 3) / 1000;
const rawUpdate = sdk.encodeUpdate(1, 100, updateEntries);
report.raw_update_decode_us = time("raw update decode (3 poses)", () => sdk.decodeMessage(rawUpdate), 3) / 1000;
const snap = sdk.encodeSnapshot(1, 100, poses(100, POSES));
report.raw_snapshot_decode_us = time(`raw snapshot decode (${POSES} poses)`, () => sdk.decodeMessage(snap), POSES) / 1000;
if (typeof sdk.CompactSession?.benchmark === "function") Object.assign(report, sdk.CompactSession.benchmark(time, poses));

const min = readFileSync(join(root, "dist/posecast.min.js"));
report.bundle_min_bytes = min.length;
report.bundle_min_gzip_bytes = gzipSync(min, { level: 9 }).length;
console.log(`dist/posecast.min.js: ${min.length} bytes, ${report.bundle_min_gzip_bytes} gzipped`);
console.log(JSON.stringify(report));
