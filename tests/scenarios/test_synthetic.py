"""Synthetic motions: exactness fixtures, determinism, physical plausibility, parameters."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from posecast.interp import evaluate_track, quat_conj, quat_mul, quat_rotate
from posecast.scenarios.motion import SYNTHETIC_MOTIONS, MotionSpec
from posecast.scenarios.qoe import sample_keyframes
from posecast.scenarios.synthetic import (
    NATIVE_RATE,
    load_params,
    load_suite,
    motion_names,
    suite_traces,
    synthetic_motion,
)
from posecast.scenarios.traces import Trace, TraceError

RATES = [5.0, 7.3, 12.0, 30.0, 45.0]


def _max_pose_error(trace: Trace, rate: float, method: str) -> float:
    """Largest component error of ``method`` rebuilding the trace from keyframes at ``rate``."""
    _, idx = sample_keyframes(trace.times, rate)
    kt = trace.times[idx]
    inside = (trace.times >= kt[0]) & (trace.times <= kt[-1])
    shown = evaluate_track(kt, trace.poses[idx], trace.times[inside], method).poses
    truth = trace.poses[inside]
    sign = np.sign(np.einsum("...i,...i->...", shown[..., 3:], truth[..., 3:]))[..., None]
    return float(
        max(
            np.abs(shown[..., :3] - truth[..., :3]).max(),
            np.abs(shown[..., 3:] * sign - truth[..., 3:]).max(),
        )
    )


@pytest.mark.parametrize("rate", RATES)
@pytest.mark.parametrize("seed", [0, 7])
def test_constant_screw_is_exact_for_dq_slerp(rate: float, seed: int) -> None:
    """A constant twist exp(t xi) is rebuilt by dq-slerp to 1e-9 from keyframes at any rate."""
    trace = synthetic_motion("screw", seed, duration_s=10.0)
    assert _max_pose_error(trace, rate, "dq-slerp") < 1e-9


@pytest.mark.parametrize("rate", RATES)
@pytest.mark.parametrize("seed", [0, 7])
def test_spin_with_linear_translation_is_exact_for_soa(rate: float, seed: int) -> None:
    """Constant spin about the body origin plus linear drift is rebuilt by soa to 1e-9."""
    trace = synthetic_motion("spin-drift", seed, duration_s=10.0)
    assert _max_pose_error(trace, rate, "soa") < 1e-9


def test_fixtures_discriminate_between_methods() -> None:
    """Each fixture is exact only for its method: the other one errs by far more than 1e-9."""
    screw = synthetic_motion("screw", 1, duration_s=10.0)
    spin = synthetic_motion("spin-drift", 1, duration_s=10.0)
    assert _max_pose_error(screw, 5.0, "soa") > 1e-4
    assert _max_pose_error(spin, 5.0, "dq-slerp") > 1e-4


@pytest.mark.parametrize("name", motion_names())
def test_same_seed_gives_the_same_trace(name: str) -> None:
    """Every motion is a pure function of its parameters and seed."""
    a = synthetic_motion(name, 3, duration_s=8.0)
    b = synthetic_motion(name, 3, duration_s=8.0)
    c = synthetic_motion(name, 4, duration_s=8.0)
    assert a.name == b.name and a.streams == b.streams
    np.testing.assert_array_equal(a.times, b.times)
    np.testing.assert_array_equal(a.poses, b.poses)
    assert not np.array_equal(a.poses, c.poses)


@pytest.mark.parametrize("name", motion_names())
def test_motions_are_90hz_unit_and_sign_continuous(name: str) -> None:
    """Samples at 90 Hz from 0, finite, unit quaternions, sign-continuous like real traces."""
    tr = synthetic_motion(name, 0, duration_s=6.0)
    np.testing.assert_allclose(np.diff(tr.times), 1.0 / NATIVE_RATE, rtol=1e-9)
    assert tr.times[0] == 0.0 and tr.poses.shape == (tr.times.size, len(tr.streams), 7)
    assert np.all(np.isfinite(tr.poses))
    np.testing.assert_allclose(np.linalg.norm(tr.poses[..., 3:], axis=-1), 1.0, atol=1e-12)
    dots = np.einsum("nsi,nsi->ns", tr.poses[1:, :, 3:], tr.poses[:-1, :, 3:])
    assert np.all(dots >= 0)


def test_object_streams_are_named() -> None:
    """throw-catch carries object:ball and drill carries object:drill after the three devices."""
    assert synthetic_motion("throw-catch", 0, duration_s=3).streams == (
        "head",
        "left",
        "right",
        "object:ball",
    )
    assert synthetic_motion("drill", 0, duration_s=3).streams[-1] == "object:drill"
    assert synthetic_motion("reach-grasp", 0, duration_s=3).streams == ("head", "left", "right")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ball_is_thrown_caught_and_never_jumps(seed: int) -> None:
    """The ball moves continuously, spends time in flight, and is held by a hand otherwise."""
    tr = synthetic_motion("throw-catch", seed, duration_s=30.0)
    ball = tr.poses[:, 3, :3]
    step = np.linalg.norm(np.diff(ball, axis=0), axis=-1)
    assert step.max() < 6.0 / NATIVE_RATE  # under 6 m/s
    to_hand = np.minimum(
        np.linalg.norm(ball - tr.poses[:, 1, :3], axis=-1),
        np.linalg.norm(ball - tr.poses[:, 2, :3], axis=-1),
    )
    held = to_hand < 0.1
    assert 0.5 < held.mean() < 0.95
    assert np.count_nonzero(np.diff(held.astype(int)) == -1) >= 5  # several releases


def test_ball_flies_ballistically() -> None:
    """Away from both hands the ball accelerates at g = 9.81 m/s^2 straight down."""
    tr = synthetic_motion("throw-catch", 0, duration_s=30.0)
    ball = tr.poses[:, 3, :3]
    to_hand = np.minimum(
        np.linalg.norm(ball - tr.poses[:, 1, :3], axis=-1),
        np.linalg.norm(ball - tr.poses[:, 2, :3], axis=-1),
    )
    far = to_hand > 0.25
    inner = far[:-2] & far[1:-1] & far[2:]
    acc = (ball[2:] - 2 * ball[1:-1] + ball[:-2]) * NATIVE_RATE**2
    assert inner.sum() > 50
    np.testing.assert_allclose(acc[inner], np.tile([0.0, -9.81, 0.0], (inner.sum(), 1)), atol=1e-6)


def test_drill_spins_about_its_own_axis_in_the_hand() -> None:
    """In the hand's frame the drill only turns about its local z, at spin_rps."""
    tr = synthetic_motion("drill", 0, duration_s=5.0, params={"spin_rps": 1.5})
    hand, drill = tr.poses[:, 2], tr.poses[:, 3]
    rel_q = quat_mul(quat_conj(hand[:, 3:]), drill[:, 3:])
    np.testing.assert_allclose(rel_q[:, 1:3], 0.0, atol=1e-12)  # no x/y component
    angle = np.unwrap(2 * np.arctan2(rel_q[:, 3], rel_q[:, 0]))
    np.testing.assert_allclose(np.diff(angle) * NATIVE_RATE, 2 * np.pi * 1.5, rtol=1e-9)
    offset = quat_rotate(quat_conj(hand[:, 3:]), drill[:, :3] - hand[:, :3])
    np.testing.assert_allclose(offset, np.tile([0.0, -0.02, -0.08], (len(offset), 1)), atol=1e-12)


