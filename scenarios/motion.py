"""Motion sources for bots, and labels that let receivers rebuild the truth.

Every source is a :class:`Trace` sampled at a native rate, anchored in server
time at ``t0``: sample ``i`` is the pose at server time ``t0 + times[i]``. A
sender publishes the newest sample at each send time; a receiver that knows the
sender's label (``MotionSpec.label()``, carried in the join) rebuilds the same
samples as ground truth.

Labels: ``trace:<path>|t0=<seconds>`` or ``synthetic:<name>|seed=<n>|t0=<s>``,
where a trace path under the vr-traces folder is written relative to it
(``dev/S02_riftS_expertplus.csv``) so it resolves on every machine. A motion
moved to a spawn point (:mod:`scenarios.spawn`) adds ``|at=<yaw_deg>,<x>,<z>``,
the rigid map its samples went through.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from posecast.interp import quat_mul
from posecast.protocol.codec import DEFAULT_VOLUME, Volume
from posecast.scenarios import synthetic
from posecast.scenarios.spawn import Placement, SpawnPoint, check_inside, place, placement_for
from posecast.scenarios.throw_catch import ROLES, SCENE, scene_motion, scene_role
from posecast.scenarios.traces import (
    DEVICE_NAMES,
    Trace,
    TraceError,
    default_trace_root,
    load_trace,
)

__all__ = [
    "SCENE_MOTIONS",
    "SYNTHETIC_MOTIONS",
    "MotionSpec",
    "SpawnPoint",
    "loop_period",
    "sample_at",
    "synthetic_trace",
]

#: ``orbit`` plus every motion of :mod:`scenarios.synthetic` (reach-grasp, throw-catch, ...).
SYNTHETIC_MOTIONS = ("orbit", *synthetic.motion_names())
#: The roles of the live throw-catch scene (:mod:`scenarios.throw_catch`), and its drill.
SCENE_MOTIONS = tuple(f"{SCENE}.{role}" for role in (*ROLES, "drill"))
_SYNTH_RATE = 90.0
_SYNTH_DURATION = 120.0


def _axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Quaternions (w first) for rotations by ``angle (N,)`` about unit ``axis``."""
    half = 0.5 * angle
    return np.concatenate([np.cos(half)[:, None], np.sin(half)[:, None] * axis[None, :]], axis=1)


def synthetic_trace(name: str = "orbit", seed: int = 0, duration: float = _SYNTH_DURATION) -> Trace:
    """A deterministic head + two hands (+ objects) motion sampled at 90 Hz.

    ``orbit``: the head looks around (yaw and pitch oscillations); each hand
    circles in front of the body while its wrist rolls, like a slow stirring.
    Every other name is a motion of :mod:`scenarios.synthetic` with its default
    parameters (it may add object streams such as ``object:ball``), or a role
    of the live throw-catch scene (``throw-catch.thrower``, ``.catcher``,
    ``.watcher``, or ``.drill``: the object; one cycle, ``duration`` unused).
    """
    if scene_role(name) is not None:
        return scene_motion(name, seed)
    if name not in SYNTHETIC_MOTIONS:
        known = ", ".join((*SYNTHETIC_MOTIONS, *SCENE_MOTIONS))
        raise TraceError(f"unknown synthetic motion {name!r}; known: {known}")
    if name != "orbit":
        return synthetic.synthetic_motion(name, seed, duration_s=duration)
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration, 1.0 / _SYNTH_RATE)
    n = t.size
    poses = np.zeros((n, 3, 7))
    f_head = rng.uniform(0.15, 0.3)
    yaw = 0.5 * np.sin(2 * np.pi * f_head * t + rng.uniform(0, 2 * np.pi))
    pitch = 0.15 * np.sin(2 * np.pi * 1.7 * f_head * t)
    q_head = quat_mul(
        _axis_angle(np.array([0.0, 1.0, 0.0]), yaw), _axis_angle(np.array([1.0, 0.0, 0.0]), pitch)
    )
    poses[:, 0, :3] = [0.0, 1.6, 0.0]
    poses[:, 0, 0] += 0.03 * np.sin(2 * np.pi * 0.4 * f_head * t)
    poses[:, 0, 3:] = q_head
    for j, side in ((1, -1.0), (2, 1.0)):
        f = rng.uniform(0.4, 0.9)
        phase = 2 * np.pi * f * t + rng.uniform(0, 2 * np.pi)
        radius = rng.uniform(0.12, 0.25)
        centre = np.array([0.25 * side, 1.2, -0.35])
        poses[:, j, 0] = centre[0] + radius * np.cos(phase)
        poses[:, j, 1] = centre[1] + radius * np.sin(phase)
        poses[:, j, 2] = centre[2] + 0.05 * np.sin(2 * phase)
        roll = 0.8 * np.sin(phase + 0.5)
        q = quat_mul(
            _axis_angle(np.array([0.0, 0.0, 1.0]), phase),
            _axis_angle(np.array([1.0, 0.0, 0.0]), roll),
        )
        poses[:, j, 3:] = q
    return Trace(f"synthetic-{name}-{seed}", t, poses, DEVICE_NAMES)


