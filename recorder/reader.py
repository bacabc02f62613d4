"""Reading session files: records, time ranges, per-stream numpy arrays, ``info``.

:class:`SessionReader` opens a finished ``.mcap`` through mcap's indexed reader
(chunk indexes from the summary); an unfinished ``.mcap.part`` is read linearly
with :class:`recorder.scan.McapScanner` (every intact chunk, nothing else) so a
running or crashed recording can be inspected without recovering it first.

- :meth:`SessionReader.records` yields :class:`recorder.format.PoseRecord`,
  :class:`EventRecord`, :class:`PresenceRecord` and :class:`DropRecord` in
  arrival order, optionally limited to ``start <= arrival < end`` (seconds on
  the server clock, the MCAP log time).
- :meth:`SessionReader.load_streams` / :meth:`SessionReader.load_stream` give,
  per ``(user, stream)``, capture times (f64), arrival times (f64) and poses
  ``(K, 7)`` float32, in arrival order, with the stream's name from the presence
  records and the session metadata.
- :func:`info` summarises a file as a dict (users, streams, durations, rates,
  sizes, drops); :func:`format_info` renders it for ``posecast info FILE``.
"""

from __future__ import annotations

import heapq
import itertools
import json
import math
import mmap
import os
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import numpy as np
from mcap.reader import McapReader, make_reader
from numpy.typing import NDArray

from posecast.recorder.check import check_recording
from posecast.recorder.compact import GROUP_SPAN_MAX, expand_group, is_group
from posecast.recorder.format import (
    DROPS_TOPIC,
    EVENTS_TOPIC,
    FORMAT_VERSION,
    POSE_HEADER_SIZE,
    POSE_STREAM_SIZE,
    POSES_TOPIC,
    PRESENCE_TOPIC,
    QUEUE_OVERFLOW_KIND,
    SESSION_END_METADATA,
    SESSION_METADATA,
    VELOCITY_FLAG,
    VELOCITY_SIZE,
    FormatError,
    PoseRecord,
    decode_json,
    decode_pose,
    to_ns,
)
from posecast.recorder.objects import format_objects, objects_info, split_objects
from posecast.recorder.scan import (
    ChannelRecord,
    HeaderRecord,
    McapScanner,
    MessageRecord,
    MetadataRecord,
)
from posecast.recorder.streams import StreamData, UserInfo

__all__ = [
    "DropRecord",
    "EventRecord",
    "PoseColumns",
    "PresenceRecord",
    "Record",
    "SessionReader",
    "StreamData",
    "UserInfo",
    "check_recording",
    "decode_poses",
    "format_info",
    "info",
    "load_streams",
    "read_records",
    "split_streams",
    "users_from",
]


@dataclass(frozen=True)
class _JsonRecord:
    time: float
    """Arrival time, s, server clock."""
    data: dict[str, Any]

    @property
    def kind(self) -> str:
        return str(self.data.get("kind", ""))


@dataclass(frozen=True)
class EventRecord(_JsonRecord):
    """A record of the ``events`` channel."""


@dataclass(frozen=True)
class PresenceRecord(_JsonRecord):
    """A record of the ``presence`` channel (join, leave, rate)."""


@dataclass(frozen=True)
class DropRecord(_JsonRecord):
    """A record of the ``drops`` channel (server drops and skips, recorder losses)."""


Record = PoseRecord | EventRecord | PresenceRecord | DropRecord


# (topic, log_time ns, publish_time ns, sequence, data)
_Raw = tuple[str, int, int, int, bytes]


