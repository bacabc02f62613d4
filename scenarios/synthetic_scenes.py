"""The scripted scenes of :mod:`scenarios.synthetic`: parameters and builders.

One frozen parameter dataclass and one builder per motion (reach-grasp,
throw-catch, drill-toss, hand-over, drill, look-around, and the exactness
fixtures screw and spin-drift; see :mod:`scenarios.synthetic` for what each one shows). A builder
takes its parameters, a seeded generator and the sample times and returns
poses ``(N, S, 7)`` and the stream names; it draws from the generator in a
fixed order, so a motion is a pure function of its parameters and the seed.
Built from the primitives of :mod:`scenarios.synthetic_body`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from posecast.interp import quat_conj, quat_mul, quat_rotate
from posecast.scenarios.synthetic_body import (
    _EYE_OFFSET,
    _G,
    _IDENTITY,
    _NECK,
    _X,
    _Z,
    F64,
    Range,
    _Arm,
    _ArmTrack,
    _axis_angle,
    _head_looking_at,
    _pose_inv,
    _pose_mul,
    _slerp,
    _sway,
    _uniform,
    _unit,
    _ypr,
    min_jerk,
)

__all__ = [
    "DrillParams",
    "DrillTossParams",
    "HandOverParams",
    "LookAroundParams",
    "ReachGraspParams",
    "ScrewParams",
    "SpinDriftParams",
    "ThrowCatchParams",
]


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
    thing: str = "ball"
    """What is tossed: the object stream is ``object:<thing>``."""


@dataclass(frozen=True)
class DrillTossParams(ThrowCatchParams):
    """The throw-catch scene with a drill: tumbles slowly end over end, held by its grip.

    Close to the paper's medical-training scene (a tool thrown and caught).
    """

    thing: str = "drill"
    spin_rps: Range = (0.4, 1.0)
    """Tumble in flight, about the throwing hand's angular velocity (rev/s)."""
    grip: tuple[float, float, float] = (0.0, -0.02, -0.10)
    """Drill origin in the hand frame at the first grasp (m)."""
    flight_s: Range = (0.50, 0.70)


@dataclass(frozen=True)
class HandOverParams:
    """A tool passes slowly from hand to hand; the taker works with it in between.

    Close to the paper's medical-training scene (a slow tool hand-over).
    """

    reach_s: Range = (0.9, 1.5)
    """Minimum-jerk reach to the hand-over point, and back (s): slow."""
    hold_s: Range = (0.3, 0.6)
    """Both hands still on the tool before it changes hands (s)."""
    use_s: Range = (1.0, 2.0)
    """Each of the taker's slow wrist turns while it works with the tool (s)."""
    use_turn_deg: Range = (20.0, 60.0)
    meet_x: Range = (-0.05, 0.05)
    meet_y: Range = (1.05, 1.30)
    meet_z: Range = (-0.50, -0.35)
    offer_yaw_deg: float = 35.0
    """How far each hand turns towards the other at the hand-over (deg)."""
    grip: tuple[float, float, float] = (0.0, -0.02, -0.10)
    """Tool origin in the first holder's hand frame (m)."""
    target_x: Range = (0.10, 0.35)
    target_y: Range = (0.95, 1.30)
    target_z: Range = (-0.50, -0.30)
    pitch_deg: Range = (-40.0, 0.0)
    head_gain: float = 0.7
    head_smooth_s: float = 0.3


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


@dataclass
class _Juggle:
    """A throw-catch scene in progress: both arms, their tracks, the ball's segments."""

    arms: dict[float, _Arm]
    tracks: dict[float, _ArmTrack]
    hold_pose: dict[float, F64]
    """Where each hand holds the ball between tosses."""
    grip: F64
    """Ball pose in the hand frame at the first grasp."""
    segments: list[_BallSegment]


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
    scene = _Juggle(arms, tracks, hold_pose, grip, [_BallSegment(0.0, "held", thrower, grip)])
    now = 0.5
    while now <= end:
        now = _toss(scene, p, rng, thrower, now)
        thrower = -thrower
    left, right = tracks[-1.0].poses(t), tracks[1.0].poses(t)
    ball = _ball_poses(scene.segments, {-1.0: left, 1.0: right}, t)
    head = _head_looking_at(t, ball[:, :3], p.head_smooth_s, p.head_gain)
    streams = ("head", "left", "right", f"object:{p.thing}")
    return np.stack([head, left, right, ball], axis=1), streams


