"""Build hook for the compiled parts: the compact codec's accelerator and the
render kernels.

``protocol/_speedups.c`` builds as ``posecast.protocol._speedups`` and
``interp/_rowkernels.c`` as ``posecast.interp._rowkernels`` wherever a C compiler
is found. Both are optional: without a compiler the build says so and goes on,
and the codec runs its pure-Python twin (byte-identical, slower), the render its
numpy kernels (the same to float rounding, slower).
Everything else about the package is in pyproject.toml.
"""

import hashlib
import sys
from pathlib import Path

from setuptools import Extension, setup

HERE = Path(__file__).parent
SOURCES = ["protocol/_speedups.c", "protocol/_speedups_update.h", "protocol/_speedups_relay.h"]
# The sources' hash, compiled in: protocol/_accel.py refuses an extension built
# from other sources than the ones beside it (a stale in-place build).
DIGEST = hashlib.sha256(b"".join((HERE / p).read_bytes() for p in SOURCES)).hexdigest()[:16]
# Floating point as CPython computes it: no fused multiply-add (MSVC does not fuse
# by default).
FLAGS = [] if sys.platform == "win32" else ["-O2", "-ffp-contract=off"]
RENDER = "interp/_rowkernels.c"
RENDER_DIGEST = hashlib.sha256((HERE / RENDER).read_bytes()).hexdigest()[:16]

setup(
    ext_modules=[
        Extension(
            "posecast.protocol._speedups",
            sources=SOURCES[:1],
            depends=SOURCES[1:],
            define_macros=[("SOURCE_HASH", f'"{DIGEST}"')],
            extra_compile_args=FLAGS,
            optional=True,
        ),
        Extension(
            "posecast.interp._rowkernels",
            sources=[RENDER],
            define_macros=[("SOURCE_HASH", f'"{RENDER_DIGEST}"')],
            extra_compile_args=FLAGS,
            optional=True,
        ),
    ]
)