class SessionReader:
    """An open session file; use as a context manager or call :meth:`close`."""

    def __init__(self, path: str | os.PathLike[str], *, linear: bool = False) -> None:
        """Open ``path``; ``linear`` reads it chunk by chunk even if it has an index.

        A finished file whose chunks are damaged raises :class:`FormatError` when
        read through its index; ``linear=True`` skips the damaged chunks instead.
        """
        self.path = Path(path)
        self._file = self.path.open("rb")
        self._reader: McapReader | None = None
        self._mmap: mmap.mmap | None = None
        self._metadata: dict[str, dict[str, str]] = {}
        self.profile = ""
        self.complete = False
        """True for a finished, indexed file; False for one read linearly."""
        try:
            if linear:
                raise FormatError("linear reading requested")
            reader = make_reader(self._file, validate_crcs=True)
            summary = reader.get_summary()
            if summary is None or not summary.chunk_indexes:
                raise FormatError("no chunk index")
            self.profile = reader.get_header().profile
            for md in reader.iter_metadata():
                self._metadata[md.name] = dict(md.metadata)
            self._reader = reader
            self.complete = True
        except Exception:
            self._open_linear()

    def _open_linear(self) -> None:
        size = os.fstat(self._file.fileno()).st_size
        if size:
            self._mmap = mmap.mmap(self._file.fileno(), 0, access=mmap.ACCESS_READ)
        for rec in McapScanner(self._mmap if self._mmap is not None else b"").records():
            if isinstance(rec, HeaderRecord):
                self.profile = rec.profile
            elif isinstance(rec, MetadataRecord):
                self._metadata[rec.name] = dict(rec.metadata)

    def close(self) -> None:
        """Release the file."""
        if self._mmap is not None:
            self._mmap.close()
            self._mmap = None
        self._file.close()

    def __enter__(self) -> SessionReader:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # -- raw messages ----------------------------------------------------------------

    def _raw(
        self,
        topics: Iterable[str] | None = None,
        start: float | None = None,
        end: float | None = None,
        time_order: bool = True,
    ) -> Iterator[_Raw]:
        lo = None if start is None else to_ns(start)
        hi = None if end is None else to_ns(end)
        wanted = None if topics is None else set(topics)
        if self._reader is not None:
            yield from self._indexed(wanted, lo, hi, time_order)
            return
        out: list[_Raw] = []
        channels: dict[int, str] = {}
        buf = self._mmap if self._mmap is not None else b""
        for rec in McapScanner(buf).records():
            if isinstance(rec, ChannelRecord):
                channels[rec.id] = rec.topic
            elif isinstance(rec, MessageRecord):
                topic = channels.get(rec.channel_id)
                if topic is None or (wanted is not None and topic not in wanted):
                    continue
                if topic == POSES_TOPIC and is_group(rec.data):
                    out.extend(_expand(rec.sequence, rec.data, lo, hi))
                    continue
                t = rec.log_time
                if (lo is not None and t < lo) or (hi is not None and t >= hi):
                    continue
                out.append((topic, rec.log_time, rec.publish_time, rec.sequence, rec.data))
        if time_order:
            out.sort(key=lambda r: r[1])
        yield from out

    def _indexed(
        self, wanted: set[str] | None, lo: int | None, hi: int | None, time_order: bool
    ) -> Iterator[_Raw]:
        """Messages through mcap's indexed reader; layout 2 pose messages expanded.

        A layout 2 message's log time is its first update's arrival and its updates
        span at most ``GROUP_SPAN_MAX`` s, so the query starts that much earlier and
        expanded updates wait in a heap until no earlier message can follow.
        """
        assert self._reader is not None
        early = lo
        if lo is not None and (wanted is None or POSES_TOPIC in wanted):
            early = max(0, lo - to_ns(GROUP_SPAN_MAX))
        messages = self._reader.iter_messages(
            topics=None if wanted is None else sorted(wanted),
            log_time_order=time_order,
            starting_at=early,
            ending_before=hi,
        )
        waiting: list[tuple[int, int, _Raw]] = []
        count = itertools.count()
        while True:
            try:
                _schema, channel, msg = next(messages)
            except StopIteration:
                break
            except Exception as exc:  # mcap and zstd raise many types on bad data
                raise FormatError(
                    f"{self.path} is damaged ({exc!r}); read it with linear=True or recover it"
                ) from exc
            t = msg.log_time
            while waiting and waiting[0][0] <= t:
                yield heapq.heappop(waiting)[2]
            if channel.topic == POSES_TOPIC and is_group(msg.data):
                for raw in _expand(msg.sequence, msg.data, lo, hi):
                    if time_order:
                        heapq.heappush(waiting, (raw[1], next(count), raw))
                    else:
                        yield raw
            elif lo is None or t >= lo:
                yield channel.topic, t, msg.publish_time, msg.sequence, msg.data
        while waiting:
            yield heapq.heappop(waiting)[2]

    # -- records ---------------------------------------------------------------------

    def records(
        self,
        start: float | None = None,
        end: float | None = None,
        topics: Iterable[str] | None = None,
    ) -> Iterator[Record]:
        """Decoded records with ``start <= arrival < end``, in arrival order."""
        for topic, log_time, _pub, _seq, data in self._raw(topics, start, end):
            if topic == POSES_TOPIC:
                yield decode_pose(data)
            elif topic == EVENTS_TOPIC:
                yield EventRecord(log_time / 1e9, decode_json(data))
            elif topic == PRESENCE_TOPIC:
                yield PresenceRecord(log_time / 1e9, decode_json(data))
            elif topic == DROPS_TOPIC:
                yield DropRecord(log_time / 1e9, decode_json(data))

    def poses(self, start: float | None = None, end: float | None = None) -> Iterator[PoseRecord]:
        """Pose records only."""
        for rec in self.records(start, end, (POSES_TOPIC,)):
            assert isinstance(rec, PoseRecord)
            yield rec

    def events(self, start: float | None = None, end: float | None = None) -> list[EventRecord]:
        """Records of the ``events`` channel."""
        return [r for r in self.records(start, end, (EVENTS_TOPIC,)) if isinstance(r, EventRecord)]

    def presence(
        self, start: float | None = None, end: float | None = None
    ) -> list[PresenceRecord]:
        """Records of the ``presence`` channel."""
        recs = self.records(start, end, (PRESENCE_TOPIC,))
        return [r for r in recs if isinstance(r, PresenceRecord)]

    def drops(self, start: float | None = None, end: float | None = None) -> list[DropRecord]:
        """Records of the ``drops`` channel."""
        return [r for r in self.records(start, end, (DROPS_TOPIC,)) if isinstance(r, DropRecord)]

    # -- session metadata ------------------------------------------------------------

    @property
    def metadata(self) -> dict[str, dict[str, str]]:
        """MCAP metadata records by name."""
        return {k: dict(v) for k, v in self._metadata.items()}

    @property
    def session(self) -> dict[str, str]:
        """The ``posecast.session`` metadata (room, version, start times, ...)."""
        return dict(self._metadata.get(SESSION_METADATA, {}))

    def users(self) -> dict[int, UserInfo]:
        """Users from the session metadata and the presence records, by id."""
        return users_from(self.session, ((rec.time, rec.data) for rec in self.presence()))

    # -- arrays ----------------------------------------------------------------------

    def load_streams(
        self,
        users: Iterable[int] | None = None,
        streams: Iterable[int] | None = None,
        start: float | None = None,
        end: float | None = None,
    ) -> dict[tuple[int, int], StreamData]:
        """Every stream (or those of ``users`` / with ids in ``streams``) as arrays."""
        datas = [raw[4] for raw in self._raw((POSES_TOPIC,), start, end, time_order=True)]
        cols = decode_poses(datas)
        user_set = None if users is None else set(users)
        stream_set = None if streams is None else set(streams)
        return {
            key: data
            for key, data in split_streams(cols, self.users()).items()
            if (user_set is None or key[0] in user_set)
            and (stream_set is None or key[1] in stream_set)
        }

    def load_stream(
        self,
        user: int,
        stream: int | str,
        start: float | None = None,
        end: float | None = None,
    ) -> StreamData:
        """One stream by id or by name (``"head"``, ``"left"``, ...); KeyError if absent."""
        if isinstance(stream, str):
            ui = self.users().get(user)
            ids = [sid for sid, name in (ui.streams.items() if ui else ()) if name == stream]
            if not ids:
                raise KeyError(f"user {user} has no stream named {stream!r}")
            sid = ids[0]
        else:
            sid = stream
        found = self.load_streams([user], [sid], start, end)
        if (user, sid) not in found:
            raise KeyError(f"no keyframes of user {user} stream {sid}")
        return found[(user, sid)]

    # -- summary ---------------------------------------------------------------------

    def info(self) -> dict[str, Any]:
        """What :func:`info` returns."""
        return _info(self)


