"""The relay bench's load generator, bare baseline and curve: real servers, real sockets.

What is checked is behaviour (bytes equal the protocol's, frames parsed, clients
joined and counted, rows carry their keys), never a rate or a time.
"""

from __future__ import annotations

import asyncio
import io
import math
import os
import time

import numpy as np
import pytest
from rich.console import Console
from support import CliForker, poll_until
from websockets.asyncio.server import ServerConnection, serve
from websockets.utils import accept_key

from posecast.bench import run_relay_bench, run_relay_curve
from posecast.bench.common import MOTION_FRAMES, Motion
from posecast.bench.loadclient import SAMPLE_EVERY, _BenchClient, _LoadStats
from posecast.bench.procs import _histogram_quantile
from posecast.bench.report import saturation
from posecast.bench.sweep import BASELINE_KEYS, CURVE_KEYS, parse_counts
from posecast.bench.wsclient import (
    MAX_FRAME,
    CompactUpdateFrames,
    RawUpdateFrames,
    client_frame,
    connect,
    open_connection,
)
from posecast.protocol import Hello, Join, Joined, PoseUpdate, Welcome, encode_update, pack_snapshot
from posecast.protocol._compact import UpstreamDecoder, UpstreamEncoder
from posecast.protocol.codec import DEFAULT_VOLUME
from posecast.protocol.wire import encode_message
from posecast.server.wsframe import frame_binary


def _console() -> Console:
    return Console(file=io.StringIO(), width=200)


# ---------------------------------------------------------------------------------
# Pre-encoded updates
# ---------------------------------------------------------------------------------


def _moving_cycle(frames: int) -> np.ndarray:
    """A cycle (frames, 3, 7) of moving, turning poses (unit quaternions)."""
    k = np.arange(frames)[:, None]
    s = np.arange(3)[None, :]
    angle = 0.3 * k + 0.2 * s
    cycle = np.zeros((frames, 3, 7))
    cycle[..., 0] = 0.4 * np.cos(0.1 * k + s)
    cycle[..., 1] = 1.5 + 0.05 * np.sin(0.2 * k)
    cycle[..., 2] = -0.3 + 0.01 * k + 0.1 * s
    cycle[..., 3] = np.cos(angle / 2)
    cycle[..., 5] = np.sin(angle / 2)
    return cycle


@pytest.mark.parametrize("seq", [1, 127, 128, 255, 256, 65535, 65536, 2**32 + 5])
def test_raw_update_frames_are_the_protocols_bytes(seq: int) -> None:
    """The spliced raw update equals encode_update for every size of the seq varint."""
    cycle = _moving_cycle(5)
    frames = RawUpdateFrames([4, 5, 6], cycle)
    t = 12345.678901
    poses = cycle[(seq - 1) % 5]
    expected = encode_update(seq, [4, 5, 6], [t] * 3, poses, base_time=t)
    assert frames.payload(seq, t) == expected
    frame = frames.frame(seq, t)
    # masked (bit 7 of byte 1) with the zero key, the payload left as it is
    assert frame[1] & 0x80 and frame.endswith(b"\0\0\0\0" + expected)


@pytest.mark.parametrize("frames", [1, 4])
def test_compact_update_frames_match_the_encoder_and_decode_on_the_server_side(
    frames: int,
) -> None:
    """After the first cycle, each spliced frame is the encoder's own, and decodes to its poses."""
    ids = [3, 4, 5]
    cycle = _moving_cycle(frames)
    client = UpstreamEncoder(DEFAULT_VOLUME)

    def encode(update: PoseUpdate) -> bytes:
        data = client.encode(update)
        client.commit()
        return data

    spliced = CompactUpdateFrames(ids, cycle, encode)
    reference = UpstreamEncoder(DEFAULT_VOLUME)
    server = UpstreamDecoder(DEFAULT_VOLUME)
    t = 5000.0
    seqs = [*range(1, 3 * frames + 4), 127, 128, 300, 70000]
    for i, seq in enumerate(seqs):
        t += 0.05123
        data = spliced.payload(seq, t)
        poses = cycle[i % frames]
        update = PoseUpdate.from_arrays(seq, ids, [t] * 3, poses, base_time=t)
        assert data == reference.encode(update), (i, seq)
        reference.commit()
        got = server.decode(data)
        assert got.seq == seq and got.base_time == pytest.approx(t, abs=1e-6)
        assert np.allclose(got.poses[:, :3], poses[:, :3], atol=1e-3)
        assert list(got.streams) == ids


