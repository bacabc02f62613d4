"""``posecast replay --start --duration --users --loop``: the recording-player controls."""

from __future__ import annotations

import asyncio
import contextlib
import json
import signal
import sys
from pathlib import Path

import numpy as np
import pytest
from support import running_server
from typer.testing import CliRunner
from websockets.exceptions import ConnectionClosed

from posecast.cli import app
from posecast.client.connection import ClientConnection
from posecast.client.replay import plan_replay, select_plan
from posecast.protocol import Join, Snapshot
from posecast.recorder.export import sorted_streams
from posecast.recorder.replay import synthesize_recording

runner = CliRunner()


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """3 users playing the bundled real traces for 5 s at 30 Hz, through the recorder."""
    return synthesize_recording(tmp_path_factory.mktemp("rec"), users=3, rate=30.0, duration=5.0)


def test_select_plan_keeps_the_window_and_the_users(recording: Path) -> None:
    """Only updates arriving in [origin + start, + duration] of the named users remain."""
    plan = plan_replay(recording)
    first, second = plan.users[0], plan.users[1]
    part = select_plan(plan, start=1.0, duration=2.0, users=[f"u{first.user}", second.name])
    assert [u.user for u in part.users] == [first.user, second.user]
    assert part.origin == pytest.approx(plan.origin + 1.0)
    for up in part.users:
        assert up.arrival.min() >= plan.origin + 1.0
        assert up.arrival.max() <= plan.origin + 3.0
        full = next(u for u in plan.users if u.user == up.user)
        inside = (full.arrival >= plan.origin + 1.0) & (full.arrival <= plan.origin + 3.0)
        assert len(up.updates) == int(inside.sum()) > 0
    assert select_plan(plan, users=[str(first.user)]).users[0].user == first.user


def test_select_plan_refuses_clearly(recording: Path) -> None:
    """An unknown user or a start past the end is one clear ValueError."""
    plan = plan_replay(recording)
    with pytest.raises(ValueError, match=r"no recorded user 'zed'; the recording has u"):
        select_plan(plan, users=["zed"])
    with pytest.raises(ValueError, match=r"past the recording's end"):
        select_plan(plan, start=60.0)
    with pytest.raises(ValueError, match=r"--duration positive"):
        select_plan(plan, duration=0.0)


def test_offline_replay_takes_the_window_and_refuses_loop(recording: Path, tmp_path: Path) -> None:
    """Offline, --start/--duration/--users reconstruct that window of those users only;
    --loop needs --url (one line, exit 2)."""
    res = runner.invoke(app, ["replay", str(recording), "--offline", "--loop"])
    assert res.exit_code == 2 and "--loop applies to a live replay" in res.output
    full, part = tmp_path / "full.json", tmp_path / "part.json"
    args = ["replay", str(recording), "--offline", "--rate", "10", "--json"]
    assert runner.invoke(app, [*args, str(full)]).exit_code == 0
    first = sorted_streams(recording)[0]
    res = runner.invoke(
        app, [*args, str(part), "--start", "1", "--duration", "1", "--users", f"u{first.user}"]
    )
    assert res.exit_code == 0, res.output
    whole, window = json.loads(full.read_text()), json.loads(part.read_text())
    assert window["streams"] == len([s for s in sorted_streams(recording) if s.user == first.user])
    assert window["streams"] < whole["streams"]
    assert 0.5 < window["session_s"] <= 1.1 < whole["session_s"]
    res = runner.invoke(app, [*args, str(part), "--users", "nobody"])
    assert res.exit_code != 0 and "no recorded user 'nobody'" in res.output


async def _watch(url: str, room: str, seen: dict[int, list[float]]) -> None:
    """A spectator that notes, per publishing user, the capture times it receives."""
    conn = await ClientConnection.connect(url, agent="watcher")
    await conn.send(Join(room=room, streams=("head",), rate=30.0, spectator=True))
    with contextlib.suppress(ConnectionClosed):
        while True:
            ev = (await conn.recv()).event
            if isinstance(ev, Snapshot):
                for i in range(len(ev)):
                    seen.setdefault(int(ev.users[i]), []).append(float(ev.capture_times[i]))


def _default_sigint() -> None:
    # A shell without job control starts background jobs with SIGINT ignored, and
    # children inherit that: give the command the Ctrl-C a user's terminal gives it.
    signal.signal(signal.SIGINT, signal.SIG_DFL)


async def _posecast(*args: str) -> asyncio.subprocess.Process:
    return await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "posecast.cli",
        *args,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.STDOUT,
        preexec_fn=_default_sigint,
    )


async def test_cli_replays_a_window_of_one_user(recording: Path, tmp_path: Path) -> None:
    """The command replays 2 s of one user into a live room, as a spectator sees."""
    out = tmp_path / "report.json"
    seen: dict[int, list[float]] = {}
    async with running_server() as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        async with asyncio.TaskGroup() as tg:
            watcher = tg.create_task(_watch(url, "win", seen))
            proc = await _posecast(
                "replay", str(recording), "--url", url, "--room", "win", "--start", "1",
                "--duration", "2", "--users", "u1", "--json", str(out),
            )  # fmt: skip
            output, _ = await asyncio.wait_for(proc.communicate(), 60)
            watcher.cancel()
    assert proc.returncode == 0, output.decode()
    report = json.loads(out.read_text())
    assert report["users"] == 1 and report["bots"][0]["recorded_user"] == 1
    assert 1.8 < report["duration_s"] <= 2.0
    assert len(seen) == 1
    (captures,) = seen.values()
    assert np.ptp(captures) <= 2.0 + 1e-3


async def test_cli_loop_replays_until_interrupted(recording: Path) -> None:
    """With --loop the replay starts again after each pass, until Ctrl-C (SIGINT)."""
    async with running_server() as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        proc = await _posecast(
            "replay", str(recording), "--url", url, "--duration", "0.5", "--loop",
        )  # fmt: skip
        assert proc.stdout is not None
        lines: list[str] = []
        try:
            while not any("pass 2 done" in line for line in lines):
                # A hang guard, not a timing check: a fresh venv's first start is slow.
                line = await asyncio.wait_for(proc.stdout.readline(), 240)
                assert line, "".join(lines)
                lines.append(line.decode())
            proc.send_signal(signal.SIGINT)
            # Read on to the end: a child blocked writing to a full pipe cannot exit.
            try:  # a hang guard: a pass closes its bots' connections before it ends
                rest, _ = await asyncio.wait_for(proc.communicate(), 180)
            except TimeoutError:
                raise AssertionError("no exit after SIGINT; output:\n" + "".join(lines)) from None
            lines.append(rest.decode(errors="replace"))
        finally:
            if proc.returncode is None:  # never leave it running for later tests
                proc.kill()
                await proc.wait()
    assert proc.returncode == 130
