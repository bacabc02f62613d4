"""``posecast web``: its options' mistakes are one line, and its server hands the page
its settings (``/config.json``) beside the page's files."""

from __future__ import annotations

import json
import urllib.request
from pathlib import Path

import pytest
from typer.testing import CliRunner

from posecast.cli import app
from posecast.cli.web import PAGE_DIR, page_server


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--url", "http://relay:8765"], "ws://HOST:PORT"),
        (["--url", "ws://relay:8765", "--codec", "zip"], "raw or compact"),
        (["--url", "ws://relay:8765", "--interp", "cubic"], "dq-slerp"),
        (["--url", "ws://relay:8765", "--port", "70000"], "not a TCP port"),
        (["--url", "ws://relay:8765", "--certfile", "c.pem"], "--keyfile"),
    ],
)
def test_web_refuses_bad_options_in_one_line(args: list[str], words: str) -> None:
    """Each unusable option: exit 2 and one error line naming the fix."""
    res = CliRunner().invoke(app, ["web", *args])
    assert res.exit_code == 2, res.output
    assert words in res.output and "Traceback" not in res.output


def test_the_page_server_serves_config_and_files(tmp_path: Path) -> None:
    """/config.json is the options as JSON (never cached); other paths are the page's files."""
    (tmp_path / "index.html").write_text("<!doctype html><title>t</title>")
    config = {"url": "ws://10.0.0.2:8765", "room": "lab", "codec": "compact", "method": "soa"}
    with page_server(config, "127.0.0.1", 0, tmp_path) as port:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/config.json") as r:
            assert json.loads(r.read()) == config
            assert r.headers["Cache-Control"] == "no-store"
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/") as r:
            assert b"<title>t</title>" in r.read()
    assert (PAGE_DIR / "index.html").exists() and (PAGE_DIR / "package-lock.json").exists()
