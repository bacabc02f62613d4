"""Table 1's receiver running-time bench covers velocity methods.

``motor-hermite`` is benched on the velocity variant of the snapshots (12 B
more a pose), its buffers keep the decoded velocities, and the report gives it
a running time and a running-time saving like every other method.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from posecast.protocol import VELOCITY_BYTES, decode_message, frame_size
from posecast.protocol.poses import Snapshot
from posecast.scenarios.table1 import (
    _prepare_receiver,
    keyframe_velocities,
    receiver_cpu_times,
    run_table1,
)
from posecast.scenarios.traces import load_trace

#: What the velocity variant adds to a 6-pose snapshot: 12 B a pose, and framing.
EXTRA_BYTES = frame_size(6, velocities=True) - frame_size(6)
assert EXTRA_BYTES >= 6 * VELOCITY_BYTES


def _snapshots(frames: list[bytes]) -> list[Snapshot]:
    out = []
    for f in frames:
        snap = decode_message(f)
        assert isinstance(snap, Snapshot)
        out.append(snap)
    return out


def test_velocity_bench_snapshots_carry_the_sources_keyframe_velocities(
    dev_trace_path: Path,
) -> None:
    """Same poses as the plain bench, plus the float16 velocities of the same samples."""
    trace = load_trace(dev_trace_path).window(20.0, 30.0)
    plain = _prepare_receiver(12.0, 6, 0.5, 90.0, trace)
    with_v = _prepare_receiver(12.0, 6, 0.5, 90.0, trace, velocities=True)
    assert with_v.send_times == plain.send_times and with_v.render_times == plain.render_times
    vel = keyframe_velocities(trace)
    idx = (np.arange(len(plain.frames)) / 12.0 * trace.native_rate).astype(int)
    assert np.abs(vel[idx[1:]]).min(axis=-1).max() > 0  # real motion, not zeros
    for k, (a, b) in enumerate(
        zip(_snapshots(plain.frames), _snapshots(with_v.frames), strict=True)
    ):
        assert a.velocities is None and b.velocities is not None
        np.testing.assert_array_equal(a.poses, b.poses)
        cols = np.arange(6) % 3
        np.testing.assert_array_equal(b.velocities.astype(np.float64), vel[idx[k], cols])
        assert len(with_v.frames[k]) - len(plain.frames[k]) == EXTRA_BYTES


def test_receiver_cpu_times_bench_velocity_methods_on_velocity_frames() -> None:
    """motor-hermite gets its own velocity-frame run; the others share the plain one."""
    configs = [("soa", 10.0), ("motor-hermite", 10.0), ("motor-lerp", 10.0), ("motor-hermite", 5.0)]
    out = receiver_cpu_times(configs, streams=6, seconds=0.5, repeats=1)
    assert set(out) == set(configs)
    for (_, rate), c in out.items():
        assert c["snapshots"] == int(0.5 * rate) + 1 and c["frames"] == 45 and c["streams"] == 6
        assert c["decode_s"] > 0 and c["render_s"] > 0
    soa, hermite = out[("soa", 10.0)], out[("motor-hermite", 10.0)]
    assert hermite["snapshot_bytes"] - soa["snapshot_bytes"] == EXTRA_BYTES
    assert out[("motor-lerp", 10.0)]["snapshot_bytes"] == soa["snapshot_bytes"]


def test_report_gives_velocity_methods_a_running_time(dev_trace_path: Path) -> None:
    """Every tier row has a running time for motor-hermite and, at its equal rate, a saving."""
    method = "motor-hermite"
    trace = load_trace(dev_trace_path).window(20.0, 32.0)
    report = run_table1(
        [trace],
        rates=[5, 10, 15],
        methods=[method],
        link=False,
        frontier=False,
        plots=False,
        bench_seconds=0.2,
        bench_repeats=1,
    )
    saw_saving = False
    for row in report["tiers"]:
        times = row["running_time_s"][method]
        at_soa = times["at_soa_rate"]
        assert at_soa["rate"] == row["soa_rate"] and at_soa["total_s"] > 0
        assert (
            at_soa["snapshot_bytes"] > row["running_time_s"]["soa"]["at_soa_rate"]["snapshot_bytes"]
        )
        r = row["equal_qoe_rate"][method]
        saving = row["running_time_saving_pct"][method]
        if r is None:
            assert saving is None and times["at_equal_rate"] is None
        else:
            assert times["at_equal_rate"]["rate"] == r
            assert saving is not None and np.isfinite(saving)
            saw_saving = True
    assert saw_saving
