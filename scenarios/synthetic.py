"""Deterministic synthetic motions: parameters + seed -> a 90 Hz :class:`Trace`.

Realistic motions (modelled on what the paper shows; every hand is a two-link
arm whose shoulder, elbow and wrist rotations follow minimum-jerk profiles in
joint space, so hand paths are arcs about the shoulder and elbow pivots):

- ``reach-grasp``: each hand reaches to a target, turns the wrist to grasp,
  carries the grasp to a place target, releases and returns to rest; the head
  looks at the working hands.
- ``throw-catch``: the hands toss ``object:ball`` to each other. The ball sits
  in the throwing hand, leaves it at the swing's fastest point with the hand's
  velocity, flies ballistically while spinning, and is caught by the other hand,
  which reaches the catch point as the ball falls through it.
- ``drill``: the right hand holds ``object:drill`` (spinning about its own bit
  axis, local z, through its origin), moves it between drilling spots and
  pushes it in and out along the bit; the left hand steadies; the head watches
  the bit.
- ``look-around``: a calm head turning about the neck pivot between fixations
  (minimum-jerk head turns), idle hands swaying slightly.

Exactness fixtures (one independent motion per stream):

- ``screw``: constant twist, ``pose(t) = exp(t xi) pose(0)``; dual-quaternion
  ScLERP reproduces it exactly from keyframes at any rate whose interval turns
  less than half a turn.
- ``spin-drift``: constant spin about the body origin (body-fixed axis) and
  constant linear velocity; position LERP + SLERP (``soa``) reproduces it
  exactly, ScLERP does not.

Parameters are frozen dataclasses with defaults; :func:`synthetic_motion`
takes overrides as a mapping (e.g. one table of a TOML file, see
:func:`load_params`). A suite of motions and seeds (what ``table1`` runs on
``--traces synthetic``) is a TOML file too: :func:`load_suite`, default
``scenarios/data/synthetic.toml``. Everything is a pure function of the
parameters and the seed.

Frame: OpenXR (+x right, +y up, +z backward); the controller's -z points
forward out of the hand. Units: metres, seconds, degrees in parameters.
"""

from __future__ import annotations

import dataclasses
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from interp import quat_conj, quat_mul, quat_rotate
from scenarios.traces import Trace, TraceError

__all__ = [
    "MOTIONS",
    "NATIVE_RATE",
    "DrillParams",
    "LookAroundParams",
    "MotionDef",
    "ReachGraspParams",
    "ScrewParams",
    "SpinDriftParams",
    "SuiteEntry",
    "ThrowCatchParams",
    "load_params",
    "load_suite",
    "make_params",
    "min_jerk",
    "motion_names",
    "suite_traces",
    "synthetic_motion",
]

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


# ---------------------------------------------------------------- parameters


@dataclass(frozen=True)
class ReachGraspParams:
    """Reach, grasp, carry, release, return; per hand, independently timed."""

    reach_s: Range = (0.5, 1.0)
    """Duration of one minimum-jerk reach (s)."""
    hold_s: Range = (0.25, 0.6)
    """Time at a target while the wrist turns to grasp or release (s)."""
    pause_s: Range = (0.2, 1.0)
    """Rest between cycles (s)."""
    grasp_twist_deg: Range = (20.0, 80.0)
    """Wrist turn about the forearm while grasping (deg)."""
    target_x: Range = (0.0, 0.40)
    """Target distance from the body's midline towards the hand's side (m)."""
    target_y: Range = (0.95, 1.50)
    target_z: Range = (-0.55, -0.25)
    yaw_deg: float = 40.0
    pitch_deg: Range = (-40.0, 20.0)
    roll_deg: float = 50.0
    head_gain: float = 0.7
    head_smooth_s: float = 0.3


@dataclass(frozen=True)
class ThrowCatchParams:
    """Hands toss a ball to each other; the head follows the ball."""

    flight_s: Range = (0.45, 0.65)
    """Planned flight time of a toss (s)."""
    swing_s: Range = (0.30, 0.40)
    """Minimum-jerk swing of the throwing arm; release at its middle (s)."""
    windup_s: float = 0.45
    catch_reach_s: float = 0.45
    pause_s: Range = (0.3, 0.9)
    spin_rps: Range = (0.5, 2.0)
    """Ball spin in flight, about the throwing hand's angular velocity (rev/s)."""
    grip: tuple[float, float, float] = (0.0, 0.03, -0.05)
    """Ball centre in the hand frame at the first grasp (m)."""
    head_gain: float = 0.8
    head_smooth_s: float = 0.2