def users_from(
    session: Mapping[str, str], presence: Iterable[tuple[float, dict[str, Any]]]
) -> dict[int, UserInfo]:
    """Users, by id, from the ``posecast.session`` metadata and the presence
    records as ``(time, record)`` in file order (joins, leaves, rate changes)."""
    out: dict[int, UserInfo] = {}
    try:
        initial = json.loads(session.get("users", "{}")).get("users", [])
    except (ValueError, AttributeError):
        initial = []
    for u in initial:
        if isinstance(u, dict) and "user" in u:
            _apply_join(out, u, None)
    for time, d in presence:
        if not isinstance(d.get("user"), int):
            continue
        kind = d.get("kind")
        if kind == "join":
            _apply_join(out, d, time)
        elif kind == "leave":
            out.setdefault(d["user"], UserInfo(d["user"])).left = time
        elif kind == "rate" and isinstance(d.get("rate"), int | float):
            out.setdefault(d["user"], UserInfo(d["user"])).rate = float(d["rate"])
    return out


def _apply_join(out: dict[int, UserInfo], d: dict[str, Any], time: float | None) -> None:
    u = out.setdefault(int(d["user"]), UserInfo(int(d["user"])))
    if isinstance(d.get("name"), str):
        u.name = d["name"]
    if isinstance(d.get("label"), str):
        u.label = d["label"]
    if isinstance(d.get("rate"), int | float):
        u.rate = float(d["rate"])
    streams = d.get("streams")
    if isinstance(streams, dict):
        for name, sid in streams.items():
            if isinstance(sid, int):
                u.streams[sid] = str(name)
    if time is not None and u.joined is None:
        u.joined = time


