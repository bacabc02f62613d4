"""What one peer may cost the others: the relay's limits, sans I/O.

:class:`server.core.RelayCore` applies these; each limit is a
:class:`server.core.ServerConfig` field and a ``posecast serve`` flag, and
``docs/guides/security.md`` gives the threat model behind them.

- :func:`normalise_room`: one room per name as people read it (NFC, stripped),
  refusing names that display as something else (control characters, bidi
  overrides and isolates), empty names and names over ``MAX_ROOM_NAME_BYTES``.
- :func:`update_refusal`: an update whose capture times are too old or ahead of
  the server clock, or whose positions leave the room volume, is refused whole.
- :class:`Budget`: the misbehaviour budget of one connection (a token bucket
  each refused frame or update costs a token of).
- :class:`Admission`: connections in total and per source address.
- :func:`bounded_text`, :func:`error_message`: every text the relay derives from
  what a peer sent (a refusal, a log line) is cut to ``MAX_TEXT_LENGTH``
  characters, so that no input can make a refusal invalid (and the relay raise).
"""

from __future__ import annotations

import heapq
import struct
import unicodedata
from collections.abc import Callable, Mapping, Sized
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

from posecast.protocol import (
    MAX_TEXT_LENGTH,
    UPDATE_DTYPE,
    UPDATE_VELOCITY_DTYPE,
    ErrorCode,
    ErrorMessage,
    PoseUpdate,
    ProtocolError,
)
from posecast.protocol.codec import Volume

if TYPE_CHECKING:
    from posecast.server.config import ServerConfig

__all__ = [
    "MAX_ROOM_NAME_BYTES",
    "Admission",
    "Budget",
    "Deadlines",
    "Refusal",
    "RoomSize",
    "bounded_text",
    "error_message",
    "normalise_room",
    "room_refusal",
    "update_refusal",
]

#: Longest room name, in UTF-8 bytes, once normalised.
MAX_ROOM_NAME_BYTES = 64

# Bidi embeddings and overrides (U+202A-U+202E) and isolates (U+2066-U+2069):
# they make a name display as another one.
_BIDI = frozenset(range(0x202A, 0x202F)) | frozenset(range(0x2066, 0x206A))


def normalise_room(name: str) -> str:
    """The room ``name`` stands for (NFC, stripped); ValueError says why there is none."""
    norm = unicodedata.normalize("NFC", name).strip()
    if not norm:
        raise ValueError("room name is empty")
    for ch in norm:
        if ord(ch) in _BIDI or unicodedata.category(ch) == "Cc":
            raise ValueError(f"room name holds the control character U+{ord(ch):04X}")
    size = len(norm.encode("utf-8"))
    if size > MAX_ROOM_NAME_BYTES:
        raise ValueError(f"room name is {size} bytes, over {MAX_ROOM_NAME_BYTES}")
    return norm


def bounded_text(text: str, limit: int = MAX_TEXT_LENGTH) -> str:
    """``text`` cut to at most ``limit`` characters (an ellipsis marks a cut)."""
    return text if len(text) <= limit else text[: limit - 1] + "\u2026"


def error_message(
    code: ErrorCode | ProtocolError, message: str = "", what: str | None = None
) -> ErrorMessage:
    """The ``error`` message of a refusal (or of a :class:`ProtocolError`), its texts bounded:
    a message built from a peer's input (a name, a number) is always a valid one."""
    if isinstance(code, ProtocolError):
        return error_message(code.code, code.message, code.in_reply_to)
    reply = None if what is None else bounded_text(what)
    return ErrorMessage.from_code(code, bounded_text(message), in_reply_to=reply)


def _number(value: float, digits: int = 3) -> str:
    """A number for a refusal text: ``digits`` decimals, and short for any float a peer
    sends (``f"{1e300:.3f}"`` has 305 characters, more than an error message may hold)."""
    return f"{value:.{digits}f}" if abs(value) < 1e9 else f"{value:.3g}"


@dataclass(frozen=True, slots=True)
class Refusal:
    """Why an update was refused: the drops record ``kind`` and the error message."""

    kind: str
    message: str


def update_refusal(
    update: PoseUpdate, now: float, max_age: float, max_ahead: float, volume: Volume
) -> Refusal | None:
    """Whether ``update`` is refused at server time ``now`` (None: it is fine).

    Every capture time must lie in ``[now - max_age, now + max_ahead]`` (the
    allowance ahead is the clock-sync error a client may have), and every
    position within the room ``volume`` (the one compact codes quantise in).
    """
    entries = update.entries
    if len(entries) == 0:
        return None
    if len(entries) <= _SMALL_UPDATE and _accepted(update, now, max_age, max_ahead, volume):
        return None
    # Refused (or big, or unusual): numpy says which refusal, as it always did.
    dt = entries["dt"]
    oldest = update.base_time + float(dt.min())
    newest = update.base_time + float(dt.max())
    if oldest < now - max_age:
        return Refusal(
            "stale-capture", f"capture time {_number(now - oldest)} s old, over {max_age:g} s"
        )
    if newest > now + max_ahead:
        return Refusal(
            "future-capture",
            f"capture time {_number(newest - now)} s ahead of the server, over {max_ahead:g} s",
        )
    xyz = entries["pose"][:, :3]
    low, high = xyz.min(axis=0), xyz.max(axis=0)
    for axis, name in enumerate("xyz"):
        lo, hi = volume.lo[axis], volume.hi[axis]
        if not lo <= float(low[axis]) <= float(high[axis]) <= hi:
            bad = float(low[axis]) if not float(low[axis]) >= lo else float(high[axis])
            return Refusal(
                "out-of-bounds",
                f"position {name}={_number(bad, 2)} m outside the room volume [{lo:g}, {hi:g}]",
            )
    return None


