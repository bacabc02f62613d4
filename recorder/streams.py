"""What a reader gives back per stream and per user: :class:`StreamData`, :class:`UserInfo`.

Plain records of their own, so ``recorder.reader`` (which builds them from a file)
and ``recorder.objects`` (which builds object streams beside them) both use them
without importing each other.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

__all__ = ["StreamData", "UserInfo"]


@dataclass(frozen=True, eq=False)
class StreamData:
    """One stream's keyframes in arrival order: ``times`` are capture times (s)."""

    user: int
    stream: int
    name: str | None
    user_name: str | None
    times: NDArray[np.float64]
    arrival: NDArray[np.float64]
    poses: NDArray[np.float32]
    #: ``(N, 6)`` velocities the updates carried (float32; NaN where one carried
    #: none), or ``None`` if none of this stream's updates carried velocities.
    velocities: NDArray[np.float32] | None = None

    def __len__(self) -> int:
        return len(self.times)

    @property
    def duration(self) -> float:
        """Capture time span of the keyframes, s."""
        return float(self.times.max() - self.times.min()) if len(self.times) > 1 else 0.0

    @property
    def rate(self) -> float:
        """Keyframes per second over the capture time span (0 for fewer than two)."""
        d = self.duration
        return (len(self.times) - 1) / d if d > 0 else 0.0


@dataclass
class UserInfo:
    """A user as the presence records and the session metadata describe it."""

    user: int
    name: str | None = None
    label: str | None = None
    streams: dict[int, str] = field(default_factory=dict)
    """Stream id -> name."""
    rate: float | None = None
    joined: float | None = None
    left: float | None = None