@dataclass(frozen=True)
class MotionSpec:
    """What a bot plays and when it started, in server time."""

    source: str  # "trace:<path>" or "synthetic:<name>"
    seed: int = 0
    t0: float = 0.0
    #: The rigid map to its spawn point (None: where the motion is).
    placement: Placement | None = None

    def label(self) -> str:
        parts = [self.source]
        if self.source.startswith("synthetic:"):
            parts.append(f"seed={self.seed}")
        parts.append(f"t0={self.t0!r}")
        if self.placement is not None:
            parts.append(f"at={self.placement.label()}")
        return "|".join(parts)

    @classmethod
    def parse(cls, label: str) -> MotionSpec:
        fields = label.split("|")
        source, opts = fields[0], {}
        for f in fields[1:]:
            key, _, value = f.partition("=")
            opts[key] = value
        if not (source.startswith("trace:") or source.startswith("synthetic:")):
            raise TraceError(f"unknown motion label {label!r}")
        at = Placement.parse(opts["at"]) if "at" in opts else None
        try:
            return cls(source, int(opts.get("seed", 0)), float(opts.get("t0", 0.0)), at)
        except ValueError:
            raise TraceError(f"malformed motion label {label!r}") from None

    @classmethod
    def for_trace(cls, path: Path, t0: float = 0.0) -> MotionSpec:
        root = default_trace_root().resolve()
        p = path.resolve()
        try:
            rel = p.relative_to(root)
            return cls(f"trace:{rel.as_posix()}", 0, t0)
        except ValueError:
            return cls(f"trace:{p}", 0, t0)

    def load(self) -> Trace:
        """The motion's samples, times relative to its own start (not ``t0``), at its
        spawn point (``placement``)."""
        return place(self.load_unplaced(), self.placement)

    def load_unplaced(self) -> Trace:
        """The motion's samples where they were recorded (no ``placement``)."""
        kind, _, what = self.source.partition(":")
        if kind == "synthetic":
            return synthetic_trace(what, self.seed)
        path = Path(what)
        if not path.is_absolute():
            path = default_trace_root() / path
        return load_trace(path)

    def placed(self, point: SpawnPoint | None, volume: Volume | None = None) -> MotionSpec:
        """This motion moved to ``point``: the spec with the placement that puts it there
        (:func:`scenarios.spawn.placement_for`, after any placement it had). A scripted
        scene's roles (``throw-catch.*``) and ``point`` None keep their place. Refuses,
        in one line, a placed motion that leaves ``volume`` (a room's ``welcome.volume``;
        default: the default volume). Loads the motion: not for an event loop."""
        if point is None or scene_role(self.source.partition(":")[2]) is not None:
            return self
        at = placement_for(self.load(), point)
        if self.placement is not None:
            at = self.placement.then(at)
        vol = DEFAULT_VOLUME if volume is None else volume
        spec = replace(self, placement=at)
        check_inside(spec.load(), vol.lo, vol.hi, f"{self.source} at ({point.x:g}, {point.z:g})")
        return spec

    def truth(self, until: float | None = None) -> Trace:
        """The samples in server time (``t0 + times``), looped up to ``until``."""
        tr = self.load()
        period = loop_period(tr)
        loops = 1 if until is None else max(1, int(np.ceil((until - self.t0) / period)))
        times = np.concatenate([tr.times + k * period for k in range(loops)])
        poses = np.concatenate([tr.poses] * loops)
        return Trace(tr.name, times + self.t0, poses, tr.streams)


def loop_period(trace: Trace) -> float:
    """A looping sender restarts its motion after this long (one frame of rest)."""
    return float(trace.times[-1] - trace.times[0]) + 1.0 / trace.native_rate


def sample_at(trace: Trace, t: float) -> tuple[int, float]:
    """Newest sample at motion time ``t >= 0`` (looping): its index and its time.

    The time is on the looped time line of :meth:`MotionSpec.truth` (add ``t0``
    for server time).
    """
    period = loop_period(trace)
    k = int(t // period)
    local = t - k * period + float(trace.times[0])
    idx = max(0, int(np.searchsorted(trace.times, local, side="right")) - 1)
    return idx, k * period + float(trace.times[idx])
