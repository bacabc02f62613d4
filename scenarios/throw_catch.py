"""The live throw-catch scene: two people pass ``object:drill``, one script on server time.

The paper's own scene (its Figure 1), made live for bots. Two users stand
:data:`GAP` metres apart, facing each other; a third may watch from the side.
Every :data:`PERIOD` seconds of server time (cycles start at multiples of it,
so bots that join at different times agree on the schedule without talking):

==========  ==========  ===================================================
cycle time  who         what
==========  ==========  ===================================================
0           thrower     holds the drill in its right hand (creates it, or
                        requests it, if it does not hold it)
release     thrower     swings and lets go: ``release`` with the drill's
                        velocity and the hand's angular velocity (the server
                        flies it from the release keyframe from then on)
catch       catcher     its right hand meets the falling drill and asks for
                        it (``request_ownership``: a catch), carries it
hand-back   catcher     reaches to the middle and lets go at rest
grab        thrower     takes it from there (``request_ownership``) and
                        brings it back to where it held it at 0
==========  ==========  ===================================================

The arms are the two-link arms of :mod:`scenarios.synthetic_body` (minimum-jerk
joint motions), heads look at the drill. Every action time is a 90 Hz sample
time, so the keyframe a bot sends with an action is a sample of the script.

Ground truth of the drill (what a receiver is scored against): in a hand, the
hand's pose times the grip; thrown, the server's own ballistic law from the
release keyframe (``p0 + v dt - g dt^2 / 2``, rotation ``exp(w dt / 2) q0``, g =
9.81 m/s^2 along -y); handed back, at rest where it was let go. The release
keyframe is the sample at the release time, which is also where the flight
starts, so the server's flight and the script's agree (to the wire's rounding).

:func:`score_drill` scores a receiver's drill stream in three classes: ``object``
(all of it), ``object-flight`` (release to catch) and ``object-catch``
(:data:`CATCH_WINDOW` around each catch).
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from posecast.interp import quat_conj, quat_mul, quat_rotate
from posecast.scenarios.qoe import ErrorSamples, KeyframeLog, evaluate_group
from posecast.scenarios.synthetic_body import (
    _G,
    _IDENTITY,
    _X,
    _Y,
    _Z,
    F64,
    NATIVE_RATE,
    _Arm,
    _ArmTrack,
    _axis_angle,
    _head_looking_at,
    _pose_inv,
    _pose_mul,
    _unit,
)
from posecast.scenarios.traces import DEVICE_NAMES, Trace

__all__ = [
    "CATCH_WINDOW",
    "DRILL",
    "GAP",
    "OBJECT_CLASSES",
    "PERIOD",
    "ROLES",
    "SCENE",
    "Action",
    "Script",
    "drill_label",
    "role_motion",
    "scene_epoch",
    "scene_motion",
    "scene_role",
    "scene_script",
    "score_drill",
]

SCENE = "throw-catch"
#: The roles, in the order bots take them (bot 0 throws, bot 1 catches, others watch).
ROLES = ("thrower", "catcher", "watcher")
DRILL = "object:drill"
#: One cycle of the scene (s); cycles start at multiples of it in server time.
PERIOD = 4.0
#: Distance between the thrower's and the catcher's bodies (m).
GAP = 0.9
#: The catch window: this long before and after each catch (s).
CATCH_WINDOW = (0.25, 0.25)
#: QoE classes of the drill (in :data:`scenarios.qoe.CLASS_ORDER`).
OBJECT_CLASSES = ("object", "object-flight", "object-catch")
#: Drill origin in the hand frame (m): 10 cm ahead of the hand, held by its grip.
_GRIP = np.array([0.0, -0.02, -0.10, 1.0, 0.0, 0.0, 0.0])
#: Where each role stands: [px, py, pz, qw, qx, qy, qz] of its body in the world.
_PLACES = {
    "thrower": np.array([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]),
    "catcher": np.array([0.0, 0.0, -GAP, 0.0, 0.0, 1.0, 0.0]),  # turned to face the thrower
    "watcher": np.array([1.1, 0.0, -0.5 * GAP, *_axis_angle(_Y, 0.5 * np.pi)]),
}

ActionKind = Literal["hold", "throw", "catch", "hand-back", "grab"]


@dataclass(frozen=True)
class Action:
    """What ``role`` does at cycle time ``at`` (a sample time of the script)."""

    at: float
    role: str
    kind: ActionKind
    #: A throw's release velocity (m/s) and angular velocity (rad/s, world frame).
    velocity: tuple[float, float, float] | None = None
    angular: tuple[float, float, float] | None = None

    @property
    def keyframe(self) -> bool:
        """The actor sends the sample at ``at`` first (a release starts from it)."""
        return self.kind in ("throw", "hand-back")


@dataclass(frozen=True)
class Script:
    """One cycle of the scene for a seed: every stream at 90 Hz and the actions."""

    seed: int
    times: F64
    """(N,) cycle times ``n / 90``, N = PERIOD * 90."""
    bodies: dict[str, F64]
    """Each role's (N, 3, 7) head, left, right in the world frame."""
    drill: F64
    """(N, 7) the drill's true pose."""
    release: float
    catch: float
    hand_back: float
    grab: float
    velocity: F64
    angular: F64

    def actions(self) -> tuple[Action, ...]:
        v = (float(self.velocity[0]), float(self.velocity[1]), float(self.velocity[2]))
        w = (float(self.angular[0]), float(self.angular[1]), float(self.angular[2]))
        return (
            Action(0.0, "thrower", "hold"),
            Action(self.release, "thrower", "throw", v, w),
            Action(self.catch, "catcher", "catch"),
            Action(self.hand_back, "catcher", "hand-back"),
            Action(self.grab, "thrower", "grab"),
        )

    def in_flight(self, dt: F64) -> F64:
        """The drill's poses ``(N, 7)`` ``dt`` seconds after the release (the server's law)."""
        release = self.drill[round(self.release * NATIVE_RATE)]
        return _flight(release[:3], release[3:], self.velocity, self.angular, np.asarray(dt))

    def role_trace(self, role: str) -> Trace:
        """The streams ``role`` publishes (head, left, right), one cycle."""
        return Trace(f"{SCENE}-{role}-{self.seed}", self.times, self.bodies[role], DEVICE_NAMES)

    def drill_trace(self) -> Trace:
        return Trace(f"{SCENE}-drill-{self.seed}", self.times, self.drill[:, None], (DRILL,))

    def windows(self, kind: str, span: tuple[float, float], t0: float) -> list[tuple[float, float]]:
        """Absolute ``flight`` or ``catch`` windows inside ``span`` (scene anchored at ``t0``)."""
        if kind == "flight":
            a, b = self.release, self.catch
        else:
            a, b = self.catch - CATCH_WINDOW[0], self.catch + CATCH_WINDOW[1]
        k0 = int(np.floor((span[0] - t0 - b) / PERIOD))
        out = []
        for k in range(k0, int(np.ceil((span[1] - t0 - a) / PERIOD)) + 1):
            lo, hi = max(span[0], t0 + k * PERIOD + a), min(span[1], t0 + k * PERIOD + b)
            if hi > lo:
                out.append((lo, hi))
        return out


