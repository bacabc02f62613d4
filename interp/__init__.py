"""Pose math and interpolators: pure numpy, no I/O, no clocks.

Public API: :func:`get` (name to ``f(a, b, s)``), :func:`names`,
:func:`register`, :func:`evaluate_track`, the pose conversions and the QoE
error measures.
"""

from interp.methods import dq_slerp, motor_lerp, soa
from interp.metrics import TIP_OFFSET_M, position_error_mm, rotation_error_deg, tip_error_mm
from interp.pose import (
    as_pose,
    dq_to_pose,
    matrix_to_pose,
    motor_to_pose,
    pose_from_tq,
    pose_to_dq,
    pose_to_matrix,
    pose_to_motor,
    pose_to_tq,
    quat_conj,
    quat_mul,
    quat_rotate,
)
from interp.registry import (
    ENTRY_POINT_GROUP,
    Interpolator,
    InterpolatorInfo,
    get,
    info,
    names,
    register,
)
from interp.track import Brackets, TrackResult, bracket, evaluate_track, interpolate_brackets

__all__ = [
    "ENTRY_POINT_GROUP",
    "TIP_OFFSET_M",
    "Brackets",
    "Interpolator",
    "InterpolatorInfo",
    "TrackResult",
    "as_pose",
    "bracket",
    "dq_slerp",
    "dq_to_pose",
    "evaluate_track",
    "get",
    "info",
    "interpolate_brackets",
    "matrix_to_pose",
    "motor_lerp",
    "motor_to_pose",
    "names",
    "pose_from_tq",
    "pose_to_dq",
    "pose_to_matrix",
    "pose_to_motor",
    "pose_to_tq",
    "position_error_mm",
    "quat_conj",
    "quat_mul",
    "quat_rotate",
    "register",
    "rotation_error_deg",
    "soa",
    "tip_error_mm",
]
