"""The posecast command line: help, compare on a real trace, clear errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from posecast.cli import app

runner = CliRunner()


def test_help_lists_commands() -> None:
    """posecast --help exits 0 and names the main commands."""
    res = runner.invoke(app, ["--help"])
    assert res.exit_code == 0
    for cmd in ("compare", "demo", "bench"):
        assert cmd in res.output


def test_compare_prints_table_and_json(dev_trace_path: Path, tmp_path: Path) -> None:
    """compare prints a row per rate/method/class and writes the same numbers as JSON."""
    out = tmp_path / "cmp.json"
    res = runner.invoke(
        app, ["compare", "--trace", str(dev_trace_path), "--rates", "10,30", "--json", str(out)]
    )
    assert res.exit_code == 0, res.output
    assert "motor-lerp" in res.output and "hands" in res.output
    data = json.loads(out.read_text())
    assert set(data) == {"10.0", "30.0"}
    assert data["30.0"]["soa"]["hands"]["tip_p95_mm"] < data["10.0"]["soa"]["hands"]["tip_p95_mm"]


def test_compare_bad_inputs_are_clear(tmp_path: Path) -> None:
    """A missing trace, bad rates or an unknown method exit 2 with a message."""
    res = runner.invoke(app, ["compare", "--trace", str(tmp_path / "x.csv")])
    assert res.exit_code == 2 and "no such trace" in res.output
    res = runner.invoke(app, ["compare", "--trace", "x.csv", "--rates", "fast"])
    assert res.exit_code == 2 and "cannot parse rates" in res.output
    res = runner.invoke(app, ["compare", "--trace", "x.csv", "--interp", "cubic"])
    assert res.exit_code == 2 and "unknown interpolator" in res.output


@pytest.fixture(scope="module")
def small_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 3-user, 4 s recording synthesised from the dev traces."""
    from posecast.recorder.replay import synthesize_recording

    folder = tmp_path_factory.mktemp("rec")
    return synthesize_recording(folder, users=3, rate=30.0, duration=4.0)


def test_info_replay_export_analyze_on_a_recording(small_recording: Path, tmp_path: Path) -> None:
    """info, offline replay, every export format and analyze run on one recording."""
    res = runner.invoke(app, ["info", str(small_recording)])
    assert res.exit_code == 0, res.output
    assert "users: 3" in res.output
    out_json = tmp_path / "replay.json"
    res = runner.invoke(
        app,
        [
            "replay",
            str(small_recording),
            "--offline",
            "--rate",
            "10",
            "--interp",
            "soa",
            "--out",
            str(tmp_path / "rendered"),
            "--json",
            str(out_json),
        ],
    )
    assert res.exit_code == 0, res.output
    assert json.loads(out_json.read_text())["qoe"]["soa"]["hands"]["tip_p95_mm"] > 0
    assert any((tmp_path / "rendered").iterdir())
    for fmt, name in (("csv", "csv"), ("npz", "x.npz"), ("foxglove", "fx.mcap")):
        res = runner.invoke(
            app, ["export", str(small_recording), "--to", fmt, "--out", str(tmp_path / name)]
        )
        assert res.exit_code == 0, res.output
        assert (tmp_path / name).exists()
    res = runner.invoke(app, ["analyze", str(small_recording), "--keep-every", "2"])
    assert res.exit_code == 0, res.output
    assert "Keep 1 in 2" in res.output


def test_recording_commands_refuse_bad_input(small_recording: Path, tmp_path: Path) -> None:
    """Missing files, a replay without a mode, bad formats and decimations exit 2."""
    assert runner.invoke(app, ["info", str(tmp_path / "none.mcap")]).exit_code == 2
    res = runner.invoke(app, ["replay", str(small_recording)])
    assert res.exit_code == 2 and "--offline" in res.output
    res = runner.invoke(app, ["export", str(small_recording), "--to", "xml"])
    assert res.exit_code == 2 and "csv, npz or foxglove" in res.output
    res = runner.invoke(app, ["analyze", str(small_recording), "--keep-every", "1"])
    assert res.exit_code == 2
    res = runner.invoke(app, ["recover", str(tmp_path / "none.mcap.part")])
    assert res.exit_code == 2


def test_table1_command_writes_the_documented_json(dev_trace_path: Path, tmp_path: Path) -> None:
    """posecast table1 prints the tier table and writes table1.json/md in the contract shape."""
    out = tmp_path / "t1"
    res = runner.invoke(
        app,
        [
            "table1",
            "--traces",
            str(dev_trace_path),
            "--rates",
            "10,20,30",
            "--out",
            str(out),
            "--no-link",
            "--no-bench",
            "--no-plots",
            "--no-frontier",
        ],
    )
    assert res.exit_code == 0, res.output
    assert "excellent" in res.output
    data = json.loads((out / "table1.json").read_text())
    assert set(data["curves"]) == {"soa", "dq-slerp", "motor-lerp"}
    point = data["curves"]["soa"]["30"]["hands"]
    assert {
        "pos_p50_mm",
        "pos_p95_mm",
        "rot_p50_deg",
        "rot_p95_deg",
        "tip_p50_mm",
        "tip_p95_mm",
    } <= set(point)
    names = [t["name"] for t in data["tiers"]]
    assert names == ["excellent", "good", "mediocre", "poor"]
    for t in data["tiers"]:
        assert {
            "soa_rate",
            "equal_qoe_rate",
            "bandwidth_saving_pct",
            "running_time_saving_pct",
        } <= set(t)
    assert "paper" in data and (out / "table1.md").is_file()
