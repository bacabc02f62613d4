"""Remote streams' keyframes as a receiver buffers them, one array per room.

- :class:`RoomBuffers`: every remote stream's keyframes in one preallocated
  array per room (a row per stream), validated once on arrival, with the views
  a render frame needs (:meth:`RoomBuffers.whole`).
- :class:`StreamBuffer`: one remote stream's keyframes ordered by capture time
  (a row of a room), each with the velocity it came with (zeros without one);
  duplicates and stale frames dropped; bounded (oldest evicted).

A stream that ends (its peer left) gives its row back (:meth:`RoomBuffers.release`):
the last row moves into its place, so a render frame touches only the rows of the
streams present, however many came and went.

:mod:`client.render` renders them (``render_buffers``).
"""

from __future__ import annotations

import bisect
import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from posecast.interp.pose import UNIT_TOLERANCE

__all__ = ["DEFAULT_BUFFER_CAPACITY", "RoomBuffers", "StreamBuffer"]

F64 = NDArray[np.float64]

DEFAULT_BUFFER_CAPACITY = 64

#: The velocity of a keyframe that came without one (shared, read-only).
_NO_VELOCITY = np.zeros(6)
_NO_VELOCITY.setflags(write=False)


class _WholeRoom(NamedTuple):
    """Views of a room's first ``n`` rows (``newest`` and ``counts`` change in place,
    so the views stay current until the arrays are reallocated)."""

    n: int
    times: F64
    base: NDArray[np.intp]
    base_m1: NDArray[np.intp]  # base - 1: the slot before each row's first
    newest: NDArray[np.intp]
    counts: NDArray[np.intp]
    has_velocities: NDArray[np.bool_]
    rows: NDArray[np.intp]
    flat_times: F64  # times (R * W,)
    pose_rows: F64  # poses (R * W, 7), slot after slot
    #: Each row's last bracket (the compiled render's, :attr:`RoomBuffers.brackets`).
    lo: NDArray[np.intp]
    hi: NDArray[np.intp]
    s: F64


