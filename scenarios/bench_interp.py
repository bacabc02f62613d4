"""``posecast bench interp``: interpolation throughput beside reference libraries.

For each batch size, every posecast interpolator is timed on random pose pairs
(poses in, poses out, validation included) in the same run as reference
implementations of the same maths (scipy ``Rotation`` slerp and ``Slerp``
objects for SoA; scipy ``RigidTransform`` exp-coords and pytransform3d's
ScLERP, per pose and vectorised, for dq-slerp; a kingdon PGA motor blend with
``.normalized()`` for motor-lerp). References run on their own representation,
built before the clock starts, so their figures leave out the pose conversions
that posecast's include; a missing library is reported as "not installed". The
window and velocity methods (``motor-cubic``, ``motor-quintic``,
``motor-hermite``) are timed on their own random windows, intervals and
velocities; they have no reference library.

Timing: ``time.perf_counter``, each figure the best of several repeats of a loop
long enough to measure. Everything timed is single-threaded numpy/scipy code
(no BLAS calls). Then:

- the receiver's render frame: 100 remote streams of real motion (slices of the
  bundled sample traces, keyframes at 15 Hz) in one
  :class:`~client.buffers.RoomBuffers`, rendered at successive 90 Hz playout
  times through :func:`client.render.render_buffers` (the bot's path:
  bracket every stream, gather, one kernel call per method), per frame in
  microseconds, for each pair method and the bot's default three; beside it
  each row kernel alone on 100 poses;
- one keyframe-track render (``interp.evaluate_track``, K = 30 keyframes, 100
  streams, one query time), median of many runs, microseconds;
- the entry paths: throughput at batch 10,000 in this process, in a fresh
  ``python -m posecast.scenarios.bench_interp`` (a plain interpreter, glibc's allocator
  as it comes; the ``posecast`` CLI tunes it) and in a fresh ``python -c`` that
  imports ``interp`` only (as a notebook does; pair methods), side by side.

The bench prints figures and ratios against the targets; it never decides pass
or fail. ``python -m posecast.scenarios.bench_interp [--batch N]`` prints this
process's poses/s of every method at batch N as JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray
from rich.console import Console
from rich.table import Table

from posecast import interp
from posecast.client.buffers import RoomBuffers
from posecast.client.render import render_buffers
from posecast.scenarios.bench_interp_refs import REFERENCES, Unavailable, version
from posecast.scenarios.traces import find_traces, load_trace

__all__ = ["TARGETS", "frame_room", "run_interp_bench", "throughput_at"]

F64 = NDArray[np.float64]

#: Throughput targets at batch 10,000 (poses/s) and the track-render target (us).
TARGETS: dict[str, float] = {
    "soa": 10e6,
    "dq-slerp": 5e6,
    "motor-lerp": 10e6,
    "motor-cubic": 2e6,
    "motor-hermite": 2e6,
    "motor-quintic": 2e6,
    "track_us": 50.0,
    #: One render frame of 100 streams: one method, and the bot's default three.
    "frame_one_us": 50.0,
    "frame_three_us": 100.0,
}
TARGET_BATCH = 10_000
#: Pair methods (with reference libraries).
METHODS = ("soa", "dq-slerp", "motor-lerp")
#: Window and velocity methods (posecast's own; no reference).
EXTRA_METHODS = ("motor-cubic", "motor-hermite", "motor-quintic")
ALL_METHODS = METHODS + EXTRA_METHODS

#: Pairs timed for per-pose reference loops (their rate does not depend on batch).
LOOP_PAIRS = 300
TRACK_KEYFRAMES = 30
TRACK_STREAMS = 100
TRACK_RUNS = 3000
#: The render frame: remote streams, their keyframe rate, the render rate, and
#: the method sets timed (each pair method alone, then the bot's default three).
FRAME_STREAMS = 100
FRAME_KEY_RATE = 15.0
FRAME_RATE = 90.0
FRAME_SETS: tuple[tuple[str, ...], ...] = (*((m,) for m in METHODS), METHODS)

# Many short repeats, keep the best: on a shared machine the best repeat is the
# one no other process interrupted.
_MIN_REPEAT_S = 0.002  # each repeat runs at least this long
_REPEATS = 50
_MAX_CASE_S = 4.0  # cap on the time spent on one (case, batch) figure


def _random_poses(rng: np.random.Generator, n: int) -> F64:
    """Positions within 3 m per axis, uniform unit quaternions (w first)."""
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.concatenate([rng.uniform(-3.0, 3.0, (n, 3)), q], axis=1)


def _random_velocities(rng: np.random.Generator, n: int) -> F64:
    """Hand-like velocities: up to 5 m/s and 20 rad/s per axis."""
    return np.concatenate([rng.uniform(-5.0, 5.0, (n, 3)), rng.uniform(-20.0, 20.0, (n, 3))], 1)


def _extra_call(name: str, rng: np.random.Generator, n: int) -> Callable[[], object]:
    """The timed call of a window or velocity method on ``n`` random queries."""
    f = interp.get(name)
    entry = interp.info(name)
    s = rng.uniform(0.0, 1.0, n)
    if entry.kind == "window":
        k, lo = entry.window_size, entry.lookbehind
        keys = _random_poses(rng, k * n).reshape(n, k, 7)
        times = np.cumsum(rng.uniform(0.03, 0.2, (n, k)), axis=1)
        t = times[:, lo] + s * (times[:, lo + 1] - times[:, lo])
        return partial(f, keys, times, t)
    a, b = _random_poses(rng, n), _random_poses(rng, n)
    va, vb = _random_velocities(rng, n), _random_velocities(rng, n)
    dt = rng.uniform(0.03, 0.2, n)
    return partial(f, a, b, va, vb, dt, s)


def _best_seconds(call: Callable[[], object]) -> float:
    """Best time of one ``call()`` over a few repeats of a loop of calls."""
    start = time.perf_counter()
    call()  # warm-up, and a first estimate
    once = max(time.perf_counter() - start, 1e-7)
    if once >= _MAX_CASE_S / 2:
        return once  # a slow reference at a huge batch: one timed call is enough
    number = max(1, math.ceil(_MIN_REPEAT_S / once))
    repeats = max(2, min(_REPEATS, int(_MAX_CASE_S / (once * number))))
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(number):
            call()
        best = min(best, (time.perf_counter() - start) / number)
    return best


# --- measurement --------------------------------------------------------------------


def _machine() -> dict[str, Any]:
    model = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            names = [x.split(":", 1)[1].strip() for x in f if x.startswith("model name")]
        model = names[0] if names else model
    except OSError:
        pass
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return {
        "cpu": model,
        "cores": os.cpu_count() or 0,
        "load_1min": round(load, 2),
        "python": sys.version.split()[0],
        "numpy": np.__version__,
        "scipy": version("scipy"),
        "pytransform3d": version("pytransform3d"),
        "kingdon": version("kingdon"),
    }


def _run_times_us(call: Callable[[], object]) -> F64:
    """Wall time of each of ``TRACK_RUNS`` calls, in microseconds (after a warm-up)."""
    call()
    runs = np.empty(TRACK_RUNS)
    for i in range(TRACK_RUNS):
        start = time.perf_counter()
        call()
        runs[i] = time.perf_counter() - start
    return runs * 1e6


def _track_medians(rng: np.random.Generator) -> dict[str, dict[str, float]]:
    """Median microseconds of one 100-stream track render, and of its parts."""
    times = np.cumsum(rng.uniform(0.02, 0.1, TRACK_KEYFRAMES))
    poses = _random_poses(rng, TRACK_KEYFRAMES * TRACK_STREAMS).reshape(
        TRACK_KEYFRAMES, TRACK_STREAMS, 7
    )
    query = np.array([0.37 * times[11] + 0.63 * times[12]])
    br = interp.bracket(times, query)
    lo, hi, s = poses[br.lo], poses[br.hi], br.s[:, None]
    bracket_us = float(np.median(_run_times_us(partial(interp.bracket, times, query))))
    as_pose_us = float(np.median(_run_times_us(partial(interp.as_pose, poses, "poses"))))
    vel = _random_velocities(rng, TRACK_KEYFRAMES * TRACK_STREAMS).reshape(
        TRACK_KEYFRAMES, TRACK_STREAMS, 6
    )
    out: dict[str, dict[str, float]] = {}
    for name in ALL_METHODS:
        f = interp.get(name)
        if name in METHODS:
            track = partial(interp.evaluate_track, times, poses, query, f)
            alone = partial(f, lo, hi, s)
        else:
            # By name: evaluate_track gathers the window or the velocities itself.
            track = partial(interp.evaluate_track, times, poses, query, name, velocities=vel)
            k = np.array([br.lo[0]])
            alone = partial(
                interp.interpolate_brackets,
                poses,
                k,
                k + 1,
                br.s,
                name,
                times=times,
                velocities=vel,
            )
        runs = _run_times_us(track)
        out[name] = {
            "evaluate_track_us": float(np.median(runs)),
            "evaluate_track_min_us": float(np.min(runs)),
            "interpolator_us": float(np.median(_run_times_us(alone))),
            "bracket_us": bracket_us,
            "as_pose_us": as_pose_us,
        }
    return out


def frame_room(
    streams: int = FRAME_STREAMS, seconds: float = 4.0, seed: int = 0
) -> tuple[RoomBuffers, F64]:
    """A room of ``streams`` remote streams of real motion, and 90 Hz playout times.

    Stream ``j`` is device ``j % 3`` of a bundled sample trace from its own start
    time, keyframes at ``FRAME_KEY_RATE`` with a few ms of capture jitter, so the
    streams' brackets change at different frames. The playout times cover the
    keyframes (after the first half second) at ``FRAME_RATE``.
    """
    rng = np.random.default_rng(seed)
    traces = [load_trace(p) for p in find_traces("traces:sample")]
    room = RoomBuffers()
    n_keys = int(seconds * FRAME_KEY_RATE)
    for j in range(streams):
        tr = traces[j % len(traces)]
        dev = j % len(tr.streams)
        start = rng.uniform(0.0, tr.duration - seconds - 1.0)
        send = start + np.arange(n_keys) / FRAME_KEY_RATE + rng.uniform(-0.003, 0.003, n_keys)
        idx = np.searchsorted(tr.times, send).clip(0, len(tr.times) - 1)
        buf = room.stream()
        for i in idx:
            buf.push(float(tr.times[i] - start), tr.poses[i, dev].astype(np.float32))
    return room, np.arange(0.5, seconds - 0.2, 1.0 / FRAME_RATE)


def _render_next(room: RoomBuffers, frames: Iterator[float], methods: Sequence[str]) -> object:
    return render_buffers(room, next(frames), methods)


def _frame_figures(rng: np.random.Generator) -> dict[str, dict[str, float]]:
    """Microseconds per render frame (median, best, p90) for each method set, and
    each pair method's row kernel alone on ``FRAME_STREAMS`` poses (median)."""
    room, playout = frame_room()
    out: dict[str, dict[str, float]] = {}
    for methods in FRAME_SETS:
        frames = iter(np.resize(playout, TRACK_RUNS + 1).tolist())
        runs = _run_times_us(partial(_render_next, room, frames, methods))
        out[" + ".join(methods)] = {
            "median_us": float(np.median(runs)),
            "best_us": float(np.min(runs)),
            "p90_us": float(np.percentile(runs, 90)),
        }
    a, b = _random_poses(rng, FRAME_STREAMS).T.copy(), _random_poses(rng, FRAME_STREAMS).T.copy()
    s, res = rng.uniform(0.0, 1.0, FRAME_STREAMS), np.empty((FRAME_STREAMS, 7))
    # What a bare numpy call costs here and now: a frame is mostly numpy calls, so
    # frame / call compares across machines and loads better than microseconds.
    call = float(np.median(_run_times_us(partial(np.multiply, s, s, res[:, 0]))))
    for t in out.values():
        t["numpy_calls"] = t["median_us"] / call
        t["numpy_call_us"] = call
    for name in METHODS:
        kernel = interp.info(name).rows
        if kernel is not None:
            runs = _run_times_us(partial(kernel, a, b, s, res.T, None, True))
            out[name]["kernel_us"] = float(np.median(runs))
    return out


