"""The relay benchmark: a short real run (server + load subprocesses) and its report."""

from __future__ import annotations

import io
import math

import msgpack
import numpy as np
import pytest
from rich.console import Console

from posecast.bench import run_relay_bench, update_template
from posecast.protocol import encode_update

EXPECTED_KEYS = {
    "clients",
    "clients_joined",
    "clients_failed",
    "server_cpu_pct",
    "server_cpu_us_per_pose",
    "load_cpu_pct",
    "latency_p50_ms",
    "latency_p99_ms",
    "relay_p50_ms",
    "relay_p99_ms",
    "tick_lag_p50_ms",
    "tick_lag_p99_ms",
    "snapshots_per_client_s",
    "snapshot_rate_ratio",
    "skips",
    "tick_lag_max_ms_start",
    "tick_lag_max_ms_end",
    "bytes_per_pose",
    "poses_delivered",
    "clients_without_snapshots",
    "steal_pct",
}


def test_update_template_packs_like_encode_update() -> None:
    """The load's re-packed template is byte for byte the protocol's update frame."""
    wire = update_template([4, 5, 6], (0.5, 1.6, 0.0))
    wire["seq"], wire["time"] = 17, 1234.5678
    poses = np.tile([0.5, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0], (3, 1))
    expected = encode_update(17, [4, 5, 6], [1234.5678] * 3, poses, base_time=1234.5678)
    assert msgpack.packb(wire) == expected


def test_relay_bench_smoke() -> None:
    """20 clients in rooms of 5 for 2 s, recorder off then on (both writers): sane figures."""
    out = io.StringIO()
    console = Console(file=out, width=160)
    report = run_relay_bench(
        20,
        5,
        20.0,
        2.0,
        record=True,
        record_writer="both",
        console=console,
        warmup=1.0,
        ramp_rate=100.0,
    )
    assert report.keys() >= EXPECTED_KEYS
    assert report["clients_joined"] == 20 and report["clients_failed"] == 0
    assert report["rooms"] == 4
    assert report["clients_without_snapshots"] == 0
    assert report["clients_without_snapshots_in_window"] == 0
    assert report["poses_delivered"] > 0 and report["snapshots"] > 0
    for key in EXPECTED_KEYS - {"clients"}:
        value = report[key]
        assert isinstance(value, int | float) and math.isfinite(value), key
        assert value >= 0, key
    # Remote poses only: each snapshot carries at most the 4 peers' 3 streams.
    assert report["poses_delivered"] <= 12 * report["snapshots"]
    assert report["latency_p50_ms"] <= report["latency_p99_ms"]
    assert report["server_exit_code"] == 0
    assert report["metrics_ok"]
    text = out.getvalue()
    assert "relay bench" in text and "capture->receipt" in text
    rec = report["recorder"]
    assert rec["files"] == 4  # one recording per room
    assert rec["disk_bytes"] > 0 and 0 < rec["disk_bytes_per_pose"] < 100
    assert rec["throughput_ratio"] > 0 and "recorder cost (Table 4)" in text
    assert report["recorder_off"]["record"] is False and report["record"] is True
    # the process writer's CPU is measured (its own process), the thread writer's is the relay's
    assert report["record_writer"] == "process" and rec["writer"] == "process"
    assert rec["recorder_process_cpu_us_per_pose"] > 0
    thread = report["recorder_by_writer"]["thread"]
    assert thread["files"] == 4 and thread["recorder_process_cpu_us_per_pose"] == 0
    assert report["recorder_on_thread"]["record_writer"] == "thread"
    assert "on (process writer)" in text and "on (thread writer)" in text


def test_recorder_rounds_report_medians_and_every_round() -> None:
    """With --repeat, each figure is the median over rounds and every round's loss is kept."""
    from posecast.bench.recorder import _median_summary

    rounds = [
        {
            "writer": "process",
            "throughput_loss_pct": x,
            "total_cpu_overhead_pct": 10 * x,
            "files": 4,
        }
        for x in (3.0, -1.0, 1.5)
    ]
    out = _median_summary(rounds)
    assert out["throughput_loss_pct"] == 1.5 and out["total_cpu_overhead_pct"] == 15.0
    assert out["throughput_loss_pct_rounds"] == [3.0, -1.0, 1.5]
    assert out["throughput_loss_pct_mean"] == pytest.approx(3.5 / 3)
    assert out["throughput_loss_pct_se"] == pytest.approx(np.std([3.0, -1.0, 1.5], ddof=1) / 3**0.5)
    assert out["rounds"] == 3 and out["files"] == 4 and out["writer"] == "process"
    with pytest.raises(ValueError, match="repeat"):
        run_relay_bench(2, 2, 20.0, 1.0, record=True, repeat=0)


