"""Table 1 with the compact codec: snapshot sizes as an observer receives them, through the
public codec API, and bytes/s at equal QoE per codec."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from posecast.protocol.codec import DEFAULT_VOLUME
from posecast.protocol.codec_relay import decode_relay_snapshot, snapshot_counts
from posecast.scenarios.network import frame_size, wire_bytes
from posecast.scenarios.table1 import keyframe_velocities, run_table1
from posecast.scenarios.table1.codec_bytes import (
    KEY_INTERVAL_S,
    compact_snapshot_bytes,
    payload_wire_bytes,
)
from posecast.scenarios.traces import Trace, load_trace


@pytest.fixture(scope="module")
def traces(sample_dir: Path) -> list[Trace]:
    """Two real 20 s windows of the bundled sample."""
    files = sorted(sample_dir.glob("*.csv.gz"))[:2]
    return [load_trace(f).window(5.0, 25.0) for f in files]


def test_payload_framing_matches_the_raw_wire_model() -> None:
    """A payload is framed like a raw snapshot: websocket header plus TCP/IP per segment."""
    for n in (1, 16, 48, 200):
        assert payload_wire_bytes(frame_size(n, "snapshot")) == wire_bytes(n)


def test_observer_decodes_every_frame_and_gets_the_room_within_the_codec_error(
    traces: list[Trace],
) -> None:
    """Every frame is a relay snapshot that decodes against the observer's own baselines,
    holds only the room's streams, and its poses are the sampled ones within half a step;
    a key snapshot opens the run and comes at least every 2 s."""
    baselines: dict[tuple[int, int], list[int]] = {}
    seen: list[tuple[bool, int]] = []

    def check(data: bytes, poses: np.ndarray) -> None:
        frame = decode_relay_snapshot(data, DEFAULT_VOLUME, baselines)
        delta = _counts(data)[1] > 0
        frame.remember(baselines)
        seen.append((delta, len(frame)))
        assert set(frame.users) <= set(range(1, 17))
        decoded, _ = frame.arrays()
        np.testing.assert_allclose(decoded[:, :3], poses[:, :3], atol=2.5e-4 + 1e-6)

    size = compact_snapshot_bytes(traces, 10, on_frame=check)
    assert size.snapshots == len(seen) > 0
    keys = [i for i, (delta, _) in enumerate(seen) if not delta]
    assert keys[0] == 0 and np.diff(keys).max() <= KEY_INTERVAL_S * 10
    assert size.poses_per_snapshot == pytest.approx(np.mean([n for _, n in seen]))
    assert size.key_payload_bytes > size.delta_payload_bytes


def _counts(data: bytes) -> tuple[int, int]:
    """``(n_key, n_delta)`` from a relay snapshot's header (after tick and base time)."""
    return snapshot_counts(data)[2:]


def test_velocity_variant_costs_more_and_rates_share_the_key_cost(traces: list[Trace]) -> None:
    """The velocity variant is bigger at the same rate; a higher rate has smaller deltas."""
    vel = [keyframe_velocities(tr) for tr in traces]
    plain10 = compact_snapshot_bytes(traces, 10)
    plain30 = compact_snapshot_bytes(traces, 30)
    vel10 = compact_snapshot_bytes(traces, 10, velocities=vel)
    assert vel10.wire_bytes > plain10.wire_bytes
    assert plain30.delta_payload_bytes < plain10.delta_payload_bytes
    assert plain10.bytes_per_pose == pytest.approx(plain10.wire_bytes / 48)
    assert plain10.wire_bytes < wire_bytes(48)


@pytest.fixture(scope="module")
def report(traces: list[Trace]) -> dict[str, Any]:
    out: dict[str, Any] = run_table1(
        traces,
        rates=range(8, 31),
        methods=["dq-slerp", "soa-hermite"],
        link=False,
        bench=False,
        plots=False,
        frontier_rates=[10, 15, 20, 30],
    )
    return out


