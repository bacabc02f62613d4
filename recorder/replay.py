"""Offline replay: reconstruct a recorded session headlessly, as a receiver would have seen it.

:func:`replay_offline` takes every recorded stream (its keyframes, capture time
order) as the full-rate ground truth, samples it at an update rate ``R`` (the
newest recorded keyframe at each send time ``t0 + k/R``, as a sender would),
and renders every stream at ``render_rate`` (90 Hz) with each interpolator on
an ideal network with one-interval playout (plus a window method's look-ahead)
-- the definitions of :mod:`scenarios.qoe`. It writes the rendered poses (one
CSV and one NPZ per method) and scores the QoE against the recorded streams with
:func:`scenarios.qoe.evaluate_group`.

Rendered output, one row per stream and render frame::

    user, stream, name, time, px, py, pz, qw, qx, qy, qz, stall

``time`` is the playout time tau on the server clock (the frame is shown at
``tau + D``); ``stall`` is 1 where no keyframe pair brackets tau (the newest
keyframe is held). The NPZ holds the same columns as arrays (``user``,
``stream``, ``name``, ``time``, ``poses`` (M, 7) float64, ``stall``).

:func:`synthesize_recording` writes a session with :class:`SessionRecorder` from
real traces (bots publishing the newest trace sample at their send rate), and
:func:`bench_replay` times the replay of a 20-user, 60 s one (figures only).
Wall-clock timings here are report figures (``time.perf_counter``), never inputs.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from posecast.interp import info as interp_info
from posecast.recorder.export import POSE_COLUMNS, csv_bytes, read_session
from posecast.recorder.objects import ObjectTrack
from posecast.recorder.reader import StreamData
from posecast.recorder.writer import SessionRecorder
from posecast.scenarios.motion import MotionSpec
from posecast.scenarios.qoe import (
    ErrorSamples,
    KeyframeLog,
    evaluate_group,
    ideal_delay,
    ideal_log,
    interpolate_playout,
    playout_brackets,
    summarize,
    window_depth,
)
from posecast.scenarios.spawn import layout_points, place, placement_for
from posecast.scenarios.traces import DEVICE_NAMES, Trace, find_traces, load_trace

__all__ = [
    "DEFAULT_RENDER_RATE",
    "bench_replay",
    "recording_stem",
    "replay_offline",
    "synthesize_recording",
]

F64 = NDArray[np.float64]

DEFAULT_RENDER_RATE = 90.0
_METHODS = ("soa", "dq-slerp", "motor-lerp")


def recording_stem(path: str | os.PathLike[str]) -> str:
    """``NAME`` of ``NAME.mcap`` or ``NAME.mcap.part``."""
    name = Path(path).name
    for suffix in (".part", ".mcap"):
        name = name.removesuffix(suffix)
    return name


def _dedupe(s: StreamData) -> tuple[F64, F64, F64 | None]:
    """Capture times strictly increasing (first of equal ones), float64 poses, velocities."""
    keep = np.ones(s.times.shape, dtype=bool)
    keep[1:] = s.times[1:] != s.times[:-1]
    vel = None
    if s.velocities is not None and not np.isnan(s.velocities[keep]).any():
        vel = s.velocities[keep].astype(np.float64)
    return s.times[keep], s.poses[keep].astype(np.float64), vel


_Member = tuple[StreamData, F64, F64 | None]


def _groups(streams: Sequence[StreamData]) -> list[tuple[int, F64, list[_Member]]]:
    """Streams of one user with identical capture times, batched: (user, times, members).

    A member is ``(stream, poses, velocities)``; velocities are ``None`` unless
    every update of the stream carried them.
    """
    found: dict[tuple[int, bytes], tuple[int, F64, list[_Member]]] = {}
    for s in streams:
        times, poses, vel = _dedupe(s)
        if times.size < 2:
            continue
        key = (s.user, times.tobytes())
        found.setdefault(key, (s.user, times, []))[2].append((s, poses, vel))
    return list(found.values())


def _write_rendered(
    out: Path,
    stem: str,
    method: str,
    rate: float,
    rows: list[tuple[StreamData, F64, F64, NDArray[np.bool_]]],
    formats: Sequence[str],
) -> dict[str, str]:
    """One CSV and/or NPZ with every stream's rendered frames; returns the paths."""
    users = np.concatenate([np.full(t.size, s.user, dtype=np.uint16) for s, t, _p, _st in rows])
    sids = np.concatenate([np.full(t.size, s.stream, dtype=np.uint16) for s, t, _p, _st in rows])
    names = np.concatenate(
        [np.full(t.size, (s.name or f"stream{s.stream}").encode()) for s, t, _p, _st in rows]
    )
    times = np.concatenate([t for _s, t, _p, _st in rows])
    poses = np.concatenate([p for _s, _t, p, _st in rows])
    stall = np.concatenate([st for _s, _t, _p, st in rows]).astype(np.uint8)
    base = out / f"{stem}.{method}.{rate:g}hz"
    files: dict[str, str] = {}
    if "npz" in formats:
        path = base.with_name(base.name + ".npz")
        with path.open("wb") as fh:
            np.savez(
                fh,
                user=users,
                stream=sids,
                name=names.astype(str),
                time=times,
                poses=poses,
                stall=stall.astype(bool),
            )
        files["npz"] = str(path)
    if "csv" in formats:
        path = base.with_name(base.name + ".csv")
        header = ("user", "stream", "name", "time", *POSE_COLUMNS, "stall")
        cols = [users, sids, names, times, *(poses[:, j] for j in range(7)), stall]
        decimals = (None, None, None, 6, 7, 7, 7, 8, 8, 8, 8, None)
        path.write_bytes(csv_bytes(header, cols, decimals))
        files["csv"] = str(path)
    return files


