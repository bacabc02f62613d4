"""``posecast demo --scene throw-catch``: the live scene, its object classes, its flags."""

from __future__ import annotations

import json
import math
from pathlib import Path

from typer.testing import CliRunner

from posecast.cli import app

runner = CliRunner()


def test_demo_scene_prints_and_writes_the_object_classes(tmp_path: Path) -> None:
    """Three bots (thrower, catcher, watcher); the table and JSON have the drill's classes."""
    out = tmp_path / "demo.json"
    res = runner.invoke(
        app,
        [
            "demo",
            "--scene",
            "throw-catch",
            "--duration",
            "9",
            "--rate",
            "10",
            "--interp",
            "soa,motor-lerp",
            "--no-record",
            "--json",
            str(out),
        ],
    )
    assert res.exit_code == 0, res.output
    assert "(throw-catch)" in res.output and "object-flight" in res.output
    assert "object: tip velocity error" in res.output and "object handovers:" in res.output
    data = json.loads(out.read_text())
    assert [b["role"] for b in data["bots"]] == ["thrower", "catcher", "watcher"]
    # Every receiving bot scored the drill, the watcher too.
    for bot in data["bots"]:
        assert math.isfinite(bot["object"]["soa"]["object-flight"]["tip_p95_mm"]), bot["name"]
    for method in ("soa", "motor-lerp"):
        classes = data["methods"][method]
        assert {"hands", "head", "object", "object-flight", "object-catch"} <= set(classes)
        assert math.isfinite(classes["object-flight"]["tip_p95_mm"])
    # A 9 s demo holds at least one whole throw and catch (cycles of 4 s, first by 5 s).
    assert data["objects"]["handovers"]["throw"] >= 1
    assert data["objects"]["handovers"]["catch"] >= 1


def test_demo_scene_flag_mistakes_are_one_line() -> None:
    """--scene with --motion, or a scene of one bot, exits 2 with a clear line."""
    res = runner.invoke(app, ["demo", "--scene", "throw-catch", "--motion", "synthetic"])
    assert res.exit_code == 2 and "give --scene or --motion, not both" in res.output
    res = runner.invoke(app, ["demo", "--scene", "throw-catch", "--bots", "1"])
    assert res.exit_code == 2 and "needs at least 2 bots" in res.output
    res = runner.invoke(app, ["demo", "--scene", "juggling"])
    assert res.exit_code == 2 and "throw-catch" in res.output