def throughput_at(batch: int, seed: int = 12345) -> dict[str, float]:
    """Poses/s of every posecast method at ``batch`` in this process (as the main table)."""
    rng = np.random.default_rng(seed)
    a, b, s = _random_poses(rng, batch), _random_poses(rng, batch), rng.uniform(0.0, 1.0, batch)
    rates = {name: batch / _best_seconds(partial(interp.get(name), a, b, s)) for name in METHODS}
    for name in EXTRA_METHODS:
        rates[name] = batch / _best_seconds(_extra_call(name, rng, batch))
    return rates


#: The notebook path: a fresh interpreter that imports ``interp`` (and numpy) only and
#: times the pair methods as :func:`_best_seconds` does. Argument: the batch size.
_IMPORT_INTERP = """import json, math, sys, time; import numpy as np; from posecast import interp
n, rng, rates = int(sys.argv[1]), np.random.default_rng(12345), {}
q = rng.normal(size=(2 * n, 4)); q /= np.linalg.norm(q, axis=1, keepdims=True)
p = np.concatenate([rng.uniform(-3.0, 3.0, (2 * n, 3)), q], axis=1)
a, b, s = p[:n], p[n:], rng.uniform(0.0, 1.0, n)
for name in ("soa", "dq-slerp", "motor-lerp"):
    f = interp.get(name); t0 = time.perf_counter(); f(a, b, s); best = math.inf
    k = max(1, math.ceil(0.002 / max(time.perf_counter() - t0, 1e-7)))
    for _ in range(50):
        t0 = time.perf_counter()
        for _ in range(k): f(a, b, s)
        best = min(best, (time.perf_counter() - t0) / k)
    rates[name] = n / best
print(json.dumps(rates))"""


