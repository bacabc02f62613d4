"""Compact sessions are recorded as their codes (pose layout 2), read back bit for bit.

The updates go through the real codec path: a client's ``UpstreamEncoder`` makes
the frame, the relay's ``UpstreamDecoder`` decodes it into the ``PoseUpdate`` the
relay relays and the codes (``last_codes``) the recorder keeps.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray

from posecast.protocol import DEFAULT_VOLUME, PoseUpdate
from posecast.protocol._compact import UpstreamDecoder, UpstreamEncoder
from posecast.recorder import (
    FormatError,
    PoseRecord,
    ProcessRecorder,
    SessionReader,
    SessionRecorder,
    info,
    load_streams,
    recover,
)
from posecast.recorder.compact import (
    _HEAD,
    CompactUpdate,
    _Cursor,
    compact_update,
    decode_group,
    encode_group,
    is_group,
)
from posecast.recorder.export import read_session
from posecast.recorder.format import POSES_TOPIC
from posecast.recorder.scan import ChannelRecord, McapScanner, MessageRecord
from posecast.scenarios.traces import find_traces, load_trace

#: (arrival, user, the update the relay relays, its codes)
Relayed = tuple[float, int, PoseUpdate, dict[int, list[int]]]


def _room(
    sample_dir: Path, users: int = 6, rate: float = 30.0, seconds: float = 6.0, vel: bool = False
) -> list[Relayed]:
    """Every user's updates of real traces, through a real upstream encoder and decoder."""
    traces = [load_trace(p) for p in find_traces(sample_dir)]
    rng = np.random.default_rng(5)
    t0 = 8765.4321
    out = []
    for user in range(users):
        tr = traces[user % len(traces)]
        velocities = tr.velocities() if vel else None
        sender, relay = UpstreamEncoder(DEFAULT_VOLUME), UpstreamDecoder(DEFAULT_VOLUME)
        i0 = int(rng.integers(0, len(tr.times) // 2))
        phase = float(rng.uniform(0, 1 / rate))
        for k in range(int(seconds * rate)):
            idx = int(np.searchsorted(tr.times, tr.times[i0] + k / rate))
            capture = t0 + phase + float(tr.times[idx] - tr.times[i0])
            update = PoseUpdate.from_arrays(
                k + 1,
                np.arange(3 * user, 3 * user + 3),
                capture - np.array([0.0, 0.004, 0.011]),
                tr.poses[idx],
                velocities=None if velocities is None else velocities[idx],
            )
            relayed = relay.decode(sender.encode(update))
            sender.commit()
            # the server's clock (time.monotonic) counts whole nanoseconds
            arrival = round((capture + float(rng.uniform(0.02, 0.06))) * 1e9) / 1e9
            out.append((arrival, user, relayed, dict(relay.last_codes)))
    out.sort(key=lambda x: x[0])
    return out


def _record(rec: SessionRecorder | ProcessRecorder, room: list[Relayed]) -> Path:
    for arrival, user, update, codes in room:
        assert rec.record_pose_update(user, arrival, update, codes, DEFAULT_VOLUME)
    return rec.close(room[-1][0] + 1.0)


def _pose_messages(path: Path) -> Iterator[MessageRecord]:
    topics = {}
    for r in McapScanner(path.read_bytes()).records():
        if isinstance(r, ChannelRecord):
            topics[r.id] = r.topic
        elif isinstance(r, MessageRecord) and topics[r.channel_id] == POSES_TOPIC:
            yield r


def _assert_same(rec: PoseRecord, arrival: float, user: int, update: PoseUpdate) -> None:
    assert (rec.user, rec.seq, rec.arrival) == (user, update.seq, arrival)
    assert np.array_equal(rec.streams, update.streams)
    assert rec.capture_times.tobytes() == update.capture_times.tobytes()
    assert rec.poses.tobytes() == update.poses.tobytes()
    if update.velocities is None:
        assert rec.velocities is None
    else:
        assert rec.velocities is not None
        assert rec.velocities.tobytes() == update.velocities.astype("<f2").tobytes()


def _check_file(path: Path, room: list[Relayed]) -> dict[tuple[int, int], PoseRecord]:
    """Every relayed update is in the file, bit for bit, through every reader path."""
    with SessionReader(path) as reader:
        got = {(r.user, r.seq): r for r in reader.poses()}
    assert len(got) == len(room)
    for arrival, user, update, _codes in room:
        _assert_same(got[(user, update.seq)], arrival, user, update)
    by_stream: dict[tuple[int, int], list[tuple[float, NDArray[np.float32]]]] = {}
    for _arrival, user, update, _codes in room:
        for sid, cap, pose in zip(
            update.streams.tolist(), update.capture_times, update.poses, strict=True
        ):
            by_stream.setdefault((user, sid), []).append((cap, pose))
    streams = load_streams(path)
    session = {(s.user, s.stream): s for s in read_session(path).streams}
    for key, rows in by_stream.items():
        times = np.array([r[0] for r in rows])
        poses = np.array([r[1] for r in rows], np.float32)
        assert streams[key].times.tobytes() == times.tobytes()
        assert streams[key].poses.tobytes() == poses.tobytes()
        order = np.argsort(times, kind="stable")
        assert session[key].poses.tobytes() == poses[order].tobytes()
    return got


@pytest.mark.parametrize("writer", ["thread", "process"])
def test_compact_session_is_recorded_as_codes_and_read_back_bit_exact(
    tmp_path: Path, sample_dir: Path, writer: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """Real traces through the real codec: layout 2 on disk, the relayed floats read back."""
    room = _room(sample_dir, users=10, seconds=10.0)
    if writer == "thread":
        # a live room closes a chunk every 0.5 s: 10 users x 30 Hz x 0.5 s = 150 updates
        rec: SessionRecorder | ProcessRecorder = SessionRecorder.open(
            tmp_path, "c", chunk_records=150, queue_size=20_000
        )
    else:
        rec = ProcessRecorder.open(tmp_path, "c", queue_size=20_000)
    path = _record(rec, room)
    assert all(is_group(m.data) for m in _pose_messages(path))
    _check_file(path, room)
    summary = info(path)
    assert summary["records"]["poses"] == len(room)
    assert summary["sizes"]["poses"] == 3 * len(room)
    per_pose = summary["sizes"]["bytes_per_pose"]
    with capsys.disabled():
        print(f"\ncompact recording ({writer}, 10 users x 30 Hz x 10 s): {per_pose:.2f} B/pose")
    assert per_pose <= 12.0


def test_compact_velocities_are_recorded_bit_exact(tmp_path: Path, sample_dir: Path) -> None:
    """The velocity variant (13 codes an entry) gives back the float16 velocities relayed."""
    room = _room(sample_dir, users=3, seconds=2.0, vel=True)
    assert room[0][2].velocities is not None
    path = _record(SessionRecorder.open(tmp_path, "v", chunk_records=45), room)
    assert all(is_group(m.data) for m in _pose_messages(path))
    _check_file(path, room)


def test_small_chunks_and_time_ranges_read_exactly(tmp_path: Path, sample_dir: Path) -> None:
    """Each chunk codes its own keys: 7-update chunks read back exactly, and a time range
    gives exactly the updates that arrived in it (a message starting before it too)."""
    room = _room(sample_dir, users=4, seconds=3.0)
    path = _record(SessionRecorder.open(tmp_path, "s", chunk_records=7), room)
    messages = list(_pose_messages(path))
    assert len({m.chunk for m in messages}) >= len(room) // 7
    _check_file(path, room)
    start, end = room[40][0], room[130][0]
    with SessionReader(path) as reader:
        window = [(r.user, r.seq) for r in reader.poses(start, end)]
    with SessionReader(path, linear=True) as reader:
        linear = [(r.user, r.seq) for r in reader.poses(start, end)]
    assert window == linear == [(u, up.seq) for a, u, up, _ in room if start <= a < end]


def test_big_chunks_read_exactly_in_a_time_range(tmp_path: Path, sample_dir: Path) -> None:
    """A message of many updates (one chunk) still yields only the updates in range."""
    room = _room(sample_dir, users=2, seconds=2.0)
    path = _record(SessionRecorder.open(tmp_path, "b"), room)
    assert len(list(_pose_messages(path))) == 1
    start, end = room[10][0], room[50][0]
    with SessionReader(path) as reader:
        window = [(r.user, r.seq) for r in reader.poses(start, end)]
    assert window == [(u, up.seq) for a, u, up, _ in room if start <= a < end]


def test_codes_that_do_not_give_the_relayed_poses_are_recorded_as_layout_1(
    tmp_path: Path, sample_dir: Path
) -> None:
    """The writer checks the codes against the relayed floats: a mismatch goes as floats."""
    room = _room(sample_dir, users=2, seconds=1.0)
    wrong = dict(room[1][3])  # another update's codes
    room[0] = (room[0][0], room[0][1], room[0][2], wrong)
    rec = SessionRecorder.open(tmp_path, "w")
    path = _record(rec, room)
    layouts = sorted(m.data[0] for m in _pose_messages(path))
    assert layouts == [1, 2]
    _check_file(path, room)


def test_recovery_keeps_the_intact_chunks_exact(tmp_path: Path, sample_dir: Path) -> None:
    """A crashed recording with one corrupted chunk: recovery keeps the other chunks, and
    every update read back is exactly the relayed one (a lost chunk loses only its own)."""
    room = _room(sample_dir, users=3, seconds=3.0)
    rec = SessionRecorder.open(tmp_path, "r", chunk_records=30)
    for arrival, user, update, codes in room:
        assert rec.record_pose_update(user, arrival, update, codes, DEFAULT_VOLUME)
    part = rec.abandon()
    data = bytearray(part.read_bytes())
    data[len(data) // 2] ^= 0x5A  # inside some chunk's compressed bytes
    part.write_bytes(bytes(data))
    report = recover(part)
    assert report.chunks_lost == 1
    with SessionReader(report.output) as reader:
        got = list(reader.poses())
    assert 0 < len(got) < len(room)
    relayed = {(u, up.seq): (a, up) for a, u, up, _ in room}
    for r in got:
        arrival, update = relayed[(r.user, r.seq)]
        _assert_same(r, arrival, r.user, update)


def _group(sample_dir: Path) -> bytes:
    room = _room(sample_dir, users=2, seconds=0.2)
    updates = [
        cu
        for a, u, up, codes in room
        if (cu := compact_update(u, a, up, codes, DEFAULT_VOLUME)) is not None
    ]
    data, bad = encode_group(updates)
    assert data is not None and not bad
    return data


def test_every_truncation_and_bit_flip_of_a_message_is_refused(sample_dir: Path) -> None:
    """Layout 2 is decoded whole or refused: a cut or a flipped bit is a FormatError."""
    data = _group(sample_dir)
    assert len(decode_group(data)) == 12
    for cut in range(len(data)):
        with pytest.raises(FormatError):
            decode_group(data[:cut])
    with pytest.raises(FormatError):
        decode_group(data + b"\x00")
    for i in range(len(data)):
        for bit in (0, 3, 7):
            bad = bytearray(data)
            bad[i] ^= 1 << bit
            with pytest.raises(FormatError):
                decode_group(bytes(bad))


def test_out_of_range_codes_are_refused_even_with_a_good_crc(sample_dir: Path) -> None:
    """A message whose CRC matches but whose codes leave the volume is refused."""
    data = bytearray(_group(sample_dir))
    m, k = struct.unpack_from("<II", data, 2)
    cur = _Cursor(bytes(data))
    for count in [m] * 6 + [k] * 8:  # per update columns, stream, dt, idx, a, b, c, px
        cur.column(count)
    # the last column (pz): every byte of its first value (a key: zigzag of a negative code)
    width = data[cur.at]
    for plane in range(width):
        data[cur.at + 1 + plane * k] = 0xFF
    crc_at = _HEAD.size - 4
    crc = zlib.crc32(data[_HEAD.size :], zlib.crc32(data[:crc_at]))
    struct.pack_into("<I", data, crc_at, crc)
    with pytest.raises(FormatError, match=r"outside the room volume|rotation"):
        decode_group(bytes(data))


def test_a_corrupt_compact_message_in_a_file_is_an_error_not_a_pose(
    tmp_path: Path, sample_dir: Path
) -> None:
    """A recording holding a cut layout 2 message reads as a FormatError, naming why."""
    data = _group(sample_dir)
    rec = SessionRecorder.open(tmp_path, "h")
    assert rec.offer_encoded(POSES_TOPIC, 10**12, 10**12, data[:-3], 12)
    path = rec.close(1001.0)
    with SessionReader(path) as reader, pytest.raises(FormatError, match="compact pose message"):
        reader.load_streams()


def test_compact_update_refuses_codes_of_other_streams(sample_dir: Path) -> None:
    """Codes that do not name the update's streams are not taken (recorded as layout 1)."""
    arrival, user, update, codes = _room(sample_dir, users=1, seconds=0.1)[0]
    assert isinstance(compact_update(user, arrival, update, codes, DEFAULT_VOLUME), CompactUpdate)
    fewer = dict(list(codes.items())[:2])
    assert compact_update(user, arrival, update, fewer, DEFAULT_VOLUME) is None
    other = {sid + 100: row for sid, row in codes.items()}
    assert compact_update(user, arrival, update, other, DEFAULT_VOLUME) is None


def test_when_the_relay_vanishes_the_compact_updates_are_in_the_part(
    tmp_path: Path, sample_dir: Path
) -> None:
    """The pipe closes without a stop (the server was SIGKILLed): the writer process
    writes the open group before it keeps the ``.part``; recovery reads it exactly."""
    room = _room(sample_dir, users=3, seconds=2.0)
    rec = ProcessRecorder.open(tmp_path, "k", batch_size=16)
    for arrival, user, update, codes in room:
        assert rec.record_pose_update(user, arrival, update, codes, DEFAULT_VOLUME)
    rec._handoff()
    rec.host.drain(block=True)  # everything is in the pipe; now close it as a dying process does
    proc = rec.host.process
    assert proc.stdin is not None
    proc.stdin.close()
    assert proc.wait(30) == 2
    assert proc.stdout is not None
    proc.stdout.close()
    assert all(is_group(m.data) for m in _pose_messages(rec.part_path))
    report = recover(rec.part_path, tmp_path / "recovered.mcap")
    assert report.chunks_lost == 0 and not report.complete
    _check_file(report.output, room)
