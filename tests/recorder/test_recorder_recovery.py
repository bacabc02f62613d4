"""Recovering .part files: truncation, corrupted chunks, corrupted lengths, leftovers."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from reckit import Msg, OracleChunk, make_updates, messages_of, oracle_chunks, write_session

from posecast.recorder import (
    FormatError,
    PoseRecord,
    RecoveryReport,
    SessionReader,
    SessionRecorder,
    find_leftovers,
    read_records,
    recover,
    recover_leftovers,
)
from posecast.recorder.scan import MAGIC


@pytest.fixture(scope="module")
def many_chunks(tmp_path_factory: pytest.TempPathFactory) -> tuple[bytes, list[OracleChunk]]:
    """A finished session of 1200 updates in chunks of 25 records, and its chunks."""
    path = write_session(tmp_path_factory.mktemp("src"), make_updates(1200), chunk_records=25)
    data = path.read_bytes()
    chunks = oracle_chunks(data)
    assert len(chunks) > 45
    return data, chunks


def _expected_before(chunks: list[OracleChunk], cut: int) -> list[Msg]:
    return [m for c in chunks if c.offset + c.length <= cut for m in c.messages]


def _recover_bytes(tmp_path: Path, data: bytes, name: str) -> tuple[RecoveryReport, list[Msg]]:
    part = tmp_path / f"{name}.mcap.part"
    part.write_bytes(data)
    report = recover(part)
    assert report.output == tmp_path / f"{name}.mcap"
    return report, messages_of(report.output)


def test_truncation_sweep_keeps_exactly_the_complete_chunks(
    tmp_path: Path, many_chunks: tuple[bytes, list[OracleChunk]]
) -> None:
    """Cut anywhere: recovered records are exactly those of the chunks complete before the cut."""
    data, chunks = many_chunks
    rng = np.random.default_rng(7)
    first, last = chunks[0].offset, chunks[-1].offset + chunks[-1].length
    cuts = set(rng.integers(0, len(data), 30).tolist())
    cuts |= set(rng.integers(first, last, 20).tolist())
    cuts |= {0, 5, 8, first, first + 1, chunks[3].offset, chunks[3].offset + chunks[3].length}
    cuts |= {last, last + 3, len(data) - 1}
    for cut in sorted(cuts):
        report, got = _recover_bytes(tmp_path, data[:cut], f"cut{cut}")
        assert got == _expected_before(chunks, cut), f"cut at {cut}"
        assert report.lost_records == 0  # nothing missing between recovered records
        assert report.chunks_lost == 0
        if first < cut < last:
            assert report.truncated_at is not None or cut in {c.offset for c in chunks}
            assert not report.complete


def test_finished_file_recovers_completely(
    tmp_path: Path, many_chunks: tuple[bytes, list[OracleChunk]]
) -> None:
    """Recovering an intact file keeps every message and reports nothing wrong."""
    data, chunks = many_chunks
    report, got = _recover_bytes(tmp_path, data, "whole")
    assert got == [m for c in chunks for m in c.messages]
    assert report.complete and report.clean
    assert report.chunks_recovered == len(chunks)


@pytest.mark.parametrize("which", [0, 1, 17, -1])
def test_flipped_bit_in_compressed_data_loses_only_that_chunk(
    tmp_path: Path, many_chunks: tuple[bytes, list[OracleChunk]], which: int
) -> None:
    """A bit flipped in one chunk's compressed data loses that chunk alone, and names it."""
    data, chunks = many_chunks
    bad = chunks[which]
    corrupted = bytearray(data)
    corrupted[bad.offset + bad.length // 2] ^= 0x04
    report, got = _recover_bytes(tmp_path, bytes(corrupted), f"flip{which}")
    assert got == [m for c in chunks if c is not bad for m in c.messages]
    assert report.chunks_lost == 1
    assert [(p.offset, p.kind) for p in report.problems] == [(bad.offset, "bad-chunk")]
    assert report.problems[0].length == bad.length
    if which != -1:
        assert report.lost_records == len(bad.messages)
    # The channel definitions are written outside the chunks: none is lost with one.
    assert report.restored_channels == ()


def test_channels_lost_with_a_chunk_are_restored(
    tmp_path: Path, many_chunks: tuple[bytes, list[OracleChunk]]
) -> None:
    """mcap's own Writer puts channel records into the first chunk: lost with it, restored."""
    from mcap.writer import CompressionType, Writer

    from posecast.recorder.format import CHANNELS, PROFILE

    _data, chunks = many_chunks
    part = tmp_path / "old.mcap.part"
    with part.open("wb") as f:
        writer = Writer(f, compression=CompressionType.ZSTD, chunk_size=1 << 62)
        writer.start(profile=PROFILE, library="mcap")
        ids = {}
        for spec in CHANNELS:
            schema = writer.register_schema(
                spec.schema_name, spec.schema_encoding, spec.schema_data
            )
            ids[spec.topic] = writer.register_channel(spec.topic, spec.message_encoding, schema)
        for chunk in chunks[:6]:
            for topic, seq, log_ns, pub_ns, payload in chunk.messages:
                writer.add_message(ids[topic], log_ns, payload, pub_ns, seq)
            writer.flush()  # type: ignore[no-untyped-call]
        writer.finish()  # type: ignore[no-untyped-call]
    old = oracle_chunks(part.read_bytes())
    corrupted = bytearray(part.read_bytes())
    corrupted[old[0].offset + old[0].length // 2] ^= 0x04
    part.write_bytes(bytes(corrupted))
    report = recover(part)
    later = [m for c in chunks[1:6] for m in c.messages]
    assert messages_of(report.output) == later
    assert set(report.restored_channels) == {m[0] for m in later}


def test_flipped_bit_in_a_chunk_length_field(
    tmp_path: Path, many_chunks: tuple[bytes, list[OracleChunk]]
) -> None:
    """A damaged chunk length is repaired from the chunk's framing; later chunks all recovered."""
    data, chunks = many_chunks
    for bit in (3, 20, 45):
        bad = chunks[10]
        corrupted = bytearray(data)
        corrupted[bad.offset + 1 + bit // 8] ^= 1 << (bit % 8)
        report, got = _recover_bytes(tmp_path, bytes(corrupted), f"len{bit}")
        assert got == [m for c in chunks for m in c.messages], f"bit {bit}"
        assert [(p.offset, p.kind) for p in report.problems] == [(bad.offset, "repaired")]


def test_resync_after_corrupted_framing(
    tmp_path: Path, many_chunks: tuple[bytes, list[OracleChunk]]
) -> None:
    """A chunk with a damaged length that cannot be repaired is skipped by resyncing."""
    data, chunks = many_chunks
    bad = chunks[10]
    # Chunk record: opcode @0, length u64 @1, start/end/size/crc @9..36, compression
    # "zstd" @37..44, records length u64 @45, compressed records @53.
    for second in (45 + 5, bad.length // 2):  # the inner length, or the compressed data
        corrupted = bytearray(data)
        corrupted[bad.offset + 1 + 5] ^= 0x10  # outer length: + 2**44, past the end
        corrupted[bad.offset + second] ^= 0x01
        report, got = _recover_bytes(tmp_path, bytes(corrupted), f"sync{second}")
        assert got == [m for c in chunks if c is not bad for m in c.messages]
        assert report.chunks_lost == 1
        problem = report.problems[0]
        assert (problem.offset, problem.length) == (bad.offset, bad.length)
        assert report.lost_records == len(bad.messages)


def test_garbage_between_chunks_is_skipped(
    tmp_path: Path, many_chunks: tuple[bytes, list[OracleChunk]]
) -> None:
    """Junk bytes overwriting a whole chunk are skipped; everything else is kept."""
    data, chunks = many_chunks
    bad = chunks[20]
    junk = np.random.default_rng(3).integers(0, 256, bad.length, dtype=np.uint8).tobytes()
    corrupted = data[: bad.offset] + junk + data[bad.offset + bad.length :]
    report, got = _recover_bytes(tmp_path, corrupted, "junk")
    assert got == [m for c in chunks if c is not bad for m in c.messages]
    assert report.problems and report.problems[0].offset == bad.offset


def test_empty_and_header_only_files(tmp_path: Path) -> None:
    """An empty or header-only .part becomes a valid, empty MCAP file."""
    for name, data in (("empty", b""), ("magic", MAGIC), ("junk", b"not an mcap file")):
        report, got = _recover_bytes(tmp_path, data, name)
        assert got == [] and report.messages == 0


def test_recovered_file_keeps_metadata_and_reads_as_a_session(
    tmp_path: Path, many_chunks: tuple[bytes, list[OracleChunk]]
) -> None:
    """The recovered file is a normal session file: metadata, records, a recovery note."""
    data, chunks = many_chunks
    cut = chunks[30].offset + 7
    report, _ = _recover_bytes(tmp_path, data[:cut], "meta")
    with SessionReader(report.output) as reader:
        assert reader.complete
        assert reader.session["room"] == "test-room"
        assert reader.metadata["posecast.recovery"]["truncated_at"] == str(chunks[30].offset)
        poses = list(reader.poses())
        assert len(poses) == sum(m[0] == "poses" for c in chunks[:30] for m in c.messages)
        assert all(isinstance(p, PoseRecord) for p in poses)


def test_leftovers_are_found_and_recovered(tmp_path: Path) -> None:
    """find_leftovers lists .part files; recover_leftovers recovers them and never overwrites."""
    updates = make_updates(50)
    for name in ("a", "b"):
        rec = SessionRecorder.open(tmp_path, "room", name=name, chunk_records=10)
        for u in updates:
            rec.record_update(u.user, u.seq, u.arrival, u.streams, u.capture_times, u.poses)
        rec.hold()  # a crash: the file stays .part
    (tmp_path / "b.mcap").write_bytes(b"someone else's file")
    (tmp_path / "notes.txt").write_text("x")
    assert [p.name for p in find_leftovers(tmp_path)] == ["a.mcap.part", "b.mcap.part"]
    reports = recover_leftovers(tmp_path)
    assert [r.output.name for r in reports] == ["a.mcap", "b.recovered.mcap"]
    assert find_leftovers(tmp_path) == []
    assert (tmp_path / "b.mcap").read_bytes() == b"someone else's file"
    for r in reports:
        assert r.messages_by_topic["poses"] == 50
        assert sum(isinstance(x, PoseRecord) for x in read_records(r.output)) == 50


def test_recover_refuses_to_overwrite(tmp_path: Path) -> None:
    """recover() never replaces an existing output unless asked to."""
    part = tmp_path / "x.mcap.part"
    part.write_bytes(MAGIC)
    (tmp_path / "x.mcap").write_bytes(b"keep")
    with pytest.raises(FileExistsError):
        recover(part)
    assert recover(part, overwrite=True).output.read_bytes() != b"keep"
    assert part.exists()
    assert recover(part, tmp_path / "y.mcap", remove_part=True).messages == 0
    assert not part.exists()


def test_chunk_layout_assumed_by_these_tests(many_chunks: tuple[bytes, list[OracleChunk]]) -> None:
    """Chunk records start with opcode 6 and a u64 length, as the tests above assume."""
    data, chunks = many_chunks
    for c in chunks[:3]:
        op, length = struct.unpack_from("<BQ", data, c.offset)
        assert (op, 9 + length) == (6, c.length)


def test_random_damage_never_yields_a_record_that_was_not_written(
    tmp_path: Path, many_chunks: tuple[bytes, list[OracleChunk]]
) -> None:
    """Random garbage anywhere: recovery succeeds, and every record it keeps is an original one."""
    data, chunks = many_chunks
    original = [m for c in chunks for m in c.messages]
    position = {m: i for i, m in enumerate(original)}
    rng = np.random.default_rng(99)
    for trial in range(20):
        damaged = bytearray(data)
        for _ in range(int(rng.integers(1, 4))):
            at = int(rng.integers(0, len(data) - 8))
            width = int(rng.integers(1, 9))
            damaged[at : at + width] = rng.integers(0, 256, width, dtype=np.uint8).tobytes()
        report, got = _recover_bytes(tmp_path, bytes(damaged), f"fuzz{trial}")
        indexes = [position.get(m, -1) for m in got]
        assert -1 not in indexes, f"trial {trial}: a record that was never written"
        assert indexes == sorted(indexes), f"trial {trial}: records out of order"
        # chunks are kept whole or lost whole
        got_set = set(got)
        partly = [c for c in chunks if 0 < sum(m in got_set for m in c.messages) < len(c.messages)]
        assert partly == [], f"trial {trial}: a chunk was kept in part"
        assert report.messages == len(got)


def test_damaged_finished_file_reads_linearly(
    tmp_path: Path, many_chunks: tuple[bytes, list[OracleChunk]]
) -> None:
    """Reading a damaged finished file through its index fails clearly; linear reading skips."""
    data, chunks = many_chunks
    bad = chunks[5]
    damaged = bytearray(data)
    damaged[bad.offset + bad.length // 2] ^= 0x01
    path = tmp_path / "damaged.mcap"
    path.write_bytes(bytes(damaged))
    with SessionReader(path) as reader, pytest.raises(FormatError, match="recover"):
        list(reader.records())
    with SessionReader(path, linear=True) as reader:
        poses = list(reader.poses())
    expected = [m for c in chunks if c is not bad for m in c.messages if m[0] == "poses"]
    assert len(poses) == len(expected)
