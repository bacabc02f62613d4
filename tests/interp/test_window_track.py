"""Window interpolators of any size through the registry and the keyframe-track evaluator.

The probes (``tests/window_probe.py``) are registered window methods with 2/2 and
0/3 neighbours whose output is a known function of every keyframe and time of
their window; a direct per-query loop applying the registry's rule for missing
neighbours says what the batched evaluator must return.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from numpy.typing import ArrayLike, NDArray
from window_probe import Probe, expected, probes  # noqa: F401

from posecast import interp
from posecast.interp import registry

F64 = NDArray[np.float64]


def track(k: int = 9, streams: int = 3, seed: int = 0) -> tuple[F64, F64]:
    rng = np.random.default_rng(seed)
    times = np.cumsum(rng.uniform(0.05, 0.2, k))
    pos = rng.uniform(-2.0, 2.0, (k, streams, 3))
    q = rng.normal(size=(k, streams, 4))
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    return times, np.concatenate([pos, q], axis=-1)


def loop_window(times: F64, t: float, lb: int, la: int) -> list[int]:
    """The window of query ``t`` in a complete track, by the registry's rule, one at a time."""
    k = len(times)
    below = [i for i in range(k) if times[i] <= t]
    if not below:
        lo = hi = 0  # before the track: hold the first keyframe
    elif below[-1] == k - 1:
        lo = hi = k - 1  # on or after the last keyframe
    else:
        lo, hi = below[-1], below[-1] + 1
    before = [lo] * lb
    for j in range(lb - 1, -1, -1):  # nearest first, outwards
        inward = before[j + 1] if j + 1 < lb else lo
        before[j] = inward - 1 if inward > 0 else inward
    after = []
    for _ in range(la):
        inward = after[-1] if after else hi
        after.append(inward + 1 if (hi > lo and inward + 1 < k) else inward)
    return [*before, lo, hi, *after]


def queries(times: F64) -> F64:
    """Before the track, on and between the first, middle and last keyframes, after it."""
    mids = 0.5 * (times[:-1] + times[1:])
    return np.sort(
        np.concatenate([[times[0] - 0.1, times[-1] + 0.1], times, mids, times[:-1] + 0.01])
    )


@pytest.mark.parametrize("name", ["probe-2-2", "probe-0-3"])
def test_track_gathers_any_window_size_in_one_call(name: str, probes: dict[str, Probe]) -> None:  # noqa: F811
    """evaluate_track equals a per-query, per-stream loop at both ends and in the middle."""
    probe = probes[name]
    times, poses = track()
    q = queries(times)
    result = interp.evaluate_track(times, poses, q, name)
    assert probe.calls == [((q.size, 3, probe.size, 7), (q.size, 3, probe.size), (q.size, 3))]
    for i, t in enumerate(q):
        win = loop_window(times, float(t), probe.lookbehind, probe.lookahead)
        tq = float(np.clip(t, times[0], times[-1]))
        for s in range(poses.shape[1]):
            want = expected(probe, poses[:, s], times, win, tq)
            np.testing.assert_allclose(result.poses[i, s], want, rtol=0, atol=1e-12)


def test_loop_window_rule_examples() -> None:
    """The loop's rule on a 5-keyframe track, spelled out."""
    times = np.arange(5.0)
    assert loop_window(times, 0.5, 2, 2) == [0, 0, 0, 1, 2, 3]
    assert loop_window(times, 1.5, 2, 2) == [0, 0, 1, 2, 3, 4]
    assert loop_window(times, 2.5, 2, 2) == [0, 1, 2, 3, 4, 4]
    assert loop_window(times, 3.5, 2, 2) == [1, 2, 3, 4, 4, 4]
    assert loop_window(times, 9.0, 2, 2) == [2, 3, 4, 4, 4, 4]
    assert loop_window(times, -1.0, 0, 3) == [0, 0, 0, 0, 0]