@dataclass(frozen=True)
class DrillParams:
    """A drill held in the right hand spins about its bit axis while it moves."""

    spin_rps: float = 2.0
    """Spin about the bit (rev/s); above 2.5 rev/s a 5 Hz stream aliases for every method."""
    offset: tuple[float, float, float] = (0.0, -0.02, -0.08)
    """Drill origin (on the bit axis) in the hand frame (m); bit along the hand's -z."""
    reach_s: Range = (0.6, 1.1)
    drill_s: Range = (1.0, 2.0)
    depth_m: Range = (0.02, 0.05)
    pause_s: Range = (0.2, 0.6)
    target_x: Range = (-0.05, 0.35)
    target_y: Range = (0.95, 1.35)
    target_z: Range = (-0.50, -0.30)
    pitch_deg: Range = (-45.0, 0.0)
    yaw_deg: float = 25.0
    head_gain: float = 0.7
    head_smooth_s: float = 0.3


@dataclass(frozen=True)
class LookAroundParams:
    """Calm head turning between fixations; idle hands."""

    yaw_deg: float = 70.0
    pitch_deg: Range = (-25.0, 15.0)
    turn_s_per_90deg: float = 0.6
    """Duration of a minimum-jerk head turn per 90 degrees (plus 0.25 s)."""
    fixation_s: Range = (0.6, 2.0)
    sway_m: float = 0.015
    sway_hz: Range = (0.1, 0.3)
    hand_sway_m: float = 0.01
    hand_sway_deg: float = 3.0


@dataclass(frozen=True)
class ScrewParams:
    """Constant twist per stream: rotation about a fixed axis through a point + slide."""

    omega_deg_s: Range = (30.0, 150.0)
    """Rotation speed about the screw axis (deg/s); keep below 900 for 5 Hz keyframes."""
    pitch_m_per_rad: Range = (-0.05, 0.05)
    """Slide along the axis per radian turned (m/rad)."""
    axis_point_spread_m: float = 0.3


@dataclass(frozen=True)
class SpinDriftParams:
    """Constant spin about a body-fixed axis through the origin + constant velocity."""

    omega_deg_s: Range = (30.0, 300.0)
    """Spin speed (deg/s); keep below 900 for 5 Hz keyframes."""
    speed_m_s: Range = (0.05, 0.3)


@dataclass(frozen=True)
class MotionDef:
    """A registered synthetic motion."""

    name: str
    params: type[Any]
    build: Callable[[Any, np.random.Generator, F64], tuple[F64, tuple[str, ...]]]
    description: str
    default_duration_s: float


def _coerce(value: Any, default: Any, where: str) -> Any:
    if isinstance(default, tuple):
        if not isinstance(value, list | tuple) or len(value) != len(default):
            raise TraceError(f"{where}: expected a list of {len(default)} numbers")
        return tuple(_coerce(v, d, where) for v, d in zip(value, default, strict=True))
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise TraceError(f"{where}: expected a number, got {value!r}")
        return float(value)
    return value


def make_params(name: str, overrides: Mapping[str, Any] | None = None) -> Any:
    """The parameters of motion ``name``: defaults with ``overrides`` applied."""
    cls = _motion(name).params
    if not overrides:
        return cls()
    defaults = cls()
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise TraceError(
            f"unknown parameter(s) {unknown} for synthetic motion {name!r}; known: "
            f"{', '.join(sorted(known))}"
        )
    values = {k: _coerce(v, getattr(defaults, k), f"{name}.{k}") for k, v in overrides.items()}
    return dataclasses.replace(defaults, **values)


def load_params(path: str | Path) -> dict[str, dict[str, Any]]:
    """Parameter overrides per motion from a TOML file (one table per motion name)."""
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except FileNotFoundError:
        raise TraceError(f"{p}: no such parameter file") from None
    except tomllib.TOMLDecodeError as exc:
        raise TraceError(f"{p}: not valid TOML ({exc})") from None
    out: dict[str, dict[str, Any]] = {}
    for name, table in data.items():
        if not isinstance(table, dict):
            raise TraceError(f"{p}: [{name}] must be a table of parameters")
        make_params(name, table)  # validate now, with the file's name in errors
        out[name] = dict(table)
    return out


