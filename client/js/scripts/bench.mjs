// Speed of the SDK's codecs per pose in Node (CPU time), and the bundle's size.
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

// CPU time of this process (user + system), not wall time: on a shared, loaded
// machine the wall clock measures the other processes too.
function cpuNs() {
  const u = process.cpuUsage();
  return (u.user + u.system) * 1000;
}

function time(label, fn, perCall) {
  for (let i = 0; i < 2000; i++) fn(i); // warm up
  let n = 0;
  const start = cpuNs();
  let elapsed = 0;
  while (elapsed < 1e9) {
    for (let i = 0; i < 1000; i++) fn(n++);
    elapsed = cpuNs() - start;
  }
  const ns = elapsed / (n * perCall);
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
// Compact: a client's updates (3 poses, deltas after the first), decoded as the relay does.
const up = new sdk.CompactSession([-8, -2, -8, 8, 4, 8], false);
let seqC = 0;
report.compact_update_encode_us = time("compact update encode (3 poses, delta)", (i) => {
  const t = 100 + i / 30;
  return up.encodeUpdate(++seqC, t, poses(t, 3).map((e) => ({ ...e, user: -1 })));
}, 3) / 1000;
const relay = new Map();
let prev = null;
const frames = [];
const enc = new sdk.CompactSession([-8, -2, -8, 8, 4, 8], false);
for (let i = 0; i < 64; i++) frames.push(enc.encodeUpdate(i + 1, 100 + i / 30, poses(100 + i / 30, 3).map((e) => ({ ...e, user: -1 }))));
const volume = new sdk.Volume([-8, -2, -8, 8, 4, 8]);
report.compact_update_decode_us = time("compact update decode (3 poses, delta)", (i) => {
  const k = i % 64;
  if (k === 0) { relay.clear(); prev = null; }
  const f = sdk.decodeUpdateFrame(frames[k], volume, relay, prev);
  for (const e of f.entries) relay.set(e.stream, e.codes);
  prev = { number: f.number, baseUs: f.baseUs };
  return f;
}, 3) / 1000;
// Snapshots: the golden vectors' relay frames (a key snapshot, a delta snapshot),
// each decoded against its stated baselines.
for (const name of ["snapshot-key", "snapshot-delta"]) {
  const v = JSON.parse(readFileSync(join(root, "../../protocol/vectors", `${name}.json`), "utf8"));
  const data = new Uint8Array(Buffer.from(v.hex, "hex"));
  const base = new Map(v.baselines_before.map((b) => [b.user * 65536 + b.stream, b.codes]));
  const n = v.pose_frame.entries.length;
  const down = new sdk.CompactSession(v.volume, false);
  report[`compact_${name.replace("-", "_")}_decode_us`] = time(`compact ${name} decode (${n} poses)`, () => {
    down.down.clear();
    for (const [k, c] of base) down.down.set(k, c);
    return down.decodeSnapshot(data);
  }, n) / 1000;
}

const min = readFileSync(join(root, "dist/posecast.min.js"));
report.bundle_min_bytes = min.length;
report.bundle_min_gzip_bytes = gzipSync(min, { level: 9 }).length;
console.log(`dist/posecast.min.js: ${min.length} bytes, ${report.bundle_min_gzip_bytes} gzipped`);
console.log(JSON.stringify(report));
