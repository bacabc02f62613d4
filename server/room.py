"""Rooms: latest-wins stream store, per-subscriber tick schedule, fan-out.

A :class:`Room` owns the newest keyframe of every stream of its members and a
schedule: each member is due on its own grid ``k / rate`` of the server clock.
At a tick the room encodes, once, a snapshot of every stream that changed since
the member's last snapshot, and hands the same bytes to every due member that
shares that last snapshot (members of one rate are always in step); members that
asked for velocities (``Join.wants_velocities``) get the velocity variant, also
encoded once per tick and shared the same way, with each stream's latest
velocity beside its pose (zeros for a sender that reports none). Nothing
here touches a socket: members receive bytes through an :class:`Outbox`, whose
single pose slot is latest-wins (an unsent snapshot replaced by a newer one is a
skip) and whose event queue is bounded (overflow is reported to the caller,
which closes the connection). Time is always an argument; nothing here waits
(the relay core, ``server/core.py``, decides when a room ticks).

Members that joined with ``codec="compact"`` get compact snapshots
(``protocol.codec_relay``): each stream that changed since the snapshot the
member's writer last took is delta-coded against the codes of that stream as of
that snapshot (the room keeps each stream's last ``CODES_HISTORY`` coded
versions; older baselines go as key entries), which the member holds because
the socket is reliable and ordered. Members with the same last snapshot share
the baselines, so their group's entries are encoded once and each member's
frame is spliced from them without its own streams (unless it asked for
``echo``). A member gets a key snapshot (every stream, absolute) at join, after
a rate change and at least every ``KEY_INTERVAL`` seconds: at its first tick in
each slot of ``KEY_INTERVAL`` less one tick interval of the server clock, the
same slots for every member of one rate, so that they share it too.
"""

from __future__ import annotations

import math
import struct
import zlib
from bisect import bisect_left
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from posecast.protocol import (
    ROOM_USER,
    UPDATE_VELOCITY_ENTRY_SIZE,
    ZERO_VELOCITY,
    PeerJoined,
    PoseUpdate,
    _accel,
    pack_snapshot,
    pack_velocity_snapshot,
)
from posecast.protocol.codec import DEFAULT_VOLUME, Volume, quantise
from posecast.protocol.codec_relay import GroupSnapshot, encode_stored
from posecast.protocol.codec_store import CodeHistory, baseline_of
from posecast.server.actions import Action, PollRecording, Record, RecordPose, Wake
from posecast.server.member import IdAllocator, Member, Outbox
from posecast.server.shared import RoomObject
from posecast.server.view_rates import Motion, ViewRates, ViewState, encode_peers, peer_divisor

# (IdAllocator, Member, Outbox: ``server.member``; named here too for the callers
# that import them from here.)
__all__ = [
    "TICK_LAG_BUCKETS",
    "IdAllocator",
    "LagHistogram",
    "Member",
    "Outbox",
    "Room",
    "RoomStatistics",
    "room_phase",
]

#: A compact subscriber gets a key snapshot at least this often (s).
KEY_INTERVAL = 2.0
#: Coded versions kept per stream as baselines of compact subscribers' deltas.
CODES_HISTORY = 16
#: A pose's position (the first 12 of its 28 wire bytes).
_POSITION = struct.Struct("<3f")
#: An update's record: stream, dt, the 28 pose bytes [, the 12 velocity bytes].
_RECORD = struct.Struct("<Hf28s")
_VELOCITY_RECORD = struct.Struct("<Hf28s12s")
#: The velocity codes of a compact update without velocities.
_NO_VELOCITY_CODES = [0] * 6


def _key_slot(now: float, rate: float) -> int:
    """A compact subscriber's key slot at ``now``: slots of KEY_INTERVAL less one tick,
    per rate, so keys come at most KEY_INTERVAL apart and members of one rate share them."""
    return math.floor(now / max(KEY_INTERVAL - 1.0 / rate, 1e-3))


#: Upper bounds (s) of the tick lag histogram's buckets (``posecast_tick_lag_seconds``;
#: one more bucket, +Inf, holds the rest).
TICK_LAG_BUCKETS = (0.0005, 0.001, 0.002, 0.005, 0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0)