def test_motion_cycles_come_from_the_traces_or_stand_still() -> None:
    """traces:sample: each client a cycle of real poses, from its own start; static: one pose."""
    motion = Motion("traces:sample", 20.0)
    a, b = motion.cycle(0), motion.cycle(len(motion.traces))
    assert a.shape == (MOTION_FRAMES, 3, 7) and b.shape == a.shape
    assert not np.allclose(a, b)  # same trace, another start
    assert np.allclose(np.linalg.norm(a[..., 3:], axis=-1), 1.0, atol=1e-6)
    assert np.ptp(a[:, 0, :3], axis=0).max() > 0  # the head moves
    assert Motion("static", 20.0).cycle(3).shape == (1, 3, 7)
    with pytest.raises(ValueError, match="unknown trace set"):
        Motion("traces:nope", 20.0)


# ---------------------------------------------------------------------------------
# The websocket client, against a real websockets server
# ---------------------------------------------------------------------------------


def test_frame_connection_talks_to_a_websockets_server() -> None:
    """Handshake, three header sizes both ways, a ping answered, a close answered."""

    async def main() -> tuple[list[bytes], bool, str]:
        pinged = False

        async def handler(ws: ServerConnection) -> None:
            nonlocal pinged
            for _ in range(3):
                await ws.send(await ws.recv())
            pong = await ws.ping()
            await asyncio.wait_for(pong, 5.0)
            pinged = True
            await ws.close(1000, "done")

        async with serve(handler, "127.0.0.1", 0, compression=None) as server:
            port = next(iter(server.sockets)).getsockname()[1]
            conn, _ = await open_connection(f"ws://127.0.0.1:{port}", time.monotonic, 5.0)
            got: asyncio.Queue[bytes] = asyncio.Queue(maxsize=8)
            conn.on_message = lambda data, arrival: got.put_nowait(data)
            sent = [b"a" * 10, b"b" * 300, bytes(range(256)) * 300]
            received = []
            for payload in sent:
                conn.write(client_frame(payload))
                received.append(await asyncio.wait_for(got.get(), 5.0))
            reason = await asyncio.wait_for(conn.closed, 5.0)
            assert received == sent
            return received, pinged, reason

    received, pinged, reason = asyncio.run(main())
    assert len(received) == 3 and pinged
    assert reason == "1000 done"


