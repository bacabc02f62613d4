"""``posecast view``: its one-line refusals, and a replay served for a given time."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from posecast.cli import app
from posecast.recorder.replay import synthesize_recording

runner = CliRunner()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ([], "give either a recording FILE"),
        (["x.mcap", "--url", "ws://h:1"], "give either a recording FILE"),
        (["--url", "http://h:1"], "is not a websocket URL"),
        (["--url", "ws://h:1", "--interp", "nope"], "unknown interpolator"),
        (["--url", "ws://h:1", "--port", "70000"], "is not a TCP port"),
        (["--url", "ws://h:1", "--fps", "0"], "--fps must be positive"),
        (["--url", "ws://h:1", "--spread", "-1"], "--spread must be 0 or more"),
        (["missing.mcap"], "no such recording"),
    ],
)
def test_view_refuses_bad_input_in_one_line(args: list[str], message: str) -> None:
    """Each mistake is one line on stderr and exit code 2, before anything is served."""
    res = runner.invoke(app, ["view", *args])
    assert res.exit_code == 2 and message in res.output


def test_view_serves_a_recording_for_its_duration(tmp_path: Path) -> None:
    """``view FILE --duration`` serves the page, plays, and returns 0 when the time is up."""
    rec = synthesize_recording(tmp_path, users=2, rate=30.0, duration=2.0)
    res = runner.invoke(app, ["view", str(rec), "--port", "0", "--duration", "1"])
    assert res.exit_code == 0, res.output
    assert "viewer at http://127.0.0.1:" in res.output and rec.name in res.output
