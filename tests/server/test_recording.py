"""The server's recorder end to end: bit-exact round trip, crash, recovery."""

from __future__ import annotations

import asyncio
import os
import re
import signal
import subprocess
import sys
import time
from functools import partial
from pathlib import Path

import numpy as np
import pytest
from support import poll_until, running_server, wait_until

from posecast.client.bot import Bot, BotConfig, BotReport
from posecast.client.connection import ClientConnection
from posecast.protocol import Snapshot, encode_update
from posecast.recorder import ProcessRecorder, find_leftovers, info, load_streams, recover
from posecast.recorder.scan import ChannelRecord, McapScanner, MessageRecord
from posecast.server.app import RelayServer, ServerConfig


def _proc_state(pid: int) -> str:
    text = Path(f"/proc/{pid}/stat").read_text()
    return text[text.rindex(")") + 2 :].split()[0]


#: Keyframes each bot must receive of every remote stream before the session ends.
_KEYFRAMES = 20


async def _recorded_session(
    tmp: Path, methods: tuple[str, ...] = ("soa",), codec: str = "raw"
) -> tuple[list[BotReport], list[Path]]:
    """Three bots on a recording server until each has received ``_KEYFRAMES`` keyframes
    of every remote stream (not a fixed time: a loaded machine takes longer); the
    recordings once the server stopped."""
    config = ServerConfig(host="127.0.0.1", port=0, record_dir=tmp)
    async with running_server(config) as server:
        url = f"ws://127.0.0.1:{server.port}"
        bots = [
            Bot(
                BotConfig(
                    url=url,
                    room="rec",
                    rate=20,
                    motion="synthetic:orbit",
                    seed=i,
                    duration=120.0,  # a hang guard: stopped once the keyframes are in
                    methods=methods,
                    codec=codec,
                )
            )
            for i in range(3)
        ]

        def enough() -> bool:
            return all(
                len(b.remote) == 6
                and all(len(rs.capture) >= _KEYFRAMES for rs in b.remote.values())
                for b in bots
            )

        async with asyncio.TaskGroup() as tg:
            tasks = [tg.create_task(b.run()) for b in bots]
            await poll_until(lambda: enough() or any(t.done() for t in tasks), every=0.05)
            for b in bots:
                b.stop()
    return [t.result() for t in tasks], server.recordings


@pytest.mark.parametrize("codec", ["raw", "compact"])
def test_every_relayed_keyframe_is_in_the_recording_bit_exact(tmp_path: Path, codec: str) -> None:
    """After a graceful stop, each keyframe a bot received is in the file, same bits.

    Compact: the poses too (the recording holds the decoded codes the relay forwards);
    capture times to the codec's 1 ms (0.5 ms up, 0.5 ms down)."""
    reports, files = asyncio.run(_recorded_session(tmp_path, codec=codec))
    time_tol = 1e-5 if codec == "raw" else 1.0e-3 + 1e-6
    assert len(files) == 1 and files[0].suffix == ".mcap"
    assert not find_leftovers(tmp_path)
    streams = load_streams(files[0])
    checked = 0
    for rep in reports:
        for (user, sid), rs in rep.streams.items():
            rec = streams[(user, sid)]
            assert rec.name == rs.name
            for cap, pose in zip(rs.capture, rs.poses, strict=True):
                # Snapshots carry capture times as float32 offsets from the send time.
                i = int(np.argmin(np.abs(rec.times - cap)))
                assert abs(rec.times[i] - cap) < time_tol
                assert rec.poses[i].tobytes() == np.asarray(pose, dtype=np.float32).tobytes()
                checked += 1
        assert len(rep.streams) == 6 and all(rs.capture for rs in rep.streams.values())
    # Every received keyframe is checked; how many there are depends on the machine's load.
    assert checked >= 3 * 6 * _KEYFRAMES  # the session ran until each bot had them
    summary = info(files[0])
    assert len(summary["users"]) == 3
    # a compact session is recorded as its codes (pose layout 2), a raw one as floats (1)
    layouts = {m.data[0] for m in _pose_messages(files[0])}
    assert layouts == ({2} if codec == "compact" else {1})


def _pose_messages(path: Path) -> list[MessageRecord]:
    scanned = list(McapScanner(path.read_bytes()).records())
    channels = {r.id: r.topic for r in scanned if isinstance(r, ChannelRecord)}
    return [
        r for r in scanned if isinstance(r, MessageRecord) and channels[r.channel_id] == "poses"
    ]


