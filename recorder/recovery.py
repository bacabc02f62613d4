"""Turn a left-over ``NAME.mcap.part`` (the recorder crashed) into a complete ``NAME.mcap``.

:func:`recover` reads the file linearly with :class:`recorder.scan.McapScanner`
(every intact chunk is kept, a corrupted chunk is skipped and reported, a
truncated tail ends the scan, a corrupted length field is resynchronised on the
next intact chunk), writes every recovered schema, channel, message and
metadata record into a new, fully indexed MCAP file, and re-opens that file with
mcap's indexed reader to prove it reads (message count and summary). Channels of
a posecast file whose definitions were in a lost chunk are restored from
:data:`recorder.format.CHANNELS`. The output is written as ``*.recovering`` and
renamed when verified; the source is only deleted on request.

The server should call :func:`recover_leftovers` on its recording directory at
start-up (:func:`find_leftovers` lists the candidates).
"""

from __future__ import annotations

import itertools
import logging
import mmap
import os
from dataclasses import dataclass, field
from pathlib import Path

from mcap.reader import make_reader
from mcap.writer import CompressionType, IndexType, Writer

from posecast.protocol.errors import PosecastError
from posecast.recorder.format import CHANNELS, POSE_ENCODING, PROFILE, posecast_version
from posecast.recorder.scan import (
    ChannelRecord,
    HeaderRecord,
    McapScanner,
    MessageRecord,
    MetadataRecord,
    ScanProblem,
    SchemaRecord,
)
from posecast.recorder.writer import PART_SUFFIX, fsync_dir

__all__ = [
    "RecoveryError",
    "RecoveryReport",
    "find_leftovers",
    "recover",
    "recover_leftovers",
]

log = logging.getLogger("posecast.recorder")

RECOVERY_METADATA = "posecast.recovery"


class RecoveryError(PosecastError, RuntimeError):
    """The recovered file did not read back as written (it is not kept)."""


@dataclass(frozen=True)
class RecoveryReport:
    """What :func:`recover` found and wrote."""

    source: Path
    output: Path
    source_bytes: int
    output_bytes: int
    complete: bool
    """The source had its Data End record: the writer finished it."""
    truncated_at: int | None
    """Offset of the record the source ends inside (the tail after it is lost)."""
    chunks_recovered: int
    chunks_lost: int
    messages: int
    messages_by_topic: dict[str, int]
    lost_records: int
    """Records missing between recovered ones (gaps in the file's sequence numbers)."""
    orphan_messages: int
    """Messages of channels whose definition was lost (not written)."""
    restored_channels: tuple[str, ...]
    """Topics whose channel definition was restored from posecast's defaults."""
    first_time: int | None
    last_time: int | None
    """Log time (ns) of the first and last recovered message."""
    problems: tuple[ScanProblem, ...] = field(default_factory=tuple)

    @property
    def clean(self) -> bool:
        """Nothing was lost, skipped or repaired (apart from the summary section)."""
        return not self.problems and not self.lost_records and not self.orphan_messages

    def summary(self) -> str:
        """A few lines for logs and the CLI."""
        state = "finished" if self.complete else "unfinished"
        if self.truncated_at is not None:
            state += f", truncated at byte {self.truncated_at}"
        topics = ", ".join(f"{k} {v}" for k, v in sorted(self.messages_by_topic.items()))
        lines = [
            f"recovered {self.source.name} ({state}, {self.source_bytes} B) -> "
            f"{self.output.name} ({self.output_bytes} B)",
            f"  {self.messages} messages ({topics or 'none'}) in {self.chunks_recovered} chunks;"
            f" {self.chunks_lost} chunks lost, {self.lost_records} records missing"
            f" between recovered ones",
        ]
        if self.orphan_messages:
            lines.append(f"  {self.orphan_messages} messages of unknown channels dropped")
        if self.restored_channels:
            lines.append(f"  channel definitions restored: {', '.join(self.restored_channels)}")
        for p in self.problems:
            lines.append(f"  at byte {p.offset}: {p.kind}: {p.reason} ({p.length} B)")
        return "\n".join(lines)


def _default_output(source: Path) -> Path:
    name = source.name
    if name.endswith(PART_SUFFIX):
        return source.with_name(name[: -len(PART_SUFFIX)])
    stem = name[:-5] if name.endswith(".mcap") else name
    return source.with_name(f"{stem}.recovered.mcap")