# ---------------------------------------------------------------- builders


def _target_pose(
    rng: np.random.Generator,
    side: float,
    x: Range,
    y: Range,
    z: Range,
    yaw_deg: float,
    pitch_deg: Range,
    roll_deg: float,
) -> F64:
    pos = np.array([side * _uniform(rng, x), _uniform(rng, y), _uniform(rng, z)])
    q = _ypr(
        float(rng.uniform(-yaw_deg, yaw_deg)),
        _uniform(rng, pitch_deg),
        float(rng.uniform(-roll_deg, roll_deg)),
    )
    return np.concatenate([pos, q])


def _twist(pose: F64, deg: float) -> F64:
    """``pose`` turned about its own z axis (the forearm) by ``deg``."""
    q = quat_mul(pose[3:], _axis_angle(_Z, np.radians(deg)))
    return np.concatenate([pose[:3], q])


def _build_reach_grasp(
    p: ReachGraspParams, rng: np.random.Generator, t: F64
) -> tuple[F64, tuple[str, ...]]:
    end = float(t[-1])
    tracks: list[_ArmTrack] = []
    for side in (-1.0, 1.0):
        arm = _Arm(side)
        track = _ArmTrack(arm, 0.0, arm.rest)
        now = _uniform(rng, (0.0, 1.0))
        track.hold(now)
        while now <= end:
            grab = _target_pose(
                rng,
                side,
                p.target_x,
                p.target_y,
                p.target_z,
                p.yaw_deg,
                p.pitch_deg,
                p.roll_deg,
            )
            place = _target_pose(
                rng,
                side,
                p.target_x,
                p.target_y,
                p.target_z,
                p.yaw_deg,
                p.pitch_deg,
                p.roll_deg,
            )
            twist = _uniform(rng, p.grasp_twist_deg) * rng.choice([-1.0, 1.0])
            now += _uniform(rng, p.reach_s)
            track.move(now, grab)
            now += _uniform(rng, p.hold_s)
            track.move(now, _twist(grab, twist))
            now += _uniform(rng, p.reach_s)
            track.move(now, _twist(place, twist))
            now += _uniform(rng, p.hold_s)
            track.move(now, place)
            now += _uniform(rng, p.reach_s)
            track.move(now, arm.rest)
            now += _uniform(rng, p.pause_s)
            track.hold(now)
        tracks.append(track)
    left, right = (tr.poses(t) for tr in tracks)
    # The head follows the faster-moving hand's neighbourhood: the mean of both hands.
    head = _head_looking_at(t, 0.5 * (left[:, :3] + right[:, :3]), p.head_smooth_s, p.head_gain)
    return np.stack([head, left, right], axis=1), ("head", "left", "right")


@dataclass
class _BallSegment:
    start: float
    kind: str  # "held" or "flight"
    side: float = 0.0
    rel: F64 = dataclasses.field(default_factory=lambda: np.zeros(7))
    p0: F64 = dataclasses.field(default_factory=lambda: np.zeros(3))
    v0: F64 = dataclasses.field(default_factory=lambda: np.zeros(3))
    q0: F64 = dataclasses.field(default_factory=lambda: _IDENTITY.copy())
    omega: F64 = dataclasses.field(default_factory=lambda: np.zeros(3))