def _in_hand_frame(hand: np.ndarray, obj: np.ndarray) -> np.ndarray:
    """The object's pose ``(N, 7)`` in the hand's frame."""
    q = quat_conj(hand[:, 3:])
    return np.concatenate([quat_rotate(q, obj[:, :3] - hand[:, :3]), quat_mul(q, obj[:, 3:])], 1)


@pytest.mark.parametrize("seed", [0, 1])
def test_tool_is_handed_over_slowly_and_always_held(seed: int) -> None:
    """hand-over: the tool never jumps, is rigidly held by one hand at every sample (its
    pose in that hand's frame constant while held) and changes hands several times."""
    tr = synthetic_motion("hand-over", seed, duration_s=40.0)
    assert tr.streams == ("head", "left", "right", "object:tool")
    tool = tr.poses[:, 3]
    step = np.linalg.norm(np.diff(tool[:, :3], axis=0), axis=-1)
    assert step.max() < 1.5 / NATIVE_RATE  # slow: under 1.5 m/s
    rel = {side: _in_hand_frame(tr.poses[:, j], tool) for side, j in (("left", 1), ("right", 2))}
    # Rigidly held: the pose in the holding hand's frame does not change from one sample
    # to the next (sign-insensitive for the quaternion).
    still = {}
    for side, r in rel.items():
        dq = np.abs(np.einsum("ni,ni->n", r[1:, 3:], r[:-1, 3:]))
        still[side] = (np.linalg.norm(np.diff(r[:, :3], axis=0), axis=-1) < 1e-9) & (dq > 1 - 1e-12)
    held_by = np.where(still["right"], 1, np.where(still["left"], -1, 0))
    assert np.all(still["left"] | still["right"])
    changes = np.count_nonzero(np.diff(held_by[held_by != 0]) != 0)
    assert changes >= 4


