"""Which implementation of the compact codec's hot paths runs: compiled or pure Python.

``protocol/_speedups.c`` (built by ``pip install`` where a C compiler exists)
does the relay's per-pose work in C: the upstream update decode (all of
``_compact.UpstreamDecoder._decode_fast`` in one call; its parts
``codec_fast.decode_update_rows``, ``_compact._update_of_rows``), the group
encode of snapshots (all of ``codec_relay.encode_group`` in one call, its frames
spliced from C buffers; ``codec_relay._delta_blocks``) and Exp-Golomb packing
(``bits.eg_pack``). Each has a pure-Python twin that is the reference: same
bytes, same values; the compiled one returns None where its twin would take
another path, and the twin then decides.

:data:`speedups` is the compiled module or None; the twins read it on every
call, so :func:`use` switches a running process (the tests run both). Set
``POSECAST_PURE=1`` to run pure Python from the start. An extension built from
other sources than the ones beside it (a stale in-place build) is not used.
Importing says nothing (a CLI error must stay one line): :data:`NOTICE` is the
one line the relay logs at start when the accelerator should run and does not.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from types import ModuleType

__all__ = ["IMPLEMENTATION", "NOTICE", "PURE_ENV", "compiled", "speedups", "use"]

#: Set to 1 (or anything but 0 and empty) to run the pure-Python codec.
PURE_ENV = "POSECAST_PURE"
COMPILED = "compiled (C accelerator)"
_SOURCES = ("_speedups.c", "_speedups_update.h", "_speedups_relay.h")


def _source_hash() -> str | None:
    """The hash setup.py compiles in, of the sources beside this file (None if absent)."""
    here = Path(__file__).parent
    try:
        data = b"".join((here / name).read_bytes() for name in _SOURCES)
    except OSError:
        return None
    return hashlib.sha256(data).hexdigest()[:16]


def _load() -> tuple[ModuleType | None, str, str]:
    """The compiled module (or None), what runs, and why it is not compiled."""
    try:
        from posecast.protocol import _speedups
    except ImportError:
        return (
            None,
            "pure Python (accelerator not built)",
            "the compact codec's C accelerator is not built (no C compiler at install?); "
            "running its pure-Python twin",
        )
    source = _source_hash()
    if source is not None and source != _speedups.SOURCE_HASH:
        return (
            None,
            "pure Python (accelerator out of date)",
            "the compact codec's C accelerator was built from older sources; running "
            "pure Python (rebuild: pip install -e .)",
        )
    return _speedups, COMPILED, ""


_forced = os.environ.get(PURE_ENV, "") not in ("", "0")
_compiled, _why, _notice = _load()
#: The compiled module while it runs, else None.
speedups: ModuleType | None = None if _forced else _compiled
#: What runs, for ``posecast --version`` and ``/metrics``.
IMPLEMENTATION = f"pure Python ({PURE_ENV}=1)" if _forced else _why
#: Why the accelerator does not run although it was not turned off ("": it runs, or
#: ``POSECAST_PURE`` asked for pure Python): the relay logs it once at start.
NOTICE = "" if _forced else _notice


def compiled() -> ModuleType | None:
    """The compiled module if it is built and current (whether it runs or not)."""
    return _compiled


def use(pure: bool) -> str:
    """Run the pure-Python twins (``pure``) or the compiled module, if there is one;
    returns :data:`IMPLEMENTATION`."""
    global speedups, IMPLEMENTATION
    if pure or _compiled is None:
        speedups = None
        IMPLEMENTATION = f"pure Python ({PURE_ENV}=1)" if pure else _why
    else:
        speedups, IMPLEMENTATION = _compiled, COMPILED
    return IMPLEMENTATION