def scene_epoch(server_time: float) -> float:
    """The start of the cycle ``server_time`` is in: every bot's shared ``t0``."""
    return float(np.floor(server_time / PERIOD) * PERIOD)


def scene_role(motion: str) -> str | None:
    """The role of a synthetic motion name ``throw-catch.ROLE`` (``drill``: the object)."""
    head, dot, role = motion.partition(".")
    if head == SCENE and dot and role in (*ROLES, "drill"):
        return role
    return None


def role_motion(index: int) -> str:
    """``--motion throw-catch``: bot ``index``'s synthetic motion name."""
    return f"{SCENE}.{ROLES[min(index, len(ROLES) - 1)]}"


def scene_motion(name: str, seed: int) -> Trace:
    """The trace of synthetic motion ``throw-catch.ROLE`` (one cycle; it loops)."""
    role = scene_role(name)
    script = scene_script(seed)
    if role == "drill":
        return script.drill_trace()
    if role is None:
        raise ValueError(f"{name!r} is no role of the {SCENE} scene")
    return script.role_trace(role)


def drill_label(seed: int, t0: float) -> str:
    """The motion label of the drill's ground truth (``scenarios.motion.MotionSpec``)."""
    return f"synthetic:{SCENE}.drill|seed={seed}|t0={t0!r}"


def _grid(t: float) -> float:
    return round(t * NATIVE_RATE) / NATIVE_RATE


def _hold_pose(arm: _Arm) -> F64:
    """The right hand holding the drill before a throw (turned in, a little up)."""
    q = quat_mul(arm.rest[3:], _axis_angle(_Z, np.radians(-25.0)))
    return np.concatenate([arm.rest[:3] + np.array([0.0, 0.05, 0.0]), q])


def _world(place: F64, body: F64) -> F64:
    return _pose_mul(place, body)


def _flight(p0: F64, q0: F64, v: F64, w: F64, dt: F64) -> F64:
    """The server's ballistic law (``server.objects.Flight``, before landing)."""
    pos = p0 + v * dt[:, None] + 0.5 * _G * (dt * dt)[:, None]
    rate = float(np.linalg.norm(w))
    axis = w / rate if rate > 0 else _X
    return np.concatenate([pos, quat_mul(_axis_angle(axis, rate * dt), q0)], axis=-1)