_Row = tuple[StreamData, F64, F64, NDArray[np.bool_]]
_QoeGroup = dict[str, dict[str, ErrorSamples]]


def _check_replay_args(
    interp_names: Sequence[str],
    rate: float,
    render_rate: float,
    out_dir: str | os.PathLike[str] | None,
    formats: Sequence[str],
) -> tuple[list[str], list[str], tuple[str, ...]]:
    """Validated ``(methods, velocity methods, output formats)`` of :func:`replay_offline`."""
    if not rate > 0 or not render_rate > 0:
        raise ValueError("rate and render_rate must be positive")
    methods = list(interp_names)
    if not methods:
        raise ValueError("expected at least one interpolator")
    velocity_methods = [m for m in methods if interp_info(m).needs_velocity]
    fmts = tuple(formats) if out_dir is not None else ()
    for f in fmts:
        if f not in ("csv", "npz"):
            raise ValueError(f"unknown output format {f!r}; expected csv or npz")
    return methods, velocity_methods, fmts


def _require_velocities(
    groups: list[tuple[int, F64, list[_Member]]], velocity_methods: list[str]
) -> None:
    """Refuse velocity methods unless every grouped stream carried velocities."""
    if velocity_methods and any(v is None for _u, _t, ms in groups for _s, _p, v in ms):
        raise ValueError(
            f"{', '.join(velocity_methods)} need keyframe velocities, which this recording "
            "does not carry for every stream (record bots that send the velocity variant); "
            "use a pair or window method"
        )


def _group_inputs(times: F64, members: list[_Member], rate: float) -> tuple[Trace, KeyframeLog]:
    """One group's ground truth and its keyframes sampled at ``rate`` on an ideal network."""
    poses = np.stack([p for _s, p, _v in members], axis=1)  # (N, S, 7)
    vels = [v for _s, _p, v in members]
    truth = Trace(
        f"user{members[0][0].user}",
        times,
        poses,
        tuple(s.name or f"stream{s.stream}" for s, _p, _v in members),
    )
    velocities = (
        None
        if any(v is None for v in vels)
        else np.stack([v for v in vels if v is not None], axis=1)
    )
    # Ideal network: each keyframe arrives the instant it is sent.
    return truth, ideal_log(times, poses, rate, velocities)