def test_recorder_rounds_alternate_which_run_goes_first(monkeypatch: pytest.MonkeyPatch) -> None:
    """Off runs first in even rounds, last in odd ones; each on run pairs with its round's off."""
    import posecast.bench.relay as bench

    calls: list[str] = []

    def fake_run(*args: object, record_dir: object, record_writer: str = "process", **_: object):
        name = "off" if record_dir is None else record_writer
        calls.append(name)
        k = len(calls)
        # Relay CPU per pose: off runs cost 10 + k, on runs 11 + k (k = call index).
        cost = 10.0 + k + (0.0 if record_dir is None else 1.0)
        return {
            "record_writer": None if record_dir is None else record_writer,
            "record": record_dir is not None,
            "server_cpu_us_per_pose": cost,
            "recorder_cpu_us_per_pose": 0.0,
            "poses_per_s": 1.0,
            "latency_p99_ms": 1.0,
        }

    monkeypatch.setattr(bench, "_run_once", fake_run)
    console = Console(file=io.StringIO(), width=160)
    report = bench.run_relay_bench(
        2, 2, 20.0, 1.0, record=True, record_writer="both", repeat=3, console=console
    )
    assert calls == [
        "off",
        "process",
        "thread",
        "thread",
        "process",
        "off",
        "off",
        "process",
        "thread",
    ]
    by = report["recorder_by_writer"]
    # Round 2 runs off last (call 6, cost 16) after process (call 5, cost 16): a 0 % loss there.
    expected = [100.0 * (1 - off / on) for off, on in [(11, 13), (16, 16), (17, 19)]]
    assert by["process"]["throughput_loss_pct_rounds"] == pytest.approx(expected)


def test_interleaved_recorder_bench_pauses_and_resumes_one_server() -> None:
    """--interleave: one recording run, phases alternate paused/recording, pairs compared."""
    out = io.StringIO()
    console = Console(file=out, width=200)
    report = run_relay_bench(
        20, 5, 20.0, 4.5, record=True, interleave=1.0, console=console, warmup=1.0, ramp_rate=100.0
    )
    phases = report["phases"]
    assert [p["recording"] for p in phases] == [False, True, True, False]
    for p in phases:
        assert p["poses"] > 0 and p["relay_cpu_s"] > 0 and math.isfinite(p["steal_pct"])
    summary = report["recorder_interleaved"]["process"]
    assert summary["pairs"] == 2 and len(summary["throughput_loss_pct_pairs"]) == 2
    assert math.isfinite(summary["throughput_loss_pct_mean"])
    assert "interleaved" in out.getvalue()
    assert report["server_exit_code"] == 0


def test_interleaved_summary_pairs_each_paused_phase_with_its_recording_neighbour() -> None:
    from posecast.bench.recorder import _interleaved_summary

    def phase(recording: bool, cpu: float) -> dict[str, object]:
        return {
            "recording": recording,
            "relay_cpu_s": cpu,
            "writer_cpu_s": 0.5 if recording else 0.0,
            "poses": 1e6,
            "relay_cpu_us_per_pose": cpu,
            "steal_pct": 1.0,
        }

    # paused 10 / recording 11, then recording 12 / paused 12, then a lone phase
    out = _interleaved_summary(
        [phase(False, 10), phase(True, 11), phase(True, 12), phase(False, 12), phase(False, 9)]
    )
    assert out["pairs"] == 2
    assert out["throughput_loss_pct_pairs"] == pytest.approx([100 * (1 - 10 / 11), 0.0])
    assert out["relay_cpu_us_per_pose_recording"] == pytest.approx(11.5)
    assert out["quiet_pairs"] == 2 and out["throughput_loss_pct_quiet_mean"] == pytest.approx(
        np.mean(out["throughput_loss_pct_pairs"])
    )
    noisy = _interleaved_summary(
        [
            phase(False, 10),
            phase(True, 11),
            {**phase(True, 20), "steal_pct": 40.0},
            phase(False, 10),
        ]
    )
    assert noisy["pairs"] == 2 and noisy["quiet_pairs"] == 1
    assert noisy["throughput_loss_pct_quiet_mean"] == pytest.approx(100 * (1 - 10 / 11))
    assert out["relay_cpu_us_per_pose_paused"] == pytest.approx((10 + 12 + 9) / 3)
    with pytest.raises(ValueError, match="interleave"):
        run_relay_bench(2, 2, 20.0, 1.0, record=True, interleave=0.2)