def test_refused_handshake_says_so() -> None:
    """A server that answers the upgrade with an HTTP error: ConnectionError naming it."""

    async def main() -> None:
        async def http_only(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            await reader.readuntil(b"\r\n\r\n")
            writer.write(b"HTTP/1.1 403 Forbidden\r\nContent-Length: 0\r\n\r\n")
            await writer.drain()
            writer.close()

        server = await asyncio.start_server(http_only, "127.0.0.1", 0)
        async with server:
            port = server.sockets[0].getsockname()[1]
            with pytest.raises(ConnectionError, match="403"):
                await open_connection(f"ws://127.0.0.1:{port}", time.monotonic, 5.0)

    asyncio.run(main())


async def upgrade_key(reader: asyncio.StreamReader) -> str:
    """Read a client's upgrade request; its Sec-WebSocket-Key."""
    request = (await reader.readuntil(b"\r\n\r\n")).decode()
    return next(
        line.split(":", 1)[1].strip()
        for line in request.split("\r\n")
        if line.lower().startswith("sec-websocket-key:")
    )


async def _raw_server_exchange(answer: bytes, then: bytes) -> tuple[str, bytes]:
    """A bench client against a server that answers the upgrade with ``answer`` (its
    ``{accept}`` filled in) and then sends ``then``: how the client ended and the
    bytes it wrote after its request."""
    wrote: asyncio.Future[bytes] = asyncio.get_running_loop().create_future()

    async def server(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        key = await upgrade_key(reader)
        writer.write(answer.replace(b"{accept}", accept_key(key).encode()) + then)
        await writer.drain()
        wrote.set_result(await asyncio.wait_for(reader.read(-1), 5.0))
        writer.close()

    srv = await asyncio.start_server(server, "127.0.0.1", 0)
    async with srv:
        port = srv.sockets[0].getsockname()[1]
        try:
            conn, _ = await open_connection(f"ws://127.0.0.1:{port}", time.monotonic, 5.0)
        except ConnectionError as exc:
            return f"refused: {exc}", await asyncio.wait_for(wrote, 5.0)
        ended = await asyncio.wait_for(conn.closed, 5.0)
        return ended, await asyncio.wait_for(wrote, 5.0)


_UPGRADE = (
    b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
    b"Sec-WebSocket-Accept: {accept}\r\n\r\n"
)


def _close_code(wrote: bytes) -> int:
    """The code of the (zero-key) close frame the client wrote."""
    assert wrote[0] == 0x88 and wrote[1] & 0x80, wrote[:4]
    key = wrote[2:6]
    body = bytes(b ^ key[i % 4] for i, b in enumerate(wrote[6 : 6 + (wrote[1] & 0x7F)]))
    return int.from_bytes(body[:2], "big")


def test_a_masked_server_frame_closes_1002() -> None:
    """A server must not mask its frames: the client closes 1002 and says so."""
    masked = bytes((0x82, 0x80 | 3)) + b"\x01\x02\x03\x04" + b"abc"
    ended, wrote = asyncio.run(_raw_server_exchange(_UPGRADE, masked))
    assert ended.startswith("1002") and "mask" in ended
    assert _close_code(wrote) == 1002


def test_an_oversized_server_frame_closes_1009() -> None:
    """A frame over the load's limit is refused from its header: 1009, nothing buffered."""
    huge = bytes((0x82, 127)) + (MAX_FRAME + 1).to_bytes(8, "big")
    ended, wrote = asyncio.run(_raw_server_exchange(_UPGRADE, huge))
    assert ended.startswith("1009")
    assert _close_code(wrote) == 1009


def test_a_wrong_accept_key_is_a_refused_handshake() -> None:
    """A 101 whose Sec-WebSocket-Accept does not answer the key: ConnectionError naming it."""
    answer = _UPGRADE.replace(b"{accept}", b"d3Jvbmcga2V5IGZvciB0aGlz")
    ended, wrote = asyncio.run(_raw_server_exchange(answer, b""))
    assert ended.startswith("refused: handshake refused") and "Sec-WebSocket-Accept" in ended
    assert wrote == b""  # no frame after a failed handshake


def test_frames_right_after_the_upgrade_and_split_reads_arrive_whole() -> None:
    """Frames in the read that ends the upgrade, a ping between them and a frame cut
    mid-header reach on_message whole and in order; the ping is answered."""

    async def main() -> tuple[list[bytes], bytes]:
        got: list[bytes] = []
        wrote: asyncio.Future[bytes] = asyncio.get_running_loop().create_future()
        first, second, big = b"one", b"two" * 50, bytes(range(256)) * 300
        stream = frame_binary(first) + bytes((0x89, 2)) + b"hi" + frame_binary(second)

        async def server(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            key = await upgrade_key(reader)
            writer.write(_UPGRADE.replace(b"{accept}", accept_key(key).encode()) + stream)
            await writer.drain()
            wrote.set_result(await reader.readexactly(8))
            writer.close()

        srv = await asyncio.start_server(server, "127.0.0.1", 0)
        async with srv:
            port = srv.sockets[0].getsockname()[1]
            conn = await connect(f"ws://127.0.0.1:{port}", time.monotonic, 5.0)
            conn.on_message = lambda data, arrival: got.append(data)
            await conn.upgraded(5.0)
            pong = await asyncio.wait_for(wrote, 5.0)
            await poll_until(lambda: len(got) == 2)
            # One frame over four reads, cut inside its header and its payload.
            tail = frame_binary(big)
            for piece in (tail[:1], tail[1:3], tail[3:5000], tail[5000:]):
                conn.data_received(piece)
            conn.abort()
        return got, pong

    got, pong = asyncio.run(main())
    assert got == [b"one", b"two" * 50, bytes(range(256)) * 300]
    assert pong[0] == 0x8A and pong[1] == 0x80 | 2  # a masked pong of the ping's 2 bytes


# ---------------------------------------------------------------------------------
# Counting without decoding
# ---------------------------------------------------------------------------------


def _client(user: int, own_ids: list[int]) -> _BenchClient:
    """A load client whose session went through hello and join (no socket needed)."""
    stats = _LoadStats(1)
    stats.t0, stats.t1 = 0.0, math.inf
    client = _BenchClient(0, "room", 20.0, stats, "raw")
    session = client.session
    session.send(Hello(agent="test"))
    session.receive_data(encode_message(Welcome(user=user, server_time=0.0)))
    session.send(Join(room="room", streams=("head", "left", "right")[: len(own_ids)], rate=20.0))
    names = dict(zip(("head", "left", "right"), own_ids, strict=False))
    session.receive_data(encode_message(Joined(room="room", streams=names, rate=20.0)))
    client.user = user
    client._own = tuple(int.to_bytes(user, 2, "little") + s.to_bytes(2, "little") for s in own_ids)
    return client


def test_cheap_count_agrees_with_a_full_decode() -> None:
    """Raw snapshots: the header parse counts the same poses and own echoes as decoding."""
    pose = np.array([0.1, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0], np.float32).tobytes()
    # own user 7 (streams 21-23), peers 5 and 300 (whose low byte is 7's neighbour's);
    # a peer's record whose pose bytes contain 7's (user, stream) prefix unaligned.
    tricky = b"\x00\x00" + int.to_bytes(7, 2, "little") + (21).to_bytes(2, "little") + pose[6:]
    entries = [(5, 11, 99.99, pose), (7, 21, 99.99, pose), (300, 12, 99.98, tricky)]
    entries += [(7, 22, 99.99, pose), (7, 23, 99.99, pose), (5, 13, 99.97, pose)]
    fast, slow = _client(7, [21, 22, 23]), _client(7, [21, 22, 23])
    for tick in range(1, 2 * SAMPLE_EVERY + 1):
        data = pack_snapshot(tick * 300, 100.0 + tick / 20, entries)
        fast._on_message(data, 100.01 + tick / 20)
        slow._decode(data, 100.01 + tick / 20)
    for client in (fast, slow):
        stats = client.stats
        assert stats.poses_all == 6 * 2 * SAMPLE_EVERY
        assert stats.poses_remote == 3 * 2 * SAMPLE_EVERY
        assert stats.bad_frames == 0 and stats.other_frames == 0
        arrays = stats.arrays()
        assert len(arrays["relay"]) == 2 * SAMPLE_EVERY
        # two sampled snapshots, three remote poses each
        assert len(arrays["latency"]) == 2 * 3
        assert (arrays["latency"] > 0).all()
    assert fast.stats.decoded_frames == 0 and slow.stats.decoded_frames == 2 * SAMPLE_EVERY
    assert np.allclose(fast.stats.arrays()["latency"], slow.stats.arrays()["latency"])


def test_control_messages_and_garbage_are_counted_apart() -> None:
    """A non-snapshot message is an other frame, bytes that are no message a bad frame."""
    from posecast.protocol.messages import PeerLeft

    client = _client(7, [21])
    client._on_message(encode_message(PeerLeft(user=3)), 1.0)
    client._on_message(b"\x84\xa4type\xa8snapshot\xa4tick\x01garbage", 1.0)
    assert client.stats.other_frames == 1 and client.stats.bad_frames == 1
    assert client.stats.poses_all == 0


# ---------------------------------------------------------------------------------
# Verdicts and /metrics
# ---------------------------------------------------------------------------------


def _figures(**over: float) -> dict[str, float]:
    base = {
        "load_cpu_pct_max": 40.0,
        "send_lag_p99_ms": 1.0,
        "server_cpu_pct": 50.0,
        "skips": 0.0,
        "rate_hz": 20.0,
        "tick_lag_p99_ms": 2.0,
        "machine_cpu_pct": 60.0,
    }
    return {**base, **over}


def test_saturation_names_who_limited_the_run() -> None:
    """A busy load process or late loop blames the load; skips, late ticks, a full core: server."""
    assert saturation(_figures())["saturated_by"] == "none"
    gen = saturation(_figures(load_cpu_pct_max=97.0))
    assert gen["saturated_by"] == "generator" and gen["generator_saturated"]
    assert "97 %" in gen["saturation_notes"][0]
    assert saturation(_figures(send_lag_p99_ms=40.0))["generator_saturated"]
    # with no idle core, a late loop is the machine's doing: noted, not blamed on the load
    full = saturation(_figures(send_lag_p99_ms=40.0, machine_cpu_pct=99.0))
    assert full["saturated_by"] == "machine" and not full["generator_saturated"]
    assert any("late" in note for note in full["saturation_notes"])
    assert saturation(_figures(skips=3.0))["saturated_by"] == "server"
    assert saturation(_figures(tick_lag_p99_ms=30.0))["server_saturated"]
    assert saturation(_figures(updates_refused=50.0))["saturated_by"] == "server"
    assert saturation(_figures(clients_closed=3))["saturated_by"] == "server"
    both = saturation(_figures(server_cpu_pct=99.0, load_cpu_pct_max=95.0, machine_cpu_pct=99.0))
    assert both["saturated_by"] == "server+generator+machine"
    # no /metrics (the baseline): NaN skips blame nobody
    assert saturation(_figures(skips=math.nan))["saturated_by"] == "none"


def test_histogram_quantile_of_the_window() -> None:
    """The window's quantile comes from bucket deltas; no histogram: NaN."""
    name = "posecast_tick_lag_seconds"
    m0 = {f"{name}_bucket|0.001": 10.0, f"{name}_bucket|0.01": 10.0, f"{name}_bucket|+Inf": 10.0}
    m1 = {f"{name}_bucket|0.001": 60.0, f"{name}_bucket|0.01": 110.0, f"{name}_bucket|+Inf": 110.0}
    # window: 50 in (0, 1 ms], 50 in (1, 10 ms]; p99 is 98 % of the way into the second
    assert _histogram_quantile(m0, m1, name, 0.99) == pytest.approx(0.001 + 0.009 * 0.98)
    assert _histogram_quantile(m0, m1, name, 0.5) == pytest.approx(0.001)
    assert math.isnan(_histogram_quantile({}, {}, name, 0.99))
    assert math.isnan(_histogram_quantile(None, m1, name, 0.99))


def test_parse_counts() -> None:
    assert parse_counts("100, 200,500") == [100, 200, 500]
    for bad in ("", "100,,200", "0", "-5", "1e3"):
        with pytest.raises(ValueError, match="--clients"):
            parse_counts(bad)


# ---------------------------------------------------------------------------------
# Real runs
# ---------------------------------------------------------------------------------


def test_curve_with_baseline_from_two_load_processes() -> None:
    """Two counts, relay and bare baseline each, two load processes: rows with every key."""
    out = _console()
    result = run_relay_curve(
        [10, 20], 5, 20.0, 1.5, baseline=True, procs=2, console=out, warmup=1.0, ramp_rate=100.0
    )
    rows = result["curve"]
    assert [row["clients"] for row in rows] == [10, 20]
    for row in rows:
        assert set(CURVE_KEYS) | set(BASELINE_KEYS) <= row.keys()
        assert row["clients_joined"] == row["clients"]
        assert math.isfinite(row["relay_over_baseline"]) and row["relay_over_baseline"] > 0
    for report in result["relay"] + result["baseline"]:
        assert report["load_procs"] == 2 and len(report["load_cpu_pct_per_proc"]) == 2
        assert report["clients_without_snapshots_in_window"] == 0
        assert report["clients_closed"] == 0 and report["bad_frames"] == 0
        assert report["server_errors"] == {}
        # remote poses only: at most the 4 room mates' 3 streams a snapshot
        assert 0 < report["poses_delivered"] <= 12 * report["snapshots"]
        assert report["server_exit_code"] == 0
    bare = result["baseline"][0]
    assert bare["server"] == "baseline" and not bare["metrics_ok"]
    assert bare["latency_samples"] > 0
    text = out.file.getvalue()  # type: ignore[attr-defined]
    assert "relay curve" in text and "baseline (bare broadcast server) bench" in text


def test_compact_updates_are_relayed() -> None:
    """--codec compact: the relay accepts the spliced codec frames and relays the poses."""
    report = run_relay_bench(10, 5, 20.0, 1.5, codec="compact", console=_console(), warmup=1.0)
    assert report["codec"] == "compact" and report["clients_joined"] == 10
    assert report["clients_closed"] == 0 and report["bad_frames"] == 0
    assert report["server_errors"] == {}
    assert report["poses_delivered"] > 0 and report["clients_without_snapshots_in_window"] == 0
    assert report["metrics_ok"] and report["skips"] == 0
    # codec snapshots (once the relay sends them) never echo the subscriber's own
    # streams: what lets most clients count them from the header alone
    assert report["codec_own_echo"] == 0
    # ticks: the snapshots and the ticks that had nothing new for the client
    assert report["ticks_per_client_s"] >= report["snapshots_per_client_s"] > 0
    assert report["ticks_per_client_s_min"] >= report["snapshots_per_client_s_min"]


def test_cli_refuses_bad_relay_bench_options_in_one_line(cli: CliForker) -> None:
    """Bad --clients, --procs, --codec or --record with a curve: one line, exit 2 (usage)."""
    cases = [
        (["--clients", "100,abc"], "--clients takes positive counts"),
        (["--procs", "0"], "--procs must be at least 1"),
        (["--codec", "zip"], "--codec must be raw or compact"),
        (["--clients", "10,20", "--record"], "--record takes one --clients count"),
    ]
    for args, message in cases:
        code, _, stderr = cli.run(["bench", "relay", *args], dict(os.environ), limit=60)
        assert code == 2, (args, stderr)
        assert message in stderr and "Traceback" not in stderr


def test_a_send_time_rounded_to_the_microsecond_is_due_at_its_own_grid_point() -> None:
    """A codec snapshot carries its send time rounded to 1 us: a tick that ran just
    after its grid point can read as half a microsecond before it, and must not be
    taken for one due a whole period earlier (it made compact runs' relay p99 read
    one period, 50 ms, at low load)."""
    client = _client(7, [21])
    rate, phase = client.rate, client._phase
    grid = [(k + phase) / rate for k in range(1000, 1040)]
    for point in grid:
        send = round(point * 1e6) / 1e6  # rounded as a relay codec snapshot's base
        assert abs(client._due(send) - point) < 1e-6
    # A tick that ran late by a tenth of a period is still due at its grid point.
    assert abs(client._due(grid[-1] + 0.1 / rate + 1 / rate) - (grid[-1] + 1 / rate)) < 1e-6


def test_a_tick_that_sent_a_client_nothing_does_not_make_its_next_snapshot_late() -> None:
    """In a room of two (codec snapshots leave out one's own streams) a tick can send a
    subscriber nothing. Alone, its next snapshot, on time, reads a whole period late;
    with its room mate's snapshot of that tick seen (RoomTicks), it is due at its own
    grid point, and the empty tick is counted. A tick that ran late is still late."""
    a, b = _client(7, [21]), _client(8, [22])
    b.ticks = a.ticks  # one room
    rate, phase = a.rate, a._phase
    grid = [(k + phase) / rate for k in range(1000, 1010)]
    on_time = [point + 0.002 for point in grid]
    assert abs(b._due(on_time[0]) - grid[0]) < 1e-6
    a._due(on_time[0])
    a._due(on_time[1])  # b's tick at grid[1] was empty: only a got a snapshot
    assert abs(b._due(on_time[2]) - grid[2]) < 1e-6
    assert b.stats.empty_ticks == [1]
    # Without the room mate the same snapshot reads a period late (the old reading).
    lone = _client(9, [23])
    lone._due(on_time[0])
    assert abs(lone._due(on_time[2]) - grid[1]) < 1e-6
    # The tick due at grid[4] ran 1.5 periods late, for both: due at grid[4] still.
    for c in (a, b):
        c._due(on_time[3])
    late = grid[4] + 1.5 / rate
    assert abs(a._due(late) - grid[4]) < 1e-6 and abs(b._due(late) - grid[4]) < 1e-6
    assert b.stats.empty_ticks == [1]