@dataclass
class _Tracks:
    thrower: _ArmTrack
    catcher: _ArmTrack
    hold: F64
    rel_catch: F64 = field(default_factory=lambda: _GRIP.copy())
    rel_grab: F64 = field(default_factory=lambda: _GRIP.copy())
    rest_drill: F64 = field(default_factory=lambda: _GRIP.copy())


def _swing(arm: _Arm, track: _ArmTrack, rng: np.random.Generator) -> tuple[float, float]:
    """The thrower's wind-up and swing towards the catcher; (release time, planned flight)."""
    hold = _hold_pose(arm)
    p_rel = arm.shoulder + np.array([-0.05, -0.22, -0.32]) + rng.uniform(-0.02, 0.02, 3)
    aim_body = _Arm(1.0).shoulder + np.array([-0.02, -0.22, -0.30]) + rng.uniform(-0.02, 0.02, 3)
    p_aim = _world(_PLACES["catcher"], np.r_[aim_body, _IDENTITY])[:3]
    flight = float(rng.uniform(0.50, 0.60))
    v_des = (p_aim - p_rel - 0.5 * _G * flight**2) / flight
    swing = float(rng.uniform(0.32, 0.40))
    chord = float(np.linalg.norm(v_des)) * swing / 1.875
    vhat = _unit(v_des)
    q_w = quat_mul(hold[3:], _axis_angle(_X, np.radians(-35.0)))
    q_f = quat_mul(hold[3:], _axis_angle(_X, np.radians(30.0)))
    drill_w, drill_f = p_rel - 0.5 * chord * vhat, p_rel + 0.5 * chord * vhat
    release = _grid(0.95 + 0.5 * swing)
    t_s = release - 0.5 * swing
    track.hold(0.3)
    track.move(t_s - 0.1, np.concatenate([drill_w - quat_rotate(q_w, _GRIP[:3]), q_w]))
    track.hold(t_s)
    track.move(t_s + swing, np.concatenate([drill_f - quat_rotate(q_f, _GRIP[:3]), q_f]))
    return release, float(p_aim[1])


def _release_state(track: _ArmTrack, t: float) -> tuple[F64, F64, F64]:
    """(drill pose, velocity, hand angular velocity in the world frame) at ``t``."""
    h = 1e-4
    hand = track.poses(np.array([t - h, t, t + h]))
    drill = _pose_mul(hand, _GRIP)
    v = (drill[2, :3] - drill[0, :3]) / (2 * h)
    dq = quat_mul(hand[2, 3:], quat_conj(hand[0, 3:]))
    dq = dq * np.sign(dq[0])
    vn = float(np.linalg.norm(dq[1:]))
    angle = 2.0 * np.arctan2(vn, dq[0])
    w = dq[1:] / max(vn, 1e-12) * angle / (2 * h)
    return drill[1], v, w


def _catch_time(p0: F64, v0: F64, y_catch: float, release: float) -> float:
    """The first sample time after the apex at which the falling drill is at ``y_catch``."""
    a, b, c = -0.5 * 9.81, float(v0[1]), float(p0[1]) - y_catch
    dt = (-b - np.sqrt(max(b * b - 4 * a * c, 0.0))) / (2 * a)
    return _grid(release + max(float(dt), 0.2))


def _body(role: str, pose: F64) -> F64:
    """A world pose in ``role``'s body frame."""
    return _pose_mul(_pose_inv(_PLACES[role]), pose)


def _catcher_moves(tr: _Tracks, drill_c: F64, catch: float) -> tuple[float, F64]:
    """The catcher's reach, catch, carry and hand-back; (hand-back time, drill at rest)."""
    arm = _Arm(1.0)
    q_hold = _hold_pose(arm)[3:]
    hand_c = np.concatenate(
        [_body("catcher", drill_c)[:3] - quat_rotate(q_hold, _GRIP[:3]), q_hold]
    )
    tr.catcher.hold(catch - 0.45)
    tr.catcher.move(catch, hand_c)
    hand_c = tr.catcher.poses(np.array([catch]))[0]
    tr.rel_catch = _pose_mul(_pose_inv(hand_c), _body("catcher", drill_c))
    tr.catcher.hold(catch + 0.15)
    hand_back = _grid(catch + 0.95)
    # The drill at rest in the middle, pointing as the thrower will hold it.
    rest = np.concatenate([[0.0, 1.22, -0.5 * GAP], tr.hold[3:]])
    tr.catcher.move(hand_back, _pose_mul(_body("catcher", rest), _pose_inv(tr.rel_catch)))
    hand_h = tr.catcher.poses(np.array([hand_back]))[0]
    tr.rest_drill = _world(_PLACES["catcher"], _pose_mul(hand_h, tr.rel_catch))
    tr.catcher.hold(hand_back + 0.1)
    tr.catcher.move(hand_back + 0.8, arm.rest)
    tr.catcher.hold(PERIOD)
    return hand_back, tr.rest_drill


