"""The interpolator registry: names to callables ``f(a, b, s) -> poses``.

Built-in methods register here at import; third-party packages add theirs
through the entry-point group ``posecast.interpolators`` (the entry point's
object is the callable; its name is the entry point's name). Entry points are
loaded lazily, the first time a name is looked up or listed. A plug-in declares
how it is called with attributes on its callable: ``posecast_kind`` (``"pair"``,
the default, ``"window"`` or ``"velocity"``) and, for window methods,
``posecast_lookbehind`` / ``posecast_lookahead`` (ints, default 1 each), e.g.::

    def my_spline(keys, times, t): ...     # keys (..., 6, 7), times (..., 6)
    my_spline.posecast_kind = "window"
    my_spline.posecast_lookbehind = 2
    my_spline.posecast_lookahead = 2

    # pyproject.toml
    [project.entry-points."posecast.interpolators"]
    my-spline = "my_package.module:my_spline"

Window methods
--------------
A window method is called as ``f(keys (..., K, 7), times (..., K), t (...))``
with ``K = lookbehind + 2 + lookahead``: ``keys[..., :lookbehind]`` are the
keyframes before the bracket, ``keys[..., lookbehind]`` and ``keys[...,
lookbehind + 1]`` the bracket ``lo``/``hi`` (``T[lb] <= t <= T[lb + 1]``), the
rest the keyframes after it; the window is in time order. The receiver
needs ``lookahead`` keyframes past the bracket, so it plays out ``lookahead``
intervals later (:func:`scenarios.qoe.ideal_delay`).

**Missing neighbours.** A neighbour that does not exist (the ends of a track),
has not arrived by the query's deadline (QoE and live paths: not-yet-arrived
keyframes are skipped, as the receiver cannot see them) or lies past a held
bracket is given as a *copy of its inward neighbour with the same time*. So
window times never decrease, and ``T[j] == T[j + 1]`` (before the bracket) or
``T[j] == T[j - 1]`` (after it) means "nothing from here outwards". A bracket
with ``lo == hi`` (a held query, or one exactly on a keyframe; ``T[lb] == T[lb +
1]``) must return ``keys[..., lb, :]``, whatever the neighbours. Window functions
fall back to what the available keyframes allow.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata
from typing import Any, Literal

from numpy.typing import ArrayLike

from posecast.interp.cubic import motor_cubic, motor_hermite
from posecast.interp.hermite import soa_hermite
from posecast.interp.kernels import RowKernel, dq_slerp_rows, motor_lerp_rows, soa_rows
from posecast.interp.methods import dq_slerp, motor_lerp, soa
from posecast.interp.pose import F64
from posecast.interp.quintic import QUINTIC_LOOKAHEAD, QUINTIC_LOOKBEHIND, motor_quintic

__all__ = [
    "ENTRY_POINT_GROUP",
    "MAX_NEIGHBOURS",
    "Interpolator",
    "InterpolatorInfo",
    "Kind",
    "generation",
    "get",
    "info",
    "names",
    "register",
]

ENTRY_POINT_GROUP = "posecast.interpolators"
#: Most neighbours a window method may ask for on either side.
MAX_NEIGHBOURS = 16

Interpolator = Callable[[ArrayLike, ArrayLike, ArrayLike], F64]
"""A pair interpolator ``f(a, b, s)``."""

#: How an interpolator is called:
#: ``pair``: ``f(a, b, s)`` on the two bracketing keyframes;
#: ``window``: ``f(keys (..., K, 7), times (..., K), t)`` on the bracket and
#: ``lookbehind`` / ``lookahead`` neighbours before / after it (see the module
#: docstring for the order and for missing neighbours);
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
    #: Keyframes used before the bracket (window methods; no delay cost).
    lookbehind: int = 0
    #: A pair method's row kernel, if it has one (:mod:`interp.kernels`): the same
    #: poses from validated component-major rows, with no allocation per call.
    rows: RowKernel | None = None

    @property
    def window_size(self) -> int:
        """Keyframes per query: ``lookbehind + 2 + lookahead`` (2 for pair/velocity)."""
        return self.lookbehind + 2 + self.lookahead


_REGISTRY: dict[str, InterpolatorInfo] = {}
_entry_points_loaded = False
_generation = 0


def generation() -> tuple[int, int]:
    """A token that changes whenever an entry is registered (or the table is swapped,
    as tests do): a caller that keeps what it looked up (a render loop's plan of
    methods) looks again when it changes."""
    return _generation, id(_REGISTRY)


def register(
    name: str,
    func: Callable[..., F64],
    *,
    description: str = "",
    frame_invariant: bool = False,
    kind: Kind = "pair",
    replace: bool = False,
    lookbehind: int | None = None,
    lookahead: int | None = None,
    rows: RowKernel | None = None,
) -> None:
    """Register ``func`` under ``name``; refuse to shadow a name unless ``replace``.

    ``lookbehind`` / ``lookahead``: neighbours a window method sees before / after
    the bracket (default 1 each for window methods; pair and velocity methods
    take none). ``rows``: a pair method's row kernel (:class:`interp.kernels.RowKernel`).
    """
    if not name or not name.replace("-", "").replace("_", "").isalnum():
        raise ValueError(f"invalid interpolator name {name!r}")
    if name in _REGISTRY and not replace:
        raise ValueError(f"interpolator {name!r} is already registered")
    if kind not in ("pair", "window", "velocity"):
        raise ValueError(f"invalid interpolator kind {kind!r}")
    default = 1 if kind == "window" else 0
    lb = default if lookbehind is None else lookbehind
    la = default if lookahead is None else lookahead
    for label, v in (("lookbehind", lb), ("lookahead", la)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 0:
            raise ValueError(f"{label} must be a non-negative int, got {v!r}")
        if v > MAX_NEIGHBOURS:
            raise ValueError(f"{label} must be at most {MAX_NEIGHBOURS}, got {v}")
    if kind != "window" and (lb or la):
        raise ValueError(f"only window interpolators take neighbours, not {kind!r} ones")
    if rows is not None and kind != "pair":
        raise ValueError(f"only pair interpolators take a row kernel, not {kind!r} ones")
    global _generation
    _generation += 1
    _REGISTRY[name] = InterpolatorInfo(
        name,
        func,
        description,
        frame_invariant,
        kind,
        lookahead=la,
        needs_velocity=kind == "velocity",
        lookbehind=lb,
        rows=rows,
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
        register(
            ep.name,
            func,
            description=f"plug-in from {ep.value}",
            kind=kind,
            lookbehind=getattr(func, "posecast_lookbehind", None),
            lookahead=getattr(func, "posecast_lookahead", None),
        )


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
    rows=soa_rows,
)
register(
    "dq-slerp",
    dq_slerp,
    description="unit dual quaternion screw interpolation (ScLERP)",
    frame_invariant=True,
    rows=dq_slerp_rows,
)
register(
    "motor-lerp",
    motor_lerp,
    description="linear blend of 3D PGA motors, then Study-number normalisation",
    frame_invariant=True,
    rows=motor_lerp_rows,
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
register(
    "soa-hermite",
    soa_hermite,
    description=(
        "cubic Hermite position + quaternion Hermite rotation from keyframe poses "
        "+ tracker velocities (SoA with velocities)"
    ),
    frame_invariant=False,
    kind="velocity",
)
register(
    "motor-quintic",
    motor_quintic,
    description=(
        "C2 quintic on motors over 6 keyframes, derivatives from local quartics "
        "(2 keyframes look-ahead)"
    ),
    frame_invariant=True,
    kind="window",
    lookbehind=QUINTIC_LOOKBEHIND,
    lookahead=QUINTIC_LOOKAHEAD,
)
