"""The interpolator registry: names to callables ``f(a, b, s) -> poses``.

Built-in methods register here at import; third-party packages add theirs
through the entry-point group ``posecast.interpolators`` (the entry point's
object is the callable; its name is the entry point's name). Entry points are
loaded lazily, the first time a name is looked up or listed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata
from typing import Any, Literal

from numpy.typing import ArrayLike

from interp.cubic import motor_cubic, motor_hermite
from interp.methods import dq_slerp, motor_lerp, soa
from interp.pose import F64

__all__ = [
    "ENTRY_POINT_GROUP",
    "Interpolator",
    "InterpolatorInfo",
    "Kind",
    "get",
    "info",
    "names",
    "register",
]

ENTRY_POINT_GROUP = "posecast.interpolators"

Interpolator = Callable[[ArrayLike, ArrayLike, ArrayLike], F64]
"""A pair interpolator ``f(a, b, s)``."""

#: How an interpolator is called:
#: ``pair``: ``f(a, b, s)`` on the two bracketing keyframes;
#: ``window``: ``f(keys (..., 4, 7), times (..., 4), t)`` on the bracket and one
#: neighbour each side (a missing neighbour repeats its bracket keyframe);
#: ``velocity``: ``f(a, b, va, vb, dt, s)`` with (..., 6) keyframe velocities.
Kind = Literal["pair", "window", "velocity"]


@dataclass(frozen=True, slots=True)
class InterpolatorInfo:
    """A registered interpolator and what the receiver must know to use it."""

    name: str
    func: Callable[..., F64]
    description: str
    #: Whether it commutes with a change of body frame (which point of the device
    #: is tracked), i.e. treats the pose as one rigid motion. All built-ins commute
    #: with a change of world frame; SoA does not commute with a body-frame change.
    frame_invariant: bool
    kind: Kind = "pair"
    #: Keyframes needed after the bracket (each costs one interval of playout delay).
    lookahead: int = 0
    #: Whether keyframes must carry velocities (6 more floats each).
    needs_velocity: bool = False


_REGISTRY: dict[str, InterpolatorInfo] = {}
_entry_points_loaded = False


def register(
    name: str,
    func: Callable[..., F64],
    *,
    description: str = "",
    frame_invariant: bool = False,
    kind: Kind = "pair",
    replace: bool = False,
) -> None:
    """Register ``func`` under ``name``; refuse to shadow a name unless ``replace``."""
    if not name or not name.replace("-", "").replace("_", "").isalnum():
        raise ValueError(f"invalid interpolator name {name!r}")
    if name in _REGISTRY and not replace:
        raise ValueError(f"interpolator {name!r} is already registered")
    if kind not in ("pair", "window", "velocity"):
        raise ValueError(f"invalid interpolator kind {kind!r}")
    _REGISTRY[name] = InterpolatorInfo(
        name,
        func,
        description,
        frame_invariant,
        kind,
        lookahead=1 if kind == "window" else 0,
        needs_velocity=kind == "velocity",
    )


def _load_entry_points() -> None:
    global _entry_points_loaded
    if _entry_points_loaded:
        return
    _entry_points_loaded = True
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        if ep.name in _REGISTRY:
            continue  # built-ins win; a plug-in cannot silently replace them
        func: Any = ep.load()
        if not callable(func):
            raise TypeError(f"entry point {ep.name!r} ({ep.value}) is not callable")
        kind: Kind = getattr(func, "posecast_kind", "pair")
        register(ep.name, func, description=f"plug-in from {ep.value}", kind=kind)


def names() -> list[str]:
    """Names of every available interpolator, built-ins first."""
    _load_entry_points()
    return list(_REGISTRY)


def info(name: str) -> InterpolatorInfo:
    """The registry entry for ``name``; ``KeyError`` lists the known names."""
    _load_entry_points()
    try:
        return _REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown interpolator {name!r}; known: {', '.join(_REGISTRY)}") from None


def get(name: str) -> Callable[..., F64]:
    """The callable registered under ``name`` (``f(a, b, s)`` for pair methods)."""
    return info(name).func


register(
    "soa",
    soa,
    description="position LERP + quaternion SLERP (what engines do today)",
    frame_invariant=False,
)
register(
    "dq-slerp",
    dq_slerp,
    description="unit dual quaternion screw interpolation (ScLERP)",
    frame_invariant=True,
)
register(
    "motor-lerp",
    motor_lerp,
    description="linear blend of 3D PGA motors, then Study-number normalisation",
    frame_invariant=True,
)
register(
    "motor-cubic",
    motor_cubic,
    description="Catmull-Rom cubic on motors over 4 keyframes (1 keyframe look-ahead)",
    frame_invariant=True,
    kind="window",
)
register(
    "motor-hermite",
    motor_hermite,
    description="Hermite cubic on motors from keyframe poses + tracker velocities",
    frame_invariant=True,
    kind="velocity",
)