def test_window_indices_follow_the_rule() -> None:
    """interp.window_indices: adjacent keyframes, repeats past the ends and after a hold."""
    before, after = interp.window_indices([0, 3, 4, 4], [1, 4, 5, 4], 6, 2, 3)
    np.testing.assert_array_equal(before, [[0, 0], [1, 2], [2, 3], [2, 3]])
    np.testing.assert_array_equal(after, [[2, 3, 4], [5, 5, 5], [5, 5, 5], [4, 4, 4]])
    assert before.shape == (4, 2) and after.shape == (4, 3)
    b0, a0 = interp.window_indices([1], [2], 4, 0, 0)
    assert b0.shape == (1, 0) and a0.shape == (1, 0)


def test_motor_quintic_on_a_track_matches_its_windows() -> None:
    """The built-in 6-keyframe method through evaluate_track equals direct window calls."""
    times, poses = track(k=8, streams=2, seed=4)
    q = queries(times)
    result = interp.evaluate_track(times, poses, q, "motor-quintic")
    for i, t in enumerate(q):
        win = loop_window(times, float(t), 2, 2)
        tq = float(np.clip(t, times[0], times[-1]))
        for s in range(2):
            want = interp.motor_quintic(poses[win, s], times[win], tq)
            np.testing.assert_array_equal(result.poses[i, s], want)


def test_brackets_take_explicit_neighbours_per_stream(probes: dict[str, Probe]) -> None:  # noqa: F811
    """Per-stream brackets with wider ``before``/``after`` use the nearest lookbehind/lookahead."""
    probe = probes["probe-2-2"]
    times, poses = track(k=10, streams=2)
    lo = np.array([[4, 5]])
    hi = lo + 1
    s = np.array([[0.25, 0.5]])
    # Three before (oldest first), three after (nearest first); streams differ.
    before = np.array([[[0, 2, 3], [1, 3, 4]]])
    after = np.array([[[7, 9, 9], [7, 8, 9]]])
    out = interp.interpolate_brackets(
        poses, lo, hi, s, probe.name, times=times, before=before, after=after
    )
    assert out.shape == (1, 2, 7)
    for j, (b, a) in enumerate((([2, 3], [7, 9]), ([3, 4], [7, 8]))):
        win = [*b, int(lo[0, j]), int(hi[0, j]), *a]
        t = times[lo[0, j]] + s[0, j] * (times[hi[0, j]] - times[lo[0, j]])
        np.testing.assert_allclose(
            out[0, j], expected(probe, poses[:, j], times, win, t), atol=1e-12
        )


def test_prev_nxt_shorthand_still_serves_one_neighbour_windows() -> None:
    """motor-cubic with prev/nxt equals the same call with before/after."""
    times, poses = track()
    lo, hi, s = np.array([1, 4]), np.array([2, 5]), np.array([0.3, 0.7])
    via_prev = interp.interpolate_brackets(
        poses, lo, hi, s, "motor-cubic", times=times, prev=lo - 1, nxt=hi + 1
    )
    via_window = interp.interpolate_brackets(
        poses, lo, hi, s, "motor-cubic", times=times, before=lo[:, None] - 1, after=hi[:, None] + 1
    )
    np.testing.assert_array_equal(via_prev, via_window)


def test_window_neighbour_errors_are_clear(probes: dict[str, Probe]) -> None:  # noqa: F811
    """Too few neighbours, a one-neighbour shorthand for a wide window, bad indices: ValueError."""
    times, poses = track()
    lo, hi, s = np.array([3]), np.array([4]), np.array([0.5])
    name = "probe-2-2"
    with pytest.raises(ValueError, match=r"needs 2 keyframes before the bracket; `prev`"):
        interp.interpolate_brackets(poses, lo, hi, s, name, times=times, prev=lo - 1)
    with pytest.raises(ValueError, match=r"needs 2 keyframe\(s\) after the bracket"):
        interp.interpolate_brackets(poses, lo, hi, s, name, times=times, after=np.array([[5]]))
    with pytest.raises(ValueError, match=r"window keyframe indices in \[0, 9\)"):
        interp.interpolate_brackets(poses, lo, hi, s, name, times=times, before=np.array([[-1, 2]]))
    with pytest.raises(ValueError, match="needs keyframe `times`"):
        interp.interpolate_brackets(poses, lo, hi, s, name)