def _build_throw_catch(
    p: ThrowCatchParams, rng: np.random.Generator, t: F64
) -> tuple[F64, tuple[str, ...]]:
    end = float(t[-1])
    arms = {side: _Arm(side) for side in (-1.0, 1.0)}
    hold_pose = {
        side: _twist(arm.rest, -side * 25.0) + np.r_[0.0, 0.05, 0.0, 0, 0, 0, 0]
        for side, arm in arms.items()
    }
    thrower = 1.0
    tracks = {
        side: _ArmTrack(arm, 0.0, hold_pose[side] if side == thrower else arm.rest)
        for side, arm in arms.items()
    }
    grip = np.concatenate([np.asarray(p.grip), _IDENTITY])
    segments = [_BallSegment(0.0, "held", thrower, grip)]
    now = 0.5
    h = 1e-4
    while now <= end:
        catcher = -thrower
        a_arm, b_arm = arms[thrower], arms[catcher]
        a_track, b_track = tracks[thrower], tracks[catcher]
        rel = segments[-1].rel
        # Plan: release point, aim point, flight time -> desired release velocity.
        p_rel = a_arm.shoulder + np.array([-thrower * 0.05, -0.22, -0.32])
        p_rel = p_rel + rng.uniform(-0.03, 0.03, 3)
        p_aim = b_arm.shoulder + np.array([thrower * 0.02, -0.25, -0.33])
        p_aim = p_aim + rng.uniform(-0.03, 0.03, 3)
        flight = _uniform(rng, p.flight_s)
        v_des = (p_aim - p_rel - 0.5 * _G * flight**2) / flight
        swing = _uniform(rng, p.swing_s)
        chord = float(np.linalg.norm(v_des)) * swing / 1.875
        vhat = _unit(v_des)
        # Wind-up below/behind the release point, follow-through beyond it; the
        # wrist cocks back then flicks forward about the hand's x axis.
        q_w = quat_mul(hold_pose[thrower][3:], _axis_angle(_X, np.radians(-35.0)))
        q_f = quat_mul(hold_pose[thrower][3:], _axis_angle(_X, np.radians(30.0)))
        ball_w = p_rel - 0.5 * chord * vhat
        ball_f = p_rel + 0.5 * chord * vhat
        pose_w = np.concatenate([ball_w - quat_rotate(q_w, rel[:3]), q_w])
        pose_f = np.concatenate([ball_f - quat_rotate(q_f, rel[:3]), q_f])
        t_w = now + p.windup_s
        a_track.hold(now)
        a_track.move(t_w, pose_w)
        t_s = t_w + 0.1
        a_track.hold(t_s)
        a_track.move(t_s + swing, pose_f)
        t_rel = t_s + 0.5 * swing
        # Actual release state of the ball from the arm's kinematics.
        hand = a_track.poses(np.array([t_rel - h, t_rel, t_rel + h]))
        ball = _pose_mul(hand, rel)
        p0, q0 = ball[1, :3], ball[1, 3:]
        v0 = (ball[2, :3] - ball[0, :3]) / (2 * h)
        dq = quat_mul(quat_conj(hand[0, 3:]), hand[2, 3:])
        w_axis = _unit(quat_rotate(hand[1, 3:], dq[1:] * np.sign(dq[0])))
        if np.linalg.norm(w_axis) < 0.5:
            w_axis = _X.copy()
        omega = 2 * np.pi * _uniform(rng, p.spin_rps) * w_axis
        segments.append(_BallSegment(t_rel, "flight", p0=p0, v0=v0, q0=q0, omega=omega))
        # Catch where the ball falls through the aim height (or just below release).
        apex = float(p0[1]) + max(float(v0[1]), 0.0) ** 2 / (2 * 9.81)
        y_c = float(p_aim[1]) if apex > p_aim[1] + 0.02 else float(p0[1]) - 0.05
        a2, b2, c2 = 0.5 * _G[1], v0[1], p0[1] - y_c
        t_fl = float((-b2 - np.sqrt(max(b2 * b2 - 4 * a2 * c2, 0.0))) / (2 * a2))
        t_c = t_rel + max(t_fl, 0.1)
        ball_c = _ball_flight(segments[-1], np.array([t_c]))[0]
        q_c = hold_pose[catcher][3:]
        pose_c = np.concatenate([ball_c[:3] - quat_rotate(q_c, grip[:3]), q_c])
        b_track.hold(t_c - p.catch_reach_s)
        b_track.move(t_c, pose_c)
        hand_c = b_track.poses(np.array([t_c]))[0]
        rel_c = _pose_mul(_pose_inv(hand_c), ball_c)
        segments.append(_BallSegment(t_c, "held", catcher, rel_c))
        b_track.hold(t_c + 0.15)
        t_back = t_c + 0.15 + 0.6
        b_track.move(t_back, np.concatenate([hold_pose[catcher][:3], hand_c[3:]]))
        a_track.move(max(t_s + swing + 0.6, t_c), a_arm.rest)
        now = max(t_back, a_track.end) + _uniform(rng, p.pause_s)
        b_track.hold(now)
        thrower = catcher
    left, right = tracks[-1.0].poses(t), tracks[1.0].poses(t)
    hands = {-1.0: left, 1.0: right}
    ball = np.empty((t.size, 7))
    starts = np.array([seg.start for seg in segments])
    which = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(segments) - 1)
    for i, seg in enumerate(segments):
        m = which == i
        if not m.any():
            continue
        if seg.kind == "held":
            ball[m] = _pose_mul(hands[seg.side][m], seg.rel)
        else:
            ball[m] = _ball_flight(seg, t[m])
    head = _head_looking_at(t, ball[:, :3], p.head_smooth_s, p.head_gain)
    return np.stack([head, left, right, ball], axis=1), ("head", "left", "right", "object:ball")


