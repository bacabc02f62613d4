"""One client of a bench load: its join, its socket, and how it reads and counts snapshots."""

from __future__ import annotations

import array
import asyncio
import math
import struct
import time
from typing import Any

import numpy as np

from posecast.bench.common import (
    _FLUSH_EVERY,
    STATIC,
    STREAMS,
    Motion,
    _ws_header,
)
from posecast.bench.wsclient import (
    CompactUpdateFrames,
    FrameConnection,
    RawUpdateFrames,
    StepTimeout,
    client_frame,
    connect,
)
from posecast.protocol import (
    SNAPSHOT_DTYPE,
    SNAPSHOT_ENTRY_SIZE,
    ClientSession,
    ErrorMessage,
    Hello,
    Join,
    Joined,
    PoseUpdate,
    ProtocolError,
    Snapshot,
    Welcome,
)
from posecast.protocol.codec_relay import snapshot_counts
from posecast.server.room import room_phase

#: One snapshot in this many of each client has its poses decoded (capture -> receipt).
SAMPLE_EVERY = 16
#: A client whose socket holds this many unsent bytes skips its next update.
SEND_BUFFER_LIMIT = 64 * 1024

#: Flags byte of a relay codec snapshot without velocities (protocol.codec_relay, v2).
_RELAY_SNAPSHOT_FLAGS = 0x24
_SNAP_PREFIX = b"\x84\xa4type\xa8snapshot\xa4tick"
_TIME_KEY = b"\xa4time\xcb"
_INT_SIZE = {0xCC: 2, 0xCD: 3, 0xCE: 5, 0xCF: 9, 0xD0: 2, 0xD1: 3, 0xD2: 5, 0xD3: 9}
_POSES_KEY = b"\xa5poses"
_F64 = struct.Struct(">d")
_OWN = struct.Struct("<HH")


