"""Speed of the JS SDK's codecs per pose in headless Chromium (the example page's bundle).

    .venv/bin/python tests/browser/measure_sdk.py

Prints figures only (microseconds per pose, the median of 5 runs of ~0.3 s each, wall
time in the page: a browser has no CPU-time clock), with the same workloads as
``client/js/scripts/bench.mjs`` in Node: raw update encode / decode (3 poses), raw
snapshot decode (24 poses), compact update encode / decode (3 poses, deltas), compact
key and delta snapshots decoded against their baselines (the golden vectors).
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

from playwright.async_api import async_playwright

from posecast.cli.web import ensure_built, page_server

ROOT = Path(__file__).resolve().parents[2]
CHROMIUM_ARGS = ["--use-gl=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]

BENCH_JS = """async (vectors) => {
  const sdk = window.posecastPage.sdk;
  // Nothing else on the page's thread meanwhile: no rendering.
  window.posecastPage.renderer.setAnimationLoop(null);
  const VOL = [-8, -2, -8, 8, 4, 8];
  function poses(t, n) {
    const out = [];
    for (let i = 0; i < n; i++) {
      const a = 0.8 * t + i, h = a / 2;
      out.push({ user: 1 + Math.floor(i / 3), stream: i % 3, capture: t - 0.001 * (i % 3),
        pose: [0.4 * Math.sin(a), 1.6, 0.4 * Math.cos(a), Math.cos(h), 0, Math.sin(h), 0] });
    }
    return out;
  }
  function time(fn, perCall) {
    for (let i = 0; i < 2000; i++) fn(i);
    const runs = [];
    let n = 0;
    for (let r = 0; r < 5; r++) {
      let calls = 0;
      const start = performance.now();
      let el = 0;
      while (el < 300) {
        for (let i = 0; i < 200; i++) fn(n++);
        calls += 200;
        el = performance.now() - start;
      }
      runs.push((el * 1000) / (calls * perCall));
    }
    runs.sort((a, b) => a - b);
    return runs[2];
  }
  const report = {};
  const upd = poses(100, 3).map((e) => ({ ...e, user: -1 }));
  report.raw_update_encode_us = time((i) => sdk.encodeUpdate(i, 100 + i / 30, upd), 3);
  const rawUpdate = sdk.encodeUpdate(1, 100, upd);
  report.raw_update_decode_us = time(() => sdk.decodeMessage(rawUpdate), 3);
  const snap = sdk.encodeSnapshot(1, 100, poses(100, 24));
  report.raw_snapshot_decode_us = time(() => sdk.decodeMessage(snap), 24);
  const up = new sdk.CompactSession(VOL, false);
  let seq = 0;
  report.compact_update_encode_us = time((i) => {
    const t = 100 + i / 30;
    return up.encodeUpdate(++seq, t, poses(t, 3).map((e) => ({ ...e, user: -1 })));
  }, 3);
  const enc = new sdk.CompactSession(VOL, false);
  const frames = [];
  for (let i = 0; i < 64; i++) {
    const t = 100 + i / 30;
    frames.push(enc.encodeUpdate(i + 1, t, poses(t, 3).map((e) => ({ ...e, user: -1 }))));
  }
  const volume = new sdk.Volume(VOL);
  const relay = new Map();
  let prev = null;
  report.compact_update_decode_us = time((i) => {
    const k = i % 64;
    if (k === 0) { relay.clear(); prev = null; }
    const f = sdk.decodeUpdateFrame(frames[k], volume, relay, prev);
    for (const e of f.entries) relay.set(e.stream, e.codes);
    prev = { number: f.number, baseUs: f.baseUs };
    return f;
  }, 3);
  for (const v of vectors) {
    const data = new Uint8Array(v.hex.match(/../g).map((h) => parseInt(h, 16)));
    const base = new Map(v.baselines_before.map((b) => [b.user * 65536 + b.stream, b.codes]));
    const down = new sdk.CompactSession(v.volume, false);
    report[`compact_${v.name.replace("-", "_")}_decode_us`] = time(() => {
      down.down.clear();
      for (const [k, c] of base) down.down.set(k, c);
      return down.decodeSnapshot(data);
    }, v.pose_frame.entries.length);
  }
  report.user_agent = navigator.userAgent;
  return report;
}"""


async def main() -> None:
    vectors = [
        json.loads((ROOT / "protocol" / "vectors" / f"{name}.json").read_text())
        for name in ("snapshot-key", "snapshot-delta")
    ]
    with page_server({}, "127.0.0.1", 0, ensure_built()) as port:
        async with async_playwright() as p:
            browser = await p.chromium.launch(
                executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS
            )
            page = await browser.new_page()
            # No relay: the page's connection fails, its SDK is there all the same.
            await page.goto(f"http://127.0.0.1:{port}/?url=ws://127.0.0.1:9&room=bench")
            await page.wait_for_function(
                "() => window.posecastPage && window.posecastPage.renderer"
            )
            report = await page.evaluate(BENCH_JS, vectors)
            await browser.close()
    for key, value in report.items():
        print(f"{key:40s} {value:.3f}" if isinstance(value, float) else f"{key:40s} {value}")


if __name__ == "__main__":
    asyncio.run(main())