def _ball_flight(seg: _BallSegment, t: F64) -> F64:
    dt = t - seg.start
    pos = seg.p0 + seg.v0 * dt[:, None] + 0.5 * _G * (dt * dt)[:, None]
    speed = float(np.linalg.norm(seg.omega))
    axis = seg.omega / speed if speed > 0 else _X
    q = quat_mul(_axis_angle(axis, speed * dt), seg.q0)
    return np.concatenate([pos, q], axis=-1)


def _build_drill(p: DrillParams, rng: np.random.Generator, t: F64) -> tuple[F64, tuple[str, ...]]:
    end = float(t[-1])
    right_arm, left_arm = _Arm(1.0), _Arm(-1.0)
    track = _ArmTrack(right_arm, 0.0, right_arm.rest)
    now = _uniform(rng, (0.2, 0.8))
    track.hold(now)
    while now <= end:
        spot = _target_pose(
            rng, 1.0, p.target_x, p.target_y, p.target_z, p.yaw_deg, p.pitch_deg, 0.0
        )
        # Push in along the bit (the hand's -z), then pull back out.
        bit = quat_rotate(spot[3:], -_Z)
        deep = spot.copy()
        deep[:3] += _uniform(rng, p.depth_m) * bit
        now += _uniform(rng, p.reach_s)
        track.move(now, spot)
        now += _uniform(rng, p.drill_s)
        track.move(now, deep)
        now += 0.4
        track.move(now, spot)
        now += _uniform(rng, p.pause_s)
        track.hold(now)
    right = track.poses(t)
    # The left hand steadies the work piece near the drilling area, swaying slightly.
    support = left_arm.rest + np.r_[0.12, 0.12, -0.08, 0, 0, 0, 0]
    left_track = _ArmTrack(left_arm, 0.0, support)
    left_track.hold(end + 1.0)
    left = left_track.poses(t)
    left[:, :3] += _sway(t, rng, 0.01, (0.2, 0.5))
    offset = np.concatenate([np.asarray(p.offset), _IDENTITY])
    spin = _axis_angle(_Z, 2 * np.pi * p.spin_rps * t)
    drill = _pose_mul(_pose_mul(right, offset), np.concatenate([np.zeros((t.size, 3)), spin], 1))
    tip = drill[:, :3] + quat_rotate(drill[:, 3:], np.array([0.0, 0.0, -0.15]))
    head = _head_looking_at(t, tip, p.head_smooth_s, p.head_gain)
    return np.stack([head, left, right, drill], axis=1), ("head", "left", "right", "object:drill")


def _build_look_around(
    p: LookAroundParams, rng: np.random.Generator, t: F64
) -> tuple[F64, tuple[str, ...]]:
    end = float(t[-1])
    key_t = [0.0]
    key_q = [_IDENTITY.copy()]
    yaw, pitch = 0.0, 0.0
    now = _uniform(rng, p.fixation_s)
    key_t.append(now)
    key_q.append(_IDENTITY.copy())
    while now <= end:
        new_yaw = float(rng.uniform(-p.yaw_deg, p.yaw_deg))
        new_pitch = _uniform(rng, p.pitch_deg)
        amp = float(np.hypot(new_yaw - yaw, new_pitch - pitch))
        now += 0.25 + p.turn_s_per_90deg * amp / 90.0
        yaw, pitch = new_yaw, new_pitch
        key_t.append(now)
        key_q.append(_ypr(yaw, pitch))
        now += _uniform(rng, p.fixation_s)
        key_t.append(now)
        key_q.append(key_q[-1])
    times = np.asarray(key_t)
    keys = np.stack(key_q)
    k = np.clip(np.searchsorted(times, t, side="right") - 1, 0, times.size - 2)
    s = min_jerk((t - times[k]) / (times[k + 1] - times[k]))
    q = _slerp(keys[k], keys[k + 1], s)
    sway = _sway(t, rng, p.sway_m, p.sway_hz)
    head = np.concatenate([_NECK + quat_rotate(q, _EYE_OFFSET) + sway, q], axis=-1)
    hands = []
    for side in (-1.0, 1.0):
        rest = _Arm(side).rest
        pos = rest[:3] + sway + _sway(t, rng, p.hand_sway_m, (0.2, 0.5))
        wobble = np.radians(p.hand_sway_deg) * np.sin(
            2 * np.pi * _uniform(rng, (0.2, 0.4)) * t + rng.uniform(0, 2 * np.pi)
        )
        axis = _unit(rng.normal(size=3))
        hands.append(np.concatenate([pos, _axis_angle(axis, wobble)], axis=-1))
    return np.stack([head, hands[0], hands[1]], axis=1), ("head", "left", "right")