@pytest.mark.parametrize("codec", ["raw", "compact"])
def test_velocity_keyframes_are_recorded_bit_exact(tmp_path: Path, codec: str) -> None:
    """Bots rendering a velocity method send the velocity variant; the recording keeps
    each update's velocities (float16, as on the wire) beside its poses."""
    methods = ("soa", "motor-hermite")
    reports, files = asyncio.run(_recorded_session(tmp_path, methods, codec))
    streams = load_streams(files[0])
    checked = 0
    for rep in reports:
        for (user, sid), rs in rep.streams.items():
            rec = streams[(user, sid)]
            assert rs.sends_velocities and rec.velocities is not None
            assert len(rs.velocities) == len(rs.poses)
            for cap, pose, vel in zip(rs.capture, rs.poses, rs.velocities, strict=True):
                i = int(np.argmin(np.abs(rec.times - cap)))
                assert rec.poses[i].tobytes() == np.asarray(pose, dtype=np.float32).tobytes()
                assert np.array_equal(rec.velocities[i], vel)
                checked += 1
            assert np.abs(rec.velocities).max() > 0  # real motion, not the zero filler
        assert len(rep.streams) == 6
    assert checked >= 3 * 6 * _KEYFRAMES  # the session ran until each bot had them


_PUBLISHER = r"""
import asyncio, sys, time
import numpy as np
from posecast.client.connection import ClientConnection
from posecast.protocol import Snapshot, encode_update

async def echo(conn, back):
    # The relay sends a subscriber its own streams too: seeing an update come back
    # proves the server ingested it (and handed it to the recorder).
    while True:
        ev = (await conn.recv()).event
        if isinstance(ev, Snapshot) and len(ev):
            seq = round(float(ev.poses[:, 0].max()) * 1000)
            print("relayed", seq, time.monotonic(), flush=True)
            back.set()

async def main(url):
    conn = await ClientConnection.open(url, room="crash", streams=("head",), rate=20)
    sid = np.array([conn.joined.streams["head"]])
    back = asyncio.Event()
    async with asyncio.TaskGroup() as tg:
        tg.create_task(echo(conn, back))
        seq = 0
        while True:  # the next update once the last came back: one per relay tick
            seq += 1
            pose = np.array([[seq * 1e-3, 0, 0, 1, 0, 0, 0]], dtype=np.float32)
            back.clear()
            await conn.send_bytes(encode_update(seq, sid, np.array([time.monotonic()]), pose))
            await back.wait()

asyncio.run(main(sys.argv[1]))
"""


def test_killed_recording_server_loses_nothing_older_than_one_second(tmp_path: Path) -> None:
    """SIGKILL mid-session; after recovery every update the relay had >1 s before the kill
    is there.

    "Had": the relay sent it back to its publisher (which also subscribes), so it
    was ingested and handed to the recorder; an update still in a starved server's
    socket buffer was never the recorder's to lose. The 1 s covers the writer's
    flush interval (0.5 s) and its process being scheduled.
    """
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    server = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "from posecast.cli import main; main()",
            "serve",
            "--port",
            "0",
            "--record",
            str(tmp_path),
            "--log-level",
            "warning",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=env,
    )
    publisher = None
    try:
        assert server.stdout is not None
        line = server.stdout.readline()
        port = int(re.search(r"ws://[^:]+:(\d+)", line).group(1))  # type: ignore[union-attr]
        publisher = subprocess.Popen(
            [sys.executable, "-c", _PUBLISHER, f"ws://127.0.0.1:{port}"],
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
            text=True,
            env=env,
        )
        assert publisher.stdout is not None
        relayed: list[tuple[int, float]] = []
        while len(relayed) < 60:  # about 3 s of snapshots at 20 Hz
            _, seq, t = publisher.stdout.readline().split()
            relayed.append((int(seq), float(t)))
        killed_at = time.monotonic()
        server.send_signal(signal.SIGKILL)
        server.wait(10)
    finally:
        for proc in (publisher, server):
            if proc is None:
                continue
            if proc.poll() is None:
                proc.kill()
            proc.wait(10)
            if proc.stdout is not None:
                proc.stdout.close()
    parts = find_leftovers(tmp_path)
    assert len(parts) == 1
    report = recover(parts[0])
    streams = load_streams(report.output)
    (data,) = streams.values()
    recorded = {round(float(p[0]) * 1000) for p in data.poses}
    # Updates are ingested in order: by the time seq came back, 1..seq were in.
    newest_old = max((seq for seq, t in relayed if t < killed_at - 1.0), default=0)
    old = range(1, newest_old + 1)
    assert len(old) >= 10  # liveness only: how many depends on the machine's load
    missing = [seq for seq in old if seq not in recorded]
    assert not missing, f"lost {len(missing)} old updates, e.g. {missing[:5]}"


