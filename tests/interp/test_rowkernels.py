"""The compiled render kernels (``interp/_rowkernels.c``) against the numpy ones.

:mod:`interp.accel` runs them where they are built; the numpy row kernels of
:mod:`interp.kernels` are the reference. Each case here runs both on the same
rows: the same poses to float rounding (the elementary functions may be other
libraries'), the keyframes bit for bit at ``s`` 0 and 1, and the same brackets
exactly.
"""

from __future__ import annotations

import os
import subprocess
import sys
from types import ModuleType

import numpy as np
import pytest
from numpy.typing import NDArray

from posecast.interp import accel
from posecast.interp.kernels import COMPILED_KIND, dq_slerp_rows, motor_lerp_rows, soa_rows

F64 = NDArray[np.float64]
KERNELS = [soa_rows, motor_lerp_rows, dq_slerp_rows]
#: Poses within float rounding: metres and unit quaternions.
ATOL = 1e-12


@pytest.fixture
def ck() -> ModuleType:
    module = accel.compiled()
    if module is None:
        pytest.skip(f"the render kernels are not built here: {accel.IMPLEMENTATION}")
    return module


def random_poses(rng: np.random.Generator, m: int) -> F64:
    """``(7, m)`` rows: positions within 2 m, uniform unit quaternions."""
    q = rng.normal(size=(4, m))
    q /= np.linalg.norm(q, axis=0)
    return np.vstack([rng.uniform(-2.0, 2.0, (3, m)), q])


def hard_pairs(rng: np.random.Generator) -> tuple[F64, F64]:
    """Rows that take the kernels' other branches: equal and opposite quaternions
    (zero angle), exact half turns (``q0.q1 == 0``), tiny rotations, equal positions."""
    a = random_poses(rng, 8)
    b = random_poses(rng, 8)
    b[:, 0] = a[:, 0]  # the same pose
    b[3:, 1] = -a[3:, 1]  # the same rotation, other sign
    b[3:, 2] = [0.0, 1.0, 0.0, 0.0]  # a half turn from the identity
    a[3:, 2] = [1.0, 0.0, 0.0, 0.0]
    a[3:, 3], b[3:, 3] = [0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 1.0, 0.0]  # half turn, tie
    tiny = np.array([1.0, 1e-9, 0.0, 0.0])
    b[3:, 4] = tiny / np.linalg.norm(tiny)
    a[3:, 4] = [1.0, 0.0, 0.0, 0.0]
    b[:3, 5] = a[:3, 5]
    return a, b


def numpy_rows(kernel: object, a: F64, b: F64, s: F64) -> F64:
    """The numpy kernel's ``(m, 7)`` poses, as the render calls it."""
    out = np.empty((7, s.shape[0]))
    unit = bool(np.all((s >= 0.0) & (s <= 1.0)))
    kernel(a, b, s, out, None, unit)  # type: ignore[operator]
    return out.T


def compiled_rows(ck: ModuleType, kernel: object, a: F64, b: F64, s: F64) -> F64:
    """The compiled kernel on the same rows: ``a`` and ``b`` as slots of one table."""
    m = s.shape[0]
    poses = np.ascontiguousarray(np.concatenate([a, b], axis=1).T)
    lo = np.arange(m, dtype=np.intp)
    out = np.empty((m, 7))
    ck.pair_rows(COMPILED_KIND[kernel], poses, lo, lo + m, s, out)  # type: ignore[index]
    return out


@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: k.__name__)
def test_pair_rows_equal_the_numpy_kernels(ck: ModuleType, kernel: object) -> None:
    """Random poses at random fractions, and the hard rows at 0, 1/3, 1/2 and 1."""
    rng = np.random.default_rng(7)
    a, b = random_poses(rng, 500), random_poses(rng, 500)
    s = rng.uniform(0.0, 1.0, 500)
    s[:5] = [0.0, 1.0, 0.5, 1e-12, 1.0 - 1e-12]
    np.testing.assert_allclose(
        compiled_rows(ck, kernel, a, b, s), numpy_rows(kernel, a, b, s), rtol=0, atol=ATOL
    )
    ha, hb = hard_pairs(rng)
    for frac in (0.0, 1.0 / 3.0, 0.5, 1.0):
        hs = np.full(ha.shape[1], frac)
        got = compiled_rows(ck, kernel, ha, hb, hs)
        want = numpy_rows(kernel, ha, hb, hs)
        np.testing.assert_allclose(got, want, rtol=0, atol=ATOL, err_msg=f"s = {frac}")
        assert np.all(np.isfinite(got))
    at0 = compiled_rows(ck, kernel, a, b, np.zeros(500))
    at1 = compiled_rows(ck, kernel, a, b, np.ones(500))
    np.testing.assert_array_equal(at0, a.T)  # the keyframes bit for bit
    np.testing.assert_array_equal(at1, b.T)


@pytest.mark.parametrize("kernel", KERNELS, ids=lambda k: k.__name__)
def test_pair_rows_extrapolate_as_the_numpy_kernels(ck: ModuleType, kernel: object) -> None:
    """Fractions outside [0, 1] (plain sine and cosine) agree too."""
    rng = np.random.default_rng(11)
    a, b = random_poses(rng, 200), random_poses(rng, 200)
    s = rng.uniform(-0.5, 1.5, 200)
    np.testing.assert_allclose(
        compiled_rows(ck, kernel, a, b, s), numpy_rows(kernel, a, b, s), rtol=0, atol=1e-11
    )