class _LoadStats:
    """What the load measures; only arrivals inside the window count."""

    def __init__(self, clients: int) -> None:
        self.t0 = math.inf
        self.t1 = math.inf
        # Plain lists: a numpy scalar increment costs more than the rest of a count.
        self.snapshots_total = [0] * clients
        self.snapshots = [0] * clients
        self.updates = 0
        self.updates_total = 0
        self.sends_late = 0
        self.send_skips = 0
        self.payload_bytes = 0
        self.wire_bytes = 0
        self.other_frames = 0
        self.bad_frames = 0
        self.decoded_frames = 0
        self.codec_snapshots = 0
        self.codec_own_echo = 0
        #: Per client: ticks of its room that sent it nothing (:class:`RoomTicks`) and
        #: were followed by a snapshot, in the window.
        self.empty_ticks = [0] * clients
        self.errors: dict[str, int] = {}
        self.error_examples: dict[str, str] = {}
        self.poses_all = 0
        self.poses_remote = 0
        self.relay = array.array("d")
        self.tick_lag = array.array("d")
        self.send_lag = array.array("d")
        # Sampled snapshots, flushed into per-pose arrays in batches.
        self._bodies: list[bytes] = []
        self._owner: list[int] = []
        self._send: list[float] = []
        self._due: list[float] = []
        self._arrival: list[float] = []
        self._lat: list[np.ndarray] = []
        self._hold: list[np.ndarray] = []
        # Who sent and who received each latency sample (user ids: in a cluster a
        # user id's block names the node that welcomed it).
        self._senders: list[np.ndarray] = []
        self._receivers: list[np.ndarray] = []

    def snapshot(
        self,
        index: int,
        arrival: float,
        send: float,
        due: float,
        size: int,
        poses: int,
        own: int,
    ) -> bool:
        """Count one snapshot; True if it arrived inside the window."""
        self.snapshots_total[index] += 1
        if not self.t0 <= arrival < self.t1:
            return False
        self.snapshots[index] += 1
        self.payload_bytes += size
        self.wire_bytes += size + _ws_header(size)
        self.poses_all += poses
        self.poses_remote += poses - own
        self.relay.append(arrival - due)
        self.tick_lag.append(send - due)
        return True

    def sample(self, user: int, arrival: float, send: float, due: float, body: bytes) -> None:
        """Records (``SNAPSHOT_DTYPE`` bytes) of one sampled snapshot, for per-pose latency."""
        self._bodies.append(body)
        self._owner.append(user)
        self._send.append(send)
        self._due.append(due)
        self._arrival.append(arrival)
        if len(self._bodies) >= _FLUSH_EVERY:
            self.flush()

    def sent_bucket(self, scheduled: float, now: float, n: int) -> None:
        self.updates_total += n
        if self.t0 <= now < self.t1:
            self.updates += n
            self.send_lag.append(now - scheduled)

    def flush(self) -> None:
        if not self._bodies:
            return
        counts = np.fromiter((len(b) // SNAPSHOT_ENTRY_SIZE for b in self._bodies), np.int64)
        entries = np.frombuffer(b"".join(self._bodies), dtype=SNAPSHOT_DTYPE)
        send = np.asarray(self._send, dtype=np.float64)
        owner = np.repeat(np.asarray(self._owner, dtype=np.int64), counts)
        remote = entries["user"].astype(np.int64) != owner
        capture = np.repeat(send, counts)[remote] + entries["dt"].astype(np.float64)[remote]
        arrival = np.repeat(np.asarray(self._arrival, dtype=np.float64), counts)[remote]
        due = np.repeat(np.asarray(self._due, dtype=np.float64), counts)[remote]
        self._lat.append(arrival - capture)
        self._hold.append(due - capture)
        self._senders.append(entries["user"][remote].astype(np.int32))
        self._receivers.append(owner[remote].astype(np.int32))
        for part in (self._bodies, self._owner, self._send, self._due, self._arrival):
            part.clear()

    def arrays(self) -> dict[str, np.ndarray]:
        """The window's samples in milliseconds (what the controller merges)."""
        self.flush()

        def cat(parts: list[np.ndarray]) -> np.ndarray:
            return np.concatenate(parts) * 1e3 if parts else np.zeros(0)

        def ids(parts: list[np.ndarray]) -> np.ndarray:
            return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int32)

        return {
            "latency_sender": ids(self._senders),
            "latency_receiver": ids(self._receivers),
            "latency": cat(self._lat),
            "hold": cat(self._hold),
            "relay": np.frombuffer(self.relay, dtype=np.float64) * 1e3,
            "tick_lag": np.frombuffer(self.tick_lag, dtype=np.float64) * 1e3,
            "send_lag": np.frombuffer(self.send_lag, dtype=np.float64) * 1e3,
        }

    def counts(self, joined: list[int] | None = None) -> dict[str, Any]:
        """The window's counts; per-client figures over the clients that ``joined``
        (indices; None: all of them): a refused client is not one without snapshots."""
        window = self.t1 - self.t0
        idx = range(len(self.snapshots)) if joined is None else joined
        got = np.asarray([self.snapshots[i] for i in idx], dtype=np.float64)
        ever = [self.snapshots_total[i] for i in idx]
        per_client = got / window if window > 0 else got * 0.0
        # Ticks: the snapshots and the ticks that sent nothing (nothing new to send).
        ticked = got + np.asarray([self.empty_ticks[i] for i in idx], dtype=np.float64)
        ticks = ticked / window if window > 0 else ticked * 0.0
        return {
            "window_s": window,
            "clients_measured": len(got),
            "snapshots": int(sum(self.snapshots)),
            "snapshots_per_client_s_sum": float(per_client.sum()),
            "snapshots_per_client_s_min": float(per_client.min()) if len(per_client) else 0.0,
            "snapshots_per_client_s_max": float(per_client.max()) if len(per_client) else 0.0,
            "clients_without_snapshots": ever.count(0),
            "clients_without_snapshots_in_window": int((got == 0).sum()),
            "poses_delivered": self.poses_remote,
            "poses_delivered_incl_own": self.poses_all,
            "payload_bytes": self.payload_bytes,
            "wire_bytes": self.wire_bytes,
            "updates_sent": self.updates,
            "updates_sent_total": self.updates_total,
            "sends_late": self.sends_late,
            "send_skips": self.send_skips,
            "other_frames": self.other_frames,
            "bad_frames": self.bad_frames,
            "decoded_frames": self.decoded_frames,
            "codec_snapshots": self.codec_snapshots,
            "codec_own_echo": self.codec_own_echo,
            "empty_ticks": sum(self.empty_ticks),
            "ticks_per_client_s_sum": float(ticks.sum()),
            "ticks_per_client_s_min": float(ticks.min()) if len(ticks) else 0.0,
            "server_errors": dict(self.errors),
            "server_error_examples": dict(self.error_examples),
        }


#: Send times this close are one tick (a codec snapshot's is rounded to the microsecond).
_SAME_TICK = 5e-6


class RoomTicks:
    """When a room's recent ticks ran, as this process's clients of it saw them (the
    send times of their snapshots).

    A tick with nothing new for a subscriber sends it nothing: a codec snapshot
    leaves out the subscriber's own streams, so in a room of two the other's update
    that reaches the relay just after a tick leaves the next tick empty. The
    subscriber's next snapshot, a period later and on time, would then read as due at
    the empty tick's grid point, a whole period late (a relay that admits members to
    half-empty rooms, as one shedding load does, read 50-70 ms at p99 for it). A
    room mate's snapshot of the empty tick shows the room ran it: the snapshot after
    it is due at the grid point after that tick.
    """

    __slots__ = ("_times",)

    #: Ticks remembered (the room's clients see each tick about at once).
    KEEP = 8

    def __init__(self) -> None:
        self._times: list[float] = []

    def before(self, send: float) -> float:
        """The latest tick of the room seen before ``send`` (-inf: none)."""
        best = -math.inf
        for t in self._times:
            if best < t < send - _SAME_TICK:
                best = t
        return best

    def saw(self, send: float) -> None:
        """A client of the room got a snapshot sent at ``send``."""
        times = self._times
        for t in times:
            if abs(t - send) <= _SAME_TICK:
                return
        times.append(send)
        if len(times) > self.KEEP:
            del times[0]


class _Refused(RuntimeError):
    """The handshake ended without a join: ``code`` is the server's error code, or
    ``closed`` (a close with no error before it)."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code


#: What became of a client's join (besides an error code of the server's).
JOINED, HUNG, CLOSED, UNREACHABLE = "joined", "hung", "closed", "unreachable"
#: The relay's answer when it is full (``protocol.ErrorCode.SERVER_FULL``).
SERVER_FULL = "server-full"


class _BenchClient:
    """One load client: handshake through the protocol's session, then counting only."""

    def __init__(
        self,
        index: int,
        room: str,
        rate: float,
        stats: _LoadStats,
        codec: str,
        poses: np.ndarray | None = None,
        offset: float = 0.0,
        ticks: RoomTicks | None = None,
    ) -> None:
        self.index = index
        #: Its room's ticks as this process's clients of the room see them (shared).
        self.ticks = RoomTicks() if ticks is None else ticks
        #: The server's clock minus this process's (0 on one relay: both are monotonic).
        self.offset = offset
        #: What it publishes: one frame (n, 7) or a cycle (K, n, 7) (default: a fixed pose).
        self.poses = Motion(STATIC, rate).cycle(index) if poses is None else poses
        self.room = room
        self.rate = rate
        self.stats = stats
        self.codec = codec
        self.error: str | None = None
        #: How its join ended (:data:`JOINED`, a server error code such as
        #: ``server-full``, :data:`HUNG`, :data:`CLOSED`, :data:`UNREACHABLE`) and how
        #: long that took from its first byte (s).
        self.outcome = ""
        self.join_s = math.nan
        #: When its TCP connection and its websocket handshake were done (s from its
        #: first byte; NaN: never), and the step a hung join got no answer to.
        self.connect_s = self.upgrade_s = math.nan
        self.hung_at = ""
        self.conn: FrameConnection | None = None
        self.session = ClientSession()
        self.user = -1
        self.frames: RawUpdateFrames | CompactUpdateFrames | None = None
        self._waiting: asyncio.Future[Any] | None = None
        self._own: tuple[bytes, ...] = ()
        self._seq = 0
        self._count = index % SAMPLE_EVERY  # spread the sampled snapshots over clients
        self._prev: float | None = None
        self._phase = room_phase(room)
        # Codec snapshots are delta-coded against what the client holds: a client
        # either decodes all of them (one in SAMPLE_EVERY clients, for per-pose
        # latency) or none (it counts them from their headers).
        self._count_codec = index % SAMPLE_EVERY != 0

    async def open(self, url: str, within: float) -> None:
        """Connect, hello, join, each step ``within`` s; on failure ``error`` says why.

        ``outcome`` says how it ended: joined, refused (the server's error code), hung
        (no answer to a step within ``within``), closed or unreachable."""
        start = time.monotonic()
        try:
            conn = self.conn = await connect(url, time.monotonic, within)
            self.connect_s = conn.connected_at - start
            await conn.upgraded(within)
            self.upgrade_s = conn.opened_at - start
            conn.on_message = self._handshake_message
            hello = Hello(agent="posecast-bench", wants_retry_after=True)
            welcome = await self._ask(hello, within)
            join = Join(room=self.room, streams=STREAMS, rate=self.rate, codec=self.codec)
            joined = await self._ask(join, within)
        except Exception as exc:  # whatever it was, this client did not join: say why
            self.join_s = time.monotonic() - start
            self.error = f"{type(exc).__name__}: {exc}"
            if isinstance(exc, _Refused):
                self.outcome = exc.code
            elif isinstance(exc, TimeoutError):
                self.outcome = HUNG
                self.hung_at = exc.step if isinstance(exc, StepTimeout) else "?"
            else:
                self.outcome = UNREACHABLE
            if self.conn is not None:
                self.conn.abort()
            self.conn = None
            return
        self.join_s = time.monotonic() - start
        self.outcome = JOINED
        assert isinstance(welcome, Welcome) and isinstance(joined, Joined)
        self.user = welcome.user
        ids = [joined.streams[name] for name in STREAMS]
        self._own = tuple(_OWN.pack(self.user, sid) for sid in ids)
        if self.codec == "compact":
            self.frames = CompactUpdateFrames(ids, self.poses, self._send_through_session)
        else:
            self.frames = RawUpdateFrames(ids, self.poses)
        conn.on_message = self._on_message

    def _send_through_session(self, update: PoseUpdate) -> bytes:
        return self.session.send(update)

    async def _ask(self, message: Hello | Join, within: float) -> Any:
        conn = self.conn
        assert conn is not None
        waiting = self._waiting = asyncio.get_running_loop().create_future()

        def closed(done: asyncio.Future[str]) -> None:
            if not waiting.done():
                waiting.set_exception(_Refused(CLOSED, f"during the handshake: {done.result()}"))

        conn.closed.add_done_callback(closed)
        conn.write(client_frame(self.session.send(message)))
        try:
            return await asyncio.wait_for(waiting, within)
        except TimeoutError as exc:
            raise StepTimeout(message.TYPE, within) from exc
        finally:
            conn.closed.remove_done_callback(closed)

    def _handshake_message(self, data: bytes, arrival: float) -> None:
        for ev in self.session.receive_data(data):
            waiting = self._waiting
            if waiting is None or waiting.done():
                continue
            if isinstance(ev, Welcome | Joined):
                waiting.set_result(ev)
            elif isinstance(ev, ErrorMessage | ProtocolError):
                waiting.set_exception(_Refused(str(ev.code), ev.message))

    def publish(self, now: float) -> bool:
        """Send the next update; False if the socket is backed up (skipped)."""
        conn, frames = self.conn, self.frames
        if conn is None or frames is None:
            return True
        if conn.buffered() > SEND_BUFFER_LIMIT:
            return False
        self._seq += 1
        conn.write(frames.frame(self._seq, now + self.offset))
        return True

    def _due(self, send: float) -> float:
        # The server ticks a subscriber on the grid (k + phase) / rate of its clock
        # (phase: the room's, server.room.room_phase); after a tick at ``now`` the
        # next is due at the first grid point after ``now`` (missed points are
        # skipped). A snapshot's send time is the ``now`` of its tick, so each
        # snapshot's due time follows from the previous one's send time.
        # A codec snapshot's send time is rounded to the microsecond: half a
        # microsecond before the grid point it was due at reads as due a period
        # earlier. Ticks never run early, so a microsecond of slack is safe.
        # A room mate's snapshot may show a tick after our last that sent us nothing
        # (RoomTicks): the grid point after that one is ours.
        rate, ph, prev, ticks = self.rate, self._phase, self._prev, self.ticks
        slack = 1e-6 * rate + 1e-9
        latest = (math.floor(send * rate - ph + slack) + ph) / rate
        mate = ticks.before(send)
        if prev is not None and mate > prev + _SAME_TICK:
            if self.stats.t0 <= send < self.stats.t1:
                self.stats.empty_ticks[self.index] += 1
            prev = mate
        ticks.saw(send)
        due = latest if prev is None else (math.floor(prev * rate - ph + slack) + 1 + ph) / rate
        self._prev = send
        return latest if due > send else due

    def _on_message(self, data: bytes, arrival: float) -> None:
        if data[:1] == b"\xc1" and self._count_codec and data[1] == _RELAY_SNAPSHOT_FLAGS:
            self._codec_snapshot(data, arrival)
            return
        if data.startswith(_SNAP_PREFIX):
            # The tick's msgpack int is 1, 2, 3, 5 or 9 bytes: its first byte says which.
            i = 20 + _INT_SIZE.get(data[20], 1) if len(data) > 20 else 0
            if data.startswith(_TIME_KEY, i) and data.startswith(_POSES_KEY, i + 14):
                p = i + 20
                tag = data[p] if p < len(data) else 0
                if tag == 0xC4:
                    size, at = data[p + 1], p + 2
                elif tag == 0xC5:
                    size, at = int.from_bytes(data[p + 1 : p + 3], "big"), p + 3
                elif tag == 0xC6:
                    size, at = int.from_bytes(data[p + 1 : p + 5], "big"), p + 5
                else:
                    size, at = -1, 0
                if at + size == len(data) and size % SNAPSHOT_ENTRY_SIZE == 0:
                    send = _F64.unpack_from(data, i + 6)[0]
                    self._raw_snapshot(data, at, size // SNAPSHOT_ENTRY_SIZE, send, arrival)
                    return
        self._decode(data, arrival)

    def _raw_snapshot(self, data: bytes, at: int, n: int, send: float, arrival: float) -> None:
        own = self._own_run(data, at)
        if own < 0:
            own = self._own_count(data, at)
        # The tick grid is the server's: due in its clock, then both in ours.
        due = self._due(send) - self.offset
        send -= self.offset
        stats = self.stats
        if stats.snapshot(self.index, arrival, send, due, len(data), n, own):
            self._count += 1
            if self._count % SAMPLE_EVERY == 0:
                stats.sample(self.user, arrival, send, due, data[at:])

    def _own_run(self, data: bytes, at: int) -> int:
        """Own records (3) if they sit in a row, as the relay writes them; else -1."""
        own = self._own
        j = data.find(own[0], at) if own else -1
        if j < 0 or (j - at) % SNAPSHOT_ENTRY_SIZE:
            return -1
        for k in range(1, len(own)):
            if not data.startswith(own[k], j + k * SNAPSHOT_ENTRY_SIZE):
                return -1
        return len(own)  # a stream is in a snapshot once: no other aligned copy

    def _own_count(self, data: bytes, at: int) -> int:
        """Own records wherever they are: every aligned (user, stream) prefix of ours."""
        own = 0
        for pattern in self._own:
            j = data.find(pattern, at)
            while j >= 0:
                if (j - at) % SNAPSHOT_ENTRY_SIZE == 0:
                    own += 1
                j = data.find(pattern, j + 1)
        return own

    def _codec_snapshot(self, data: bytes, arrival: float) -> None:
        """A relay codec snapshot, counted from its header (it never holds our own streams)."""
        _tick, base_us, n_key, n_delta = snapshot_counts(data)
        send = base_us / 1e6
        due = self._due(send) - self.offset
        self.stats.codec_snapshots += 1
        self.stats.snapshot(
            self.index, arrival, send - self.offset, due, len(data), n_key + n_delta, 0
        )

    def _decode(self, data: bytes, arrival: float) -> None:
        """The slow path: a frame the cheap parse does not know, through the client session.

        The session decodes codec snapshots against its baselines (and forgets a
        peer's when it leaves), velocity snapshots and control messages.
        """
        stats = self.stats
        stats.decoded_frames += 1
        for event in self.session.receive_data(data):
            if isinstance(event, ProtocolError):
                stats.bad_frames += 1
                continue
            if isinstance(event, ErrorMessage):
                # The server refused something (an update, say): by code, reported.
                stats.errors[event.code] = stats.errors.get(event.code, 0) + 1
                stats.error_examples.setdefault(event.code, event.message[:120])
                continue
            if not isinstance(event, Snapshot):
                stats.other_frames += 1
                continue
            records = np.zeros(len(event.entries), dtype=SNAPSHOT_DTYPE)
            for name in ("user", "stream", "dt", "pose"):
                records[name] = event.entries[name]
            own = int((records["user"] == self.user).sum())
            if data[:1] == b"\xc1":
                stats.codec_snapshots += 1
                stats.codec_own_echo += own
            due = self._due(event.send_time) - self.offset
            send = event.send_time - self.offset
            if stats.snapshot(self.index, arrival, send, due, len(data), len(records), own):
                self._count += 1
                if self._count % SAMPLE_EVERY == 0:
                    stats.sample(self.user, arrival, send, due, records.tobytes())
