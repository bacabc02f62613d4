"""Rendering velocity interpolators live: jitter buffers that keep keyframe velocities.

:func:`scenarios.receiver.render_buffers` renders the pair and window methods;
its buffers keep poses only. :class:`VelocityBuffer` is a
:class:`~scenarios.receiver.StreamBuffer` that also keeps the velocity received
with each keyframe (6 numbers: linear m/s, angular rad/s, world frame), and
:func:`render_velocity_buffers` renders the velocity methods (``motor-hermite``)
from them in one batched call per method, with the same brackets (and so the
same stalls and holds) as ``render_buffers``.
"""

from __future__ import annotations

import bisect
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from interp import interpolate_brackets
from scenarios.receiver import DEFAULT_BUFFER_CAPACITY, StreamBuffer

__all__ = ["VelocityBuffer", "render_velocity_buffers"]

_ZERO = np.zeros(6)
_ZERO.setflags(write=False)


class VelocityBuffer(StreamBuffer):
    """A :class:`StreamBuffer` whose keyframes also carry a velocity ``(6,)``.

    ``velocities[i]`` belongs to ``times[i]``/``poses[i]``; a keyframe pushed
    without one gets zeros.
    """

    def __init__(self, capacity: int = DEFAULT_BUFFER_CAPACITY) -> None:
        super().__init__(capacity)
        self.velocities: list[NDArray[np.float64]] = []

    def push(
        self,
        capture: float,
        pose: NDArray[np.float32],
        floor: float = -np.inf,
        velocity: NDArray[np.float64] | None = None,
    ) -> bool:
        evicted = self.evicted
        if not super().push(capture, pose, floor):
            return False
        # A full buffer drops its oldest keyframe, never the new one (that is
        # refused above), so the new keyframe's index is found after the drop.
        if self.evicted != evicted:
            del self.velocities[0]
        i = bisect.bisect_left(self.times, capture)
        self.velocities.insert(i, _ZERO if velocity is None else velocity)
        return True


def render_velocity_buffers(
    buffers: Sequence[VelocityBuffer], t: float, methods: Sequence[str]
) -> dict[str, NDArray[np.float64]]:
    """Every non-empty buffer at playout time ``t`` with each velocity method, ``(S, 7)``.

    The bracket, fraction and hold are those of :meth:`StreamBuffer.bracket`
    (what ``render_buffers`` uses); a stall holds the newest keyframe.
    """
    live = [b for b in buffers if len(b)]
    n = len(live)
    if not n or not methods:
        return {m: np.empty((0, 7)) for m in methods}
    keys = np.empty((2, n, 7))
    times = np.empty((2, n))
    vel = np.empty((2, n, 6))
    s = np.empty((1, n))
    for j, buf in enumerate(live):
        lo, hi, frac, _ = buf.bracket(t)
        for row, i in enumerate((lo, hi)):
            keys[row, j] = buf.poses[i]
            times[row, j] = buf.times[i]
            vel[row, j] = buf.velocities[i]
        s[0, j] = frac
    lo_idx = np.zeros((1, n), dtype=np.intp)
    return {
        m: interpolate_brackets(keys, lo_idx, lo_idx + 1, s, m, times=times, velocities=vel)[0]
        for m in methods
    }
