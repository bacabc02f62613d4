"""Pose error measures of DESIGN.md's QoE definitions (pure functions).

Position error in mm, rotation error in degrees (sign-insensitive), and tip
error: the distance in mm between the points 0.20 m along the device's -z axis
in the two poses (a held tool's tip, coupling rotation and translation).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from posecast.interp.pose import F64, quat_rotate

__all__ = ["TIP_OFFSET_M", "position_error_mm", "rotation_error_deg", "tip_error_mm"]

#: The tracked tip: 0.20 m along the device's -z axis.
TIP_OFFSET_M = 0.20


def position_error_mm(rendered: ArrayLike, truth: ArrayLike) -> F64:
    """|p_rendered - p_true| in millimetres, shape ``(...)``."""
    r = np.asarray(rendered, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    d = r[..., :3] - t[..., :3]
    out: F64 = 1000.0 * np.sqrt(np.einsum("...i,...i->...", d, d))
    return out


def rotation_error_deg(rendered: ArrayLike, truth: ArrayLike) -> F64:
    """Angle between the two rotations in degrees (q and -q are equal)."""
    r = np.asarray(rendered, dtype=np.float64)[..., 3:]
    t = np.asarray(truth, dtype=np.float64)[..., 3:]
    # 2 atan2(|q1 - q0|, |q1 + q0|) on the aligned pair: accurate near 0 and 180.
    dot = np.einsum("...i,...i->...", r, t)
    t = t * np.where(dot < 0, -1.0, 1.0)[..., None]
    d = r - t
    m = r + t
    half = np.arctan2(
        np.sqrt(np.einsum("...i,...i->...", d, d)), np.sqrt(np.einsum("...i,...i->...", m, m))
    )
    out: F64 = np.degrees(4.0 * half)
    return out


def tip_error_mm(rendered: ArrayLike, truth: ArrayLike, offset_m: float = TIP_OFFSET_M) -> F64:
    """Distance in mm between the tips ``p + R (0, 0, -offset)`` of the two poses."""
    r = np.asarray(rendered, dtype=np.float64)
    t = np.asarray(truth, dtype=np.float64)
    tip = np.array([0.0, 0.0, -offset_m])
    d = (r[..., :3] + quat_rotate(r[..., 3:], tip)) - (t[..., :3] + quat_rotate(t[..., 3:], tip))
    out: F64 = 1000.0 * np.sqrt(np.einsum("...i,...i->...", d, d))
    return out
