"""The reference implementations ``posecast bench interp`` times beside posecast's.

Each :class:`Case` builds, from pose pairs ``a``, ``b`` (``(n, 7)``, w first) and
fractions ``s``, the zero-argument call to time, in a reference library's own
representation (built here, before the clock starts): scipy ``Rotation`` slerp and
``Slerp`` objects for SoA; scipy ``RigidTransform`` exp-coords and pytransform3d's
ScLERP, per pose and vectorised, for dq-slerp; a kingdon PGA motor blend with
``.normalized()`` for motor-lerp. A library (or feature) that is not installed
raises :class:`Unavailable` with the reason, which the bench reports in its place.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray

__all__ = ["REFERENCES", "Builder", "Case", "Unavailable", "optional", "version"]

F64 = NDArray[np.float64]


def optional(name: str) -> ModuleType | None:
    """Import a reference library, or ``None`` when it is not installed."""
    try:
        return importlib.import_module(name)
    except ImportError:
        return None


def version(name: str) -> str:
    mod = optional(name)
    return str(getattr(mod, "__version__", "?")) if mod is not None else "not installed"


# --- the cases -------------------------------------------------------------------

# A case builder takes (a, b, s) and returns the zero-argument call to time, or
# raises Unavailable with the reason.
Builder = Callable[[F64, F64, F64], Callable[[], object]]


class Unavailable(Exception):
    """A reference library (or feature) is missing."""


def _need(module: str, attr: str | None = None) -> Any:
    mod = optional(module)
    if mod is None:
        raise Unavailable("not installed")
    if attr is None:
        return mod
    obj = getattr(mod, attr, None)
    if obj is None:
        raise Unavailable(f"no {module}.{attr}")
    return obj


def _xyzw(q: F64) -> F64:
    return np.ascontiguousarray(q[:, [1, 2, 3, 0]])


def _scipy_rotation_slerp(a: F64, b: F64, s: F64) -> Callable[[], object]:
    rotation = _need("scipy.spatial.transform", "Rotation")
    r0, r1 = rotation.from_quat(_xyzw(a[:, 3:])), rotation.from_quat(_xyzw(b[:, 3:]))
    t0, t1, sc = a[:, :3], b[:, :3], s[:, None]

    def call() -> object:
        rs = r0 * rotation.from_rotvec(sc * (r0.inv() * r1).as_rotvec())
        return t0 + sc * (t1 - t0), rs

    return call


def _scipy_slerp_objects(a: F64, b: F64, s: F64) -> Callable[[], object]:
    spatial = _need("scipy.spatial.transform")
    keys = [
        spatial.Rotation.from_quat(_xyzw(np.stack([x[3:], y[3:]])))
        for x, y in zip(a, b, strict=True)
    ]

    def call() -> object:
        return [spatial.Slerp([0.0, 1.0], k)(si) for k, si in zip(keys, s, strict=True)]

    return call


def _scipy_rigid_transform(a: F64, b: F64, s: F64) -> Callable[[], object]:
    rigid = _need("scipy.spatial.transform", "RigidTransform")
    rotation = _need("scipy.spatial.transform", "Rotation")
    ta = rigid.from_components(a[:, :3], rotation.from_quat(_xyzw(a[:, 3:])))
    tb = rigid.from_components(b[:, :3], rotation.from_quat(_xyzw(b[:, 3:])))
    sc = s[:, None]

    def call() -> object:
        return ta * rigid.from_exp_coords(sc * (ta.inv() * tb).as_exp_coords())

    return call


def _pt_dual_quaternions(a: F64, b: F64) -> tuple[F64, F64]:
    ptr = _need("pytransform3d.trajectories")
    dqa = ptr.dual_quaternions_from_pqs(a)
    dqb = ptr.dual_quaternions_from_pqs(b)
    dqb[np.sum(dqa[:, :4] * dqb[:, :4], axis=1) < 0.0] *= -1.0  # short way
    return dqa, dqb


def _pt_sclerp_loop(a: F64, b: F64, s: F64) -> Callable[[], object]:
    pt = _need("pytransform3d.transformations")
    dqa, dqb = _pt_dual_quaternions(a, b)

    def call() -> object:
        return [pt.dual_quaternion_sclerp(x, y, si) for x, y, si in zip(dqa, dqb, s, strict=True)]

    return call


def _pt_sclerp_batch(a: F64, b: F64, s: F64) -> Callable[[], object]:
    ptr = _need("pytransform3d.trajectories")
    dqa, dqb = _pt_dual_quaternions(a, b)

    def call() -> object:
        return ptr.dual_quaternions_sclerp(dqa, dqb, s)

    return call


def _kingdon_motor_blend(a: F64, b: F64, s: F64) -> Callable[[], object]:
    kingdon = _need("kingdon")
    pga = kingdon.Algebra(3, 0, 1)

    def motors(p: F64) -> Any:
        t, q = p[:, :3].T, p[:, 3:].T
        translator = 1.0 - 0.5 * pga.blades.e0 * pga.vector(e1=t[0], e2=t[1], e3=t[2])
        return translator * pga.multivector(e=q[0], e23=-q[1], e13=q[2], e12=-q[3])

    m0, m1 = motors(a), motors(b)
    m1 = pga.scalar(e=np.where(np.sum(a[:, 3:] * b[:, 3:], axis=1) < 0.0, -1.0, 1.0)) * m1
    w0, w1 = pga.scalar(e=1.0 - s), pga.scalar(e=s)

    def call() -> object:
        return (w0 * m0 + w1 * m1).normalized()

    return call


@dataclass(frozen=True, slots=True)
class Case:
    label: str
    method: str
    build: Builder
    loop: bool = False  # per-pair Python loop: timed on bench_interp.LOOP_PAIRS pairs only


REFERENCES: tuple[Case, ...] = (
    Case("scipy Rotation slerp (vectorised)", "soa", _scipy_rotation_slerp),
    Case("scipy Slerp, one object per pair", "soa", _scipy_slerp_objects, loop=True),
    Case("scipy RigidTransform exp/log", "dq-slerp", _scipy_rigid_transform),
    Case("pytransform3d dual_quaternion_sclerp", "dq-slerp", _pt_sclerp_loop, loop=True),
    Case("pytransform3d dual_quaternions_sclerp", "dq-slerp", _pt_sclerp_batch),
    Case("kingdon motor blend + normalized()", "motor-lerp", _kingdon_motor_blend),
)