@dataclass
class LagHistogram:
    """Member ticks per lag bucket (``TICK_LAG_BUCKETS``, then +Inf; not cumulative),
    the lag measured from each member's due time, and the sum of those lags (s).
    One for the server, shared by its rooms."""

    counts: list[int] = field(default_factory=lambda: [0] * (len(TICK_LAG_BUCKETS) + 1))
    total: float = 0.0

    def observe(self, lag: float) -> None:
        lag = max(0.0, lag)
        self.counts[bisect_left(TICK_LAG_BUCKETS, lag)] += 1
        self.total += lag


def room_phase(name: str) -> float:
    """Where in a tick interval room ``name``'s grid sits, in ``[0, 1)``.

    Every room on one grid would fan out in one burst at the same instants; a
    phase per room (from its name, so it is stable) spreads the bursts out.
    """
    return zlib.crc32(name.encode()) / 2**32


@dataclass(frozen=True, slots=True)
class RoomStatistics:
    name: str
    members: int
    streams: int
    ticks: int
    snapshots_encoded: int
    frames_out: int
    bytes_out: int
    poses_out: int
    updates_in: int
    stale_updates: int
    skips: int
    tick_lag_max_ms: float
    tick_lag_mean_ms: float


def _new_history() -> CodeHistory | deque[tuple[int, list[int]]]:
    if _accel.speedups is not None:
        return CodeHistory(CODES_HISTORY)
    return deque(maxlen=CODES_HISTORY)


@dataclass(slots=True)
class _Stream:
    user: int
    capture: float
    #: The 28 pose bytes as they arrived (validated on receipt, never decoded here).
    pose: bytes
    version: int
    #: The 12 velocity bytes that came with the pose (zeros if its update had none).
    velocity: bytes = ZERO_VELOCITY
    #: Codec codes (13: pose and velocity) of this version: from a compact update,
    #: else quantised when a compact subscriber first needs them.
    codes: list[int] | None = None
    #: (version, codes) of the versions coded so far, oldest first (baselines): packed
    #: for the accelerator (``protocol.codec_store``) while it runs, else a deque
    #: (cheaper in Python); either works with either path.
    history: CodeHistory | deque[tuple[int, list[int]]] = field(default_factory=_new_history)

    def coded(self, volume: Volume) -> list[int]:
        """This version's codes (computed once, remembered as a baseline)."""
        codes = self.codes
        if codes is None:
            pose = np.frombuffer(self.pose, "<f4").reshape(1, 7)
            vel = np.frombuffer(self.velocity, "<f2").reshape(1, 6)
            codes = self.codes = quantise(pose, volume, vel)[0].tolist()
        h = self.history
        newest = h.last_version() if isinstance(h, CodeHistory) else (h[-1][0] if h else None)
        if newest != self.version:
            h.append((self.version, codes))
        return codes

    def baseline(self, since: int) -> list[int] | None:
        """The codes a subscriber whose last snapshot covered version ``since`` holds."""
        return baseline_of(self.history, since)