def _render_group(
    truth: Trace,
    log: KeyframeLog,
    members: list[_Member],
    taus: F64,
    methods: list[str],
    rate: float,
    depth: tuple[int, int],
) -> tuple[list[tuple[str, float]], list[tuple[str, _QoeGroup, list[_Row]]]]:
    """Score and render one group with every method at playout times ``taus``.

    Returns each method's playout delay (in ``methods`` order) and, per method,
    its QoE group and its rendered rows (one per member stream).
    """
    lookbehind, lookahead = depth
    # Methods with the same look-ahead share the playout delay, so one bracket
    # search (and one QoE pass) serves them all.
    by_delay: dict[float, list[str]] = {}
    delays: list[tuple[str, float]] = []
    for m in methods:
        delay = ideal_delay(rate, truth.native_rate, interp_info(m).lookahead)
        by_delay.setdefault(delay, []).append(m)
        delays.append((m, delay))
    outputs: list[tuple[str, _QoeGroup, list[_Row]]] = []
    for delay, group in by_delay.items():
        scored = evaluate_group(truth, log, delay, group)
        play = playout_brackets(
            log.capture, log.arrival, taus, delay, lookbehind=lookbehind, lookahead=lookahead
        )
        for m in group:
            out = interpolate_playout(log, play, m)
            rows = [(s, taus, out[:, j], play.stall) for j, (s, _p, _v) in enumerate(members)]
            outputs.append((m, {m: scored[m]}, rows))
    return delays, outputs


@dataclass
class _Reconstruction:
    """Every method's QoE groups, rendered rows and delays; the session span; frame count."""

    qoe: dict[str, list[_QoeGroup]]
    rendered: dict[str, list[_Row]]
    delays: dict[str, list[float]]
    first: float = math.inf
    last: float = -math.inf
    frames: int = 0


def _reconstruct(
    groups: list[tuple[int, F64, list[_Member]]],
    methods: list[str],
    rate: float,
    render_rate: float,
) -> _Reconstruction:
    """Render and score every group with every method (see :func:`replay_offline`)."""
    depth = window_depth(methods)
    rec = _Reconstruction(
        qoe={m: [] for m in methods},
        rendered={m: [] for m in methods},
        delays={m: [] for m in methods},
    )
    for _user, times, members in groups:
        rec.first, rec.last = min(rec.first, float(times[0])), max(rec.last, float(times[-1]))
        truth, log = _group_inputs(times, members, rate)
        n = math.floor((float(times[-1]) - float(times[0])) * render_rate + 1e-9) + 1
        taus = float(times[0]) + np.arange(n) / render_rate
        rec.frames += n * len(members)
        delays, outputs = _render_group(truth, log, members, taus, methods, rate, depth)
        for m, delay in delays:
            rec.delays[m].append(delay)
        for m, scored, rows in outputs:
            rec.qoe[m].append(scored)
            rec.rendered[m].extend(rows)
    return rec


def _write_outputs(
    path: str | os.PathLike[str],
    out_dir: str | os.PathLike[str] | None,
    methods: list[str],
    rate: float,
    rendered: dict[str, list[_Row]],
    fmts: tuple[str, ...],
) -> dict[str, dict[str, str]]:
    """Each method's rendered files (nothing without ``out_dir`` or formats)."""
    files: dict[str, dict[str, str]] = {}
    if fmts and out_dir is not None:
        folder = Path(out_dir)
        folder.mkdir(parents=True, exist_ok=True)
        stem = recording_stem(path)
        for m in methods:
            if rendered[m]:
                files[m] = _write_rendered(folder, stem, m, rate, rendered[m], fmts)
    return files


def _window(streams: list[StreamData], start: float, duration: float | None) -> tuple[float, float]:
    """The arrival times ``[lo, hi]`` :func:`select_streams` keeps."""
    lo = min(float(s.arrival.min()) for s in streams if len(s)) + start
    return lo, math.inf if duration is None else lo + duration


def _objects_report(
    tracks: list[ObjectTrack], streams: list[StreamData], window: tuple[float, float]
) -> list[dict[str, Any]]:
    """Each reconstructed object: its keyframes and its ownership changes in the window."""
    out = []
    lo, hi = window
    for t in tracks:
        s = next((s for s in streams if s.stream == t.stream and s.name == t.name), None)
        if s is None or not len(s):
            continue
        flight = t.flight[np.isin(t.arrival, s.arrival)]
        out.append(
            {
                "name": t.name,
                "stream": t.stream,
                "keyframes": len(s),
                "flight_keyframes": int(np.count_nonzero(flight)),
                "changes": [c.as_dict() for c in t.changes if lo <= c.time <= hi],
            }
        )
    return out


def user_matches(user: int, name: str | None, wanted: str) -> bool:
    """``wanted`` names the user by id (``3`` or ``u3``) or by its recorded name."""
    w = wanted.strip()
    return w in (str(user), f"u{user}", name)


