"""The receiver's running time: CPU time to decode snapshots and render every stream.

:func:`receiver_cpu_times` replays what the live client does on the real code
paths; :func:`bench_tier_rows` measures every configuration the Table 1 rows
need in one round-robin run and adds the running times and savings to them.
"""

from __future__ import annotations

import gc
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from posecast import interp
from posecast.client.buffers import StreamBuffer
from posecast.client.render import render_buffers
from posecast.protocol import decode_message, encode_snapshot
from posecast.protocol.poses import Snapshot
from posecast.scenarios.table1.common import (
    DEFAULT_ROOM_POSES,
    Progress,
    keyframe_velocities,
    saving_pct,
)
from posecast.scenarios.traces import Trace

#: ``{(method, rate): {figure: value}}``, as :func:`receiver_cpu_times` returns it.
CpuTimes = dict[tuple[str, float], dict[str, float]]


@dataclass
class _ReceiverRun:
    """Encoded snapshots and the render schedule of one bench configuration."""

    frames: list[bytes]
    send_times: list[float]
    render_times: list[float]
    delay: float


def _prepare_receiver(
    rate: float,
    streams: int,
    seconds: float,
    render_hz: float,
    source: Trace | None,
    velocities: bool = False,
) -> _ReceiverRun:
    """Snapshots at ``rate`` (the velocity variant with ``velocities``) and the render times."""
    n_snap = math.floor(seconds * rate + 1e-9) + 1
    n_frames = round(seconds * render_hz)
    if source is None:
        t = np.arange(n_snap) / rate
        poses = np.zeros((n_snap, 3, 7))
        poses[..., 0] = np.sin(t)[:, None]
        poses[..., 3] = 1.0
        vel = np.zeros((n_snap, 3, 6))
        vel[..., 0] = np.cos(t)[:, None]  # d/dt of the x above
    else:
        idx = np.arange(n_snap) / rate * source.native_rate
        idx = np.minimum(idx.astype(int), len(source.times) - 1)
        poses = source.poses[idx]
        vel = keyframe_velocities(source)[idx] if velocities else np.zeros((*poses.shape[:2], 6))
    users = np.repeat(np.arange(streams // 3 + 1), 3)[:streams].astype(np.uint16)
    sids = np.tile(np.arange(3), streams // 3 + 1)[:streams].astype(np.uint16)
    cols = np.arange(streams) % poses.shape[1]
    frames = [
        encode_snapshot(
            k,
            k / rate,
            users,
            sids,
            np.full(streams, k / rate - 0.005),
            poses[k, cols],
            vel[k, cols] if velocities else None,
        )
        for k in range(n_snap)
    ]
    delay = 1.0 / rate + 0.02
    return _ReceiverRun(
        frames,
        (np.arange(n_snap) / rate).tolist(),
        (np.arange(n_frames) / render_hz + delay).tolist(),
        delay,
    )


def _run_receiver(run: _ReceiverRun, method: str) -> tuple[float, float]:
    """One pass: CPU seconds spent decoding and rendering.

    Velocity snapshots' velocities go into the buffers with their poses.
    """
    methods = [method]
    buffers: dict[tuple[int, int], StreamBuffer] = {}
    decode = render = 0.0
    nxt, n_snap = 0, len(run.frames)
    for t_now in run.render_times:
        c0 = time.process_time()
        floor = t_now - run.delay
        while nxt < n_snap and run.send_times[nxt] <= t_now:
            snap = decode_message(run.frames[nxt])
            assert isinstance(snap, Snapshot)
            u, s, caps, ps = snap.users, snap.streams, snap.capture_times, snap.poses
            vs = None if snap.velocities is None else snap.velocities.astype(np.float64)
            for i in range(len(snap)):
                key = (int(u[i]), int(s[i]))
                buf = buffers.get(key)
                if buf is None:
                    buf = buffers[key] = StreamBuffer()
                buf.push(float(caps[i]), np.array(ps[i]), floor, None if vs is None else vs[i])
            nxt += 1
        c1 = time.process_time()
        render_buffers(list(buffers.values()), floor, methods)
        c2 = time.process_time()
        decode += c1 - c0
        render += c2 - c1
    return decode, render


def receiver_cpu_times(
    configs: Sequence[tuple[str, float]],
    *,
    streams: int = DEFAULT_ROOM_POSES,
    seconds: float = 1.0,
    render_hz: float = 90.0,
    repeats: int = 11,
    source: Trace | None = None,
) -> dict[tuple[str, float], dict[str, float]]:
    """The receiver's CPU time for each ``(method, rate)`` configuration.

    Replays what the live client does, on the real code paths: every snapshot
    (``streams`` poses, encoded beforehand with ``protocol.encode_snapshot``)
    is decoded with ``protocol.decode_message`` as it arrives and its poses are
    pushed into one :class:`~client.buffers.StreamBuffer` per stream; every
    render frame interpolates all streams with the method in one batched call
    (:func:`~client.render.render_buffers`). Velocity methods
    (``needs_velocity``) get the velocity variant of the snapshots (12 B more a
    pose; the source's :func:`keyframe_velocities`) and their buffers keep the
    decoded velocities. The number of rendered frames depends only on
    ``seconds`` and ``render_hz``, not on the rate.

    CPU time is ``time.process_time`` (garbage collection paused). The
    configurations run round-robin, ``repeats`` times each, so that load from
    other processes hits all of them alike. Returned per configuration, in
    seconds: ``decode_s``, ``render_s`` and ``total_s`` as the **median** over
    the repeats (what savings are computed from), ``best_total_s`` (the
    smallest), the counts of snapshots, frames and streams, and the mean
    ``snapshot_bytes`` of a snapshot frame. The median,
    not the best, is the headline because on a loaded machine the best of a
    few runs varied by a third between configurations doing identical render
    work, while the median stayed within a few per cent.
    """

    def run_key(config: tuple[str, float]) -> tuple[float, bool]:
        return config[1], interp.info(config[0]).needs_velocity

    runs = {
        key: _prepare_receiver(key[0], streams, seconds, render_hz, source, key[1])
        for key in sorted({run_key(c) for c in configs})
    }
    samples: dict[tuple[str, float], list[tuple[float, float]]] = {c: [] for c in configs}
    was_enabled = gc.isenabled()
    gc.disable()
    try:
        for _ in range(max(1, repeats)):
            for method, rate in samples:
                samples[(method, rate)].append(_run_receiver(runs[run_key((method, rate))], method))
    finally:
        if was_enabled:
            gc.enable()
    out: dict[tuple[str, float], dict[str, float]] = {}
    for c, v in samples.items():
        a = np.asarray(v)
        run = runs[run_key(c)]
        out[c] = {
            "decode_s": float(np.median(a[:, 0])),
            "render_s": float(np.median(a[:, 1])),
            "total_s": float(np.median(a.sum(axis=1))),
            "best_total_s": float(a.sum(axis=1).min()),
            "snapshots": float(len(run.frames)),
            "snapshot_bytes": float(np.mean([len(f) for f in run.frames])),
            "frames": float(len(run.render_times)),
            "streams": float(streams),
        }
    return out


def receiver_cpu_time(method: str, rate: float, **kwargs: Any) -> dict[str, float]:
    """:func:`receiver_cpu_times` for one configuration."""
    return receiver_cpu_times([(method, rate)], **kwargs)[(method, rate)]


# ---------------------------------------------------------------- the Table 1 stage


def bench_configs(
    tier_rows: Sequence[Mapping[str, Any]], meths: Sequence[str]
) -> list[tuple[str, float]]:
    """Every ``(method, rate)`` the rows need: SoA's rate, the equal-QoE and paper rates."""
    configs: list[tuple[str, float]] = []
    for row in tier_rows:
        configs += [(m, float(row["soa_rate"])) for m in meths]
        configs += [(m, float(r)) for m, r in row["equal_qoe_rate"].items() if r is not None]
        if "paper" in row:
            configs += [(m, float(row["paper"]["ga_rate"])) for m in row["reproduced"]]
    return list(dict.fromkeys(configs))


def bench_tier_rows(
    tier_rows: Sequence[Mapping[str, Any]],
    meths: Sequence[str],
    source: Trace,
    *,
    room_poses: int,
    seconds: float,
    repeats: int,
    progress: Progress | None = None,
) -> list[dict[str, Any]]:
    """The rows with the receiver's running time (every configuration measured in one go)."""
    if progress is not None:
        progress("running time", 0, 1)
    cpu = receiver_cpu_times(
        bench_configs(tier_rows, meths),
        streams=room_poses,
        seconds=seconds,
        repeats=repeats,
        source=source,
    )
    return [with_running_time(row, cpu, meths) for row in tier_rows]


def with_running_time(
    row: Mapping[str, Any], cpu: CpuTimes, meths: Sequence[str]
) -> dict[str, Any]:
    """A copy of a tier row with its running times and running-time savings."""
    out = dict(row)
    ref_rate = float(row["soa_rate"])
    base = cpu[("soa", ref_rate)]
    eq: Mapping[str, int | None] = row["equal_qoe_rate"]
    out["running_time_s"] = {
        m: {
            "at_soa_rate": {"rate": row["soa_rate"], **cpu[(m, ref_rate)]},
            "at_equal_rate": (None if (r := eq[m]) is None else {"rate": r, **cpu[(m, float(r))]}),
        }
        for m in meths
    }
    out["running_time_saving_pct"] = {
        m: (
            None
            if (r := eq[m]) is None
            else saving_pct(cpu[(m, float(r))]["total_s"], base["total_s"])
        )
        for m in meths
    }
    if "paper" in row:
        # Granting the paper's rates: what would the receiver save then?
        r_p = float(row["paper"]["ga_rate"])
        out["running_time_saving_at_paper_rate_pct"] = {
            m: saving_pct(cpu[(m, r_p)]["total_s"], base["total_s"]) for m in row["reproduced"]
        }
        for m in row["reproduced"]:
            out["running_time_s"][m]["at_paper_rate"] = {
                "rate": row["paper"]["ga_rate"],
                **cpu[(m, r_p)],
            }
    return out
