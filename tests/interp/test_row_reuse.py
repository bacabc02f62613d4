"""The row kernels' kept views and their two ways of scaling a block.

``interp.rowops`` keeps each kernel's views of this thread's scratch, and the
views of the last rows ``A``, ``B`` it was given; on narrow rows (up to
``NARROW`` poses) a per-pose factor is repeated into a block before it scales
one, on wider rows it broadcasts. Neither may change a result: the two ways
give the same bits, and a kernel follows its inputs when they are new arrays,
the same arrays refilled, other widths, or scratch passed in.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from functools import partial

import numpy as np
import pytest
from numpy.typing import NDArray
from test_pair_kernels import REFERENCES, hard_pairs

from posecast.interp import rowops
from posecast.interp.kernels import (
    RowKernel,
    dq_slerp_rows,
    motor_lerp_rows,
    scratch,
    share_rows,
    soa_rows,
)

F64 = NDArray[np.float64]
KERNELS: dict[str, RowKernel] = {
    "soa": soa_rows,
    "dq-slerp": dq_slerp_rows,
    "motor-lerp": motor_lerp_rows,
}


def unit_rows(n: int, seed: int, extrapolate: bool = False) -> tuple[F64, F64, F64]:
    """Hard pairs (ties, zero angles, s at 0 and 1) as validated rows ``(7, n)``."""
    a, b, s = hard_pairs(n, seed=seed, extrapolate=extrapolate)
    a[:, 3:] /= np.linalg.norm(a[:, 3:], axis=1, keepdims=True)
    return np.ascontiguousarray(a.T), np.ascontiguousarray(b.T), s


def in_fresh_thread(fn: Callable[[], F64]) -> F64:
    """``fn()`` in a new thread: its own scratch and no kept views."""
    box: list[F64] = []
    th = threading.Thread(target=lambda: box.append(fn()))
    th.start()
    th.join()
    return box[0]


@pytest.mark.parametrize("name", sorted(KERNELS))
@pytest.mark.parametrize("share", [None, False, True])
@pytest.mark.parametrize("extrapolate", [False, True])
def test_narrow_and_wide_rows_give_the_same_bits(
    name: str, share: bool | None, extrapolate: bool
) -> None:
    """The first NARROW columns of a wide call equal a narrow call on them, bit for bit."""
    n = rowops.NARROW
    A, B, S = unit_rows(n + 37, seed=5 + extrapolate, extrapolate=extrapolate)
    unit = not extrapolate
    kernel = KERNELS[name]
    wide, narrow = np.empty((7, n + 37)), np.empty((7, n))
    An, Bn, Sn = A[:, :n].copy(), B[:, :n].copy(), S[:n].copy()
    sw = None if share is None else share_rows(A, B, S, share)
    kernel(A, B, S, wide, None, unit, sw)
    sn = None if share is None else share_rows(An, Bn, Sn, share)
    kernel(An, Bn, Sn, narrow, None, unit, sn)
    np.testing.assert_array_equal(wide[:, :n], narrow)


@pytest.mark.parametrize("name", sorted(KERNELS))
def test_kernels_follow_their_rows(name: str) -> None:
    """New arrays, the same arrays refilled, other widths and passed-in scratch in turn
    each give what a fresh thread computes from the same rows."""
    kernel = KERNELS[name]
    widths = (100, 100, 3000, 7, 100, 100)
    inputs = [unit_rows(n, seed=k) for k, n in enumerate(widths)]
    A, B = np.empty((7, 100)), np.empty((7, 100))  # refilled in place, as a render does
    for k, (a, b, s) in enumerate(inputs):
        want = in_fresh_thread(partial(_fresh, kernel, a.copy(), b.copy(), s))
        if k in (1, 4, 5):
            A[:], B[:] = a, b
            a, b = A, B
        work = scratch(a.shape[1]) if k == 3 else None
        got = np.empty_like(a)
        kernel(a, b, s, got, work, True)
        np.testing.assert_array_equal(got, want, err_msg=f"call {k}")


def _fresh(kernel: RowKernel, A: F64, B: F64, S: F64) -> F64:
    out = np.empty_like(A)
    kernel(A, B, S, out, None, True)
    return out


@pytest.mark.parametrize("name", ["soa", "motor-lerp"])
def test_refilled_rows_still_equal_the_formulas(name: str) -> None:
    """Ten frames into the same rows: each equals the plain formula of its own inputs."""
    kernel = KERNELS[name]
    A, B, out = np.empty((7, 100)), np.empty((7, 100)), np.empty((7, 100))
    for k in range(10):
        a, b, s = unit_rows(100, seed=40 + k)
        A[:], B[:] = a, b
        kernel(A, B, s, out, None, True)
        want = REFERENCES[name](a.T, b.T, s)
        np.testing.assert_array_equal(out.T, want, err_msg=f"frame {k}")