def select_streams(
    streams: Sequence[StreamData],
    start: float = 0.0,
    duration: float | None = None,
    users: Sequence[str] | None = None,
) -> list[StreamData]:
    """The part of a recording a player was asked for (``replay --start --duration
    --users``): keyframes arriving in ``[first + start, first + start + duration]``
    (seconds from the recording's first arrival) of the users named (id, ``u``-id
    or recorded name). ValueError for a name that matches nobody or an empty window.
    """
    if start < 0 or (duration is not None and not duration > 0):
        raise ValueError("--start must be 0 or more and --duration positive")
    if users is not None:
        for w in users:
            if not any(user_matches(s.user, s.user_name, w) for s in streams):
                known = ", ".join(sorted({f"u{s.user} ({s.user_name})" for s in streams}))
                raise ValueError(f"no recorded user {w!r}; the recording has {known}")
    arrivals = [float(s.arrival.min()) for s in streams if len(s)]
    if not arrivals:
        raise ValueError("no pose updates in the recording")
    lo = min(arrivals) + start
    hi = math.inf if duration is None else lo + duration
    kept = []
    for s in streams:
        if users is not None and not any(user_matches(s.user, s.user_name, w) for w in users):
            continue
        keep = (s.arrival >= lo) & (s.arrival <= hi)
        if keep.any():
            vel = None if s.velocities is None else s.velocities[keep]
            kept.append(
                replace(
                    s,
                    times=s.times[keep],
                    arrival=s.arrival[keep],
                    poses=s.poses[keep],
                    velocities=vel,
                )
            )
    if not kept:
        raise ValueError("no pose updates in the chosen window and users")
    return kept


def replay_offline(
    path: str | os.PathLike[str],
    interp_names: Sequence[str],
    rate: float,
    out_dir: str | os.PathLike[str] | None,
    render_rate: float = DEFAULT_RENDER_RATE,
    *,
    formats: Sequence[str] = ("csv", "npz"),
    start: float = 0.0,
    duration: float | None = None,
    users: Sequence[str] | None = None,
) -> dict[str, Any]:
    """Reconstruct every recorded stream at ``render_rate`` from keyframes sampled at ``rate``.

    Writes ``out_dir/NAME.METHOD.RHz.csv`` and ``.npz`` (``formats`` picks which;
    ``out_dir=None`` or no formats: nothing is written) and returns::

        {"path", "rate", "render_rate", "methods", "delay_s": {method: D},
         "session_s", "streams", "frames_rendered", "files": {method: {...}},
         "qoe": {method: {class: {pos_p50_mm, ..., stall_fraction}}},
         "objects": [{"name", "stream", "keyframes", "flight_keyframes",
                      "changes": [{"time", "owner", "previous", "reason", ...}]}],
         "timing": {"read_s", "reconstruct_s", "write_s", "total_s", "speedup"}}

    ``speedup`` is the session duration over the total time taken. Velocity
    methods use the velocities the recorded updates carried (the protocol's
    velocity variant); a recording without them refuses velocity methods.
    ``start``, ``duration`` and ``users`` reconstruct only that window and those
    users (:func:`select_streams`).

    A shared object is reconstructed as one stream (user ``ROOM_USER``, named by
    the object, QoE class ``objects``) from its keyframes as the room stored them,
    whoever published them (owners, the relay in flight); ``objects`` lists its
    ownership changes in the window (``--users room`` picks the objects alone).
    """
    methods, velocity_methods, fmts = _check_replay_args(
        interp_names, rate, render_rate, out_dir, formats
    )
    t0 = time.perf_counter()
    data = read_session(path)
    streams, window = data.streams, (-math.inf, math.inf)
    if start or duration is not None or users is not None:
        streams = select_streams(streams, start, duration, users)
        window = _window(data.streams, start, duration)
    t1 = time.perf_counter()
    groups = _groups(streams)
    _require_velocities(groups, velocity_methods)
    rec = _reconstruct(groups, methods, rate, render_rate)
    t2 = time.perf_counter()
    files = _write_outputs(path, out_dir, methods, rate, rec.rendered, fmts)
    t3 = time.perf_counter()
    first, last = rec.first, rec.last
    session = max(0.0, last - first) if math.isfinite(first) else 0.0
    total = t3 - t0
    result = {
        "path": str(path),
        "rate": rate,
        "render_rate": render_rate,
        "methods": methods,
        "delay_s": {m: float(np.median(d)) if d else math.nan for m, d in rec.delays.items()},
        "session_s": session,
        "streams": len(streams),
        "frames_rendered": rec.frames * len(methods),
        "files": files,
        "qoe": summarize(g for m in methods for g in rec.qoe[m]),
        "objects": _objects_report(data.objects, streams, window),
        "timing": {
            "read_s": t1 - t0,
            "reconstruct_s": t2 - t1,
            "write_s": t3 - t2,
            "total_s": total,
            "speedup": session / total if total > 0 else math.inf,
        },
    }
    if "npz" in fmts or "csv" in fmts:
        assert out_dir is not None
        summary = Path(out_dir) / f"{recording_stem(path)}.replay.{rate:g}hz.json"
        summary.write_text(json.dumps(result, indent=1, default=float) + "\n")
    return result


