# Types of the compiled render kernels (interp/_rowkernels.c); see interp/accel.py.
from typing import Any

SOURCE_HASH: str
SOA: int
MOTOR_LERP: int
DQ_SLERP: int

def bracket_rows(
    times: Any, base: Any, newest: Any, t: Any, lo: Any, hi: Any, s: Any, stalled: Any, /
) -> bool: ...
def pair_rows(kind: int, poses: Any, lo: Any, hi: Any, s: Any, out: Any, /) -> None: ...
def render_rows(
    times: Any,
    base: Any,
    newest: Any,
    t: Any,
    lo: Any,
    hi: Any,
    s: Any,
    stalled: Any,
    poses: Any,
    kinds: tuple[int, ...],
    out: Any,
    /,
) -> bool: ...

class Renderer:
    def __init__(
        self, times: Any, base: Any, newest: Any, lo: Any, hi: Any, s: Any, poses: Any, /
    ) -> None: ...
    def render(self, n: int, t: Any, kinds: tuple[int, ...], out: Any, stalled: Any, /) -> bool: ...
