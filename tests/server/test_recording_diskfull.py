"""A full disk while the relay records: one ERROR line, a metric, the room keeps serving.

Two ways to fill the disk, both with a real ``OSError(ENOSPC)``: a 64 KiB tmpfs
(root only: skipped where ``mount`` fails) filled by a filler file, and a file
layer whose writes raise ENOSPC once the test says the disk is full (runs
everywhere). Either before the room opens or while it records.
"""

from __future__ import annotations

import asyncio
import errno
import io
import logging
import subprocess
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import IO

import pytest
from relaykit import Bot, flowing
from support import poll_until, running_server
from test_http import http_get, parse_metrics

import posecast.recorder.writer as writer_mod
from posecast.server.app import RelayServer, ServerConfig

ERROR_METRIC = "posecast_recording_errors_total"


class _FullFile(io.FileIO):
    """A file whose writes fail with ENOSPC once ``full`` is set."""

    full = threading.Event()

    def write(self, b: object) -> int:  # type: ignore[override]
        if self.full.is_set():
            raise OSError(errno.ENOSPC, "No space left on device")
        return super().write(b)  # type: ignore[arg-type]


@pytest.fixture
def failing_layer(monkeypatch: pytest.MonkeyPatch) -> Iterator[threading.Event]:
    """The thread writer's files, with writes that fail once the event is set."""
    real = writer_mod.create_part
    _FullFile.full = threading.Event()

    def create_part(folder: Path, base: str) -> tuple[Path, Path, IO[bytes]]:
        part, final, stream = real(folder, base)
        stream.close()
        return part, final, io.BufferedWriter(_FullFile(part, "r+b"))

    monkeypatch.setattr(writer_mod, "create_part", create_part)
    yield _FullFile.full


@pytest.fixture
def tiny_disk(tmp_path: Path) -> Iterator[Path]:
    """A 64 KiB tmpfs (skipped where it cannot be mounted: not root)."""
    disk = tmp_path / "disk"
    disk.mkdir()
    try:
        got = subprocess.run(
            ["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(disk)],
            capture_output=True,
            check=False,
        )
    except OSError as exc:  # no mount command
        pytest.skip(f"cannot mount a tmpfs here: {exc}")
    if got.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {got.stderr.decode().strip()}")
    try:
        yield disk
    finally:
        subprocess.run(["umount", str(disk)], check=False)


def _fill(disk: Path) -> None:
    """Write a filler file until the disk is full (a real ENOSPC)."""
    with (disk / "filler").open("wb", buffering=0) as fh:
        try:
            while True:
                fh.write(b"\0" * 1024)
        except OSError as exc:
            assert exc.errno == errno.ENOSPC


async def _errors_metric(port: int) -> float:
    _, _, body = await http_get(port, "/metrics")
    return parse_metrics(body)[ERROR_METRIC][""]


async def _session(config: ServerConfig, fill: object, before: bool) -> tuple[float, float]:
    """Two bots in a recorded room; the disk fills (``fill()``) before the room opens or
    while it records. The metric before and after; asserts the room kept serving."""
    async with running_server(config) as server:
        assert isinstance(server, RelayServer) and server.port is not None
        url = f"ws://127.0.0.1:{server.port}"
        start = await _errors_metric(server.port)
        if before:
            fill()  # type: ignore[operator]
        a = await Bot.join(url, asyncio.get_running_loop().time, room="rec", rate=30)
        b = await Bot.join(url, asyncio.get_running_loop().time, room="rec", rate=30)
        async with a.running(), b.running():
            await flowing([a, b])
            if not before:
                fill()  # type: ignore[operator]
            await poll_until(
                lambda: server.core.recording_errors > 0, limit=30.0
            )  # reported during the session, not at close
            after = await _errors_metric(server.port)
            seen = (len(a.snapshots), len(b.snapshots))
            # Members keep getting snapshots of each other after the failure.
            await poll_until(
                lambda: len(a.snapshots) > seen[0] + 5 and len(b.snapshots) > seen[1] + 5
            )
            assert a.closed is None and b.closed is None
    return start, after


def _check_logs(caplog: pytest.LogCaptureFixture, stderr: str) -> None:
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1, [r.getMessage() for r in errors]
    assert "rec" in errors[0].getMessage()
    assert not any(r.exc_info for r in caplog.records), "a traceback was logged"
    assert "Traceback" not in stderr and "Traceback" not in caplog.text


def _no_empty_part(directory: Path) -> None:
    empty = [p for p in directory.iterdir() if p.name.endswith(".part") and p.stat().st_size == 0]
    assert not empty


@pytest.mark.parametrize("before", [False, True], ids=["while-recording", "before-open"])
def test_failing_file_layer(
    tmp_path: Path,
    failing_layer: threading.Event,
    caplog: pytest.LogCaptureFixture,
    capfd: pytest.CaptureFixture[str],
    before: bool,
) -> None:
    """Writes raise ENOSPC (the thread writer, in the relay's process)."""
    caplog.set_level(logging.INFO)
    config = ServerConfig(host="127.0.0.1", port=0, record_dir=tmp_path, record_writer="thread")
    start, after = asyncio.run(_session(config, failing_layer.set, before))
    assert (start, after) == (0, 1)
    _check_logs(caplog, capfd.readouterr().err)
    _no_empty_part(tmp_path)


@pytest.mark.parametrize("before", [False, True], ids=["while-recording", "before-open"])
def test_tiny_tmpfs(
    tiny_disk: Path,
    caplog: pytest.LogCaptureFixture,
    capfd: pytest.CaptureFixture[str],
    before: bool,
) -> None:
    """A real full tmpfs under the default writer process."""
    caplog.set_level(logging.INFO)
    config = ServerConfig(host="127.0.0.1", port=0, record_dir=tiny_disk)
    start, after = asyncio.run(_session(config, lambda: _fill(tiny_disk), before))
    assert (start, after) == (0, 1)
    _check_logs(caplog, capfd.readouterr().err)
    _no_empty_part(tiny_disk)