def _plain_python_rates(batch: int, notebook: bool = False) -> dict[str, float] | str:
    """:func:`throughput_at` in a fresh ``python -m posecast.scenarios.bench_interp``: a plain
    interpreter, glibc's allocator as it comes. With ``notebook``, the pair methods in a
    fresh ``python -c`` that imports ``interp`` only. The reason as a string on failure."""
    env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
    cmd = [sys.executable, "-m", "posecast.scenarios.bench_interp", "--batch", str(batch)]
    if notebook:
        cmd = [sys.executable, "-c", _IMPORT_INTERP, str(batch)]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"not run: {exc}"
    if proc.returncode != 0:
        tail = proc.stderr.strip().splitlines()[-1:] or ["no output"]
        return f"failed: {tail[0]}"
    rates: dict[str, float] = json.loads(proc.stdout)
    return rates


def run_interp_bench(
    batch_sizes: Sequence[int] = (1, 100, 10_000, 1_000_000),
    console: Console | None = None,
    *,
    entry: str = "this process",
    entry_paths: bool = True,
) -> dict[str, Any]:
    """Time every interpolator beside the references; print tables and return the figures.

    ``entry`` names how this process was started (the CLI says it tuned the
    allocator); with ``entry_paths`` the batch-10k throughput is also measured in
    a plain ``python -m`` child and reported beside this process's.

    Returns ``{"machine", "batch_sizes", "posecast": {method: {batch: poses/s}},
    "references": [{"label", "method", "rates" | "loop_rate" | "missing"}],
    "frame": {method set: {..._us}}, "track": {method: {..._us}},
    "entry_paths": {entry: {method: poses/s}} (if timed), "targets": {...}}``.
    """
    console = console or Console()
    sizes = tuple(int(n) for n in batch_sizes)
    if not sizes or min(sizes) < 1:
        raise ValueError("batch sizes must be positive integers")
    rng = np.random.default_rng(12345)
    report: dict[str, Any] = {"machine": _machine(), "batch_sizes": list(sizes)}
    posecast: dict[str, dict[int, float]] = {name: {} for name in ALL_METHODS}
    refs: list[dict[str, Any]] = [
        {"label": c.label, "method": c.method, "rates": {}, "loop": c.loop} for c in REFERENCES
    ]

    wall0, cpu0 = time.perf_counter(), time.process_time()
    with console.status("bench interp: timing ...") as status:
        for n in sizes:
            a, b = _random_poses(rng, n), _random_poses(rng, n)
            s = rng.uniform(0.0, 1.0, n)
            for name in METHODS:
                status.update(f"bench interp: {name} at batch {n:,}")
                f = interp.get(name)
                posecast[name][n] = n / _best_seconds(partial(f, a, b, s))
            for name in EXTRA_METHODS:
                status.update(f"bench interp: {name} at batch {n:,}")
                posecast[name][n] = n / _best_seconds(_extra_call(name, rng, n))
            for case, row in zip(REFERENCES, refs, strict=True):
                if case.loop or "missing" in row:
                    continue
                status.update(f"bench interp: {case.label} at batch {n:,}")
                try:
                    call = case.build(a, b, s)
                except Unavailable as exc:
                    row["missing"] = str(exc)
                    continue
                row["rates"][n] = n / _best_seconds(call)
        m = LOOP_PAIRS
        a, b, s = _random_poses(rng, m), _random_poses(rng, m), rng.uniform(0.0, 1.0, m)
        for case, row in zip(REFERENCES, refs, strict=True):
            if not case.loop:
                continue
            status.update(f"bench interp: {case.label} on {m} pairs")
            try:
                row["loop_rate"] = m / _best_seconds(case.build(a, b, s))
            except Unavailable as exc:
                row["missing"] = str(exc)
        status.update(f"bench interp: render frame, {FRAME_STREAMS} streams")
        frame = _frame_figures(rng)
        status.update("bench interp: keyframe track, 100 streams")
        track = _track_medians(rng)

    # CPU time over wall time: well below 1 means other processes took the core.
    report["machine"]["cpu_share"] = round(
        (time.process_time() - cpu0) / (time.perf_counter() - wall0), 2
    )
    paths = _entry_paths(console, entry, posecast, sizes) if entry_paths else {}
    report["posecast"] = posecast
    report["references"] = refs
    report["frame"] = frame
    report["track"] = track
    report["entry_paths"] = paths
    report["targets"] = _target_summary(posecast, frame)
    _print_report(console, report)
    return report