@dataclass
class PoseColumns:
    """Pose messages decoded into columns: one row per recorded pose, in message order."""

    user: NDArray[np.uint16]
    stream: NDArray[np.uint16]
    arrival: NDArray[np.float64]
    capture: NDArray[np.float64]
    poses: NDArray[np.float32]
    #: ``(rows, 6)`` float32 velocities (NaN for rows whose message carried none),
    #: or ``None`` if no message carried velocities.
    velocities: NDArray[np.float32] | None = None


def decode_poses(datas: list[bytes]) -> PoseColumns:
    """Decode many pose messages (``poses`` channel payloads) at once into columns.

    The fast path behind :func:`load_streams` and the exporters: messages are
    grouped by size and each group is decoded in one numpy pass (bit-exact, like
    :func:`recorder.format.decode_pose` one by one). Raises ``FormatError`` on a
    message that is not a pose message of this format version.
    """
    groups: dict[tuple[int, int], list[int]] = {}
    for i, d in enumerate(datas):
        groups.setdefault((len(d), d[1] if len(d) > 1 else 0), []).append(i)
    parts: list[tuple[NDArray[np.int64], PoseColumns]] = []
    any_velocity = False
    for (size, flags), idx in groups.items():
        has_v = flags == VELOCITY_FLAG
        per = POSE_STREAM_SIZE + (VELOCITY_SIZE if has_v else 0)
        n, rest = divmod(size - POSE_HEADER_SIZE, per)
        if size < POSE_HEADER_SIZE or rest or flags not in (0, VELOCITY_FLAG):
            decode_pose(datas[idx[0]])  # raises FormatError with the reason
        if n == 0:
            continue  # updates without poses
        m = len(idx)
        a = np.frombuffer(b"".join(datas[i] for i in idx), np.uint8).reshape(m, size)
        if np.any(a[:, 0] != FORMAT_VERSION) or np.any(a[:, 4:6].copy().view("<u2")[:, 0] != n):
            raise FormatError("pose message with an unknown layout version or bad count")
        user = a[:, 2:4].copy().view("<u2")[:, 0]
        abits = a[:, 14:22].copy().view("<u8")[:, 0]
        off = POSE_HEADER_SIZE
        stream = a[:, off : off + 2 * n].copy().view("<u2")
        off += 2 * n
        cbits = a[:, off : off + 8 * n].copy().view("<u8") ^ abits[:, None]
        off += 8 * n
        planes = a[:, off : off + 28 * n].reshape(m, 4, 7 * n).transpose(0, 2, 1)
        poses = np.ascontiguousarray(planes).view("<f4").reshape(m * n, 7)
        off += 28 * n
        if has_v:
            any_velocity = True
            velocities = (
                np.ascontiguousarray(a[:, off:]).view("<f2").reshape(m * n, 6).astype(np.float32)
            )
        else:
            velocities = np.full((m * n, 6), np.nan, np.float32)
        msg = np.repeat(np.asarray(idx, dtype=np.int64), n)
        parts.append(
            (
                msg,
                PoseColumns(
                    user=np.repeat(user, n),
                    stream=stream.reshape(m * n),
                    arrival=np.repeat(abits.view("<f8"), n),
                    capture=cbits.view("<f8").reshape(m * n),
                    poses=poses,
                    velocities=velocities,
                ),
            )
        )
    if not parts:
        return PoseColumns(
            np.zeros(0, np.uint16),
            np.zeros(0, np.uint16),
            np.zeros(0),
            np.zeros(0),
            np.zeros((0, 7), np.float32),
        )
    msg = np.concatenate([p[0] for p in parts])
    order = np.argsort(msg, kind="stable")
    vel = None
    if any_velocity:
        vel = np.concatenate([p[1].velocities for p in parts if p[1].velocities is not None])
        vel = vel[order]
    return PoseColumns(
        user=np.concatenate([p[1].user for p in parts])[order],
        stream=np.concatenate([p[1].stream for p in parts])[order],
        arrival=np.concatenate([p[1].arrival for p in parts])[order],
        capture=np.concatenate([p[1].capture for p in parts])[order],
        poses=np.concatenate([p[1].poses for p in parts])[order],
        velocities=vel,
    )