def test_bytes_per_second_at_equal_qoe_per_codec(report: dict[str, Any]) -> None:
    """Raw is rate x the fixed raw snapshot; compact is rate x the measured compact
    snapshot of the method's variant at that rate; savings are against raw SoA."""
    cx = report["codecs"]
    for t in cx["tiers"]:
        ref = t["soa_rate"] * cx["raw_wire_bytes"]["soa"]
        assert t["reference_bytes_per_s"] == ref
        for m, r in t["equal_qoe_rate"].items():
            if r is None:
                assert t["bytes_per_s"]["compact"][m] is None
                continue
            assert t["bytes_per_s"]["raw"][m] == r * cx["raw_wire_bytes"][m]
            variant = "velocity" if m == "soa-hermite" else "plain"
            size = cx["sizes"][variant][str(r)]["wire_bytes"]
            assert t["bytes_per_s"]["compact"][m] == pytest.approx(r * size, rel=1e-6)
            saving = t["saving_vs_raw_soa_pct"]["compact"][m]
            assert saving == pytest.approx(100 * (1 - r * size / ref), abs=1e-4)


def test_headline_is_the_cheapest_match_of_raw_soa_at_30_hz(report: dict[str, Any]) -> None:
    """Every listed configuration matches raw SoA@30 at no more latency, and the best of
    a codec is the cheapest of them."""
    hl = report["codecs"]["headline"]
    ref = hl["reference"]
    for entry in hl["codecs"].values():
        per = entry["per_method"]
        for p in per.values():
            assert p["headline_mm"] <= ref["headline_mm"] and p["latency_ms"] <= ref["latency_ms"]
        assert entry["best"]["bytes_per_s"] == min(p["bytes_per_s"] for p in per.values())
    assert "## Bytes/s at equal QoE, raw and compact codec" in _markdown(report)


def _markdown(report: dict[str, Any]) -> str:
    from posecast.scenarios.table1.codec_bytes import codec_markdown

    return "\n".join(codec_markdown(report))


def test_unknown_codec_is_refused() -> None:
    """A codec name other than raw and compact fails before any work."""
    with pytest.raises(ValueError, match="unknown codec"):
        run_table1(["synthetic:screw"], rates=[10], codecs=["zip"])


def test_posecast_table1_codecs_flag(dev_trace_path: Path, tmp_path: Path) -> None:
    """--codecs raw leaves the codec prices out; an unknown codec is one line, exit 2."""
    import json

    from typer.testing import CliRunner

    from posecast.cli import app

    runner = CliRunner()
    args = ["table1", "--traces", str(dev_trace_path), "--rates", "10,20,30", "--no-link"]
    args += ["--no-bench", "--no-plots", "--no-frontier", "--out", str(tmp_path)]
    res = runner.invoke(app, [*args, "--codecs", "raw"])
    assert res.exit_code == 0, res.output
    assert "codecs" not in json.loads((tmp_path / "table1.json").read_text())
    res = runner.invoke(app, [*args, "--codecs", "raw,zip"])
    assert res.exit_code == 2 and "unknown codec(s) ['zip']" in res.output


def test_room_volume_holds_motions_that_leave_the_default() -> None:
    """The default volume where it holds the traces; grown to whole metres where not."""
    from posecast.protocol.codec import DEFAULT_VOLUME
    from posecast.scenarios.synthetic import synthetic_motion
    from posecast.scenarios.table1.codec_bytes import room_volume

    calm = synthetic_motion("look-around", 0, duration_s=5.0)
    assert room_volume([calm]) is DEFAULT_VOLUME
    high = Trace(calm.name, calm.times, calm.poses.copy(), calm.streams)
    high.poses[3, 0, 1] = 4.2
    vol = room_volume([high])
    assert vol.hi[1] == 5.0 and vol.lo == DEFAULT_VOLUME.lo
    assert compact_snapshot_bytes([high], 10, room_poses=3, volume=vol).snapshots > 0
