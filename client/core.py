"""The client's sans-I/O core: what a receiver keeps of a room, and what it shows.

:class:`ClientCore` is fed the protocol events a connection decoded, each with
the time it arrived on the caller's clock, and renders when asked with the time
of the frame; it reads no clock and touches no socket or file, so every rule it
holds is tested with fake times (``tests/client/test_client_core.py``). The asyncio bot
(:mod:`client.bot`), the viewer's spectator (``posecast.view.live``) and anything
else that receives a room are adapters over it.

What it holds, each in one place:

- the clock estimate to the server (:class:`client.playout.ClockEstimator`, fed
  by :meth:`ClientCore.pong`);
- the room's peers (names, motion labels, whether they send velocities) from
  ``peer_joined`` / ``peer_left``; a peer that leaves gives its buffer rows back,
  so a frame renders only the streams present (:meth:`ClientCore.peer_left`);
- one jitter buffer row per remote stream (:class:`client.buffers.RoomBuffers`),
  fed by snapshots (:meth:`ClientCore.snapshot`), a repeated keyframe of a key
  snapshot dropped (:func:`repeats`);
- the playout delay D per remote user (:class:`client.playout.RoomPlayoutDelay`):
  a frame's playout time is ``server_now - D`` (:meth:`ClientCore.playout`), a
  user shown late alone at its own D in the same frame;
- the render: every stream in one batched call per method
  (:meth:`ClientCore.render`, :func:`client.render.render_buffers`).

What it reports goes to its :class:`Observer` (keyframes as they arrive, each
frame as rendered, peers leaving): scoring (:class:`client.log.SessionLog`) and a
viewer's statistics are consumers of those reports, not fields in here.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from posecast.client.buffers import RoomBuffers, StreamBuffer
from posecast.client.playout import ClockEstimator, RoomPlayoutDelay
from posecast.client.render import RenderFrame, render_buffers
from posecast.interp import info as interp_info
from posecast.protocol import ROOM_USER, PeerJoined, PeerLeft, Pong, Snapshot

__all__ = ["REPEAT_TIME", "ClientCore", "Observer", "Peer", "Playout", "Rendered", "repeats"]

F64 = NDArray[np.float64]
Key = tuple[int, int]

#: A relay codec snapshot codes capture times to 1 ms against its own base time.
REPEAT_TIME = 1e-3 + 1e-9


def repeats(
    last: tuple[float, NDArray[np.float32]] | None, capture: float, pose: NDArray[np.float32]
) -> bool:
    """Whether a received keyframe is the ``last`` one again: a key snapshot resends
    a stream that did not change (a shared object at rest), its capture time coded
    anew against the snapshot's own base, so within the codec's 1 ms of the first;
    the same pose bits say it is no new keyframe."""
    return (
        last is not None and abs(capture - last[0]) <= REPEAT_TIME and np.array_equal(pose, last[1])
    )


@dataclass
class Peer:
    """A remote user as ``peer_joined`` announced it."""

    #: Stream names by stream id, and its motion label.
    names: dict[int, str]
    label: str | None
    velocities: bool = False


class Observer:
    """What a :class:`ClientCore` reports; a consumer overrides what it needs.

    Times: ``arrival`` on the server's clock (the estimate at arrival),
    ``arrival_local`` on the caller's.
    """

    def stream_added(self, key: Key, name: str, label: str | None, velocities: bool) -> None:
        """A remote stream's first keyframe is here."""

    def velocities_known(self, user: int) -> None:
        """``user`` said (after its first snapshots) that it sends velocities."""

    def keyframe(
        self,
        key: Key,
        capture: float,
        arrival: float,
        arrival_local: float,
        sent: float,
        pose: NDArray[np.float32],
        velocity: F64 | None,
    ) -> None:
        """A new keyframe of ``key`` (not a repeat), with the snapshot's send time."""

    def snapshot(
        self,
        arrival: float,
        arrival_local: float,
        sent: float,
        size: int,
        users: Mapping[int, tuple[int, int]],
    ) -> None:
        """A snapshot of ``size`` bytes was taken in; ``users``: per remote user,
        (poses of it in the snapshot, of them new keyframes)."""

    def peer_left(self, users: Sequence[int]) -> None:
        """``users`` left (or the client left their relay): their streams ended."""

    def rendered(self, frame: Rendered) -> None:
        """A frame was rendered."""


@dataclass(frozen=True)
class Playout:
    """One frame's playout: server time ``now``, the room's D, the room's playout
    time ``now - delay``, and the users shown at their own D (late alone, or slower
    peers' longer D)."""

    now: float
    delay: float
    own: Mapping[int, float]

    @property
    def time(self) -> float:
        return self.now - self.delay


