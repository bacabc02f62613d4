"""Which implementation of the render kernels runs: compiled or numpy.

``interp/_rowkernels.c`` (built by ``pip install`` where a C compiler exists)
brackets every stream of a render frame and interpolates the brackets with the
pair methods (soa, motor-lerp, dq-slerp) in two calls, where numpy takes about
fifty small ones. The numpy kernels (:mod:`interp.kernels`) are the reference:
the compiled ones agree with them to float rounding (libm's trigonometry against
numpy's half-angle forms), and give the keyframes bit for bit at ``s`` 0 and 1.
Only the render frame (``client.render``) uses them; the batch interpolators
(:func:`interp.soa` ...) stay numpy, bit for bit the formulas of
:mod:`interp.methods`.

:data:`kernels` is the compiled module or None; callers read it on every call,
so :func:`use` switches a running process (the tests run both). Set
``POSECAST_PURE=1`` to run numpy from the start (the same switch as the codec's
accelerator). A module built from other sources than the one beside it (a stale
in-place build) is not used.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from types import ModuleType

__all__ = ["IMPLEMENTATION", "PURE_ENV", "compiled", "kernels", "use"]

#: Set to 1 (or anything but 0 and empty) to run the numpy kernels.
PURE_ENV = "POSECAST_PURE"
COMPILED = "compiled (C render kernels)"
_SOURCES = ("_rowkernels.c",)


def _source_hash() -> str | None:
    """The hash setup.py compiles in, of the sources beside this file (None if absent)."""
    here = Path(__file__).parent
    try:
        data = b"".join((here / name).read_bytes() for name in _SOURCES)
    except OSError:
        return None
    return hashlib.sha256(data).hexdigest()[:16]


def _load() -> tuple[ModuleType | None, str]:
    """The compiled module (or None) and what runs."""
    try:
        from posecast.interp import _rowkernels
    except ImportError:
        return None, "numpy (render kernels not built)"
    source = _source_hash()
    if source is not None and source != _rowkernels.SOURCE_HASH:
        return None, "numpy (render kernels out of date; rebuild: pip install -e .)"
    return _rowkernels, COMPILED


_forced = os.environ.get(PURE_ENV, "") not in ("", "0")
_compiled, _why = _load()
#: The compiled module while it runs, else None.
kernels: ModuleType | None = None if _forced else _compiled
#: What runs, for ``posecast --version`` and reports.
IMPLEMENTATION = f"numpy ({PURE_ENV}=1)" if _forced else _why


def compiled() -> ModuleType | None:
    """The compiled module if it is built and current (whether it runs or not)."""
    return _compiled


def use(pure: bool) -> str:
    """Run the numpy kernels (``pure``) or the compiled ones, if built; returns
    :data:`IMPLEMENTATION`."""
    global kernels, IMPLEMENTATION
    if pure or _compiled is None:
        kernels = None
        IMPLEMENTATION = f"numpy ({PURE_ENV}=1)" if pure else _why
    else:
        kernels, IMPLEMENTATION = _compiled, COMPILED
    return IMPLEMENTATION