def split_streams(
    cols: PoseColumns, users: Mapping[int, UserInfo]
) -> dict[tuple[int, int], StreamData]:
    """The rows of ``cols`` by ``(user, stream)``, in their order, named from ``users``."""
    out: dict[tuple[int, int], StreamData] = {}
    if not len(cols.user):
        return out
    keys = (cols.user.astype(np.uint32) << np.uint32(16)) | cols.stream.astype(np.uint32)
    uniq, inverse = np.unique(keys, return_inverse=True)
    order = np.argsort(inverse, kind="stable")
    bounds = np.searchsorted(inverse[order], np.arange(len(uniq) + 1))
    for k, key in enumerate(uniq.tolist()):
        user, stream = key >> 16, key & 0xFFFF
        idx = order[bounds[k] : bounds[k + 1]]
        ui = users.get(user)
        velocities = None
        if cols.velocities is not None:
            v = cols.velocities[idx]
            velocities = None if np.isnan(v[:, 0]).all() else v
        out[(user, stream)] = StreamData(
            user=user,
            stream=stream,
            name=None if ui is None else ui.streams.get(stream),
            user_name=None if ui is None else ui.name,
            times=cols.capture[idx],
            arrival=cols.arrival[idx],
            poses=cols.poses[idx],
            velocities=velocities,
        )
    return out


def _info(reader: SessionReader) -> dict[str, Any]:
    session = reader.session
    counts: dict[str, int] = {}
    first = last = None
    seqs: list[int] = []
    for topic, log_time, _pub, seq, _data in reader._raw(time_order=False):
        counts[topic] = counts.get(topic, 0) + 1
        first = log_time if first is None else min(first, log_time)
        last = log_time if last is None else max(last, log_time)
        seqs.append(seq)
    pieces, users = reader.load_streams(), reader.users()
    streams, tracks = split_objects((e.data for e in reader.events()), pieces, users)
    for user, _sid in streams:
        users.setdefault(user, UserInfo(user))
    poses = sum(len(s) for s in pieces.values())
    size = reader.path.stat().st_size
    drop_kinds: dict[str, int] = {}
    drop_records = reader.drops()
    queue_lost = 0
    for d in drop_records:
        count = d.data.get("count", 1)
        n = int(count) if isinstance(count, int | float) else 1
        drop_kinds[d.kind or "unknown"] = drop_kinds.get(d.kind or "unknown", 0) + n
        if d.kind == QUEUE_OVERFLOW_KIND:
            queue_lost += n
    end_md = reader.metadata.get(SESSION_END_METADATA, {})
    return {
        "path": str(reader.path),
        "complete": reader.complete,
        "profile": reader.profile,
        "room": session.get("room"),
        "posecast_version": session.get("posecast_version"),
        "start_utc": session.get("start_utc"),
        **{key: session.get(key) for key in _CLUSTER_KEYS},
        "start_time": _float(session.get("start_time")),
        "end_time": _float(end_md.get("end_time")),
        "first_time": None if first is None else first / 1e9,
        "last_time": None if last is None else last / 1e9,
        "duration": 0.0 if first is None or last is None else (last - first) / 1e9,
        "records": dict(sorted(counts.items())),
        "users": [
            {
                "user": u.user,
                "name": u.name,
                "label": u.label,
                "rate": u.rate,
                "joined": u.joined,
                "left": u.left,
                "streams": {str(k): v for k, v in sorted(u.streams.items())},
            }
            for u in sorted(users.values(), key=lambda u: u.user)
        ],
        "streams": [
            {
                "user": s.user,
                "stream": s.stream,
                "name": s.name,
                "keyframes": len(s),
                "duration": s.duration,
                "rate": s.rate,
                "velocities": s.velocities is not None,
            }
            for s in sorted(streams.values(), key=lambda s: (s.user, s.stream))
        ],
        "objects": objects_info(tracks),
        "sizes": {
            "file_bytes": size,
            "poses": poses,
            "bytes_per_pose": size / poses if poses else None,
        },
        "drops": {
            "records": len(drop_records),
            "total": sum(drop_kinds.values()),
            "by_kind": dict(sorted(drop_kinds.items())),
            "recorder_queue": queue_lost,
            "missing_records": _sequence_gaps(seqs),
        },
    }