# -- synthetic sessions and the benchmark ----------------------------------------------------


# send, arrival, capture, poses, velocities of one synthetic user's updates
_SynthUpdates = tuple[F64, F64, F64, NDArray[np.float32], NDArray[np.float16] | None]


def _synth_user(
    tr: Trace,
    rng: np.random.Generator,
    *,
    rate: float,
    duration: float,
    start: float,
    velocities: bool,
) -> tuple[_SynthUpdates, float]:
    """One bot's updates from trace ``tr`` and the server time of trace time 0.

    Draws from ``rng``: the send phase, the offset into the trace, then the
    arrival delays (in that order).
    """
    phase = float(rng.uniform(0.0, 1.0 / rate))
    room_left = max(0.0, tr.duration - duration)
    offset = float(rng.uniform(0.0, room_left)) if room_left > 0 else 0.0
    anchor = start + phase - offset - float(tr.times[0])  # server time of trace time 0
    n = math.floor(duration * rate)
    send = start + phase + np.arange(n) / rate
    idx = np.searchsorted(tr.times, send - anchor, side="right") - 1
    idx = np.clip(idx, 0, tr.times.size - 1)
    fresh = np.ones(idx.shape, dtype=bool)
    fresh[1:] = idx[1:] != idx[:-1]
    send, idx = send[fresh], idx[fresh]
    arrival = send + rng.uniform(0.005, 0.020, send.size)
    capture = anchor + tr.times[idx]
    vel: NDArray[np.float16] | None = None
    if velocities:
        vel = tr.causal_velocities()[idx].astype(np.float16)
    return (send, arrival, capture, tr.poses[idx].astype(np.float32), vel), anchor


def _synth_join(u: int, label: str) -> dict[str, Any]:
    """The presence join of synthetic bot ``u``."""
    return {
        "kind": "join",
        "user": u + 1,
        "name": f"bot{u}",
        "label": label,
        "streams": {d: int(3 * u + j) for j, d in enumerate(DEVICE_NAMES)},
        "rate": 15.0,
    }


def _record_updates(rec: SessionRecorder, per_user: list[_SynthUpdates], start: float) -> float:
    """Record all users' updates in arrival order; returns the last arrival (or ``start``)."""
    ids = np.arange(3, dtype=np.uint16)
    # All users' updates in arrival order, as the server would tap them.
    user_of = np.concatenate([np.full(p[0].size, u) for u, p in enumerate(per_user)])
    row_of = np.concatenate([np.arange(p[0].size) for p in per_user])
    arrivals = np.concatenate([p[1] for p in per_user])
    order = np.argsort(arrivals, kind="stable")
    for k in order.tolist():
        u, r = int(user_of[k]), int(row_of[k])
        _send, arr, cap, poses, vel = per_user[u]
        rec.record_update(
            u + 1,
            r,
            float(arr[r]),
            ids + 3 * u,
            np.full(3, cap[r]),
            poses[r],
            None if vel is None else vel[r],
        )
    return float(arrivals.max()) if arrivals.size else start


