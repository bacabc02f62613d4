"""``out=`` on the paper's three pair interpolators: the result written into the
caller's array, the same bits as a new result, nothing allocated for it.

With ``out`` a batch call allocates nothing that grows with the batch, so its
speed cannot depend on what the allocator does with large blocks; a bad ``out``
is refused with one clear line, and an ``out`` that overlaps the input still
gets the right result.
"""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
from test_pair_kernels import hard_pairs

from posecast import interp

NAMES = ["soa", "dq-slerp", "motor-lerp"]


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize("n", [1, 100, 8192 + 17])
def test_out_receives_the_same_bits(name: str, n: int) -> None:
    """``f(a, b, s, out=res)`` fills ``res`` with ``f(a, b, s)`` and returns it."""
    a, b, s = hard_pairs(n, seed=n, extrapolate=True)
    f = interp.get(name)
    res = np.full((n, 7), np.nan)
    assert f(a, b, s, out=res) is res
    np.testing.assert_array_equal(res, f(a, b, s))


@pytest.mark.parametrize("name", NAMES)
def test_out_keeps_the_batch_shape(name: str) -> None:
    """A ``(4, 5, 7)`` batch with a scalar ``s`` goes into a ``(4, 5, 7)`` ``out``."""
    a, b, _ = hard_pairs(20, seed=2, extrapolate=False)
    a, b = a.reshape(4, 5, 7), b.reshape(4, 5, 7)
    res = np.empty((4, 5, 7))
    interp.get(name)(a, b, 0.3, out=res)
    np.testing.assert_array_equal(res, interp.get(name)(a, b, 0.3))


@pytest.mark.parametrize("name", NAMES)
def test_out_may_be_the_input(name: str) -> None:
    """Writing over ``a`` (or a view overlapping it) gives the result computed apart."""
    a, b, s = hard_pairs(9000, seed=4, extrapolate=False)
    want = interp.get(name)(a, b, s)
    got = interp.get(name)(a, b, s, out=a)
    assert got is a
    np.testing.assert_array_equal(a, want)


@pytest.mark.parametrize(
    ("out", "why"),
    [
        (np.empty((10, 6)), "shape"),
        (np.empty((10, 7), dtype=np.float32), "float32"),
        (np.empty((7, 10)).T, "not C-contiguous"),
        ([[0.0] * 7] * 10, "a list"),
    ],
)
def test_a_bad_out_is_refused_in_one_line(out: object, why: str) -> None:
    """Wrong shape, dtype, layout or type: a ValueError naming what was expected."""
    a, b, s = hard_pairs(10, seed=1, extrapolate=False)
    with pytest.raises(ValueError, match=r"expected `out` to be a writeable C-contiguous float64"):
        interp.soa(a, b, s, out=out)  # type: ignore[arg-type]


def test_read_only_out_is_refused() -> None:
    """An array the caller cannot write is refused, not silently copied."""
    a, b, s = hard_pairs(10, seed=1, extrapolate=False)
    res = np.empty((10, 7))
    res.flags.writeable = False
    with pytest.raises(ValueError, match="writeable"):
        interp.motor_lerp(a, b, s, out=res)


@pytest.mark.parametrize("name", NAMES)
def test_with_out_a_batch_call_allocates_almost_nothing(name: str) -> None:
    """At batch 10k the traced peak with ``out`` is numpy's iteration buffers of a few
    broadcasting calls (under 192 kB; the result alone would be 560 kB)."""
    rng = np.random.default_rng(11)
    q = rng.normal(size=(20_000, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    p = np.concatenate([rng.uniform(-3.0, 3.0, (20_000, 3)), q], axis=1)
    a, b, s = p[:10_000], p[10_000:], rng.uniform(0.0, 1.0, 10_000)
    f, res = interp.get(name), np.empty((10_000, 7))
    f(a, b, s, out=res)  # the thread's scratch exists from here on
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        f(a, b, s, out=res)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 192 * 1024 < res.nbytes, peak
