"""QoE through the compact codec: hands p95 tip error within 1 mm of raw, 5-30 Hz.

Each trace's keyframes (and, for velocity methods, their velocities) go through
the codec's quantisers (``dequantise(quantise(x))``: what a compact receiver
renders) and are scored against the untouched native samples, beside the same
keyframes as raw float32, ideal network (``scenarios.compare``'s model). The
capture-time rounding (at most 0.5 ms a hop) is not applied here.

Run with figures: ``pytest -s tests/scenarios/test_codec_qoe.py``; the full eval
set when present (``POSECAST_QOE_SPLIT=traces:eval``, else traces:sample).
"""

from __future__ import annotations

import os

import numpy as np
import pytest
from numpy.typing import NDArray

from posecast.interp import info
from posecast.protocol.codec import DEFAULT_VOLUME, dequantise, quantise
from posecast.scenarios.qoe import evaluate_group, ideal_delay, ideal_log, summarize
from posecast.scenarios.traces import Trace, find_traces, load_trace
from posecast.scenarios.velocity_sources import source_velocities

RATES = (5.0, 10.0, 15.0, 20.0, 30.0)
METHODS = ("soa", "motor-hermite")


def _coded(
    poses: NDArray[np.float64], vel: NDArray[np.float64] | None
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    n, s = poses.shape[:2]
    flat_vel = None if vel is None else vel.reshape(n * s, 6)
    p, v = dequantise(quantise(poses.reshape(n * s, 7), DEFAULT_VOLUME, flat_vel), DEFAULT_VOLUME)
    back_v = None if v is None else v.astype(np.float64).reshape(n, s, 6)
    return p.astype(np.float64).reshape(n, s, 7), back_v


def _groups(
    trace: Trace, poses: NDArray[np.float64], vel: NDArray[np.float64] | None
) -> dict[tuple[float, str], object]:
    out: dict[tuple[float, str], object] = {}
    for rate in RATES:
        log = ideal_log(trace.times, poses, rate, vel)
        for m in METHODS:
            delay = ideal_delay(rate, trace.native_rate, info(m).lookahead)
            out[(rate, m)] = evaluate_group(trace, log, delay, [m])
    return out


def test_hands_p95_through_the_codec_is_within_1_mm_of_raw() -> None:
    """Pooled over the split's traces, per rate and method (as Table 1 pools)."""
    split = os.environ.get("POSECAST_QOE_SPLIT", "traces:sample")
    raw: dict[tuple[float, str], list[object]] = {}
    coded: dict[tuple[float, str], list[object]] = {}
    for tr in (load_trace(p) for p in find_traces(split)):
        vel = source_velocities(tr)
        for key, g in _groups(tr, tr.poses, vel).items():
            raw.setdefault(key, []).append(g)
        coded_poses, coded_vel = _coded(tr.poses, vel)
        assert np.abs(coded_poses[..., :3] - tr.poses[..., :3]).max() <= 0.00025 + 1e-6
        for key, g in _groups(tr, coded_poses, coded_vel).items():
            coded.setdefault(key, []).append(g)
    lines = [f"hands p95 tip error (mm), {split}, pooled: raw -> compact (difference)"]
    worst = {m: 0.0 for m in METHODS}
    for key in raw:
        r = summarize(raw[key])[key[1]]["hands"]["tip_p95_mm"]  # type: ignore[arg-type]
        c = summarize(coded[key])[key[1]]["hands"]["tip_p95_mm"]  # type: ignore[arg-type]
        worst[key[1]] = max(worst[key[1]], abs(c - r))
        lines.append(f"  {key[0]:4g} Hz {key[1]:13s} {r:7.2f} -> {c:7.2f} ({c - r:+.3f})")
    lines.append("worst difference: " + ", ".join(f"{m} {w:.3f} mm" for m, w in worst.items()))
    print("\n" + "\n".join(lines))
    # Plain poses: within 1 mm. Velocity methods also carry the quantised (and at
    # +-64 clamped) velocities: reported, held to 3 mm.
    assert 0.0 < worst["soa"] <= 1.0
    assert worst["motor-hermite"] <= 3.0


@pytest.mark.parametrize("rate", [10.0])
def test_the_coded_keyframes_differ_from_raw_only_within_the_codec_bounds(rate: float) -> None:
    tr = load_trace(find_traces("traces:sample")[0])
    coded, _ = _coded(tr.poses, None)
    q0, q1 = tr.poses[..., 3:], coded[..., 3:]
    q0 = q0 / np.linalg.norm(q0, axis=-1, keepdims=True)  # the traces' are unit to 1e-6
    dots = np.abs(np.einsum("...i,...i->...", q0, q1)).clip(0.0, 1.0)
    worst = float(np.degrees(2 * np.arccos(dots)).max())
    print(f"\nrotation error over every native sample: max {worst:.4f} deg")
    # The bound (0.05 deg). The docstring's 0.0343 deg worst case is too low:
    # 0.0376 deg was found here, over every native sample of traces:sample.
    assert worst <= 0.05
