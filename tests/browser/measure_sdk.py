"""Speed of the JS SDK's codecs per pose in headless Chromium (the example page's bundle).

    .venv/bin/python tests/browser/measure_sdk.py

Prints figures only: microseconds of the page's main-thread CPU time per pose (Chrome's
``ThreadTime`` metric over DevTools; the median of 5 runs of at least 0.2 s CPU each,
the page not rendering meanwhile), with the same workloads as
``client/js/scripts/bench.mjs`` in Node: raw update encode / decode (3 poses), raw
snapshot decode (24 poses), compact update encode / decode (3 poses, deltas), compact
key and delta snapshots decoded against their baselines (the golden vectors).
"""

from __future__ import annotations

import asyncio
import json
import sys
from pathlib import Path

from playwright.async_api import CDPSession, Page, async_playwright

from posecast.cli.web import ensure_built, page_server

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

from support import CHROMIUM_ARGS, find_chromium  # noqa: E402

SETUP_JS = """async (vectors) => {
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
  const w = {};  // name -> [function of the call number, poses per call]
  const upd = poses(100, 3).map((e) => ({ ...e, user: -1 }));
  w.raw_update_encode = [(i) => sdk.encodeUpdate(i, 100 + i / 30, upd), 3];
  const rawUpdate = sdk.encodeUpdate(1, 100, upd);
  w.raw_update_decode = [() => sdk.decodeMessage(rawUpdate), 3];
  const snap = sdk.encodeSnapshot(1, 100, poses(100, 24));
  w.raw_snapshot_decode = [() => sdk.decodeMessage(snap), 24];
  const up = new sdk.CompactSession(VOL, false);
  let seq = 0;
  w.compact_update_encode = [(i) => {
    const t = 100 + i / 30;
    return up.encodeUpdate(++seq, t, poses(t, 3).map((e) => ({ ...e, user: -1 })));
  }, 3];
  const enc = new sdk.CompactSession(VOL, false);
  const frames = [];
  for (let i = 0; i < 64; i++) {
    const t = 100 + i / 30;
    frames.push(enc.encodeUpdate(i + 1, t, poses(t, 3).map((e) => ({ ...e, user: -1 }))));
  }
  const volume = new sdk.Volume(VOL);
  const relay = new Map();
  let prev = null;
  w.compact_update_decode = [(i) => {
    const k = i % 64;
    if (k === 0) { relay.clear(); prev = null; }
    const f = sdk.decodeUpdateFrame(frames[k], volume, relay, prev);
    for (const e of f.entries) relay.set(e.stream, e.codes);
    prev = { number: f.number, baseUs: f.baseUs };
    return f;
  }, 3];
  for (const v of vectors) {
    const data = new Uint8Array(v.hex.match(/../g).map((h) => parseInt(h, 16)));
    const base = new Map(v.baselines_before.map((b) => [b.user * 65536 + b.stream, b.codes]));
    const down = new sdk.CompactSession(v.volume, false);
    w[`compact_${v.name.replace("-", "_")}_decode`] = [() => {
      down.down.clear();
      for (const [k, c] of base) down.down.set(k, c);
      return down.decodeSnapshot(data);
    }, v.pose_frame.entries.length];
  }
  window.__bench = w;
  return Object.fromEntries(Object.entries(w).map(([k, v]) => [k, v[1]]));
}"""

#: Run ``calls`` calls of one workload (its call numbers go on from run to run).
RUN_JS = """([name, calls]) => {
  const [fn] = window.__bench[name];
  const counts = (window.__benchN ??= {});
  let n = counts[name] ?? 0;
  for (let i = 0; i < calls; i++) fn(n++);
  counts[name] = n;
}"""


async def thread_time(cdp: CDPSession) -> float:
    """CPU time (s) of the page's main thread so far (Chrome's ``ThreadTime`` metric)."""
    metrics = await cdp.send("Performance.getMetrics")
    return float(next(m["value"] for m in metrics["metrics"] if m["name"] == "ThreadTime"))


async def measure(page: Page, cdp: CDPSession, name: str, per_call: int) -> float:
    """Microseconds of main-thread CPU per pose: the median of 5 runs of ~0.2 s CPU."""
    await page.evaluate(RUN_JS, [name, 2000])  # warm up
    calls, runs = 2000, []
    while len(runs) < 5:
        before = await thread_time(cdp)
        await page.evaluate(RUN_JS, [name, calls])
        spent = await thread_time(cdp) - before
        if spent < 0.2:
            calls = int(calls * min(10.0, 0.25 / max(spent, 1e-3)))
            continue
        runs.append(spent * 1e6 / (calls * per_call))
    return sorted(runs)[2]


async def main() -> None:
    vectors = [
        json.loads((ROOT / "protocol" / "vectors" / f"{name}.json").read_text())
        for name in ("snapshot-key", "snapshot-delta")
    ]
    with page_server({}, "127.0.0.1", 0, ensure_built()) as port:
        async with async_playwright() as p:
            browser = await p.chromium.launch(
                executable_path=find_chromium() or "/usr/bin/chromium", args=CHROMIUM_ARGS
            )
            page = await browser.new_page()
            # No relay: the page's connection fails, its SDK is there all the same.
            await page.goto(f"http://127.0.0.1:{port}/?url=ws://127.0.0.1:9&room=bench")
            await page.wait_for_function(
                "() => window.posecastPage && window.posecastPage.renderer"
            )
            cdp = await page.context.new_cdp_session(page)
            await cdp.send("Performance.enable")
            workloads = await page.evaluate(SETUP_JS, vectors)
            print(await page.evaluate("() => navigator.userAgent"))
            for name, per_call in workloads.items():
                us = await measure(page, cdp, name, per_call)
                print(f"{name:36s} {us:8.3f} us/pose  ({per_call} poses a call)")
            await browser.close()


if __name__ == "__main__":
    asyncio.run(main())
