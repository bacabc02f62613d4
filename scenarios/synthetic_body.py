"""Motion primitives of :mod:`scenarios.synthetic`: quaternions, a two-link arm, the head.

Internal to the synthetic motions (:mod:`scenarios.synthetic_scenes` builds
its scenes from these): minimum-jerk profiles, quaternion and pose helpers, a
two-link arm with IK/FK and a keypose track in joint space, a head turning
about the neck pivot, and slow body sway. Frame: OpenXR (+x right, +y up,
+z backward); units: metres, seconds, radians unless a name says degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from posecast.interp import quat_conj, quat_mul, quat_rotate

__all__ = ["NATIVE_RATE", "min_jerk"]

F64 = NDArray[np.float64]
Range = tuple[float, float]

#: Sample rate of every synthetic motion (Hz).
NATIVE_RATE = 90.0

_G = np.array([0.0, -9.81, 0.0])
_X = np.array([1.0, 0.0, 0.0])
_Y = np.array([0.0, 1.0, 0.0])
_Z = np.array([0.0, 0.0, 1.0])
_DOWN = np.array([0.0, -1.0, 0.0])
_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])

# Body (metres): shoulders, arm segments, neck pivot and eye offset in the head frame.
_SHOULDER_Y = 1.42
_SHOULDER_X = 0.19
_UPPER_ARM = 0.30
_FOREARM = 0.30
_NECK = np.array([0.0, 1.50, 0.03])
_EYE_OFFSET = np.array([0.0, 0.12, -0.09])


# ---------------------------------------------------------------- quaternion helpers


def min_jerk(tau: F64) -> F64:
    """Minimum-jerk position profile ``10 tau^3 - 15 tau^4 + 6 tau^5`` on [0, 1]."""
    x = np.clip(tau, 0.0, 1.0)
    out: F64 = x * x * x * (10.0 + x * (-15.0 + 6.0 * x))
    return out


def _axis_angle(axis: F64, angle: F64 | float) -> F64:
    """Quaternions for rotations by ``angle`` (rad) about unit ``axis`` (broadcast)."""
    a = np.asarray(angle, dtype=np.float64)
    ax = np.asarray(axis, dtype=np.float64)
    half = 0.5 * a
    out: F64 = np.concatenate([np.cos(half)[..., None], np.sin(half)[..., None] * ax], axis=-1)
    return out


def _unit(v: F64) -> F64:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    out: F64 = v / np.where(n > 0, n, 1.0)
    return out


def _shortest_arc(a: F64, b: F64) -> F64:
    """The smallest rotation taking unit vector ``a`` to unit vector ``b`` (3,)."""
    d = float(np.dot(a, b))
    if d < -1.0 + 1e-9:
        perp = np.cross(a, _X if abs(a[0]) < 0.9 else _Y)
        return _axis_angle(_unit(perp), np.pi)
    q = np.concatenate([[1.0 + d], np.cross(a, b)])
    out: F64 = q / np.linalg.norm(q)
    return out


def _slerp(q0: F64, q1: F64, s: F64) -> F64:
    """Quaternion SLERP, rows ``(N, 4)`` and ``s (N,)``, shortest path."""
    dot = np.einsum("...i,...i->...", q0, q1)
    q1 = np.where(dot[..., None] < 0, -q1, q1)
    rel = quat_mul(quat_conj(q0), q1)
    vn = np.linalg.norm(rel[..., 1:], axis=-1)
    angle = 2.0 * np.arctan2(vn, rel[..., 0])
    axis = rel[..., 1:] / np.where(vn > 0, vn, 1.0)[..., None]
    return quat_mul(q0, _axis_angle(axis, s * angle))


def _ypr(yaw_deg: float, pitch_deg: float, roll_deg: float = 0.0) -> F64:
    """Orientation: yaw about +y, then pitch about +x, then roll about +z (body axes)."""
    q = quat_mul(_axis_angle(_Y, np.radians(yaw_deg)), _axis_angle(_X, np.radians(pitch_deg)))
    return quat_mul(q, _axis_angle(_Z, np.radians(roll_deg)))


def _pose_mul(a: F64, b: F64) -> F64:
    """Compose poses ``a b`` (apply ``b`` in ``a``'s frame), broadcasting ``(..., 7)``."""
    t = a[..., :3] + quat_rotate(a[..., 3:], b[..., :3])
    q = quat_mul(a[..., 3:], b[..., 3:])
    batch = np.broadcast_shapes(t.shape[:-1], q.shape[:-1])
    return np.concatenate(
        [np.broadcast_to(t, (*batch, 3)), np.broadcast_to(q, (*batch, 4))], axis=-1
    )


def _pose_inv(a: F64) -> F64:
    qi = quat_conj(a[..., 3:])
    return np.concatenate([-quat_rotate(qi, a[..., :3]), qi], axis=-1)


def _uniform(rng: np.random.Generator, r: Range) -> float:
    return float(rng.uniform(r[0], r[1]))


# ---------------------------------------------------------------- arm kinematics


@dataclass(frozen=True)
class _Arm:
    """Two-link arm: shoulder rotation, elbow rotation, wrist rotation (quaternions).

    At identity joints the upper arm and forearm hang straight down and the
    hand frame equals the world frame; the hand's origin is the forearm's end.
    """

    side: float  # -1 left, +1 right

    @property
    def shoulder(self) -> F64:
        return np.array([self.side * _SHOULDER_X, _SHOULDER_Y, 0.0])

    @property
    def rest(self) -> F64:
        """Elbow at the side bent 90 degrees, controller pointing forward."""
        s = self.shoulder
        return np.array([s[0], s[1] - _UPPER_ARM, s[2] - _FOREARM, 1.0, 0.0, 0.0, 0.0])

    def ik(self, pose: F64) -> F64:
        """Joint quaternions ``(3, 4)`` placing the hand at ``pose`` (clamped to reach)."""
        s = self.shoulder
        d = pose[:3] - s
        dist = float(np.linalg.norm(d))
        dn = d / dist
        reach = float(np.clip(dist, 0.15, _UPPER_ARM + _FOREARM - 1e-3))
        a = (_UPPER_ARM**2 - _FOREARM**2 + reach**2) / (2.0 * reach)
        r = float(np.sqrt(max(_UPPER_ARM**2 - a * a, 0.0)))
        hint = np.array([self.side * 0.5, -1.0, 0.3])
        e = hint - np.dot(hint, dn) * dn
        e = _unit(e) if np.linalg.norm(e) > 1e-6 else _unit(np.cross(dn, _Z))
        elbow = s + a * dn + r * e
        hand = s + reach * dn
        q_sh = _shortest_arc(_DOWN, _unit(elbow - s))
        f_local = quat_rotate(quat_conj(q_sh), _unit(hand - elbow))
        q_el = _shortest_arc(_DOWN, f_local)
        q_arm = quat_mul(q_sh, q_el)
        q_wr = quat_mul(quat_conj(q_arm), pose[3:])
        return np.stack([q_sh, q_el, q_wr])

    def fk(self, joints: F64) -> F64:
        """Hand poses ``(N, 7)`` from joint quaternions ``(N, 3, 4)``."""
        q_sh, q_el, q_wr = joints[:, 0], joints[:, 1], joints[:, 2]
        elbow = self.shoulder + quat_rotate(q_sh, _DOWN * _UPPER_ARM)
        q_arm = quat_mul(q_sh, q_el)
        hand = elbow + quat_rotate(q_arm, _DOWN * _FOREARM)
        return np.concatenate([hand, quat_mul(q_arm, q_wr)], axis=-1)


class _ArmTrack:
    """Keyposes in joint space; minimum-jerk joint SLERP between consecutive ones."""

    def __init__(self, arm: _Arm, t0: float, pose: F64) -> None:
        self.arm = arm
        self.times: list[float] = [t0]
        self.joints: list[F64] = [arm.ik(pose)]

    @property
    def end(self) -> float:
        return self.times[-1]

    def move(self, t: float, pose: F64) -> None:
        """Arrive at hand ``pose`` at time ``t`` (from the previous keypose)."""
        self.move_joints(t, self.arm.ik(pose))

    def move_joints(self, t: float, joints: F64) -> None:
        if t <= self.times[-1]:
            raise ValueError("keypose times must increase")
        self.times.append(t)
        self.joints.append(joints)

    def hold(self, t: float) -> None:
        """Stay at the last keypose until ``t``."""
        if t > self.times[-1]:
            self.move_joints(t, self.joints[-1])

    def joints_at(self, t: F64) -> F64:
        times = np.asarray(self.times)
        keys = np.stack(self.joints)  # (K, 3, 4)
        if times.size == 1:
            return np.broadcast_to(keys[0], (t.size, 3, 4)).copy()
        k = np.clip(np.searchsorted(times, t, side="right") - 1, 0, times.size - 2)
        tau = (t - times[k]) / (times[k + 1] - times[k])
        s = min_jerk(tau)
        return _slerp(keys[k], keys[k + 1], np.broadcast_to(s[:, None], (t.size, 3)))

    def poses(self, t: F64) -> F64:
        return self.arm.fk(self.joints_at(t))


# ---------------------------------------------------------------- head


def _head_looking_at(t: F64, target: F64, smooth_s: float, gain: float) -> F64:
    """Head poses turning about the neck towards ``target (N, 3)``, smoothed.

    The head covers ``gain`` of the gaze angle (the eyes do the rest) and its
    yaw/pitch are smoothed by a centred moving average of ``smooth_s``.
    """
    d = target - (_NECK + _EYE_OFFSET)
    yaw = np.unwrap(np.arctan2(-d[:, 0], -d[:, 2]))
    pitch = np.arctan2(d[:, 1], np.hypot(d[:, 0], d[:, 2]))
    n = max(1, round(smooth_s * NATIVE_RATE)) | 1
    kernel = np.ones(n) / n
    yaw = np.convolve(np.pad(yaw, n // 2, mode="edge"), kernel, mode="valid")
    pitch = np.convolve(np.pad(pitch, n // 2, mode="edge"), kernel, mode="valid")
    return _head_pose(gain * yaw, np.clip(gain * pitch, -0.6, 0.4))


def _head_pose(yaw: F64, pitch: F64, sway: F64 | None = None) -> F64:
    q = quat_mul(_axis_angle(_Y, yaw), _axis_angle(_X, pitch))
    pos = _NECK + quat_rotate(q, _EYE_OFFSET)
    if sway is not None:
        pos = pos + sway
    return np.concatenate([pos, q], axis=-1)


def _sway(t: F64, rng: np.random.Generator, amp_m: float, freq: Range) -> F64:
    """Slow body sway (N, 3): two sinusoids per horizontal axis, seeded."""
    out = np.zeros((t.size, 3))
    for axis in (0, 2):
        for _ in range(2):
            f = _uniform(rng, freq)
            out[:, axis] += 0.5 * amp_m * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
    return out
