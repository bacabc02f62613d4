"""Per-class QoE statistics: the error samples of :mod:`scenarios.qoe` and their summary.

:class:`ErrorSamples` pools the per-sample errors of DESIGN.md's definitions
over the streams of one device class; :meth:`ErrorSamples.stats` gives their
p50/p95 (:data:`STAT_KEYS`). :func:`tip_velocity_error_mps` is the velocity
error (smoothness): the tip's velocity from differences over consecutive
source sample times, rendered against true, ``|v_rendered - v_true|`` in m/s.
:mod:`scenarios.qoe` re-exports all of it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from posecast.interp import TIP_OFFSET_M, quat_rotate

__all__ = [
    "EXTRAPOLATION_KEYS",
    "STAT_KEYS",
    "ErrorSamples",
    "tip_velocity_error_mps",
]

F64 = NDArray[np.float64]

STAT_KEYS = (
    "pos_p50_mm",
    "pos_p95_mm",
    "rot_p50_deg",
    "rot_p95_deg",
    "tip_p50_mm",
    "tip_p95_mm",
    "vel_p50_mps",
    "vel_p95_mps",
    "stall_fraction",
)
#: Extra statistics of :meth:`ErrorSamples.extrapolation_stats` (stalls rendered by
#: dead reckoning, and the corrections when the next keyframe arrives).
EXTRAPOLATION_KEYS = (
    "extrapolated_fraction",
    "beyond_horizon_fraction",
    "correction_events",
    "correction_tip_p50_mm",
    "correction_tip_p95_mm",
    "correction_pos_p50_mm",
    "correction_pos_p95_mm",
)


@dataclass
class ErrorSamples:
    """Per-sample errors pooled over streams of one device class.

    With extrapolation on (:func:`evaluate_group`'s ``extrapolate_horizon``),
    ``extrapolated`` and ``beyond_horizon`` count samples (per stream, like
    ``samples``) rendered by dead reckoning, and ``correction_*_mm`` hold the
    size of each correction: the distance between the stalled pose continued
    to the first frame after a keyframe arrives and the pose the new keyframes
    give there (the jump a renderer without smoothing would show).
    ``vel_mps`` holds the velocity errors (:func:`tip_velocity_error_mps`; none
    when the caller did not measure them: NaN statistics).
    """

    pos_mm: list[F64] = field(default_factory=list)
    rot_deg: list[F64] = field(default_factory=list)
    tip_mm: list[F64] = field(default_factory=list)
    stalls: int = 0
    samples: int = 0
    extrapolated: int = 0
    beyond_horizon: int = 0
    correction_tip_mm: list[F64] = field(default_factory=list)
    correction_pos_mm: list[F64] = field(default_factory=list)
    vel_mps: list[F64] = field(default_factory=list)

    def add(
        self, pos: F64, rot: F64, tip: F64, stalls: int, samples: int, *, vel: F64 | None = None
    ) -> None:
        self.pos_mm.append(pos)
        self.rot_deg.append(rot)
        self.tip_mm.append(tip)
        if vel is not None:
            self.vel_mps.append(vel)
        self.stalls += stalls
        self.samples += samples

    def add_extrapolation(
        self, extrapolated: int, beyond_horizon: int, correction_tip: F64, correction_pos: F64
    ) -> None:
        """Count dead-reckoned samples and record correction sizes (mm)."""
        self.extrapolated += extrapolated
        self.beyond_horizon += beyond_horizon
        self.correction_tip_mm.append(correction_tip)
        self.correction_pos_mm.append(correction_pos)

    def merge(self, other: ErrorSamples) -> None:
        self.pos_mm += other.pos_mm
        self.rot_deg += other.rot_deg
        self.tip_mm += other.tip_mm
        self.stalls += other.stalls
        self.samples += other.samples
        self.extrapolated += other.extrapolated
        self.beyond_horizon += other.beyond_horizon
        self.correction_tip_mm += other.correction_tip_mm
        self.correction_pos_mm += other.correction_pos_mm
        self.vel_mps += other.vel_mps

    def stats(self) -> dict[str, float]:
        """p50/p95 of each error and the stall fraction (NaN where no samples)."""
        return {
            "pos_p50_mm": _pct(self.pos_mm, 50),
            "pos_p95_mm": _pct(self.pos_mm, 95),
            "rot_p50_deg": _pct(self.rot_deg, 50),
            "rot_p95_deg": _pct(self.rot_deg, 95),
            "tip_p50_mm": _pct(self.tip_mm, 50),
            "tip_p95_mm": _pct(self.tip_mm, 95),
            "vel_p50_mps": _pct(self.vel_mps, 50),
            "vel_p95_mps": _pct(self.vel_mps, 95),
            "stall_fraction": self.stalls / self.samples if self.samples else float("nan"),
        }

    def extrapolation_stats(self) -> dict[str, float]:
        """Shares of dead-reckoned samples and correction sizes (:data:`EXTRAPOLATION_KEYS`)."""
        n = self.samples
        return {
            "extrapolated_fraction": self.extrapolated / n if n else float("nan"),
            "beyond_horizon_fraction": self.beyond_horizon / n if n else float("nan"),
            "correction_events": float(sum(x.size for x in self.correction_tip_mm)),
            "correction_tip_p50_mm": _pct(self.correction_tip_mm, 50),
            "correction_tip_p95_mm": _pct(self.correction_tip_mm, 95),
            "correction_pos_p50_mm": _pct(self.correction_pos_mm, 50),
            "correction_pos_p95_mm": _pct(self.correction_pos_mm, 95),
        }


def _pct(parts: list[F64], p: float) -> float:
    arr = np.concatenate(parts) if parts else np.empty(0)
    return float(np.percentile(arr, p)) if arr.size else float("nan")


def _tips(poses: F64, offset_m: float) -> F64:
    """The points ``p + R (0, 0, -offset)`` of poses ``(..., 7)``."""
    tip = np.broadcast_to(np.array([0.0, 0.0, -offset_m]), (*poses.shape[:-1], 3))
    out: F64 = poses[..., :3] + quat_rotate(poses[..., 3:], tip)
    return out


def tip_velocity_error_mps(
    rendered: F64,
    truth: F64,
    times: F64,
    shown: NDArray[np.bool_] | None = None,
    offset_m: float = TIP_OFFSET_M,
) -> F64:
    """``|v_rendered - v_true|`` (m/s) of the tip between consecutive sample times.

    ``truth`` ``(Q, S, 7)`` are the source poses at the source's sample ``times``
    ``(Q,)``; ``rendered`` are the poses shown at the ``shown`` ones (all if
    None), in order. The tip (0.20 m along -z) of each is differenced over each
    pair of consecutive sample times ``i, i + 1`` that were both shown, and the
    rendered velocity compared with the true one: ``(P, S)`` for the ``P``
    such pairs.
    """
    idx = np.arange(times.shape[0]) if shown is None else np.flatnonzero(shown)
    ref = truth[idx]
    if rendered.shape != ref.shape:
        raise ValueError(f"expected rendered poses of shape {ref.shape}, got {rendered.shape}")
    dt = np.diff(times[idx])
    pair = (np.diff(idx) == 1) & (dt > 0)
    d_ren = np.diff(_tips(rendered, offset_m), axis=0)[pair]
    d_true = np.diff(_tips(ref, offset_m), axis=0)[pair]
    dv = (d_ren - d_true) / dt[pair][:, None, None]
    out: F64 = np.sqrt(np.einsum("...i,...i->...", dv, dv))
    return out