def _toss(
    sc: _Juggle, p: ThrowCatchParams, rng: np.random.Generator, thrower: float, now: float
) -> float:
    """One toss from ``thrower`` to the other hand from ``now``; returns the next toss's start."""
    catcher = -thrower
    a_track, b_track = sc.tracks[thrower], sc.tracks[catcher]
    p_aim, t_s, swing = _swing(sc, p, rng, thrower, now)
    t_rel = t_s + 0.5 * swing
    _release(sc, p, rng, thrower, t_rel)
    t_c, t_back = _catch(sc, p, catcher, p_aim, t_rel)
    a_track.move(max(t_s + swing + 0.6, t_c), sc.arms[thrower].rest)
    now = max(t_back, a_track.end) + _uniform(rng, p.pause_s)
    b_track.hold(now)
    return now


def _swing(
    sc: _Juggle, p: ThrowCatchParams, rng: np.random.Generator, thrower: float, now: float
) -> tuple[F64, float, float]:
    """Plan a toss and move the thrower's arm through its swing.

    Returns the aim point near the catching hand, when the swing starts and
    how long it takes (the ball leaves the hand at its middle).
    """
    a_arm, b_arm = sc.arms[thrower], sc.arms[-thrower]
    a_track = sc.tracks[thrower]
    rel = sc.segments[-1].rel
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
    q_w = quat_mul(sc.hold_pose[thrower][3:], _axis_angle(_X, np.radians(-35.0)))
    q_f = quat_mul(sc.hold_pose[thrower][3:], _axis_angle(_X, np.radians(30.0)))
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
    return p_aim, t_s, swing


def _release(
    sc: _Juggle, p: ThrowCatchParams, rng: np.random.Generator, thrower: float, t_rel: float
) -> None:
    """The ball leaves the thrower's hand at ``t_rel``: append its flight segment.

    Release state from the arm's kinematics (central differences); the spin is
    about the hand's angular velocity.
    """
    h = 1e-4
    hand = sc.tracks[thrower].poses(np.array([t_rel - h, t_rel, t_rel + h]))
    ball = _pose_mul(hand, sc.segments[-1].rel)
    p0, q0 = ball[1, :3], ball[1, 3:]
    v0 = (ball[2, :3] - ball[0, :3]) / (2 * h)
    dq = quat_mul(quat_conj(hand[0, 3:]), hand[2, 3:])
    w_axis = _unit(quat_rotate(hand[1, 3:], dq[1:] * np.sign(dq[0])))
    if np.linalg.norm(w_axis) < 0.5:
        w_axis = _X.copy()
    omega = 2 * np.pi * _uniform(rng, p.spin_rps) * w_axis
    sc.segments.append(_BallSegment(t_rel, "flight", p0=p0, v0=v0, q0=q0, omega=omega))


def _catch(
    sc: _Juggle, p: ThrowCatchParams, catcher: float, p_aim: F64, t_rel: float
) -> tuple[float, float]:
    """The catching hand meets the ball in flight; returns the catch time and its return time.

    Catch where the ball falls through the aim height (or just below release).
    """
    flight = sc.segments[-1]
    p0, v0 = flight.p0, flight.v0
    b_track = sc.tracks[catcher]
    apex = float(p0[1]) + max(float(v0[1]), 0.0) ** 2 / (2 * 9.81)
    y_c = float(p_aim[1]) if apex > p_aim[1] + 0.02 else float(p0[1]) - 0.05
    a2, b2, c2 = 0.5 * _G[1], v0[1], p0[1] - y_c
    t_fl = float((-b2 - np.sqrt(max(b2 * b2 - 4 * a2 * c2, 0.0))) / (2 * a2))
    t_c = t_rel + max(t_fl, 0.1)
    ball_c = _ball_flight(flight, np.array([t_c]))[0]
    q_c = sc.hold_pose[catcher][3:]
    pose_c = np.concatenate([ball_c[:3] - quat_rotate(q_c, sc.grip[:3]), q_c])
    b_track.hold(t_c - p.catch_reach_s)
    b_track.move(t_c, pose_c)
    hand_c = b_track.poses(np.array([t_c]))[0]
    rel_c = _pose_mul(_pose_inv(hand_c), ball_c)
    sc.segments.append(_BallSegment(t_c, "held", catcher, rel_c))
    b_track.hold(t_c + 0.15)
    t_back = t_c + 0.15 + 0.6
    b_track.move(t_back, np.concatenate([sc.hold_pose[catcher][:3], hand_c[3:]]))
    return t_c, t_back