#: Updates of at most this many entries are checked without numpy first.
_SMALL_UPDATE = 64
#: The record layouts of updates (``protocol.poses``): stream, dt, pose [, velocity].
_RECORDS = {
    UPDATE_DTYPE: struct.Struct("<Hf7f"),
    UPDATE_VELOCITY_DTYPE: struct.Struct("<Hf7f6e"),
}


def _accepted(
    update: PoseUpdate, now: float, max_age: float, max_ahead: float, volume: Volume
) -> bool:
    """True if :func:`update_refusal` finds nothing to refuse; False if it may (then its
    numpy code decides, and words the refusal). Python floats of the float32 fields,
    the same comparisons per record, no numpy call (this runs for every update).

    Record by record is min and max: ``base + dt`` rounds monotonically in dt. A NaN
    position fails its comparison here (numpy refuses it); a NaN time passes both
    here and in numpy (whose min and max are then NaN, never out of range)."""
    record = _RECORDS.get(update.entries.dtype)
    if record is None:
        return False
    base = update.base_time
    oldest, newest = now - max_age, now + max_ahead
    (lx, ly, lz), (hx, hy, hz) = volume.lo, volume.hi
    for fields in record.iter_unpack(update.entries.tobytes()):
        t = base + fields[1]
        if t < oldest or t > newest:
            return False
        if not (lx <= fields[2] <= hx and ly <= fields[3] <= hy and lz <= fields[4] <= hz):
            return False
    return True


class Budget:
    """A token bucket of ``burst`` tokens refilled ``refill`` a second; 0 tokens: no limit."""

    __slots__ = ("_last", "_tokens", "burst", "refill")

    def __init__(self, burst: int, refill: float, now: float) -> None:
        self.burst = burst
        self.refill = refill
        self._tokens = float(burst)
        self._last = now

    def spend(self, now: float) -> bool:
        """Take one token; False when there was none left (over budget)."""
        if self.burst <= 0:
            return True
        self._tokens = min(self.burst, self._tokens + (now - self._last) * self.refill)
        self._last = max(self._last, now)
        if self._tokens < 1.0:
            return False
        self._tokens -= 1.0
        return True


@dataclass
class Admission:
    """Open connections, in total and per source address (0: no limit)."""

    max_total: int
    max_per_address: int
    total: int = 0
    by_address: dict[str, int] = field(default_factory=dict)

    def admit(self, address: str | None) -> str | None:
        """Count one more connection, or say why it is refused (nothing counted)."""
        if self.max_total and self.total >= self.max_total:
            return f"too many connections ({self.max_total})"
        if address is not None:
            held = self.by_address.get(address, 0)
            if self.max_per_address and held >= self.max_per_address:
                return f"too many connections from one address ({self.max_per_address})"
            self.by_address[address] = held + 1
        self.total += 1
        return None

    def release(self, address: str | None) -> None:
        """A connection :meth:`admit` counted has ended."""
        self.total -= 1
        if address is not None:
            left = self.by_address.pop(address, 1) - 1
            if left > 0:
                self.by_address[address] = left


class RoomSize(Protocol):
    """What :func:`room_refusal` reads of a room (``server.room.Room`` is one)."""

    @property
    def members(self) -> Sized: ...

    @property
    def recorded(self) -> bool: ...


def room_refusal(cfg: ServerConfig, rooms: Mapping[str, RoomSize], name: str) -> str | None:
    """Why a join of room ``name`` is refused (``room-full``) now; None: it is not."""
    room = rooms.get(name)
    if room is not None:
        if cfg.max_members and len(room.members) >= cfg.max_members:
            return f"room is full ({cfg.max_members} members)"
        return None
    if cfg.max_rooms and len(rooms) >= cfg.max_rooms:
        return f"too many rooms ({cfg.max_rooms}), try later"
    if cfg.record_dir is not None and cfg.max_recorded_rooms:
        recorded = sum(r.recorded for r in rooms.values())
        if recorded >= cfg.max_recorded_rooms:
            return f"too many recorded rooms ({cfg.max_recorded_rooms}), try later"
    return None


class Deadlines:
    """When connections are due to be closed (a heap); an entry a later change made
    moot (``still_due(conn, deadline)`` false: joined, renewed, gone) is dropped
    when met, so each check costs O(log n)."""

    def __init__(self, still_due: Callable[[int, float], bool]) -> None:
        self._heap: list[tuple[float, int]] = []
        self._still_due = still_due

    def add(self, conn: int, deadline: float) -> None:
        heapq.heappush(self._heap, (deadline, conn))

    def next(self) -> float | None:
        """The earliest deadline still due (None: none)."""
        heap = self._heap
        while heap:
            deadline, conn = heap[0]
            if self._still_due(conn, deadline):
                return deadline
            heapq.heappop(heap)
        return None

    def pop_due(self, now: float) -> list[int]:
        """The connections whose deadline is ``now`` or earlier, removed."""
        out = []
        while (deadline := self.next()) is not None and deadline <= now:
            out.append(heapq.heappop(self._heap)[1])
        return out