def _random_quat(rng: np.random.Generator) -> F64:
    q = rng.normal(size=4)
    out: F64 = q / np.linalg.norm(q)
    return out


def _build_screw(p: ScrewParams, rng: np.random.Generator, t: F64) -> tuple[F64, tuple[str, ...]]:
    streams = ("head", "left", "right")
    out = np.empty((t.size, len(streams), 7))
    for j in range(len(streams)):
        axis = _unit(rng.normal(size=3))
        point = np.array([0.0, 1.3, -0.3]) + rng.uniform(-1, 1, 3) * p.axis_point_spread_m
        omega = np.radians(_uniform(rng, p.omega_deg_s)) * rng.choice([-1.0, 1.0])
        pitch = _uniform(rng, p.pitch_m_per_rad)
        p0 = np.array([0.0, 1.3, -0.3]) + rng.uniform(-0.3, 0.3, 3)
        q0 = _random_quat(rng)
        # exp(t xi) applied in the world frame: turn about (axis, point), slide along axis.
        rot = _axis_angle(axis, omega * t)
        out[:, j, :3] = point + quat_rotate(rot, p0 - point) + (pitch * omega * t)[:, None] * axis
        out[:, j, 3:] = quat_mul(rot, q0)
    return out, streams


def _build_spin_drift(
    p: SpinDriftParams, rng: np.random.Generator, t: F64
) -> tuple[F64, tuple[str, ...]]:
    streams = ("head", "left", "right")
    out = np.empty((t.size, len(streams), 7))
    for j in range(len(streams)):
        axis = _unit(rng.normal(size=3))
        omega = np.radians(_uniform(rng, p.omega_deg_s)) * rng.choice([-1.0, 1.0])
        vel = _unit(rng.normal(size=3)) * _uniform(rng, p.speed_m_s)
        p0 = np.array([0.0, 1.3, -0.3]) + rng.uniform(-0.3, 0.3, 3)
        q0 = _random_quat(rng)
        out[:, j, :3] = p0 + t[:, None] * vel
        out[:, j, 3:] = quat_mul(q0, _axis_angle(axis, omega * t))  # body-fixed axis
    return out, streams


MOTIONS: dict[str, MotionDef] = {
    d.name: d
    for d in (
        MotionDef(
            "reach-grasp",
            ReachGraspParams,
            _build_reach_grasp,
            "hands reach, grasp, carry and release (arm arcs, minimum-jerk)",
            60.0,
        ),
        MotionDef(
            "throw-catch",
            ThrowCatchParams,
            _build_throw_catch,
            "hands toss object:ball (ballistic, spinning) to each other",
            60.0,
        ),
        MotionDef(
            "drill",
            DrillParams,
            _build_drill,
            "object:drill spinning about its bit while the hand moves it",
            60.0,
        ),
        MotionDef(
            "look-around",
            LookAroundParams,
            _build_look_around,
            "calm head turns between fixations, idle hands",
            60.0,
        ),
        MotionDef(
            "screw",
            ScrewParams,
            _build_screw,
            "fixture: constant twist exp(t xi) per stream (dq-slerp exact)",
            20.0,
        ),
        MotionDef(
            "spin-drift",
            SpinDriftParams,
            _build_spin_drift,
            "fixture: constant body spin + constant velocity per stream (soa exact)",
            20.0,
        ),
    )
}