def _expand(sequence: int, data: bytes, lo: int | None, hi: int | None) -> list[_Raw]:
    """The layout 1 pose messages of a layout 2 message, those in ``lo <= t < hi``."""
    return [
        (POSES_TOPIC, t, pub, sequence, raw)
        for t, pub, raw in expand_group(data)
        if (lo is None or t >= lo) and (hi is None or t < hi)
    ]


def _sequence_gaps(seqs: list[int]) -> int:
    """Records missing from the file's record counter (lost chunks)."""
    if not seqs:
        return 0
    s = sorted(set(seqs))
    return (s[-1] - s[0] + 1) - len(s)


def _float(text: str | None) -> float | None:
    try:
        return None if text is None else float(text)
    except ValueError:
        return None


def info(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Summary of a session file: users, streams (rates), durations, sizes, drops."""
    with SessionReader(path) as reader:
        return reader.info()


def load_streams(
    path: str | os.PathLike[str],
    users: Iterable[int] | None = None,
    streams: Iterable[int] | None = None,
    start: float | None = None,
    end: float | None = None,
) -> dict[tuple[int, int], StreamData]:
    """:meth:`SessionReader.load_streams` on a file."""
    with SessionReader(path) as reader:
        return reader.load_streams(users, streams, start, end)


def read_records(
    path: str | os.PathLike[str],
    start: float | None = None,
    end: float | None = None,
    topics: Iterable[str] | None = None,
) -> list[Record]:
    """Every decoded record of a file (or of a time range), in arrival order."""
    with SessionReader(path) as reader:
        return list(reader.records(start, end, topics))


def _num(x: float | None, fmt: str = ".1f") -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, fmt)


#: Session metadata of a cluster node's recording: the node that recorded it, and
#: the lost node whose recording of the room it continues (docs/guides/cluster.md).
_CLUSTER_KEYS = ("cluster_node", "continues_from_node")


def _cluster_lines(data: dict[str, Any]) -> list[str]:
    node, lost = data.get("cluster_node"), data.get("continues_from_node")
    if not node:
        return []
    line = f"  recorded on cluster node {node}"
    if lost:
        line += f"; continues the room's recording on node {lost} (lost; recovered there)"
    return [line]


def format_info(data: dict[str, Any]) -> str:
    """Plain-text rendering of :func:`info` for ``posecast info FILE``."""
    sizes, drops = data["sizes"], data["drops"]
    state = "finished" if data["complete"] else "UNFINISHED (read linearly; run recover)"
    lines = [
        f"{data['path']}: {state}",
        f"  room {data['room']!r}, posecast {data['posecast_version']},"
        f" started {data['start_utc']}",
        *_cluster_lines(data),
        f"  duration {_num(data['duration'])} s"
        f" (server clock {_num(data['first_time'], '.3f')} .. {_num(data['last_time'], '.3f')})",
        "  records: " + ", ".join(f"{k} {v}" for k, v in data["records"].items()),
        f"  size {sizes['file_bytes']} B, {sizes['poses']} poses,"
        f" {_num(sizes['bytes_per_pose'])} B/pose",
        f"  drops: {drops['total']} in {drops['records']} records"
        + (
            " (" + ", ".join(f"{k} {v}" for k, v in drops["by_kind"].items()) + ")"
            if drops["by_kind"]
            else ""
        )
        + f"; recorder queue lost {drops['recorder_queue']}; missing records"
        f" {drops['missing_records']}",
        f"  users: {len(data['users'])}",
    ]
    by_user: dict[int, list[dict[str, Any]]] = {}
    for s in data["streams"]:
        by_user.setdefault(s["user"], []).append(s)
    for u in data["users"]:
        name = u["name"] or f"user{u['user']}"
        label = f" [{u['label']}]" if u["label"] else ""
        lines.append(f"    {u['user']:>5} {name}{label} rate {_num(u['rate'], 'g')}")
        for s in by_user.get(u["user"], []):
            lines.append(
                f"          stream {s['stream']:>5} {s['name'] or '?':<10}"
                f" {s['keyframes']:>8} keyframes {_num(s['duration'])} s"
                f" {_num(s['rate'])} /s" + (" + velocities" if s.get("velocities") else "")
            )
    return "\n".join(lines + format_objects(data.get("objects", [])))
