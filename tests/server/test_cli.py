"""The posecast command line: help, compare on a real trace, clear errors."""

from __future__ import annotations

import json
from pathlib import Path

from typer.testing import CliRunner

from server.cli import app

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