class _Copier:
    """Writes scanned records into a new MCAP file, remapping schema and channel ids."""

    def __init__(self, writer: Writer, posecast: bool) -> None:
        self.w = writer
        self._posecast = posecast
        self.schemas: dict[int, SchemaRecord] = {}
        self.schema_ids: dict[int, int] = {}
        self.channel_ids: dict[int, int] = {}
        self.topics: dict[int, str] = {}
        self.restored: list[str] = []
        self.orphans = 0
        self.messages = 0
        self.by_topic: dict[str, int] = {}
        self.first: int | None = None
        self.last: int | None = None
        self.lost = 0
        self._prev_seq: int | None = None

    def schema(self, rec: SchemaRecord) -> None:
        if rec.id not in self.schema_ids and rec.id != 0:
            self.schemas[rec.id] = rec
            self.schema_ids[rec.id] = self.w.register_schema(rec.name, rec.encoding, rec.data)

    def channel(self, rec: ChannelRecord) -> None:
        if rec.id in self.channel_ids:
            return
        schema_id = 0
        if rec.schema_id != 0:
            if rec.schema_id not in self.schema_ids:
                self._restore_schema(rec.schema_id)
            schema_id = self.schema_ids.get(rec.schema_id, 0)
        self.channel_ids[rec.id] = self.w.register_channel(
            rec.topic, rec.message_encoding, schema_id, rec.metadata
        )
        self.topics[rec.id] = rec.topic
        if rec.message_encoding == POSE_ENCODING:
            self._posecast = True

    def posecast(self) -> bool:
        """A posecast file: by its profile, or by a channel only posecast writes."""
        return self._posecast

    def _restore_schema(self, schema_id: int) -> None:
        if self.posecast() and 1 <= schema_id <= len(CHANNELS):
            spec = CHANNELS[schema_id - 1]
            self.schema(
                SchemaRecord(schema_id, spec.schema_name, spec.schema_encoding, spec.schema_data)
            )

    def _restore_channel(self, channel_id: int) -> bool:
        if not (self.posecast() and 1 <= channel_id <= len(CHANNELS)):
            return False
        spec = CHANNELS[channel_id - 1]
        self.channel(ChannelRecord(channel_id, channel_id, spec.topic, spec.message_encoding, {}))
        self.restored.append(spec.topic)
        return True

    def message(self, rec: MessageRecord) -> None:
        if rec.channel_id not in self.channel_ids and not self._restore_channel(rec.channel_id):
            self.orphans += 1
            return
        self.w.add_message(
            self.channel_ids[rec.channel_id], rec.log_time, rec.data, rec.publish_time, rec.sequence
        )
        self.messages += 1
        topic = self.topics[rec.channel_id]
        self.by_topic[topic] = self.by_topic.get(topic, 0) + 1
        self.first = rec.log_time if self.first is None else min(self.first, rec.log_time)
        self.last = rec.log_time if self.last is None else max(self.last, rec.log_time)
        if self.posecast():
            # posecast numbers the records of a file from 0
            prev = -1 if self._prev_seq is None else self._prev_seq
            gap = (rec.sequence - prev - 1) & 0xFFFFFFFF
            if gap < 1 << 31:  # a smaller number is a reordering, not a loss
                self.lost += gap
        self._prev_seq = rec.sequence


def recover(
    path_part: str | os.PathLike[str],
    out_path: str | os.PathLike[str] | None = None,
    *,
    overwrite: bool = False,
    remove_part: bool = False,
) -> RecoveryReport:
    """Recover every intact chunk of ``path_part`` into a complete, indexed MCAP file.

    ``out_path`` defaults to the source without ``.part`` (``x.mcap`` for
    ``x.mcap.part``; ``x.recovered.mcap`` for any other name). Raises
    ``FileExistsError`` if it exists and ``overwrite`` is false, and
    :class:`RecoveryError` if the new file does not read back. With
    ``remove_part`` the source is deleted once the output is verified.
    """
    source = Path(path_part)
    out = Path(out_path) if out_path is not None else _default_output(source)
    if out.resolve() == source.resolve():
        raise ValueError("the output must not be the source file")
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} exists")
    tmp = out.with_name(out.name + ".recovering")
    source_bytes = source.stat().st_size
    with source.open("rb") as f:
        if source_bytes:
            with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
                scanner, copier = _copy(mm, source, tmp)
        else:
            scanner, copier = _copy(b"", source, tmp)
    try:
        _verify(tmp, copier.messages)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    os.replace(tmp, out)
    fsync_dir(out.parent)
    if remove_part:
        source.unlink()
        fsync_dir(source.parent)
    report = RecoveryReport(
        source=source,
        output=out,
        source_bytes=source_bytes,
        output_bytes=out.stat().st_size,
        complete=scanner.complete,
        truncated_at=scanner.truncated_at,
        chunks_recovered=scanner.chunks_ok,
        chunks_lost=scanner.chunks_lost,
        messages=copier.messages,
        messages_by_topic=dict(copier.by_topic),
        lost_records=copier.lost,
        orphan_messages=copier.orphans,
        restored_channels=tuple(copier.restored),
        first_time=copier.first,
        last_time=copier.last,
        problems=tuple(scanner.problems),
    )
    log.info("%s", report.summary())
    return report