# --- registry ---------------------------------------------------------------------------


def _window_fn(keys: ArrayLike, times: ArrayLike, t: ArrayLike) -> F64:
    return np.asarray(keys, dtype=np.float64)[..., 0, :]


def test_register_records_window_sizes(monkeypatch: pytest.MonkeyPatch) -> None:
    """lookbehind/lookahead are stored; window methods default to 1/1, others to 0/0."""
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    interp.register("w-0-3", _window_fn, kind="window", lookbehind=0, lookahead=3)
    interp.register("w-default", _window_fn, kind="window")
    assert (interp.info("w-0-3").lookbehind, interp.info("w-0-3").lookahead) == (0, 3)
    assert interp.info("w-0-3").window_size == 5
    assert (interp.info("w-default").lookbehind, interp.info("w-default").lookahead) == (1, 1)
    assert interp.info("motor-cubic").window_size == 4
    assert (interp.info("soa").lookbehind, interp.info("soa").lookahead) == (0, 0)
    assert interp.info("soa").window_size == 2


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"kind": "window", "lookbehind": -1}, "lookbehind must be a non-negative int"),
        ({"kind": "window", "lookahead": 1.5}, "lookahead must be a non-negative int"),
        ({"kind": "window", "lookahead": True}, "lookahead must be a non-negative int"),
        ({"kind": "window", "lookahead": 17}, "lookahead must be at most 16"),
        ({"kind": "pair", "lookahead": 1}, "only window interpolators take neighbours"),
        ({"kind": "velocity", "lookbehind": 2}, "only window interpolators take neighbours"),
    ],
)
def test_register_rejects_bad_window_sizes(
    monkeypatch: pytest.MonkeyPatch, kwargs: dict[str, object], message: str
) -> None:
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    with pytest.raises(ValueError, match=message):
        interp.register("bad", _window_fn, **kwargs)  # type: ignore[arg-type]
    assert "bad" not in registry._REGISTRY


class _EntryPoint:
    def __init__(self, name: str, obj: Callable[..., F64]) -> None:
        self.name, self.value, self.obj = name, f"plugin:{name}", obj

    def load(self) -> Callable[..., F64]:
        return self.obj


def test_entry_points_declare_window_sizes(monkeypatch: pytest.MonkeyPatch) -> None:
    """A plug-in's posecast_lookbehind/posecast_lookahead attributes set its window."""
    from types import SimpleNamespace

    def wide(keys: ArrayLike, times: ArrayLike, t: ArrayLike) -> F64:
        return _window_fn(keys, times, t)

    wide.posecast_kind = "window"  # type: ignore[attr-defined]
    wide.posecast_lookbehind = 3  # type: ignore[attr-defined]
    wide.posecast_lookahead = 2  # type: ignore[attr-defined]

    def plain(keys: ArrayLike, times: ArrayLike, t: ArrayLike) -> F64:
        return _window_fn(keys, times, t)

    plain.posecast_kind = "window"  # type: ignore[attr-defined]
    eps = [_EntryPoint("wide", wide), _EntryPoint("plain", plain)]
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    monkeypatch.setattr(registry, "_entry_points_loaded", False)
    monkeypatch.setattr(registry, "metadata", SimpleNamespace(entry_points=lambda *, group: eps))
    assert (interp.info("wide").lookbehind, interp.info("wide").lookahead) == (3, 2)
    assert (interp.info("plain").lookbehind, interp.info("plain").lookahead) == (1, 1)