@dataclass(frozen=True)
class Rendered:
    """A rendered frame: its index (from 0), its playout, the poses per method and
    which streams stalled (columns: :meth:`ClientCore.shown`, in order)."""

    index: int
    playout: Playout
    frame: RenderFrame


@dataclass
class _Remote:
    """What the core keeps of one remote stream: its buffer row and last keyframe."""

    buffer: StreamBuffer
    last: tuple[float, NDArray[np.float32]] | None = None


@dataclass
class ClientCore:
    """A receiver's room, sans I/O (see the module docstring).

    ``methods``: interpolators each frame renders; ``rate``: the snapshot rate asked
    (D starts at one interval, plus one per keyframe a window method looks ahead);
    ``velocities``: it receives velocity snapshots; ``observer``: gets its reports;
    ``per_peer``: size each user's D from its own keyframe interval (a client that
    joined with ``budget_deg``, :class:`client.playout.RoomPlayoutDelay`).
    """

    methods: tuple[str, ...]
    rate: float
    velocities: bool = False
    observer: Observer = field(default_factory=Observer)
    per_peer: bool = False
    clock: ClockEstimator = field(default_factory=ClockEstimator)
    delay: RoomPlayoutDelay = field(init=False)
    buffers: RoomBuffers = field(default_factory=RoomBuffers)
    #: Its own user id (its streams in snapshots are skipped).
    me: int = -1
    peers: dict[int, Peer] = field(default_factory=dict)
    #: The room's shared objects by name (the session's live map; ids are stream ids).
    objects: Mapping[str, int] = field(default_factory=dict)
    #: The label and velocity flag of the room's own streams (``ROOM_USER``).
    room_label: str | None = None
    room_velocities: bool = False
    #: Frames rendered.
    frames: int = 0
    _streams: dict[Key, _Remote] = field(default_factory=dict)
    _by_user: dict[int, list[StreamBuffer]] = field(default_factory=dict)
    #: The room's playout time of the last frame: an older keyframe is stale.
    _floor: float = -np.inf
    #: Each row's playout time of the frame being rendered, when some differ.
    _t_rows: F64 = field(default_factory=lambda: np.empty(0))

    def __post_init__(self) -> None:
        # A window method waits for the keyframe after the bracket: one more interval.
        lookahead = max(interp_info(m).lookahead for m in self.methods)
        self.delay = RoomPlayoutDelay(
            interval=(1.0 + lookahead) / self.rate, rate=self.rate, per_peer=self.per_peer
        )

    # -- what arrives -------------------------------------------------------------

    def receive(self, event: object, arrival: float, size: int = 0) -> None:
        """Take in one decoded event that arrived at ``arrival`` (caller's clock);
        events that are not the receiver's (e.g. ``owner``) are left to the caller."""
        if isinstance(event, Snapshot):
            self.snapshot(event, arrival, size)
        elif isinstance(event, Pong):
            self.pong(event, arrival)
        elif isinstance(event, PeerJoined):
            self.peer_joined(event)
        elif isinstance(event, PeerLeft):
            self.peer_left(event.user)

    def pong(self, pong: Pong, arrival: float) -> None:
        """A ping's answer: one sample of the clock offset."""
        self.clock.add(pong.offset(arrival), pong.round_trip(arrival))

    def server_time(self, local: float) -> float:
        """The server's clock at ``local`` (caller's clock), as estimated."""
        return local + self.clock.offset

    def peer_joined(self, ev: PeerJoined) -> None:
        """A peer is announced: its stream names, label, and whether it sends velocities
        (streams of it that came first learn it now)."""
        self.peers[ev.user] = Peer({sid: name for name, sid in ev.streams.items()}, ev.label)
        if ev.velocities:
            self.peers[ev.user].velocities = True
            buffers = self._by_user.get(ev.user, ())
            for b in buffers:
                b.has_velocities = True
            if buffers:
                self.observer.velocities_known(ev.user)

    def peer_left(self, user: int) -> None:
        """``user`` left: its buffer rows are given back, its ages forgotten."""
        self._forget([user])

    def left_relay(self) -> list[int]:
        """The client rejoined as a new member elsewhere: everyone it knew is gone
        (returns who)."""
        users = sorted(u for u in {*self._by_user, *self.peers} if u <= ROOM_USER)
        self._forget(users)
        return users

    def _forget(self, users: list[int]) -> None:
        for user in users:
            for b in self._by_user.pop(user, ()):
                key = b.key
                if key is not None:
                    self._streams.pop(key, None)
                self.buffers.release(b)
            self.peers.pop(user, None)
            self.delay.forget(user)
        self.observer.peer_left(users)

    def stream_name(self, key: Key) -> str:
        """A remote stream's name: a peer's device name, a shared object's name."""
        user, sid = key
        if user == ROOM_USER:
            for name, oid in self.objects.items():
                if oid == sid:
                    return name
            return f"stream{sid}"
        peer = self.peers.get(user)
        return peer.names.get(sid, f"stream{sid}") if peer is not None else f"stream{sid}"

    def _stream(self, key: Key) -> _Remote:
        user = key[0]
        if user == ROOM_USER:
            label, velocities = self.room_label, self.room_velocities
        else:
            peer = self.peers.get(user)
            label = None if peer is None else peer.label
            velocities = peer is not None and peer.velocities
        buffer = self.buffers.stream(has_velocities=velocities, key=key)
        remote = self._streams[key] = _Remote(buffer)
        self._by_user.setdefault(user, []).append(buffer)
        self.observer.stream_added(key, self.stream_name(key), label, velocities)
        return remote

    def snapshot(self, snap: Snapshot, arrival: float, size: int = 0) -> int:
        """Take in a snapshot that arrived at ``arrival`` (caller's clock): each new
        keyframe of a remote stream into its buffer, its age into the sender's D.
        Returns the new keyframes."""
        me, obs = self.me, self.observer
        arrival_srv = arrival + self.clock.offset
        users, ids = snap.users.tolist(), snap.streams.tolist()
        caps, poses, sent = snap.capture_times.tolist(), snap.poses, snap.send_time
        vels = snap.velocities
        vel64 = None if vels is None else vels.astype(np.float64)
        floor, new = self._floor, 0
        per_user: dict[int, tuple[int, int]] = {}
        for i, user in enumerate(users):
            if user == me:
                continue
            key = (user, ids[i])
            remote = self._streams.get(key) or self._stream(key)
            cap, pose = caps[i], np.array(poses[i])
            seen, fresh = per_user.get(user, (0, 0))
            if repeats(remote.last, cap, pose):
                per_user[user] = (seen + 1, fresh)
                continue
            per_user[user] = (seen + 1, fresh + 1)
            new += 1
            remote.last = (cap, pose)
            vel = None if vel64 is None else vel64[i]
            obs.keyframe(key, cap, arrival_srv, arrival, sent, pose, vel)
            remote.buffer.push(cap, pose, floor, vel)
            self.delay.observe(user, arrival_srv - cap, sent)
        obs.snapshot(arrival_srv, arrival, sent, size, per_user)
        return new

    # -- what it shows ------------------------------------------------------------

    def playout(self, local: float) -> Playout:
        """This frame's playout at ``local`` (caller's clock): D slews towards its target."""
        now = local + self.clock.offset
        d = self.delay.update(now)
        return Playout(now, d, self.delay.own_delays())

    def render(self, playout: Playout, *, report: bool = True) -> Rendered:
        """Every remote stream at its playout time, one batched call per method.

        ``report``: tell the observer now; False leaves it to :meth:`report` (a caller
        that times the render alone)."""
        frame = render_buffers(self.buffers, self._row_times(playout), self.methods)
        self._floor = playout.now - playout.delay
        out = Rendered(self.frames, playout, frame)
        self.frames += 1
        if report:
            self.observer.rendered(out)
        return out

    def report(self, rendered: Rendered) -> None:
        """Tell the observer of a frame rendered with ``report=False``."""
        self.observer.rendered(rendered)

    def _row_times(self, p: Playout) -> float | F64:
        """The room's playout time, or one per row when a user is shown late alone."""
        now = p.now
        if not p.own:
            return now - p.delay
        # Into the core's own array (a frame reads it and keeps nothing of it): one
        # fill, then the late users' rows; the same values as ``now - D`` per row.
        n = len(self.buffers)
        t_rows = self._t_rows
        if t_rows.shape[0] != n:
            t_rows = self._t_rows = np.empty(n)
        t_rows.fill(now - p.delay)
        by_user = self._by_user
        for user, d_own in p.own.items():
            t_user = now - d_own
            for b in by_user.get(user, ()):
                t_rows[b.row] = t_user
        return t_rows

    def shown(self) -> list[Key]:
        """The streams of a render frame, column by column (non-empty rows in order)."""
        return [k for k in self.buffers.shown_keys() if k is not None]

    def streams_of(self, user: int) -> list[Key]:
        """``user``'s remote streams present."""
        return [b.key for b in self._by_user.get(user, ()) if b.key is not None]