def _entry_paths(
    console: Console, entry: str, posecast: dict[str, dict[int, float]], sizes: tuple[int, ...]
) -> dict[str, dict[str, float] | str]:
    """Batch-10k poses/s of this process (``entry``), of a plain ``python -m`` child and
    of a ``python -c`` child that imports ``interp`` only (pair methods)."""
    with console.status("bench interp: batch 10,000 in a plain `python -m` process"):
        here = (
            {m: posecast[m][TARGET_BATCH] for m in ALL_METHODS}
            if TARGET_BATCH in sizes
            else throughput_at(TARGET_BATCH)
        )
        plain = _plain_python_rates(TARGET_BATCH)
        notebook = _plain_python_rates(TARGET_BATCH, notebook=True)
    return {
        entry: here,
        "python -m posecast.scenarios.bench_interp (allocator as it comes)": plain,
        "python -c 'from posecast import interp' (as a notebook)": notebook,
    }


def _target_summary(
    posecast: dict[str, dict[int, float]], frame: dict[str, dict[str, float]]
) -> dict[str, dict[str, Any]]:
    out: dict[str, dict[str, Any]] = {}
    for name in ALL_METHODS:
        rate = posecast[name].get(TARGET_BATCH)
        goal = TARGETS[name]
        out[f"{name}@{TARGET_BATCH}"] = {
            "measured": rate,
            "target": goal,
            "ratio": None if rate is None else rate / goal,
            "met": None if rate is None else rate >= goal,
        }
    for key, t in frame.items():
        goal = TARGETS["frame_three_us" if "+" in key else "frame_one_us"]
        us = t["median_us"]
        out[f"frame {key}"] = {
            "measured": us,
            "target": goal,
            "ratio": goal / us,
            "met": us <= goal,
        }
    return out