async def _paused_session(
    tmp: Path, counts: tuple[int, int, int]
) -> tuple[Path, float, float, float, float]:
    """One client sends counts[0] updates, recording paused for counts[1], resumed for counts[2].

    Returns the recording and the server clock just before and just after the pause
    and the resume calls: (path, before pause, after pause, before resume, after resume).
    """
    from posecast.client.connection import ClientConnection
    from posecast.protocol import encode_update

    # Captures never age out here (this is not about that rule): a starved machine can
    # hold an update past the 1 s default, and a refused one is never handled.
    config = ServerConfig(host="127.0.0.1", port=0, record_dir=tmp, max_capture_age=3600.0)
    async with running_server(config) as server:
        conn = await ClientConnection.open(
            f"ws://127.0.0.1:{server.port}", room="pause", streams=("head",), rate=20
        )
        sid = np.array([conn.joined.streams["head"]])  # type: ignore[union-attr]
        room = server.rooms["pause"]
        seq = 0
        marks: list[float] = []
        for phase, count in enumerate(counts):
            if phase == 1:
                marks.append(server.clock())
                server.pause_recording()
                marks.append(server.clock())
            elif phase == 2:
                marks.append(server.clock())
                server.resume_recording()
                marks.append(server.clock())
            for _ in range(count):
                seq += 1
                pose = np.array([[seq * 1e-3, 0, 0, 1, 0, 0, 0]], dtype=np.float32)
                await conn.send_bytes(encode_update(seq, sid, np.array([time.monotonic()]), pose))
            # The relay has handled every update sent so far before the state changes.
            handled = partial(lambda n: room.statistics().updates_in >= n, seq)
            await poll_until(handled, every=0.01)  # its 60 s: a hang guard
            assert room.statistics().updates_in == seq
        await conn.close()
    (path,) = server.recordings
    marks += [float("inf")] * (4 - len(marks))
    return path, marks[0], marks[1], marks[2], marks[3]


def test_paused_recording_skips_pose_updates_and_says_so(tmp_path: Path) -> None:
    """While paused no pose update is recorded; the file has one drops record for the pause."""
    from posecast.recorder import DropRecord, PoseRecord, read_records

    path, paused_at, paused_by, resumed_at, resumed_by = asyncio.run(
        _paused_session(tmp_path, (30, 25, 20))
    )
    records = read_records(path)
    seqs = [r.seq for r in records if isinstance(r, PoseRecord)]
    assert seqs == list(range(1, 31)) + list(range(56, 76))
    (pause,) = [r for r in records if isinstance(r, DropRecord) and r.kind == "recording-paused"]
    assert pause.data["count"] == 25
    # the server's clock when the pause began and ended: read inside the two calls
    assert paused_at <= pause.data["first_time"] <= paused_by < resumed_at
    assert resumed_at <= pause.data["last_time"] <= resumed_by


def test_a_room_closed_while_paused_records_the_pause(tmp_path: Path) -> None:
    from posecast.recorder import DropRecord, PoseRecord, read_records

    path, *_ = asyncio.run(_paused_session(tmp_path, (10, 0, 0)))
    assert len([r for r in read_records(path) if isinstance(r, PoseRecord)]) == 10
    path2, *_ = asyncio.run(_paused_session(tmp_path / "b", (5, 7, 0)))
    records = read_records(path2)
    assert [r.seq for r in records if isinstance(r, PoseRecord)] == [1, 2, 3, 4, 5]
    (pause,) = [r for r in records if isinstance(r, DropRecord) and r.kind == "recording-paused"]
    assert pause.data["count"] == 7


def test_sigusr1_pauses_and_sigusr2_resumes_a_recording_server(tmp_path: Path) -> None:
    """`posecast serve --record` wires the signals: /metrics shows the state."""
    import urllib.request

    server = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "from posecast.cli import main; main()",
            "serve",
            "--port",
            "0",
            "--record",
            str(tmp_path),
            "--log-level",
            "warning",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert server.stdout is not None
        port = int(re.search(r"ws://[^:]+:(\d+)", server.stdout.readline()).group(1))  # type: ignore[union-attr]

        def paused() -> float:
            url = f"http://127.0.0.1:{port}/metrics"
            with urllib.request.urlopen(url, timeout=10) as resp:
                text = resp.read().decode()
            return float(re.search(r"^posecast_recording_paused (\S+)$", text, re.M).group(1))  # type: ignore[union-attr]

        def wait_for(value: float) -> None:
            wait_until(lambda: paused() == value, every=0.05)  # 60 s: a hang guard

        wait_for(0.0)
        server.send_signal(signal.SIGUSR1)
        wait_for(1.0)
        server.send_signal(signal.SIGUSR2)
        wait_for(0.0)
        server.send_signal(signal.SIGTERM)
        assert server.wait(30) == 0
    finally:
        if server.poll() is None:
            server.kill()
            server.wait(10)
        if server.stdout is not None:
            server.stdout.close()


