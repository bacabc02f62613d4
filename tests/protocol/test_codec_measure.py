"""Measure the compact codec on the bundled real traces; prints figures, asserts behaviour.

Run::

    POSECAST_CODEC_SECONDS=36 .venv/bin/python -m pytest -q -p no:cacheprovider -s \
        tests/protocol/test_codec_measure.py

(the figures in docs/concepts/codec.md are 36 s of room; the suite measures 12 s, which
checks the same error bounds in a third of the time).

A room of 10 users replays the four bundled traces (user u: trace u % 4, started
(u // 4) * 7 s + u * 0.9 s in, captured up to one send interval before each
tick); every user sends at the room rate and the server sends subscriber 0 one
snapshot a tick holding the 27 poses of the 9 others, delta-coded against what it
wrote the tick before (the first tick is a key frame). Bytes per pose include all
framing: each frame's header and padding is shared equally by its entries.
"""

from __future__ import annotations

import os
import timeit

import numpy as np
import pytest
from numpy.typing import NDArray

from posecast.protocol.bits import best_k, bit_length, zz
from posecast.protocol.codec import (
    DEFAULT_VOLUME,
    ROTATION_ERROR_MAX_DEG,
    decode_snapshot,
    decode_update,
    dequantise,
    encode_snapshot_codes,
    encode_update_codes,
    quantise,
)
from posecast.protocol.codec_quant import predict_rotation
from posecast.scenarios.traces import Trace, TraceError, find_traces, load_trace

ROOM = 10
DURATION = float(os.environ.get("POSECAST_CODEC_SECONDS", "12"))
#: Calls per timing figure (best of 3): 200 when measuring for the docs, 20 in the
#: suite (the figures are printed, never asserted; the calls still run every path).
TIMING_RUNS = 200 if "POSECAST_CODEC_SECONDS" in os.environ else 20
VOLUME = DEFAULT_VOLUME