def synthesize_recording(
    directory: str | os.PathLike[str],
    *,
    users: int = 20,
    rate: float = 30.0,
    duration: float = 60.0,
    traces: str = "traces:sample",
    room: str = "synthetic",
    name: str | None = None,
    start: float = 1000.0,
    seed: int = 0,
    velocities: bool = False,
    spawn: str = "none",
) -> Path:
    """Record a session of ``users`` bots playing real traces; returns the ``.mcap`` path.

    ``spawn``: a layout of :mod:`scenarios.spawn` (``circle``, ``grid``, ...) that
    stands user ``u`` on point ``u``, as ``posecast bots --spawn`` does.

    With ``velocities`` the updates are of the velocity variant, carrying the
    causal velocities a tracker could report at each capture
    (:meth:`Trace.causal_velocities`, rounded to float16 as on the wire).

    Bot ``u`` plays trace ``u % len(traces)`` (from a seeded offset into it),
    publishing head, left and right at ``rate`` Hz: at each send time the newest
    trace sample (capture time = that sample's time on the server clock), as the
    live bots do. Arrivals are 5-20 ms after sending. Every update goes through
    :class:`SessionRecorder` (a queue big enough that none is lost), with a
    presence join per user whose label is the motion label live bots use.
    """
    files = find_traces(traces)
    loaded = [load_trace(f) for f in files]
    rng = np.random.default_rng(seed)
    per_user: list[_SynthUpdates] = []
    joins = []
    points = layout_points(spawn, users)
    for u in range(users):
        tr = loaded[u % len(loaded)].select(DEVICE_NAMES)
        at = None if points is None else placement_for(loaded[u % len(loaded)], points[u])
        updates, anchor = _synth_user(
            place(tr, at), rng, rate=rate, duration=duration, start=start, velocities=velocities
        )
        per_user.append(updates)
        spec = replace(MotionSpec.for_trace(files[u % len(files)], anchor), placement=at)
        joins.append(_synth_join(u, spec.label()))
    total = sum(p[0].size for p in per_user)
    rec = SessionRecorder.open(
        directory,
        room,
        name=name or f"{room}-{users}u-{duration:g}s",
        clock=lambda: start,
        wall_clock=lambda: 0.0,
        queue_size=total + len(joins) + 16,
    )
    for j in joins:
        rec.record_presence(j, time=start)
    end = _record_updates(rec, per_user, start)
    return rec.close(time=end)


def bench_replay(
    users: int = 20,
    send_rate: float = 30.0,
    duration: float = 60.0,
    rate: float = 10.0,
    methods: Sequence[str] = _METHODS,
    render_rate: float = DEFAULT_RENDER_RATE,
    directory: str | os.PathLike[str] | None = None,
    echo: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Time :func:`replay_offline` on a synthesised session and print the speed-up.

    The session: ``users`` bots x 3 streams x ``send_rate`` Hz x ``duration`` s
    from the dev traces. Replayed at ``rate`` Hz, rendered at ``render_rate``,
    with one method and with all ``methods``, writing nothing, NPZ, and NPZ + CSV.
    Figures only: the machine may be busy with other work.
    """
    with tempfile.TemporaryDirectory(prefix="posecast-bench-") as tmp:
        base = Path(directory) if directory is not None else Path(tmp)
        t = time.perf_counter()
        path = synthesize_recording(base, users=users, rate=send_rate, duration=duration)
        synth_s = time.perf_counter() - t
        size = path.stat().st_size
        echo(
            f"synthesised {users} users x 3 streams x {send_rate:g} Hz x {duration:g} s"
            f" ({size / 1e6:.1f} MB) in {synth_s:.2f} s"
        )
        runs = []
        for ms in ([methods[-1]], list(methods)):
            for formats in ((), ("npz",), ("npz", "csv")):
                res = replay_offline(path, ms, rate, base / "out", render_rate, formats=formats)
                tm = res["timing"]
                label = "+".join(formats) or "no files"
                echo(
                    f"replay {','.join(ms)} at {rate:g} Hz -> {render_rate:g} Hz, {label}:"
                    f" {tm['total_s']:.3f} s (read {tm['read_s']:.3f}, reconstruct+QoE"
                    f" {tm['reconstruct_s']:.3f}, write {tm['write_s']:.3f})"
                    f" = {tm['speedup']:.0f}x real time"
                )
                runs.append(
                    {
                        "methods": ms,
                        "formats": list(formats),
                        "session_s": res["session_s"],
                        "frames_rendered": res["frames_rendered"],
                        **tm,
                    }
                )
        return {
            "users": users,
            "send_rate": send_rate,
            "duration": duration,
            "rate": rate,
            "render_rate": render_rate,
            "file_bytes": size,
            "synthesise_s": synth_s,
            "runs": runs,
        }


if __name__ == "__main__":  # python -m posecast.recorder.replay: the benchmark
    bench_replay()