async def _publish(conn: ClientConnection, seq: int) -> None:
    sid = np.array([conn.joined.streams["head"]])
    pose = np.array([[seq * 1e-3, 1.6, 0, 1, 0, 0, 0]], dtype=np.float32)
    await conn.send_bytes(encode_update(seq, sid, np.array([time.monotonic()]), pose))


async def _snapshot_from(conn: ClientConnection, user: int) -> None:
    """Wait until ``conn`` receives a snapshot carrying a pose of ``user`` (60 s: a hang guard)."""
    async with asyncio.timeout(60):
        while True:
            got = (await conn.recv()).event
            if isinstance(got, Snapshot) and user in got.users.tolist():
                return


async def _ingested(server: RelayServer, rooms: list[str], n: int) -> None:
    """Wait until each of ``rooms`` has taken in ``n`` updates (one after another, as
    a publisher at its rate would send them)."""
    await poll_until(
        lambda: all(server.rooms[r].statistics().updates_in >= n for r in rooms), every=0.005
    )


async def _rooms_share_one_writer(tmp: Path) -> tuple[RelayServer, list[Path], set[int]]:
    config = ServerConfig(host="127.0.0.1", port=0, record_dir=tmp)
    async with running_server(config) as server:
        url = f"ws://127.0.0.1:{server.port}"
        conns = [
            await ClientConnection.open(url, room=f"r{i // 2}", streams=("head",), rate=20)
            for i in range(6)
        ]
        recorders = list(server.recorders.open.values())
        assert len(recorders) == 3
        first = server.recorders.host
        assert first is not None and first.rooms == 3
        assert {rec.host.pid for rec in recorders if isinstance(rec, ProcessRecorder)} == {
            first.pid
        }
        for seq in range(1, 11):
            for conn in conns:
                await _publish(conn, seq)
            await _ingested(server, [f"r{i}" for i in range(3)], 2 * seq)
        # The writer process dies: the recordings fail, the relay goes on.
        os.kill(first.pid, signal.SIGKILL)
        # The host's reader sees the pipe close at once (60 s: a hang guard).
        await poll_until(lambda: all(rec is not None and rec.failed for rec in recorders))
        await _publish(conns[0], 11)
        await _snapshot_from(conns[1], conns[0].user)
        # A room opened now records through a new writer process.
        late = [
            await ClientConnection.open(url, room="late", streams=("head",), rate=20)
            for _ in range(2)
        ]
        second = server.recorders.host
        assert second is not None and second.pid != first.pid and second.alive
        for seq in range(1, 21):
            for conn in late:
                await _publish(conn, seq)
            await _ingested(server, ["late"], 2 * seq)
        await _snapshot_from(late[1], late[0].user)
        for conn in conns + late:
            await conn.close()
    return server, server.recordings, {first.pid, second.pid}


def test_rooms_share_one_writer_process_and_survive_its_death(tmp_path: Path) -> None:
    server, files, pids = asyncio.run(_rooms_share_one_writer(tmp_path))
    assert server.recorders.host is None  # closed with the server
    for pid in pids:  # no writer process outlives the server
        assert not Path(f"/proc/{pid}").exists() or "Z" in _proc_state(pid)
    # The late room finished cleanly; the three rooms the dead writer held left .part files.
    assert [f.name.split("-")[0] for f in files] == ["late"]
    late = load_streams(files[0])
    assert sorted(len(s.times) for s in late.values()) == [20, 20]
    leftovers = find_leftovers(tmp_path)
    assert len(leftovers) == 3
    for part in leftovers:
        report = recover(part, tmp_path / f"{part.name}.recovered.mcap")
        assert report.chunks_lost == 0


def test_a_join_waiting_for_a_slow_writer_is_not_taken_for_a_dead_peer(tmp_path: Path) -> None:
    """The relay stops reading a join's socket while its room's file opens; a writer
    slower than ``ping_timeout`` (stopped here; a niced child on a loaded machine)
    must not turn the unread pong into 1011 "keepalive ping timeout"."""

    async def session() -> list[Path]:
        config = ServerConfig(
            host="127.0.0.1", port=0, record_dir=tmp_path, ping_interval=0.2, ping_timeout=0.2
        )
        async with running_server(config) as server:
            host = server.recorders.host
            assert host is not None
            os.kill(host.pid, signal.SIGSTOP)
            try:
                join = asyncio.ensure_future(
                    ClientConnection.open(
                        f"ws://127.0.0.1:{server.port}", room="slow", streams=("head",), rate=20
                    )
                )
                # The join's first ping and its whole pong deadline pass unread.
                await poll_until(lambda: "slow" in server.recorders._opening)
                await asyncio.sleep(0.5)
                assert not join.done()
            finally:
                os.kill(host.pid, signal.SIGCONT)
            conn = await join
            await conn.close()
        return server.recordings

    files = asyncio.run(session())
    assert len(files) == 1 and not find_leftovers(tmp_path)