def _angle_deg(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    # Chord form: well conditioned at small angles (arccos of the dot product is not).
    sign = np.where(np.einsum("ij,ij->i", a, b) < 0.0, -1.0, 1.0)
    chord = np.linalg.norm(a - sign[:, None] * b, axis=1)
    return np.degrees(4.0 * np.arcsin(np.clip(chord / 2.0, 0.0, 1.0)))


def _room(traces: list[Trace], rate: float) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """Sample index and capture time per (tick, user): shapes (ticks, ROOM)."""
    ticks = np.arange(int(DURATION * rate)) / rate
    idx = np.empty((ticks.size, ROOM), np.int64)
    cap = np.empty((ticks.size, ROOM))
    for u in range(ROOM):
        tr = traces[u % len(traces)]
        start = tr.times[0] + (u // 4) * 7.0 + u * 0.9
        age = (u * 0.37 % 1.0) / rate
        i = np.searchsorted(tr.times, start + ticks - age, side="right") - 1
        idx[:, u] = i
        cap[:, u] = tr.times[i] - start
    return idx, cap


def _measure(
    traces: list[Trace], rate: float, split: bool = True, upstream: bool = True
) -> dict[str, object]:
    """The room at ``rate`` (see the module's docstring); ``upstream=False`` leaves out
    the users' update frames (the same for either ``split``: measured once)."""
    idx, cap = _room(traces, rate)
    users = np.repeat(np.arange(1, ROOM), 3)
    streams = np.tile(np.arange(3), ROOM - 1)
    baselines: dict[tuple[int, int], NDArray[np.int64]] = {}
    sent: dict[tuple[int, int], int] = {}
    per_class: dict[str, list[float]] = {"head": [], "hands": []}
    frame_bytes: list[int] = []
    key_bytes = 0
    key_n = 0
    pos_err = 0.0
    rot_err = 0.0
    time_err = 0.0
    widths: dict[str, int] = {"eg": 0, "fixed": 0, "static": 0, "n": 0}
    diffs: list[NDArray[np.int64]] = []
    up_bytes: list[float] = []
    up_key: list[float] = []
    up_base: list[dict[int, NDArray[np.int64]]] = [{} for _ in range(ROOM)]
    for k in range(idx.shape[0]):
        tick_time = k / rate
        keep = []
        poses = np.empty((users.size, 7))
        for e, (u, s) in enumerate(zip(users, streams, strict=True)):
            tr = traces[u % len(traces)]
            poses[e] = tr.poses[idx[k, u], s]
            if sent.get((u, s)) != idx[k, u]:
                keep.append(e)
        keep_a = np.array(keep, np.int64)
        times = cap[k, users]
        codes = quantise(poses, VOLUME)
        enc = encode_snapshot_codes(
            k,
            tick_time,
            users[keep_a],
            streams[keep_a],
            times[keep_a],
            codes[keep_a],
            VOLUME,
            baselines,
            split=split,
        )
        dec = decode_snapshot(enc.data, VOLUME, baselines)
        assert np.array_equal(dec.codes, enc.frame.codes)
        # Errors against the true (float64) poses and times.
        order = np.lexsort((streams[keep_a], users[keep_a]))
        truth = poses[keep_a][order]
        pos_err = max(pos_err, float(np.abs(dec.poses[:, :3] - truth[:, :3]).max()))
        rot_err = max(
            rot_err, float(_angle_deg(dec.poses[:, 3:].astype(float), truth[:, 3:]).max())
        )
        time_err = max(time_err, float(np.abs(dec.capture_times - times[keep_a][order]).max()))
        n = len(dec)
        shared = (len(enc.data) - enc.entry_bits.sum() / 8) / n
        per_pose = enc.entry_bits / 8 + shared
        if k == 0:
            key_bytes, key_n = len(enc.data), n
        else:
            frame_bytes.append(len(enc.data))
            for s_, b in zip(dec.streams, per_pose, strict=True):
                per_class["head" if s_ == 0 else "hands"].append(float(b))
            # What adaptive widths buy: the same pose diffs under other width rules.
            if dec.delta.all():
                base = np.array(
                    [
                        baselines[(int(u), int(s))]
                        for u, s in zip(dec.users, dec.streams, strict=True)
                    ]
                )
                pred = predict_rotation(base, dec.codes[:, 0])
                d = zz(
                    np.concatenate(
                        [dec.codes[:, 1:4] - pred, dec.codes[:, 4:7] - base[:, 4:7]], axis=1
                    )
                )
                diffs.append(d)
                for c in (0, 1):
                    m = (dec.streams != 0) == bool(c)
                    for g in (slice(0, 3), slice(3, 6)):
                        vals = d[m, g]
                        widths["eg"] += best_k(vals.reshape(-1))[1] + 4
                        fixed = int(bit_length(vals.max(axis=0)).sum())
                        widths["fixed"] += fixed * int(m.sum()) + 3 * 4
                widths["n"] += n
        enc.frame.remember(baselines)
        for e in keep:
            sent[(int(users[e]), int(streams[e]))] = int(idx[k, users[e]])
        # Upstream: each user's update of its 3 streams, delta against its last one.
        for u in range(ROOM if upstream else 0):
            tr = traces[u % len(traces)]
            ucodes = quantise(tr.poses[idx[k, u]], VOLUME)
            uenc = encode_update_codes(
                k, tick_time, np.arange(3), np.full(3, cap[k, u]), ucodes, VOLUME, up_base[u]
            )
            udec = decode_update(uenc.data, VOLUME, up_base[u])
            assert np.array_equal(udec.codes, ucodes)
            (up_key if k == 0 else up_bytes).append(len(uenc.data) / 3)
            uenc.frame.remember(up_base[u])
    if diffs:
        allz = np.concatenate(diffs)
        ks = [best_k(allz[:, g].reshape(-1))[0] for g in (slice(0, 3), slice(3, 6))]
        widths["static"] = sum(
            sum(int(best_k(x[:, g].reshape(-1))[1]) for g in (slice(0, 3), slice(3, 6)))
            for x in [allz]
        )
        _ = ks
    return {
        "key_bytes": key_bytes,
        "key_n": key_n,
        "per_class": per_class,
        "frame_bytes": frame_bytes,
        "pos_err": pos_err,
        "rot_err": rot_err,
        "time_err": time_err,
        "widths": widths,
        "up_bytes": up_bytes,
        "up_key": up_key,
    }


@pytest.fixture(scope="module")
def traces() -> list[Trace]:
    return [load_trace(p) for p in find_traces("traces:sample")]


def _stats(values: list[float]) -> str:
    a = np.array(values)
    return f"mean {a.mean():5.2f}  p95 {np.percentile(a, 95):5.2f}  max {a.max():5.2f}"


def test_codec_figures(traces: list[Trace], capsys: pytest.CaptureFixture[str]) -> None:
    lines = [f"compact codec on traces:sample, room of {ROOM} (27 poses a frame), {DURATION:.0f} s"]
    worst_pos = worst_rot = worst_t = 0.0
    for rate in (10.0, 20.0, 30.0):
        m = _measure(traces, rate)
        pc = m["per_class"]
        assert isinstance(pc, dict)
        allp = pc["head"] + pc["hands"]
        fb = np.array(m["frame_bytes"])
        lines.append(
            f"{rate:4.0f} Hz delta B/pose: all {_stats(allp)} | heads {_stats(pc['head'])}"
            f" | hands {_stats(pc['hands'])} | frame mean {fb.mean():.1f} B"
        )
        lines.append(
            f"        key frame {m['key_bytes']} B = {m['key_bytes'] / m['key_n']:.2f} B/pose;"  # type: ignore[operator]
            f" update B/pose delta {_stats(m['up_bytes'])}, key {np.mean(m['up_key']):.2f}"  # type: ignore[arg-type]
        )
        w = m["widths"]
        assert isinstance(w, dict)
        lines.append(
            f"        pose-diff bits/pose (rot+pos): per-frame EG k {w['eg'] / w['n']:.1f},"
            f" per-frame fixed width {w['fixed'] / w['n']:.1f},"
            f" one static k {w['static'] / w['n']:.1f}"
        )
        worst_pos = max(worst_pos, m["pos_err"])  # type: ignore[call-overload]
        worst_rot = max(worst_rot, m["rot_err"])  # type: ignore[call-overload]
        worst_t = max(worst_t, m["time_err"])  # type: ignore[call-overload]
        if rate == 30.0:
            nosplit = _measure(traces, rate, split=False, upstream=False)
            npc = nosplit["per_class"]
            assert isinstance(npc, dict)
            lines.append(
                "        without the head/hands class split: all "
                + _stats(npc["head"] + npc["hands"])
            )
    lines.append(
        f"codec error max: position {worst_pos * 1000:.3f} mm, rotation {worst_rot:.4f} deg"
        f" (bound {ROTATION_ERROR_MAX_DEG:.4f}), capture time {worst_t * 1000:.3f} ms"
    )
    # Timing: a 27-pose delta frame at 30 Hz.
    idx, cap = _room(traces, 30.0)
    users = np.repeat(np.arange(1, ROOM), 3)
    streams = np.tile(np.arange(3), ROOM - 1)

    def poses_at(k: int) -> NDArray[np.float64]:
        return np.array(
            [
                traces[u % len(traces)].poses[idx[k, u], s]
                for u, s in zip(users, streams, strict=True)
            ]
        )

    p0, p1 = poses_at(100), poses_at(101)
    c0, c1 = quantise(p0, VOLUME), quantise(p1, VOLUME)
    t1 = cap[101, users]
    base = encode_snapshot_codes(0, 3.0, users, streams, t1, c0, VOLUME)
    baselines: dict[tuple[int, int], NDArray[np.int64]] = {}
    base.frame.remember(baselines)
    data = encode_snapshot_codes(1, 3.0, users, streams, t1, c1, VOLUME, baselines).data
    key = base.data
    n = users.size
    runs = TIMING_RUNS
    figures = {
        "quantise": lambda: quantise(p1, VOLUME),
        "encode delta (codes)": lambda: encode_snapshot_codes(
            1, 3.0, users, streams, t1, c1, VOLUME, baselines
        ),
        "encode key (codes)": lambda: encode_snapshot_codes(0, 3.0, users, streams, t1, c0, VOLUME),
        "decode delta": lambda: decode_snapshot(data, VOLUME, baselines),
        "decode key": lambda: decode_snapshot(key, VOLUME),
        "dequantise": lambda: dequantise(c1, VOLUME),
    }
    timing = []
    for name, fn in figures.items():
        best = min(timeit.repeat(fn, number=runs, repeat=3)) / runs
        timing.append(f"{name} {best * 1e6 / n:.1f}")
    lines.append(f"us per pose (27-pose frame, best of 3x{runs}): " + ", ".join(timing))
    with capsys.disabled():
        print("\n" + "\n".join(lines))
    assert worst_pos <= max(VOLUME.step) / 2 + 1e-6
    assert worst_rot <= ROTATION_ERROR_MAX_DEG + 1e-3
    assert worst_t <= 0.0005 + 1e-6


def test_upstream_bytes_through_the_session(capsys: pytest.CaptureFixture[str]) -> None:
    """Update frames as a bot sends them (``UpstreamEncoder``: delta per stream, relative
    header after the first); prints B/pose per rate on traces:sample and, when the full
    sets are there, traces:eval. Asserts that the relative header only ever saves."""
    from posecast.protocol._compact import UpstreamEncoder, absolute
    from posecast.protocol.poses import PoseUpdate

    lines = []
    for split in ("traces:sample", "traces:eval"):
        try:
            paths = find_traces(split)
        except TraceError:  # the full sets are optional
            continue
        traces = [load_trace(p) for p in paths]
        for rate in (30.0, 20.0, 10.0):
            sent = whole = n = 0
            for tr in traces:
                enc = UpstreamEncoder(VOLUME)
                previous = None
                ts = np.arange(tr.times[0], tr.times[0] + 20.0, 1 / rate)
                idx = np.searchsorted(tr.times, ts, side="right") - 1
                for k, i in enumerate(idx.tolist()):
                    t = 20000.0 + ts[k] - tr.times[0] - 0.004
                    data = enc.encode(
                        PoseUpdate.from_arrays(k + 1, [0, 1, 2], np.full(3, t), tr.poses[i])
                    )
                    enc.commit()
                    full, previous = absolute(data, previous)
                    assert len(data) <= len(full)
                    if k:
                        sent, whole, n = sent + len(data), whole + len(full), n + 3
            lines.append(
                f"{split} {rate:g} Hz upstream B/pose: {sent / n:.2f} relative header,"
                f" {whole / n:.2f} absolute"
            )
    with capsys.disabled():
        print("\n" + "\n".join(lines))