class RoomBuffers:
    """The keyframes of every remote stream of a room, in preallocated arrays.

    One row per stream (:meth:`stream` adds one and returns its
    :class:`StreamBuffer`), ``capacity + 1`` slots per row, in capture-time order
    and padded with ``+inf`` times: ``times (R, W)``, ``pose_rows (R, W, 7)``
    (float64, validated on arrival: finite, unit quaternions; ``poses (7, R, W)``
    is its component-major view), ``velocities (R, W, 6)``, ``counts (R,)`` and
    ``has_velocities (R,)``. The
    arrays grow (doubling the rows) when streams are added; a render frame
    (:func:`render_buffers`) brackets every row with one vectorised comparison
    and gathers the bracketing keyframes with one ``take`` per side.
    """

    def __init__(self, capacity: int = DEFAULT_BUFFER_CAPACITY, streams: int = 16) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be at least 1, got {capacity}")
        self.capacity = capacity
        self.width = capacity + 1  # a spare slot: insert first, then evict
        self.n = 0  # rows in use
        #: Rows in use that hold at least one keyframe (a render frame skips the others).
        self.filled = 0
        self.times: F64
        self.pose_rows: F64
        self.poses: F64
        self.brackets: tuple[NDArray[np.intp], NDArray[np.intp], F64]
        self.velocities: F64
        self.counts: NDArray[np.intp]
        self.has_velocities: NDArray[np.bool_]
        #: Per row: its index, the flat index of its slot 0 and of its newest keyframe.
        self.row_index: NDArray[np.intp]
        self.base: NDArray[np.intp]
        self.newest: NDArray[np.intp]
        self._whole: _WholeRoom | None = None
        #: The compiled render's hold on these arrays (``client.render``; dropped
        #: when they are reallocated).
        self.renderer: object | None = None
        #: The buffer of each row in use, in row order.
        self._rows: list[StreamBuffer] = []
        self._allocate(max(1, streams))

    def _allocate(self, rows: int) -> None:
        w, n = self.width, self.n
        times = np.full((rows, w), np.inf)
        pose_rows = np.zeros((rows, w, 7))
        vels = np.zeros((rows, w, 6))
        counts = np.zeros(rows, dtype=np.intp)
        has_v = np.ones(rows, dtype=bool)
        if n:
            times[:n] = self.times[:n]
            pose_rows[:n] = self.pose_rows[:n]
            vels[:n] = self.velocities[:n]
            counts[:n] = self.counts[:n]
            has_v[:n] = self.has_velocities[:n]
        # Stored slot after slot (a keyframe's 7 values side by side, where a render
        # reads them); ``poses`` is the component-major view of the same memory.
        self.pose_rows = pose_rows
        self.poses = pose_rows.transpose(2, 0, 1)
        self.times, self.velocities = times, vels
        self.counts, self.has_velocities = counts, has_v
        #: Each row's last bracket (flat slots, fraction): where the compiled render
        #: writes it, and where its next search starts (render time moves forward).
        self.brackets = (
            np.zeros(rows, dtype=np.intp),
            np.zeros(rows, dtype=np.intp),
            np.zeros(rows),
        )
        self.row_index = np.arange(rows, dtype=np.intp)
        self.base = self.row_index * w
        self.newest = self.base + counts - 1
        self._whole = None
        self.renderer = None

    def whole(self) -> _WholeRoom:
        """Views of the rows in use, for a render frame (kept until rows are added)."""
        v = self._whole
        n = self.n
        if v is None or v.n != n:
            v = self._whole = _WholeRoom(
                n,
                self.times[:n],
                self.base[:n],
                self.base[:n] - 1,
                self.newest[:n],
                self.counts[:n],
                self.has_velocities[:n],
                self.row_index[:n],
                self.times.reshape(-1),
                self.pose_rows.reshape(-1, 7),
                self.brackets[0][:n],
                self.brackets[1][:n],
                self.brackets[2][:n],
            )
        return v

    def stream(
        self,
        capacity: int | None = None,
        *,
        has_velocities: bool = True,
        key: tuple[int, int] | None = None,
    ) -> StreamBuffer:
        """A new stream's buffer, backed by the next row (``key``: what the caller
        knows it by, e.g. ``(user, stream id)``; see :meth:`shown_keys`)."""
        return StreamBuffer(capacity, has_velocities=has_velocities, room=self, key=key)

    def _add_row(self, buffer: StreamBuffer, has_velocities: bool) -> int:
        if self.n == self.counts.shape[0]:
            self._allocate(2 * self.n)
        row = self.n
        self.n += 1
        self.has_velocities[row] = has_velocities
        self._rows.append(buffer)
        return row

    def release(self, buffer: StreamBuffer) -> None:
        """Give ``buffer``'s row back: the last row moves into it (its buffer's ``row``
        follows), the last one is cleared, and ``buffer`` is detached (empty, no row)."""
        row, last = buffer.row, self.n - 1
        if row < 0 or self._rows[row] is not buffer:
            return  # released before
        if self.counts[row]:
            self.filled -= 1
        if row != last:
            moved = self._rows[last]
            self.times[row] = self.times[last]
            self.pose_rows[row] = self.pose_rows[last]
            self.velocities[row] = self.velocities[last]
            self.counts[row] = self.counts[last]
            self.has_velocities[row] = self.has_velocities[last]
            self.newest[row] = self.base[row] + self.counts[row] - 1
            self._rows[row] = moved
            moved.row = row
        self.times[last] = np.inf
        self.counts[last] = 0
        self.has_velocities[last] = True
        self.newest[last] = self.base[last] - 1
        self._rows.pop()
        self.n = last
        buffer.detach()

    def buffers(self) -> list[StreamBuffer]:
        """The buffer of each row in use, in row order (a copy)."""
        return list(self._rows)

    def shown_keys(self) -> list[tuple[int, int] | None]:
        """The ``key`` of each non-empty row, in row order: the streams of a render
        frame (:func:`client.render.render_buffers`), column by column."""
        return [b.key for b in self._rows if b.times]

    def __len__(self) -> int:
        """Streams (rows) in use, empty ones included."""
        return self.n

    def _insert(
        self, row: int, i: int, capture: float, pose: F64, velocity: NDArray[np.float64] | None
    ) -> None:
        """Put a keyframe at slot ``i`` of ``row``, shifting later ones right."""
        c = int(self.counts[row])
        times, poses, vels = self.times, self.pose_rows, self.velocities
        if i < c:
            times[row, i + 1 : c + 1] = times[row, i:c]
            poses[row, i + 1 : c + 1] = poses[row, i:c]
            vels[row, i + 1 : c + 1] = vels[row, i:c]
        times[row, i] = capture
        poses[row, i] = pose
        vels[row, i] = 0.0 if velocity is None else velocity
        self.counts[row] = c + 1
        if not c:
            self.filled += 1
        self.newest[row] += 1

    def _evict_oldest(self, row: int) -> None:
        c = int(self.counts[row])
        times, poses, vels = self.times, self.pose_rows, self.velocities
        times[row, : c - 1] = times[row, 1:c]
        poses[row, : c - 1] = poses[row, 1:c]
        vels[row, : c - 1] = vels[row, 1:c]
        times[row, c - 1] = np.inf
        self.counts[row] = c - 1
        self.newest[row] -= 1