def _ball_poses(segments: list[_BallSegment], hands: dict[float, F64], t: F64) -> F64:
    """Ball poses ``(N, 7)``: in a hand while held, ballistic and spinning in flight."""
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
    return ball


def _ball_flight(seg: _BallSegment, t: F64) -> F64:
    dt = t - seg.start
    pos = seg.p0 + seg.v0 * dt[:, None] + 0.5 * _G * (dt * dt)[:, None]
    speed = float(np.linalg.norm(seg.omega))
    axis = seg.omega / speed if speed > 0 else _X
    q = quat_mul(_axis_angle(axis, speed * dt), seg.q0)
    return np.concatenate([pos, q], axis=-1)


def _build_hand_over(
    p: HandOverParams, rng: np.random.Generator, t: F64
) -> tuple[F64, tuple[str, ...]]:
    end = float(t[-1])
    arms = {side: _Arm(side) for side in (-1.0, 1.0)}
    tracks = {side: _ArmTrack(arm, 0.0, arm.rest) for side, arm in arms.items()}
    grip = np.concatenate([np.asarray(p.grip), _IDENTITY])
    segments = [_BallSegment(0.0, "held", 1.0, grip)]
    holder = 1.0
    now = _uniform(rng, (0.3, 0.8))
    while now <= end:
        now = _hand_over(p, rng, tracks, segments, holder, now)
        holder = -holder
    left, right = tracks[-1.0].poses(t), tracks[1.0].poses(t)
    tool = _ball_poses(segments, {-1.0: left, 1.0: right}, t)
    head = _head_looking_at(t, tool[:, :3], p.head_smooth_s, p.head_gain)
    return np.stack([head, left, right, tool], axis=1), ("head", "left", "right", "object:tool")


def _hand_over(
    p: HandOverParams,
    rng: np.random.Generator,
    tracks: dict[float, _ArmTrack],
    segments: list[_BallSegment],
    giver: float,
    now: float,
) -> float:
    """The giver offers the tool, the taker grasps it, uses it; returns when all is still.

    Both hands are still while the tool changes hands, so its path is continuous.
    """
    taker = -giver
    g_track, t_track = tracks[giver], tracks[taker]
    meet = np.array([_uniform(rng, p.meet_x), _uniform(rng, p.meet_y), _uniform(rng, p.meet_z)])
    give = np.concatenate(
        [meet + np.array([giver * 0.05, 0, 0]), _ypr(giver * p.offer_yaw_deg, -10.0)]
    )
    take = np.concatenate(
        [meet + np.array([taker * 0.06, 0, 0]), _ypr(taker * p.offer_yaw_deg, -20.0)]
    )
    g_track.hold(now)
    t_g = now + _uniform(rng, p.reach_s)
    g_track.move(t_g, give)
    t_track.hold(max(now + 0.2, t_track.end))
    t_t = max(t_g, t_track.end) + 0.15
    t_track.move(t_t, take)
    t_x = t_t + _uniform(rng, p.hold_s)
    g_track.hold(t_x)
    t_track.hold(t_x)
    # The tool changes hands at t_x: its pose in the taker's hand from both hands' poses then.
    at = np.array([t_x])
    tool = _pose_mul(g_track.poses(at)[0], segments[-1].rel)
    segments.append(
        _BallSegment(t_x, "held", taker, _pose_mul(_pose_inv(t_track.poses(at)[0]), tool))
    )
    g_track.move(t_x + _uniform(rng, p.reach_s), g_track.arm.rest)
    work = _target_pose(rng, taker, p.target_x, p.target_y, p.target_z, 25.0, p.pitch_deg, 0.0)
    now = t_x + _uniform(rng, p.reach_s)
    t_track.move(now, work)
    turn = _uniform(rng, p.use_turn_deg) * rng.choice([-1.0, 1.0])
    now += _uniform(rng, p.use_s)
    t_track.move(now, _twist(work, turn))
    now += _uniform(rng, p.use_s)
    t_track.move(now, work)
    return max(now, g_track.end) + 0.2


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