def test_drill_toss_throws_a_drill_ballistically() -> None:
    """drill-toss is throw-catch with object:drill: continuous, and in flight it falls at g."""
    tr = synthetic_motion("drill-toss", 0, duration_s=30.0)
    assert tr.streams[-1] == "object:drill"
    drill = tr.poses[:, 3, :3]
    assert np.linalg.norm(np.diff(drill, axis=0), axis=-1).max() < 6.0 / NATIVE_RATE
    to_hand = np.minimum(
        np.linalg.norm(drill - tr.poses[:, 1, :3], axis=-1),
        np.linalg.norm(drill - tr.poses[:, 2, :3], axis=-1),
    )
    far = to_hand > 0.3
    inner = far[:-2] & far[1:-1] & far[2:]
    acc = (drill[2:] - 2 * drill[1:-1] + drill[:-2]) * NATIVE_RATE**2
    assert inner.sum() > 20
    np.testing.assert_allclose(acc[inner], np.tile([0.0, -9.81, 0.0], (inner.sum(), 1)), atol=1e-6)


def test_a_string_parameter_must_be_a_string() -> None:
    """thing names the tossed object; a number there is refused with a clear error."""
    assert synthetic_motion("throw-catch", 0, duration_s=2, params={"thing": "cup"}).streams[
        -1
    ] == ("object:cup")
    with pytest.raises(TraceError, match="expected a string"):
        synthetic_motion("throw-catch", 0, duration_s=2, params={"thing": 3})


def test_reaching_hands_stay_within_arm_length() -> None:
    """Hands are two-link arms: never further than 0.6 m from their shoulder."""
    tr = synthetic_motion("reach-grasp", 2, duration_s=30.0)
    for j, side in ((1, -1.0), (2, 1.0)):
        d = np.linalg.norm(tr.poses[:, j, :3] - np.array([side * 0.19, 1.42, 0.0]), axis=-1)
        assert d.max() <= 0.6 + 1e-9
        assert np.ptp(tr.poses[:, j, 1]) > 0.2  # the hands really reach


def test_params_come_from_toml_and_unknown_names_fail(tmp_path: Path) -> None:
    """load_params reads one table per motion; overrides change the motion; typos are errors."""
    f = tmp_path / "params.toml"
    f.write_text("[drill]\nspin_rps = 0.5\ndepth_m = [0.01, 0.02]\n")
    params = load_params(f)
    assert params == {"drill": {"spin_rps": 0.5, "depth_m": [0.01, 0.02]}}
    slow = synthetic_motion("drill", 0, duration_s=3.0, params=params["drill"])
    fast = synthetic_motion("drill", 0, duration_s=3.0)
    assert not np.array_equal(slow.poses[:, 3], fast.poses[:, 3])
    bad = tmp_path / "bad.toml"
    bad.write_text("[drill]\nspin_rsp = 0.5\n")
    with pytest.raises(TraceError, match="spin_rsp"):
        load_params(bad)
    with pytest.raises(TraceError, match="unknown synthetic motion"):
        synthetic_motion("juggle")


def test_suites_load_from_the_package_and_from_files(tmp_path: Path) -> None:
    """The packaged suite lists the four realistic motions; a user suite file is honoured."""
    assert [e.motion for e in load_suite()] == [
        "reach-grasp",
        "throw-catch",
        "drill",
        "look-around",
    ]
    f = tmp_path / "suite.toml"
    f.write_text(
        'duration_s = 4.0\n[[scenario]]\nmotion = "drill"\nseeds = [5]\n'
        "[scenario.params]\nspin_rps = 1.0\n"
    )
    (trace,) = suite_traces(f)
    assert trace.name == "synthetic-drill-5" and trace.duration == pytest.approx(4.0)


def test_motion_spec_plays_registered_synthetic_motions() -> None:
    """Bots can name the new motions: MotionSpec('synthetic:NAME', seed) loads them."""
    assert {"orbit", *motion_names()} == set(SYNTHETIC_MOTIONS)
    tr = MotionSpec("synthetic:throw-catch", 2, 5.0).load()
    assert tr.name == "synthetic-throw-catch-2" and "object:ball" in tr.streams