# --- printing -------------------------------------------------------------------------


def _rate(x: float | None) -> str:
    if x is None:
        return "-"
    if x >= 1e6:
        return f"{x / 1e6:.2f} M"
    if x >= 1e3:
        return f"{x / 1e3:.1f} k"
    return f"{x:.0f}"


def _print_report(console: Console, report: dict[str, Any]) -> None:
    mach = report["machine"]
    console.print(
        f"[bold]posecast bench interp[/] on {mach['cpu']} ({mach['cores']} cores, "
        f"1-min load {mach['load_1min']}, this process got {mach.get('cpu_share', '?')} of a "
        f"core); python {mach['python']}, numpy {mach['numpy']}, "
        f"scipy {mach['scipy']}, pytransform3d {mach['pytransform3d']}, kingdon {mach['kingdon']}"
    )
    console.print(_throughput_table(report))
    console.print(_speedup_table(report))
    console.print(_frame_table(report))
    console.print(_track_table(report))
    if report["entry_paths"]:
        console.print(_entry_table(report))
    console.print(_targets_table(report))


def _throughput_table(report: dict[str, Any]) -> Table:
    """Poses/s of posecast's methods and of every reference, per batch size."""
    sizes: list[int] = report["batch_sizes"]
    table = Table(title="Interpolation throughput, poses/s (best of repeats, one thread)")
    table.add_column("implementation")
    table.add_column("method")
    for n in sizes:
        table.add_column(f"batch {n:,}", justify="right")
    table.add_column(f"per-pair loop ({LOOP_PAIRS})", justify="right")
    for name in ALL_METHODS:
        table.add_row(
            f"[bold]posecast {name}[/]",
            name,
            *(_rate(report["posecast"][name].get(n)) for n in sizes),
            "",
        )
    for row in report["references"]:
        if "missing" in row:
            table.add_row(row["label"], row["method"], *(row["missing"] for _ in sizes), "")
        elif row["loop"]:
            table.add_row(
                row["label"], row["method"], *("" for _ in sizes), _rate(row["loop_rate"])
            )
        else:
            table.add_row(
                row["label"], row["method"], *(_rate(row["rates"].get(n)) for n in sizes), ""
            )
    return table