def _checked_pose(pose: NDArray[np.float32]) -> F64 | None:
    """A keyframe pose as float64, its quaternion renormalised when it is off unit
    length by more than ``interp``'s tolerance; None when it is not finite or the
    quaternion is zero (such a keyframe could only break every render)."""
    p = np.asarray(pose, dtype=np.float64).reshape(7)
    x = p.tolist()
    n2 = x[3] * x[3] + x[4] * x[4] + x[5] * x[5] + x[6] * x[6]
    if not (math.isfinite(sum(x)) and all(map(math.isfinite, x))) or not n2 > 1e-24:
        return None
    if abs(n2 - 1.0) > 2.0 * UNIT_TOLERANCE:
        p = p.copy()
        p[3:] /= math.sqrt(n2)
    return p


class StreamBuffer:
    """Keyframes of one remote stream, by capture time, for rendering.

    ``push`` refuses duplicates (same capture time) and stale keyframes: ones
    that can never be a bracket again because a newer keyframe already sits at
    or before ``floor`` (the playout time already passed), or that are older than
    everything kept in a full buffer. A late keyframe just before the playout
    time is kept: it is the lower bracket. Beyond ``capacity`` the oldest is
    evicted. A pose that is not finite or has a zero quaternion is refused
    (``invalid``).

    ``velocities[i]`` is the velocity ``(6,)`` (linear m/s, angular rad/s, world
    frame) that came with ``times[i]``/``poses[i]``, for velocity interpolators;
    a keyframe pushed without one gets zeros. ``has_velocities`` says whether the
    sender reports velocities at all: if not, the zeros are fillers, not data,
    and velocity methods render the stream with :data:`VELOCITY_FALLBACK`.

    The keyframes live in one row of a :class:`RoomBuffers` (``room``; a buffer
    made on its own gets a room of its own); the lists here mirror that row.
    """

    def __init__(
        self,
        capacity: int | None = DEFAULT_BUFFER_CAPACITY,
        *,
        has_velocities: bool = True,
        room: RoomBuffers | None = None,
        key: tuple[int, int] | None = None,
    ) -> None:
        if room is None:
            room = RoomBuffers(DEFAULT_BUFFER_CAPACITY if capacity is None else capacity, 1)
        capacity = room.capacity if capacity is None else capacity
        if not 1 <= capacity <= room.capacity:
            raise ValueError(f"capacity must be in 1..{room.capacity}, got {capacity}")
        self.capacity = capacity
        self.room = room
        self.key = key
        self.row = room._add_row(self, has_velocities)
        self.times: list[float] = []
        self.poses: list[NDArray[np.float32]] = []
        self.velocities: list[NDArray[np.float64]] = []
        self.duplicates = 0
        self.stale = 0
        self.evicted = 0
        self.invalid = 0

    @property
    def has_velocities(self) -> bool:
        return self.row >= 0 and bool(self.room.has_velocities[self.row])

    @has_velocities.setter
    def has_velocities(self, value: bool) -> None:
        if self.row >= 0:
            self.room.has_velocities[self.row] = value

    def detach(self) -> None:
        """Its row was given back (:meth:`RoomBuffers.release`): empty, takes nothing."""
        self.row = -1
        self.times.clear()
        self.poses.clear()
        self.velocities.clear()

    def push(
        self,
        capture: float,
        pose: NDArray[np.float32],
        floor: float = -np.inf,
        velocity: NDArray[np.float64] | None = None,
    ) -> bool:
        times = self.times
        if self.row < 0:
            raise ValueError("the buffer's row was released")
        i = bisect.bisect_left(times, capture)
        if i < len(times) and times[i] == capture:
            self.duplicates += 1
            return False
        superseded = capture < floor and i < len(times) and times[i] <= floor
        if superseded or (len(times) >= self.capacity and i == 0):
            self.stale += 1
            return False
        checked = _checked_pose(pose)
        if checked is None or not math.isfinite(capture):
            self.invalid += 1
            return False
        times.insert(i, capture)
        self.poses.insert(i, pose)
        self.velocities.insert(i, _NO_VELOCITY if velocity is None else velocity)
        self.room._insert(self.row, i, capture, checked, velocity)
        if len(times) > self.capacity:
            del times[0]
            del self.poses[0]
            del self.velocities[0]
            self.room._evict_oldest(self.row)
            self.evicted += 1
        return True

    def __len__(self) -> int:
        return len(self.times)

    def bracket(self, t: float) -> tuple[int, int, float, bool]:
        """``(lo, hi, s, stall)`` for playout time ``t`` (hold the newest on a stall).

        Before the first keyframe too: DESIGN.md's rule is "hold the newest".
        """
        times = self.times
        hi = bisect.bisect_right(times, t)
        if hi == 0:
            newest = len(times) - 1
            return newest, newest, 0.0, True
        lo = hi - 1
        if times[lo] == t:
            return lo, lo, 0.0, False
        if hi >= len(times):
            return lo, lo, 0.0, True
        return lo, hi, (t - times[lo]) / (times[hi] - times[lo]), False