def _thrower_returns(tr: _Tracks, release: float, grab: float) -> None:
    tr.thrower.move(release + 0.6, _Arm(1.0).rest)
    tr.thrower.hold(grab - 0.55)
    tr.thrower.move(grab, _pose_mul(tr.rest_drill, _pose_inv(_GRIP)))
    hand_g = tr.thrower.poses(np.array([grab]))[0]
    tr.rel_grab = _pose_mul(_pose_inv(hand_g), tr.rest_drill)
    tr.thrower.hold(grab + 0.15)
    tr.thrower.move(grab + 0.85, tr.hold)
    tr.thrower.hold(PERIOD)


@functools.lru_cache(maxsize=8)
def scene_script(seed: int = 0) -> Script:
    """The scene's cycle for ``seed`` (a pure function of it)."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x7C]))
    arm = _Arm(1.0)
    tr = _Tracks(
        _ArmTrack(arm, 0.0, _hold_pose(arm)), _ArmTrack(arm, 0.0, arm.rest), _hold_pose(arm)
    )
    release, y_aim = _swing(arm, tr.thrower, rng)
    p0, v0, w0 = _release_state(tr.thrower, release)
    catch = _catch_time(p0[:3], v0, y_aim, release)
    drill_c = _flight(p0[:3], p0[3:], v0, w0, np.array([catch - release]))[0]
    hand_back, rest = _catcher_moves(tr, drill_c, catch)
    grab = _grid(hand_back + 0.3)
    _thrower_returns(tr, release, grab)
    t = np.arange(round(PERIOD * NATIVE_RATE)) / NATIVE_RATE
    hand_a = tr.thrower.poses(t)
    hand_b = _world(_PLACES["catcher"], tr.catcher.poses(t))
    drill = np.where(
        (t < release)[:, None], _pose_mul(hand_a, _GRIP), _pose_mul(hand_a, tr.rel_grab)
    )
    flying = (t >= release) & (t < catch)
    drill[flying] = _flight(p0[:3], p0[3:], v0, w0, t[flying] - release)
    held_b = (t >= catch) & (t < hand_back)
    drill[held_b] = _pose_mul(hand_b[held_b], tr.rel_catch)
    drill[(t >= hand_back) & (t < grab)] = rest
    bodies = {
        "thrower": _person("thrower", t, drill, hand_a),
        "catcher": _person("catcher", t, drill, hand_b),
        "watcher": _person("watcher", t, drill, None),
    }
    return Script(seed, t, bodies, _continuous(drill), release, catch, hand_back, grab, v0, w0)


def _person(role: str, t: F64, drill: F64, right: F64 | None) -> F64:
    """Head (looking at the drill), left hand at rest, right hand, in the world frame."""
    place = _PLACES[role]
    target = _pose_mul(_pose_inv(place), drill)[:, :3]
    head = _head_looking_at(t, target, 0.2, 0.8)
    left = np.broadcast_to(_Arm(-1.0).rest, (t.size, 7))
    rest_right = np.broadcast_to(_Arm(1.0).rest, (t.size, 7))
    poses = np.stack([_world(place, head), _world(place, left), _world(place, rest_right)], axis=1)
    if right is not None:
        poses[:, 2] = right
    return _continuous(poses)


def _continuous(poses: F64) -> F64:
    """Sign-continuous unit quaternions along the first axis (q and -q are one rotation)."""
    q = poses[..., 3:]
    flip = np.cumsum(np.einsum("n...i,n...i->n...", q[1:], q[:-1]) < 0, axis=0) % 2 == 1
    q[1:][flip] *= -1.0
    poses[..., 3:] = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return poses


def score_drill(
    truth: Trace,
    log: KeyframeLog,
    delay: Callable[[F64], F64],
    methods: Sequence[str],
    span: tuple[float, float],
    script: Script,
    t0: float,
) -> dict[str, dict[str, ErrorSamples]]:
    """A receiver's drill in the :data:`OBJECT_CLASSES`, per method.

    ``truth``: the drill's true poses in server time over ``span`` (at least);
    ``log``: the drill keyframes as they arrived; ``delay``: the D in effect at
    each tau. ``object`` covers ``span``; the windows of each flight and catch
    inside it are scored apart (each on its own, so no velocity is taken across
    two windows).
    """
    out: dict[str, dict[str, ErrorSamples]] = {m: {} for m in methods}

    def add(cls: str, window: tuple[float, float]) -> None:
        res = evaluate_group(truth, log, delay, methods, window)
        for m in methods:
            for samples in res[m].values():
                out[m].setdefault(cls, ErrorSamples()).merge(samples)

    add("object", span)
    for cls, kind in (("object-flight", "flight"), ("object-catch", "catch")):
        for window in script.windows(kind, span, t0):
            add(cls, window)
    return out
