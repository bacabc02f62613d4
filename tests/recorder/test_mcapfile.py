"""The recorder's own MCAP writer: files that the mcap package's readers and our scanner read."""

from __future__ import annotations

import io
import random

import pytest
from mcap.reader import NonSeekingReader, make_reader

from posecast.recorder.mcapfile import MAGIC, ChunkWriter
from posecast.recorder.scan import ChannelRecord, McapScanner, MessageRecord, MetadataRecord


def _write(chunks: list[list[tuple[int, int, bytes, int]]]) -> tuple[bytes, list[tuple]]:
    """A file with two channels and ``chunks`` of (channel, log ns, data, publish ns)."""
    buf = io.BytesIO()
    w = ChunkWriter(buf)
    w.start(profile="posecast", library="test")
    schema = w.register_schema("s", "jsonschema", b"{}")
    a = w.register_channel("/a", "json", schema)
    b = w.register_channel("/b", "posecast", 0, {"k": "v"})
    assert (schema, a, b) == (1, 1, 2)
    w.add_metadata("session", {"room": "r", "x": "1"})
    sent = []
    seq = 0
    for chunk in chunks:
        for channel, log_ns, data, pub_ns in chunk:
            w.add_message(channel, log_ns, data, pub_ns, seq)
            sent.append((channel, seq, log_ns, pub_ns, data))
            seq += 1
        w.flush()
    w.add_metadata("end", {"records": str(seq)})
    w.finish()
    return buf.getvalue(), sent


def _chunks(rng: random.Random, n: int) -> list[list[tuple[int, int, bytes, int]]]:
    out = []
    t = 10**18
    for _ in range(n):
        chunk = []
        for _ in range(rng.randint(1, 40)):
            t += rng.randint(0, 10**7)
            # log times are not sorted within a chunk: arrival order, not capture
            log = t + rng.randint(-(10**6), 10**6)
            chunk.append((rng.choice([1, 2]), log, rng.randbytes(rng.randint(0, 300)), t))
        out.append(chunk)
    return out


def test_the_mcap_readers_read_every_message_and_the_summary() -> None:
    rng = random.Random(3)
    chunks = _chunks(rng, 7)
    data, sent = _write(chunks)
    assert data.startswith(MAGIC) and data.endswith(MAGIC)
    reader = make_reader(io.BytesIO(data))
    got = [
        (ch.id, m.sequence, m.log_time, m.publish_time, m.data)
        for _schema, ch, m in reader.iter_messages(log_time_order=False)
    ]
    assert got == sent
    summary = reader.get_summary()
    assert summary is not None
    stats = summary.statistics
    assert stats is not None
    assert stats.message_count == len(sent) and stats.chunk_count == len(chunks)
    assert stats.channel_count == 2 and stats.schema_count == 1 and stats.metadata_count == 2
    assert stats.message_start_time == min(m[2] for m in sent)
    assert stats.message_end_time == max(m[2] for m in sent)
    assert stats.channel_message_counts == {c: sum(1 for m in sent if m[0] == c) for c in (1, 2)}
    assert len(summary.chunk_indexes) == len(chunks)
    for index, chunk in zip(summary.chunk_indexes, chunks, strict=True):
        assert index.message_start_time == min(m[1] for m in chunk)
        assert index.message_end_time == max(m[1] for m in chunk)
    assert summary.channels[2].topic == "/b" and summary.channels[2].metadata == {"k": "v"}
    # time-ordered reading and a time window go through the chunk indexes
    ordered = [m.log_time for _s, _c, m in reader.iter_messages()]
    assert ordered == sorted(m[2] for m in sent)
    lo, hi = sorted(m[2] for m in sent)[10], sorted(m[2] for m in sent)[40]
    window = [m.log_time for _s, _c, m in reader.iter_messages(starting_at=lo, ending_before=hi)]
    assert window == [t for t in ordered if lo <= t < hi]
    metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert metadata == {"session": {"room": "r", "x": "1"}, "end": {"records": str(len(sent))}}
    # the streaming reader, front to back without the summary
    streamed = [
        m.data
        for _s, _c, m in NonSeekingReader(io.BytesIO(data)).iter_messages(log_time_order=False)
    ]
    assert streamed == [m[4] for m in sent]


def test_the_scanner_reads_it_linearly_and_checks_every_chunk() -> None:
    data, sent = _write(_chunks(random.Random(5), 4))
    scanner = McapScanner(data)
    records = list(scanner.records())
    assert scanner.complete and scanner.chunks_ok == 4 and scanner.chunks_lost == 0
    assert scanner.header is not None and scanner.header.profile == "posecast"
    messages = [r for r in records if isinstance(r, MessageRecord)]
    assert [m.data for m in messages] == [m[4] for m in sent]
    assert sorted(r.id for r in records if isinstance(r, ChannelRecord)) == [1, 2]
    assert [r.name for r in records if isinstance(r, MetadataRecord)] == ["session", "end"]


def test_a_flipped_bit_in_a_chunk_fails_its_checksum() -> None:
    data, _sent = _write(_chunks(random.Random(7), 3))
    reader = make_reader(io.BytesIO(data))
    summary = reader.get_summary()
    assert summary is not None
    second = summary.chunk_indexes[1]
    damaged = bytearray(data)
    damaged[second.chunk_start_offset + second.chunk_length - 5] ^= 0x10
    scanner = McapScanner(bytes(damaged))
    list(scanner.records())
    assert scanner.chunks_ok == 2 and scanner.chunks_lost == 1


def test_an_empty_file_is_valid() -> None:
    buf = io.BytesIO()
    w = ChunkWriter(buf)
    w.start(profile="posecast", library="test")
    w.flush()  # no messages: no chunk
    w.finish()
    w.finish()  # twice is harmless
    reader = make_reader(io.BytesIO(buf.getvalue()))
    assert list(reader.iter_messages()) == []
    summary = reader.get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == 0 and summary.chunk_indexes == []


def test_an_unknown_channel_is_an_error() -> None:
    w = ChunkWriter(io.BytesIO())
    w.start()
    with pytest.raises(KeyError):
        w.add_message(3, 0, b"", 0, 0)
