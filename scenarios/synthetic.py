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
- ``drill-toss``: throw-catch with a drill (``object:drill``) instead of the
  ball, held by its grip, tumbling slowly end over end in flight.
- ``hand-over``: a tool (``object:tool``) passes slowly from hand to hand: the
  giver offers it at the midline, the taker grasps it (both hands still while
  it changes hands), carries it to a work spot and turns it slowly; the giver
  returns to rest; the head watches the tool. With ``drill-toss``, the motion
  closest to the paper's medical-training scene.
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

Layout: the motion primitives (quaternions, the two-link arm, the head) live
in :mod:`scenarios.synthetic_body`, the parameter dataclasses and the scene
builders in :mod:`scenarios.synthetic_scenes`; this module registers the
motions (:data:`MOTIONS`), samples them and loads parameters and suites.
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

from posecast.scenarios.synthetic_body import F64, NATIVE_RATE, min_jerk
from posecast.scenarios.synthetic_scenes import (
    DrillParams,
    DrillTossParams,
    HandOverParams,
    LookAroundParams,
    ReachGraspParams,
    ScrewParams,
    SpinDriftParams,
    ThrowCatchParams,
    _build_drill,
    _build_hand_over,
    _build_look_around,
    _build_reach_grasp,
    _build_screw,
    _build_spin_drift,
    _build_throw_catch,
)
from posecast.scenarios.traces import Trace, TraceError

__all__ = [
    "MOTIONS",
    "NATIVE_RATE",
    "DrillParams",
    "DrillTossParams",
    "HandOverParams",
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
    if isinstance(default, str) and not isinstance(value, str):
        raise TraceError(f"{where}: expected a string, got {value!r}")
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
            "drill-toss",
            DrillTossParams,
            _build_throw_catch,
            "hands toss object:drill (tumbling slowly) to each other",
            60.0,
        ),
        MotionDef(
            "hand-over",
            HandOverParams,
            _build_hand_over,
            "object:tool passes slowly from hand to hand and is used in between",
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
    return resources.files("posecast.scenarios").joinpath("data/synthetic.toml").read_text()


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