@dataclass
class Room:
    """One session's members, their streams and the fan-out schedule."""

    name: str
    members: dict[int, Member] = field(default_factory=dict)
    stream_ids: IdAllocator = field(default_factory=IdAllocator)
    _streams: dict[int, _Stream] = field(default_factory=dict)
    _version: int = 0
    _tick: int = 0
    _snapshots: int = 0
    _frames_out: int = 0
    _bytes_out: int = 0
    _poses_out: int = 0
    _updates_in: int = 0
    _stale: int = 0
    _lag_max: float = 0.0
    _lag_sum: float = 0.0
    _lag_n: int = 0
    retired: bool = False
    #: Offset of this room's tick grid, as a fraction of an interval (see room_phase).
    phase: float = 0.0
    #: Whether this room is recorded (``posecast serve --record``): its records go
    #: out as actions (``Record``, ``RecordPose``) into ``out``, the list of actions
    #: its owner (the core) returns; the adapter holds the recorder.
    recorded: bool = False
    out: list[Action] | None = None
    _drops: dict[tuple[str, int], int] = field(default_factory=dict)
    _skips_reported: dict[int, int] = field(default_factory=dict)
    _drops_flushed: float = 0.0
    #: Pose updates are not recorded while paused (SIGUSR1 / SIGUSR2 of the server);
    #: presence, events and drops still are, and the pause itself is a drops record.
    recording_paused: bool = False
    #: Pose updates not recorded since the pause began, and when it began.
    paused_updates: int = 0
    _paused_since: float = 0.0
    #: The volume compact codes quantise positions in (the server's, stated at welcome).
    volume: Volume = DEFAULT_VOLUME
    #: Shared objects by stream id (``server.objects``).
    objects: dict[int, RoomObject] = field(default_factory=dict)
    #: Moves its thrown objects at each tick (``server.objects.fly``, set by the core).
    fly: Callable[[Room, float], None] | None = None
    #: Sequence numbers of the recorded flight keyframes.
    flight_seq: int = 0
    #: The server's tick lag histogram, which every due member's tick goes into.
    lags: LagHistogram | None = None
    #: ``next_due()`` as last computed, and the member count it was computed for
    #: (None: to compute again). Every change of a member's due time goes through
    #: this class (add, set_rate, tick) and clears it; so does ``remove``.
    _due: float | None = None
    _due_members: int = 0
    #: The server's view-aware setting (None: ``budget_deg`` is ignored), and what
    #: this room follows of its streams' motion once a member has a budget.
    views: ViewRates | None = None
    motion: Motion | None = None

    def pause_recording(self, now: float) -> None:
        """Stop recording pose updates (counted, written as one drops record on resume)."""
        if self.recorded and not self.recording_paused:
            self.recording_paused = True
            self.paused_updates = 0
            self._paused_since = now

    def resume_recording(self, now: float) -> None:
        """Record pose updates again; the pause goes into the file as a drops record."""
        if not self.recording_paused:
            return
        self.recording_paused = False
        if self.recorded:
            self.record(
                "drop",
                {
                    "kind": "recording-paused",
                    "count": self.paused_updates,
                    "first_time": self._paused_since,
                    "last_time": now,
                },
                now,
            )

    def note_drop(self, kind: str, user: int, count: int = 1) -> None:
        """Count a server-side drop; recorded (aggregated) at most once a second."""
        if self.recorded:
            key = (kind, user)
            self._drops[key] = self._drops.get(key, 0) + count

    def flush_drops(self, now: float, force: bool = False) -> None:
        """Write the drops and snapshot skips counted since the last flush."""
        if not self.recorded:
            return
        self._emit(PollRecording(self.name))
        if not force and now - self._drops_flushed < 1.0:
            return
        self._drops_flushed = now
        for m in self.members.values():
            total = m.outbox.skips + m.congestion_skips
            new = total - self._skips_reported.get(m.user, 0)
            if new > 0:
                self._skips_reported[m.user] = total
                self._drops[("skip", m.user)] = self._drops.get(("skip", m.user), 0) + new
        for (kind, user), count in self._drops.items():
            self.record("drop", {"kind": kind, "user": user, "count": count}, now)
        self._drops.clear()

    def _emit(self, action: Action) -> None:
        assert self.out is not None, "a recorded room has a list of actions"
        self.out.append(action)

    def record(
        self, topic: Literal["presence", "event", "drop"], record: dict[str, Any], now: float
    ) -> None:
        """Write ``record`` on this room's recording, if it is recorded (an action)."""
        if self.recorded:
            self._emit(Record(self.name, topic, record, now))

    def record_pose(
        self, user: int, now: float, update: PoseUpdate, codes: dict[int, list[int]] | None
    ) -> None:
        """Record ``user``'s pose ``update`` (the caller checked :attr:`recorded`)."""
        self._emit(RecordPose(self.name, user, now, update, codes, self.volume))

    # -- membership ---------------------------------------------------------------

    def allocate_streams(self, names: tuple[str, ...]) -> dict[str, int]:
        return {n: self.stream_ids.take() for n in names}

    def add(self, member: Member, now: float) -> None:
        if member.view is not None and self.views is None:
            member.view = None  # the server does not do view-aware rates
        if member.view is not None and self.motion is None:
            self.motion = Motion()
        member.next_due = self._grid_after(now, member.rate)
        member.last_version = member.delivered_version = 0
        member.key_slot = -1
        self.members[member.user] = member
        self._due = None

    def remove(self, user: int) -> Member | None:
        member = self.members.pop(user, None)
        self._due = None
        if member is not None:
            for sid in member.streams.values():
                self._streams.pop(sid, None)
                self.stream_ids.give_back(sid)
                if self.motion is not None:
                    self.motion.forget(sid)
            if member.view is not None and all(m.view is None for m in self.members.values()):
                self.motion = None  # no budget left: stop following motion per pose
        return member

    @staticmethod
    def announce(member: Member) -> PeerJoined:
        """The ``peer_joined`` that tells others about ``member``."""
        return PeerJoined(
            user=member.user,
            streams=member.streams,
            label=member.label,
            velocities=member.sends_velocities,
        )

    def has_member_named(self, name: str) -> bool:
        """Whether a member joined as ``name`` (a token's user) is in the room."""
        return any(m.name == name for m in self.members.values())

    def set_rate(self, user: int, rate: float, now: float) -> None:
        member = self.members[user]
        member.rate = rate
        member.next_due = self._grid_after(now, rate)
        member.key_slot = -1
        if member.view is not None:
            member.view.reset()
        self._due = None

    # -- ingest -------------------------------------------------------------------

    def ingest(
        self, user: int, update: PoseUpdate, codes: dict[int, list[int]] | None = None
    ) -> int:
        """Store the newest keyframe of each stream (by capture time); returns stale count.

        ``codes``: stream id -> codec codes of a compact update (kept for compact
        subscribers, so that their poses are the sender's codes exactly).
        """
        self._updates_in += 1
        member = self.members.get(user)
        if member is not None:
            member.updates_in += 1
        stale = 0
        objects, motion, streams = self.objects, self.motion, self._streams
        base, entries = update.base_time, update.entries
        # The records' bytes read in one C call each (as protocol.update_records reads them).
        velocities = entries.itemsize == UPDATE_VELOCITY_ENTRY_SIZE
        layout = _VELOCITY_RECORD if velocities else _RECORD
        for record in layout.iter_unpack(entries.tobytes()):
            sid, t, pose = record[0], base + record[1], record[2]
            cur = streams.get(sid)
            publisher = user
            if objects and sid in objects:
                # A shared object: the room's stream, in its owner's shifted time.
                publisher = ROOM_USER
                t = objects[sid].rebase(t, None if cur is None else cur.capture)
            if cur is not None and t <= cur.capture:
                stale += 1
                continue
            if motion is not None:
                motion.observe(sid, t, pose)
            row = None if codes is None else codes.get(sid)
            if row is not None and len(row) == 7:
                row = row + _NO_VELOCITY_CODES
            velocity = record[3] if velocities else ZERO_VELOCITY
            if cur is None:
                self.store(sid, publisher, t, pose, velocity, row)
            else:  # store(), without looking the stream up again
                self._version += 1
                cur.capture, cur.pose, cur.version = t, pose, self._version
                cur.velocity, cur.codes = velocity, row
        self._stale += stale
        return stale

    def store(
        self,
        sid: int,
        user: int,
        capture: float,
        pose: bytes,
        velocity: bytes = ZERO_VELOCITY,
        codes: list[int] | None = None,
    ) -> None:
        """Make ``pose`` (captured at ``capture``) the newest keyframe of stream ``sid``."""
        self._version += 1
        cur = self._streams.get(sid)
        if cur is None:
            self._streams[sid] = _Stream(user, capture, pose, self._version, velocity, codes)
        else:
            cur.capture, cur.pose, cur.version = capture, pose, self._version
            cur.velocity, cur.codes = velocity, codes

    def stream_pose(self, sid: int) -> tuple[float, bytes]:
        """(capture time, 28 pose bytes) of stream ``sid``'s newest keyframe."""
        cur = self._streams[sid]
        return cur.capture, cur.pose

    def drop_stream(self, sid: int) -> None:
        """Forget stream ``sid`` (a removed object) and free its id."""
        self._streams.pop(sid, None)
        self.stream_ids.give_back(sid)

    # -- schedule -----------------------------------------------------------------

    def _grid_after(self, now: float, rate: float) -> float:
        """The first time on the ``(k + phase) / rate`` grid strictly after ``now``."""
        ph = self.phase
        return (math.floor(now * rate - ph + 1e-9) + 1 + ph) / rate

    def next_due(self) -> float | None:
        """The earliest due time of a member (None: no member); the relay asks at every
        check of its schedule, so it is computed once per change, not once per ask."""
        members = self.members
        if not members:
            return None
        due = self._due
        if due is None or self._due_members != len(members):
            due = self._due = min(m.next_due for m in members.values())
            self._due_members = len(members)
        return due

    def tick(self, now: float, out: list[Action] | None = None) -> int:
        """Send a snapshot to every due member; returns how many were offered. Each
        offer's ``Wake`` of the member's connection goes into ``out`` (the caller's)."""
        cache: dict[tuple[int, bool], tuple[bytes, int]] = {}
        groups: dict[tuple[int, bool], GroupSnapshot | None] = {}
        slots: dict[float, int] = {}  # the key slot of each rate at this tick
        views: dict[Any, Any] = {}  # per-peer frames of this tick (_view_frame)
        offered = 0
        self._due = None  # due members move on to their next grid point
        if self.objects and self.fly is not None:
            self.fly(self, now)
        for member in self.members.values():
            if member.next_due > now + 1e-9:
                continue
            if member.parked:
                # No snapshot while parked, but its grid moves on: a due time left
                # behind would be due for ever (and the room would tick in a loop).
                member.next_due = self._grid_after(now, member.rate)
                continue
            lag = now - member.next_due
            if self.lags is not None:
                self.lags.observe(lag)
            self._lag_max = max(self._lag_max, lag)
            self._lag_sum += lag
            self._lag_n += 1
            # Missed grid points are skipped, never sent in a burst.
            member.next_due = self._grid_after(now, member.rate)
            if member.outbox.congested():
                member.congestion_skips += 1
                continue
            if member.outbox.pose is None:
                # The previous snapshot went to the socket: deltas may start from it.
                member.delivered_version = member.last_version
            # A snapshot still waiting in the slot is about to be replaced (a skip),
            # so the new one must also carry what only the replaced one had.
            if member.view is not None:
                data, n = self._view_frame(member, member.view, now, views)
            elif member.compact:
                slot = slots.get(member.rate)
                if slot is None:
                    slot = slots[member.rate] = _key_slot(now, member.rate)
                data, n = self._compact_frame(member, now, slot, groups)
            else:
                key = (member.delivered_version, member.velocities)
                if key not in cache:
                    cache[key] = self._encode(now, *key)
                data, n = cache[key]
            member.last_version = self._version
            if n == 0:
                continue
            outbox = member.outbox
            outbox.offer_snapshot(data)
            if out is not None and outbox.conn is not None:
                out.append(Wake(outbox.conn))
            member.snapshots += 1
            member.snapshot_bytes += len(data)
            member.poses_sent += n
            self._frames_out += 1
            self._bytes_out += len(data)
            self._poses_out += n
            offered += 1
        return offered

    def _encode(self, now: float, since: int, velocities: bool = False) -> tuple[bytes, int]:
        fresh = [(sid, s) for sid, s in self._streams.items() if s.version > since]
        if not fresh:
            return b"", 0
        self._tick += 1
        self._snapshots += 1
        if velocities:
            data = pack_velocity_snapshot(
                self._tick,
                now,
                [(s.user, sid, s.capture, s.pose, s.velocity) for sid, s in fresh],
            )
        else:
            data = pack_snapshot(
                self._tick, now, [(s.user, sid, s.capture, s.pose) for sid, s in fresh]
            )
        return data, len(fresh)

    def _compact_frame(
        self,
        member: Member,
        now: float,
        slot: int,
        groups: dict[tuple[int, bool], GroupSnapshot | None],
    ) -> tuple[bytes, int]:
        """A compact member's frame, spliced from its group's (encoded once a tick)."""
        # -1: the key group (every stream absolute) of this tick.
        since = -1 if member.key_slot != slot else member.delivered_version
        if since < 0:
            member.key_slot = slot
        member.key_sent = since < 0
        key = (since, member.velocities)
        if key not in groups:
            groups[key] = self._encode_group(now, since, member.velocities)
        group = groups[key]
        if group is None:
            return b"", 0
        return group.frame(None if member.echo else member.user)

    def _encode_group(self, now: float, since: int, velocities: bool) -> GroupSnapshot | None:
        """Entries newer than ``since`` against the baselines as of ``since``
        (``since < 0``: every stream, absolute)."""
        group = encode_stored(self._tick + 1, now, self._streams, since, self.volume, velocities)
        if group is not None:
            self._tick += 1
            self._snapshots += 1
        return group

    # -- per-peer rates (``server.view_rates``) -------------------------------------

    def _view_frame(
        self, member: Member, view: ViewState, now: float, cache: dict[Any, Any]
    ) -> tuple[bytes, int]:
        """A budget member's frame: only the streams of the peers due for it now,
        each since what it holds of that peer; encoded once per tick for every
        member due the same peers at the same versions."""
        if member.outbox.pose is None:
            view.delivered = dict(view.last)
        publishers = cache.get("publishers")
        if publishers is None:
            publishers = cache["publishers"] = {}
            for sid, s in self._streams.items():
                publishers.setdefault(s.user, []).append((sid, s))
        tick = round(now * member.rate - self.phase)
        if member.compact:
            slot = _key_slot(now, member.rate)
            if member.key_slot != slot:  # a key, peer by peer as each one goes
                member.key_slot = slot
                view.absolute = set(publishers)
        head_sid = member.streams.get("head")
        head = self._streams.get(head_sid) if head_sid is not None else None
        eye = None if head is None else _POSITION.unpack_from(head.pose)
        wanted = []
        for user, streams in publishers.items():
            sids = [sid for sid, _ in streams]
            k = view.k[user] = peer_divisor(
                self.views, self.motion, view, member.rate, user == member.user, eye, sids
            )
            if self.views is not None and user != member.user:
                self.views.observe(member.rate / k)
            if view.due(user, tick, k):
                if member.compact:
                    since = -1 if user in view.absolute else view.delivered.get(user, -1)
                else:
                    since = max(0, view.delivered.get(user, 0))
                wanted.append((user, since))
        key = (member.compact, member.velocities, tuple(wanted))
        if key not in cache:
            cache[key] = encode_peers(self._tick + 1, now, key, publishers, self.volume)
            if cache[key] is not None:
                self._tick += 1
                self._snapshots += 1
        for user, _ in wanted:
            view.last[user], view.sent_tick[user] = self._version, tick
            view.absolute.discard(user)
        member.key_sent = any(since < 0 for _, since in wanted)
        frame = cache[key]
        if frame is None:
            return b"", 0
        if isinstance(frame, GroupSnapshot):
            return frame.frame(None if member.echo else member.user)
        return frame  # type: ignore[no-any-return]

    def retire(self) -> None:
        """Mark the room as removed (its members are gone or the server stops)."""
        self.retired = True

    # -- events -------------------------------------------------------------------

    def statistics(self) -> RoomStatistics:
        return RoomStatistics(
            name=self.name,
            members=len(self.members),
            streams=len(self._streams),
            ticks=self._lag_n,
            snapshots_encoded=self._snapshots,
            frames_out=self._frames_out,
            bytes_out=self._bytes_out,
            poses_out=self._poses_out,
            updates_in=self._updates_in,
            stale_updates=self._stale,
            skips=sum(m.outbox.skips + m.congestion_skips for m in self.members.values()),
            tick_lag_max_ms=1000.0 * self._lag_max,
            tick_lag_mean_ms=1000.0 * self._lag_sum / self._lag_n if self._lag_n else 0.0,
        )