def _speedup_table(report: dict[str, Any]) -> Table:
    """posecast's rate over each available reference's, per batch size."""
    sizes: list[int] = report["batch_sizes"]
    ratio = Table(title="posecast speed-up over each reference (same method)")
    ratio.add_column("reference")
    ratio.add_column("method")
    for n in sizes:
        ratio.add_column(f"batch {n:,}", justify="right")
    for row in report["references"]:
        if "missing" in row:
            continue
        ours = report["posecast"][row["method"]]
        if row["loop"]:
            cells = [f"{ours[n] / row['loop_rate']:.0f}x" for n in sizes]
        else:
            cells = [f"{ours[n] / row['rates'][n]:.1f}x" for n in sizes]
        ratio.add_row(row["label"], row["method"], *cells)
    return ratio


def _track_table(report: dict[str, Any]) -> Table:
    """Median microseconds of one keyframe-track query, split into its parts."""
    track = Table(
        title=f"Keyframe track: {TRACK_STREAMS} streams, K={TRACK_KEYFRAMES}, one query "
        f"(median of {TRACK_RUNS} runs, us)"
    )
    for col in (
        "method",
        "evaluate_track",
        "(fastest run)",
        "of which: as_pose",
        "bracket",
        "interpolator",
    ):
        track.add_column(col, justify="right")
    for name, t in report["track"].items():
        track.add_row(
            name,
            f"{t['evaluate_track_us']:.1f}",
            f"{t['evaluate_track_min_us']:.1f}",
            f"{t['as_pose_us']:.1f}",
            f"{t['bracket_us']:.1f}",
            f"{t['interpolator_us']:.1f}",
        )
    return track


