"""The expected interpolation error of a keyframe interval, from a stream's motion.

Between keyframes ``dt`` apart, linear interpolation of a point whose acceleration
stays within ``A`` is off by at most ``A dt^2 / 8`` (the chord of a parabola, at
mid-interval). Whoever receives every sample of a stream (a relay) can estimate
``A`` causally: the largest ``|a|`` over the last ``WINDOW_S`` seconds, from second
differences over a stride of ``STRIDE`` samples (a longer stride keeps tracking
noise, which second differences amplify by 1/h^2, from swamping the motion).
:func:`causal_acceleration` does it over a whole trace, :class:`Acceleration` one
sample at a time with the same numbers. ``scenarios.error_model`` checks the model
against measured errors; ``server.view_rates`` chooses per-peer rates with it.

Pure code: numbers in, numbers out; no clock.
"""

from __future__ import annotations

import math
import struct
from collections import deque

import numpy as np
from numpy.typing import NDArray

from posecast.interp.metrics import TIP_OFFSET_M

__all__ = [
    "STRIDE",
    "WINDOW_S",
    "Acceleration",
    "causal_acceleration",
    "divisor",
    "expected_error",
    "tip_of",
]

#: Samples between the points of a second difference.
STRIDE = 3
#: Seconds of look-back of the acceleration estimate (its running max).
WINDOW_S = 0.3

F64 = NDArray[np.float64]
_POSE = struct.Struct("<7f")


def expected_error(accel: float, dt: float) -> float:
    """The largest error of linear interpolation over an interval ``dt`` (s) of a point
    whose acceleration stays within ``accel`` (m/s^2): ``accel dt^2 / 8``, metres."""
    return accel * dt * dt / 8.0


def causal_acceleration(
    times: F64, pos: F64, stride: int = STRIDE, window_s: float = WINDOW_S
) -> F64:
    """At each sample: the largest |a| (m/s^2) seen over the last ``window_s``, from
    second differences over ``stride`` samples (centred on a sample ``stride`` back,
    so only past samples are used). A whole-trace form of :class:`Acceleration`."""
    n = times.shape[0]
    acc = np.zeros(n)
    h = stride
    if n > 2 * h:
        dt = (times[2 * h :] - times[: -2 * h]) / 2.0
        second = pos[2 * h :] - 2.0 * pos[h:-h] + pos[: -2 * h]
        acc[2 * h :] = np.linalg.norm(second, axis=1) / dt**2
    out = np.empty(n)
    lo = np.searchsorted(times, times - window_s, side="left")
    for i in range(n):  # a running max over a time window
        out[i] = acc[lo[i] : i + 1].max()
    return out


def tip_of(pose: bytes | tuple[float, ...]) -> tuple[float, float, float]:
    """The tip point ``p + R (0, 0, -TIP_OFFSET_M)`` of a pose (28 wire bytes, float32
    little-endian, or 7 floats): the point DESIGN.md's tip error measures."""
    px, py, pz, w, x, y, z = _POSE.unpack(pose) if isinstance(pose, bytes) else pose
    n2 = w * w + x * x + y * y + z * z
    k = -2.0 * TIP_OFFSET_M / n2 if n2 > 0 else 0.0
    tz = pz - TIP_OFFSET_M - k * (x * x + y * y)
    return (px + k * (x * z + w * y), py + k * (y * z - w * x), tz)


class Acceleration:
    """One stream's running estimate of its tip's largest recent |a| (m/s^2), fed one
    update at a time (same numbers as :func:`causal_acceleration`)."""

    __slots__ = ("_peak", "_samples", "stride", "window_s")

    def __init__(self, stride: int = STRIDE, window_s: float = WINDOW_S) -> None:
        self.stride, self.window_s = stride, window_s
        self._samples: deque[tuple[float, tuple[float, float, float]]] = deque(
            maxlen=2 * stride + 1
        )
        #: (time, |a|) with |a| decreasing: the running max's candidates.
        self._peak: deque[tuple[float, float]] = deque()

    def observe(self, t: float, point: tuple[float, float, float]) -> None:
        samples = self._samples
        samples.append((t, point))
        a = 0.0
        if len(samples) == samples.maxlen:
            (t0, p0), (_, p1), (t2, p2) = samples[0], samples[self.stride], samples[-1]
            half = (t2 - t0) / 2.0
            if half > 0:
                d = [p2[i] - 2.0 * p1[i] + p0[i] for i in range(3)]
                a = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) / (half * half)
        peak = self._peak
        while peak and peak[-1][1] <= a:
            peak.pop()
        peak.append((t, a))
        while peak[0][0] < t - self.window_s:
            peak.popleft()

    def value(self) -> float | None:
        """The estimate now (None: too few updates yet to know)."""
        if len(self._samples) < (self._samples.maxlen or 0):
            return None
        return self._peak[0][1]


def divisor(
    budget_rad: float, accel: float | None, distance: float, rate: float, k_max: int, margin: float
) -> int:
    """The largest ``k`` in ``[1, k_max]`` whose interval ``k / rate`` keeps the expected
    error ``margin accel (k / rate)^2 / 8`` within ``distance tan(budget_rad)``."""
    if accel is None:
        return 1
    if accel <= 0.0:
        return k_max
    dt = math.sqrt(8.0 * distance * math.tan(budget_rad) / (margin * accel))
    return max(1, min(k_max, int(dt * rate + 1e-9)))