def numpy_brackets(
    times: F64, counts: NDArray[np.intp], t: F64
) -> tuple[list[int], list[int], list[float], list[bool]]:
    """Each row's bracket by the rule of ``StreamBuffer.bracket``, as flat slots."""
    lo_, hi_, s_, st_ = [], [], [], []
    w = times.shape[1]
    for row, (c, tt) in enumerate(zip(counts, t, strict=True)):
        ts = times[row, :c]
        after = int(np.searchsorted(ts, tt, side="right"))
        lo = c - 1 if after == 0 else after - 1
        on = ts[lo] == tt
        held = lo == c - 1 or on
        hi = lo if held else lo + 1
        s = 0.0 if held else (tt - ts[lo]) / (ts[hi] - ts[lo])
        lo_.append(row * w + lo)
        hi_.append(row * w + hi)
        s_.append(s)
        st_.append(bool(lo == c - 1 and not on))
    return lo_, hi_, s_, st_


def test_bracket_rows_follow_the_buffer_rule(ck: ModuleType) -> None:
    """Before the first keyframe, between, exactly on one, past the newest: every row
    at its own time, and all at one time."""
    rng = np.random.default_rng(3)
    rows, w = 60, 13
    times = np.full((rows, w), np.inf)
    counts = rng.integers(1, w, rows).astype(np.intp)
    for r, c in enumerate(counts):
        times[r, :c] = np.sort(rng.uniform(0.0, 1.0, c))
    t = rng.uniform(-0.1, 1.1, rows)
    t[:4] = [times[0, 0], times[1, counts[1] - 1], -1.0, 2.0]  # on the first, on the newest
    base = np.arange(rows, dtype=np.intp) * w
    newest = base + counts - 1
    lo, hi = np.empty(rows, np.intp), np.empty(rows, np.intp)
    s, stalled = np.empty(rows), np.empty(rows, bool)
    # lo on entry is where each row's search starts: any value gives the same bracket.
    hints = [np.full(rows, -7), rng.integers(0, rows * w, rows), base, newest, newest + 1]
    for tt in (t, np.full(rows, 0.5), t + 0.02, t - 0.3):
        want = numpy_brackets(times, counts, tt)
        for hint in [*hints, np.array(want[0]) + 1, np.array(want[0]) - 1, np.array(want[0])]:
            lo[:] = hint
            ends = ck.bracket_rows(times.reshape(-1), base, newest, tt, lo, hi, s, stalled)
            assert (lo.tolist(), hi.tolist(), s.tolist(), stalled.tolist()) == want
            assert ends == bool(np.any(lo == hi) or np.any(s == 1.0))
    ck.bracket_rows(times.reshape(-1), base, newest, 0.5, lo, hi, s, stalled)  # a float
    assert (lo.tolist(), hi.tolist(), s.tolist(), stalled.tolist()) == numpy_brackets(
        times, counts, np.full(rows, 0.5)
    )


def test_bad_arguments_are_refused(ck: ModuleType) -> None:
    """Wrong dtypes, shapes or slots raise, and nothing is read out of bounds."""
    poses = np.zeros((4, 7))
    poses[:, 3] = 1.0
    lo, out = np.zeros(2, np.intp), np.empty((2, 7))
    s = np.zeros(2)
    with pytest.raises(IndexError, match=r"slot out of 0\.\.3"):
        ck.pair_rows(0, poses, lo, lo + 4, s, out)
    with pytest.raises(TypeError, match="float64"):
        ck.pair_rows(0, poses.astype(np.float32), lo, lo, s, out)
    with pytest.raises(TypeError, match="C-contiguous"):
        ck.pair_rows(0, poses, lo, lo, s, np.empty((7, 2)).T)
    with pytest.raises(ValueError, match="unknown pair kind 9"):
        ck.pair_rows(9, poses, lo, lo, s, out)
    times, st = np.array([0.0, 1.0, np.inf]), np.empty(2, bool)
    base, newest = np.zeros(2, np.intp), np.array([1, 3], np.intp)
    with pytest.raises(ValueError, match="row 1 has no keyframes"):
        ck.bracket_rows(times, base, newest, 0.5, lo, lo.copy(), s, st)


def test_the_switch_and_the_environment() -> None:
    """``use`` switches a running process; ``POSECAST_PURE=1`` starts on numpy."""
    was_pure = accel.kernels is None
    try:
        assert accel.use(True) == "numpy (POSECAST_PURE=1)" and accel.kernels is None
        accel.use(False)
        assert accel.kernels is accel.compiled()
    finally:
        accel.use(was_pure)
    probe = "from posecast.interp import accel; print(accel.kernels is None, accel.IMPLEMENTATION)"
    env = {**os.environ, "POSECAST_PURE": "1"}
    got = subprocess.run(
        [sys.executable, "-c", probe], env=env, capture_output=True, text=True, check=True
    )
    assert got.stdout.strip() == "True numpy (POSECAST_PURE=1)"