def _frame_table(report: dict[str, Any]) -> Table:
    """Microseconds per render frame through ``render_buffers``, and the kernels alone."""
    table = Table(
        title=f"Render frame: {FRAME_STREAMS} streams of real motion, bracket + gather + "
        f"interpolate (render_buffers, {TRACK_RUNS} frames at {FRAME_RATE:.0f} Hz playout, us)"
    )
    call = next(iter(report["frame"].values()))["numpy_call_us"]
    for col in (
        "methods",
        "median",
        "best",
        "p90",
        "of which the kernel alone (median)",
        f"median / one bare multiply of 100 floats ({call:.2f} us here)",
    ):
        table.add_column(col, justify="right")
    for key, t in report["frame"].items():
        kernel = t.get("kernel_us")
        table.add_row(
            key,
            f"{t['median_us']:.1f}",
            f"{t['best_us']:.1f}",
            f"{t['p90_us']:.1f}",
            "" if kernel is None else f"{kernel:.1f}",
            f"{t['numpy_calls']:.0f}",
        )
    return table


def _entry_table(report: dict[str, Any]) -> Table:
    """Poses/s at batch 10k by how the process was started, side by side."""
    paths: dict[str, dict[str, float] | str] = report["entry_paths"]
    table = Table(title=f"Entry paths: poses/s at batch {TARGET_BATCH:,} (best of repeats)")
    table.add_column("method")
    for i, label in enumerate(paths, 1):
        table.add_column(f"path {i}: {label}", justify="right")
    first, *others = paths.values()
    for i in range(len(others)):
        table.add_column(f"path {i + 2} / path 1", justify="right")
    for name in ALL_METHODS:
        cells = [v if isinstance(v, str) else _rate(v.get(name)) for v in paths.values()]
        for other in others:
            ratio = ""
            if isinstance(first, dict) and isinstance(other, dict) and name in other:
                ratio = f"{other[name] / first[name]:.2f}"
            cells.append(ratio)
        table.add_row(name, *cells)
    return table


def _targets_table(report: dict[str, Any]) -> Table:
    """Each target beside its measured figure (no verdict)."""
    goals = Table(title="Targets (figures, not a verdict)")
    for col in ("target", "measured", "goal", "measured / goal"):
        goals.add_column(col, justify="right")
    for key, t in report["targets"].items():
        if t["measured"] is None:
            goals.add_row(key, "not timed", "", "")
            continue
        if key.startswith("frame"):
            measured, goal = f"{t['measured']:.1f} us", f"<= {t['target']:.0f} us"
            share = f"{t['measured'] / t['target']:.2f} ({'met' if t['met'] else 'missed'})"
        else:
            measured, goal = _rate(t["measured"]) + "/s", f">= {_rate(t['target'])}/s"
            share = f"{t['ratio']:.2f} ({'met' if t['met'] else 'missed'})"
        goals.add_row(key, measured, goal, share)
    return goals


def _main() -> None:
    """``python -m posecast.scenarios.bench_interp --batch N``: this process's poses/s as JSON."""
    parser = argparse.ArgumentParser(description=_main.__doc__)
    parser.add_argument("--batch", type=int, default=TARGET_BATCH, help="Batch size to time.")
    args = parser.parse_args()
    if args.batch < 1:
        parser.error("--batch must be a positive integer")
    print(json.dumps(throughput_at(args.batch)))


if __name__ == "__main__":
    _main()