def _copy(data: bytes | mmap.mmap, source: Path, tmp: Path) -> tuple[McapScanner, _Copier]:
    scanner = McapScanner(data)
    records = scanner.records()
    first = next(records, None)
    header = first if isinstance(first, HeaderRecord) else None
    rest = records if first is None or header is not None else itertools.chain([first], records)
    profile = header.profile if header else ""
    library = header.library if header else "unknown"
    with tmp.open("wb") as f:
        writer = Writer(f, compression=CompressionType.ZSTD, index_types=IndexType.ALL)
        writer.start(
            profile=profile, library=f"{library}; recovered by posecast {posecast_version()}"
        )
        copier = _Copier(writer, profile == PROFILE)
        for rec in rest:
            if isinstance(rec, MessageRecord):
                copier.message(rec)
            elif isinstance(rec, ChannelRecord):
                copier.channel(rec)
            elif isinstance(rec, SchemaRecord):
                copier.schema(rec)
            elif isinstance(rec, MetadataRecord):
                writer.add_metadata(rec.name, rec.metadata)
        writer.add_metadata(
            RECOVERY_METADATA,
            {
                "source": source.name,
                "source_bytes": str(scanner.size),
                "complete": str(scanner.complete).lower(),
                "truncated_at": "" if scanner.truncated_at is None else str(scanner.truncated_at),
                "chunks_recovered": str(scanner.chunks_ok),
                "chunks_lost": str(scanner.chunks_lost),
                "lost_records": str(copier.lost),
                "problems": "; ".join(f"{p.offset}:{p.kind}:{p.reason}" for p in scanner.problems),
            },
        )
        writer.finish()  # type: ignore[no-untyped-call]
        f.flush()
        os.fsync(f.fileno())
    return scanner, copier


def _verify(path: Path, expected: int) -> None:
    """Re-open with mcap's indexed reader: summary present, every message readable."""
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        if summary is None or summary.statistics is None:
            raise RecoveryError(f"{path}: no summary written")
        count = sum(1 for _ in reader.iter_messages(log_time_order=False))
        if count != expected or summary.statistics.message_count != expected:
            raise RecoveryError(
                f"{path}: wrote {expected} messages, the indexed reader finds {count}"
                f" (statistics say {summary.statistics.message_count})"
            )


def find_leftovers(directory: str | os.PathLike[str]) -> list[Path]:
    """``*.mcap.part`` files in ``directory`` (not recursive), oldest name first."""
    folder = Path(directory)
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.glob(f"*.mcap{PART_SUFFIX}") if p.is_file())


def recover_leftovers(directory: str | os.PathLike[str]) -> list[RecoveryReport]:
    """Recover and delete every leftover ``.part`` in ``directory`` (server start-up).

    Never overwrites: an existing ``x.mcap`` makes the output
    ``x.recovered.mcap`` (``-2``, ``-3``, ... if needed). A file that cannot be
    recovered is logged and left in place.
    """
    reports = []
    for part in find_leftovers(directory):
        stem = part.name[: -len(".mcap" + PART_SUFFIX)]
        names = itertools.chain(
            (f"{stem}.mcap", f"{stem}.recovered.mcap"),
            (f"{stem}.recovered-{k}.mcap" for k in itertools.count(2)),
        )
        out = next(p for p in (part.with_name(n) for n in names) if not p.exists())
        try:
            reports.append(recover(part, out, remove_part=True))
        except Exception:
            log.exception("could not recover %s; left in place", part)
    return reports
