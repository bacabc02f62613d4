"""Pose math and interpolators: pure numpy, no I/O, no clocks.

Public API: :func:`get` (name to ``f(a, b, s)``), :func:`names`,
:func:`register`, :func:`evaluate_track`, the pose conversions and the QoE
error measures.
"""

from posecast.interp.cubic import VELOCITY_SIZE, motor_cubic, motor_hermite, screw_extrapolate
from posecast.interp.kernels import RowKernel
from posecast.interp.methods import dq_slerp, motor_lerp, soa
from posecast.interp.metrics import (
    TIP_OFFSET_M,
    position_error_mm,
    rotation_error_deg,
    tip_error_mm,
)
from posecast.interp.pose import (
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
from posecast.interp.quintic import motor_quintic
from posecast.interp.registry import (
    ENTRY_POINT_GROUP,
    Interpolator,
    InterpolatorInfo,
    Kind,
    get,
    info,
    names,
    register,
)
from posecast.interp.track import (
    Brackets,
    TrackResult,
    bracket,
    evaluate_track,
    interpolate_brackets,
    window_indices,
)

__all__ = [
    "ENTRY_POINT_GROUP",
    "TIP_OFFSET_M",
    "VELOCITY_SIZE",
    "Brackets",
    "Interpolator",
    "InterpolatorInfo",
    "Kind",
    "RowKernel",
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
    "motor_cubic",
    "motor_hermite",
    "motor_lerp",
    "motor_quintic",
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
    "screw_extrapolate",
    "soa",
    "tip_error_mm",
    "window_indices",
]