def motion_names() -> tuple[str, ...]:
    """Names of the registered synthetic motions."""
    return tuple(MOTIONS)


def _motion(name: str) -> MotionDef:
    try:
        return MOTIONS[name]
    except KeyError:
        raise TraceError(
            f"unknown synthetic motion {name!r}; known: {', '.join(MOTIONS)}"
        ) from None


def synthetic_motion(
    name: str,
    seed: int = 0,
    *,
    duration_s: float | None = None,
    params: Mapping[str, Any] | object | None = None,
) -> Trace:
    """The motion ``name`` for ``seed``, sampled at 90 Hz from t = 0.

    ``params``: a parameter dataclass of this motion, or a mapping of
    overrides of its defaults (e.g. from :func:`load_params`).
    """
    motion = _motion(name)
    if params is None or isinstance(params, Mapping):
        par = make_params(name, params)
    elif isinstance(params, motion.params):
        par = params
    else:
        raise TypeError(f"params for {name!r} must be a mapping or {motion.params.__name__}")
    duration = motion.default_duration_s if duration_s is None else float(duration_s)
    if duration <= 0:
        raise TraceError(f"duration must be positive, got {duration}")
    n = int(np.floor(duration * NATIVE_RATE + 1e-9)) + 1
    t = np.arange(n) / NATIVE_RATE
    rng = np.random.default_rng(np.random.SeedSequence([seed, _name_key(name)]))
    poses, streams = motion.build(par, rng, t)
    q = poses[..., 3:]
    # Sign-continuous quaternions, like the recorded traces (q and -q are equal).
    flip = np.cumsum(np.einsum("nsi,nsi->ns", q[1:], q[:-1]) < 0, axis=0) % 2 == 1
    q[1:][flip] *= -1.0
    poses[..., 3:] = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return Trace(f"synthetic-{name}-{seed}", t, poses, streams)


def _name_key(name: str) -> int:
    """A stable integer from the motion name (Python's hash() is salted)."""
    return int.from_bytes(name.encode(), "little") % (2**63)


# ---------------------------------------------------------------- suites


@dataclass(frozen=True)
class SuiteEntry:
    """One motion of a suite: its seeds, duration and parameter overrides."""

    motion: str
    seeds: tuple[int, ...]
    duration_s: float
    params: Mapping[str, Any]


def _default_suite_text() -> str:
    return resources.files("scenarios").joinpath("data/synthetic.toml").read_text()


def load_suite(path: str | Path | None = None) -> list[SuiteEntry]:
    """A suite of synthetic motions from TOML (default: the packaged suite).

    Layout: ``duration_s`` at the top (default for every entry), then one
    ``[[scenario]]`` per motion with ``motion``, ``seeds`` and optionally
    ``duration_s`` and a ``[scenario.params]`` table of overrides.
    """
    where = "scenarios/data/synthetic.toml" if path is None else str(path)
    try:
        text = _default_suite_text() if path is None else Path(path).read_text()
        data = tomllib.loads(text)
    except FileNotFoundError:
        raise TraceError(f"{where}: no such suite file") from None
    except tomllib.TOMLDecodeError as exc:
        raise TraceError(f"{where}: not valid TOML ({exc})") from None
    default_duration = data.get("duration_s")
    entries: list[SuiteEntry] = []
    for i, sc in enumerate(data.get("scenario", [])):
        if not isinstance(sc, dict) or "motion" not in sc:
            raise TraceError(f"{where}: scenario {i} needs a 'motion'")
        name = str(sc["motion"])
        motion = _motion(name)
        seeds = sc.get("seeds", [0])
        if not isinstance(seeds, list) or not all(isinstance(s, int) for s in seeds):
            raise TraceError(f"{where}: scenario {name!r}: seeds must be a list of integers")
        params = dict(sc.get("params", {}))
        make_params(name, params)
        duration = sc.get("duration_s", default_duration or motion.default_duration_s)
        entries.append(SuiteEntry(name, tuple(seeds), float(duration), params))
    if not entries:
        raise TraceError(f"{where}: no [[scenario]] entries")
    return entries


def suite_traces(path: str | Path | None = None) -> list[Trace]:
    """Every (motion, seed) of a suite as a trace."""
    return [
        synthetic_motion(e.motion, seed, duration_s=e.duration_s, params=e.params)
        for e in load_suite(path)
        for seed in e.seeds
    ]
