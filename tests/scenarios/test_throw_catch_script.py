"""The live throw-catch scene's script (``scenarios/throw_catch.py``): one cycle, its truth.

The script is checked against the relay's own flight law (``server.objects.Flight``,
an independent implementation), for continuity, for periodicity (the thrower takes
the drill back with the grip it started with) and for the reach of the arms.
"""

from __future__ import annotations

import numpy as np
import pytest

from posecast.client.bot import motion_for_bot
from posecast.interp import rotation_error_deg
from posecast.scenarios.motion import MotionSpec, synthetic_trace
from posecast.scenarios.qoe import KeyframeLog
from posecast.scenarios.synthetic_body import _pose_inv, _pose_mul
from posecast.scenarios.throw_catch import (
    CATCH_WINDOW,
    DRILL,
    PERIOD,
    drill_label,
    role_motion,
    scene_epoch,
    scene_role,
    scene_script,
    score_drill,
)
from posecast.scenarios.traces import TraceError
from posecast.server.objects import Flight

SEEDS = (0, 1, 7)


@pytest.mark.parametrize("seed", SEEDS)
def test_flight_is_the_relays_ballistic_law(seed: int) -> None:
    """Between release and catch the drill is exactly where the relay flies it."""
    s = scene_script(seed)
    i0 = round(s.release * 90)
    flight = Flight(s.release, tuple(s.drill[i0]), tuple(s.velocity), tuple(s.angular), floor=0.0)
    inside = (s.times >= s.release) & (s.times < s.catch)
    assert inside.sum() > 20  # a real throw (over 0.2 s of flight)
    for t, pose in zip(s.times[inside], s.drill[inside], strict=True):
        expected, _, landed = flight.at(float(t))
        assert not landed
        assert np.abs(pose[:3] - expected[:3]).max() < 1e-9
        assert rotation_error_deg(pose, np.array(expected)) < 1e-6
    # The release velocity is the hand's: the drill leaves the hand without a jump.
    step = np.linalg.norm(s.drill[i0 + 1, :3] - s.drill[i0, :3]) * 90
    assert abs(step - np.linalg.norm(s.velocity)) < 0.2 * np.linalg.norm(s.velocity)
    assert np.linalg.norm(s.angular) > 1.0  # it tumbles (rad/s)


@pytest.mark.parametrize("seed", SEEDS)
def test_drill_is_continuous_and_the_cycle_closes(seed: int) -> None:
    """No jump but the catch's stop; the thrower ends each cycle as it began it."""
    s = scene_script(seed)
    speed = np.linalg.norm(np.diff(s.drill[:, :3], axis=0), axis=1) * 90
    assert speed.max() < 6.0  # m/s: arm and throw speeds, never a teleport
    # At rest in the hand across the wrap from one cycle to the next.
    assert np.linalg.norm(s.drill[-1, :3] - s.drill[0, :3]) < 1e-9
    for role in ("thrower", "catcher", "watcher"):
        body = s.bodies[role]
        assert np.linalg.norm(body[-1, :, :3] - body[0, :, :3], axis=1).max() < 1e-9


@pytest.mark.parametrize("seed", SEEDS)
def test_hands_reach_the_drill_at_catch_and_grab(seed: int) -> None:
    """The catcher's hand is at the drill at the catch; the thrower regrips as at 0."""
    s = scene_script(seed)
    ic, ig, ih = (round(t * 90) for t in (s.catch, s.grab, s.hand_back))
    catcher, thrower = s.bodies["catcher"][:, 2], s.bodies["thrower"][:, 2]
    grip0 = _pose_mul(_pose_inv(thrower[0]), s.drill[0])
    grip_g = _pose_mul(_pose_inv(thrower[ig]), s.drill[ig])
    assert np.abs(grip_g[:3] - grip0[:3]).max() < 1e-9
    assert rotation_error_deg(grip_g, grip0) < 1e-6
    assert 0.09 < np.linalg.norm(catcher[ic, :3] - s.drill[ic, :3]) < 0.11  # in its grip
    # At rest from the hand-back to the grab, in the middle between them.
    assert np.abs(s.drill[ih:ig] - s.drill[ih]).max() == 0.0
    assert abs(s.drill[ih, 2] - (-0.45)) < 0.05
    assert s.release < s.catch < s.hand_back < s.grab < PERIOD


def test_windows_tile_the_cycles() -> None:
    """Flight and catch windows of a span: one per cycle, clipped to the span."""
    s = scene_script(0)
    t0 = 400.0
    flights = s.windows("flight", (t0, t0 + 3 * PERIOD), t0)
    assert flights == [
        pytest.approx((t0 + k * PERIOD + s.release, t0 + k * PERIOD + s.catch)) for k in range(3)
    ]
    catches = s.windows("catch", (t0 + s.catch, t0 + PERIOD + s.catch + 1.0), t0)
    assert [b - a for a, b in catches] == pytest.approx([CATCH_WINDOW[1], sum(CATCH_WINDOW)])


def test_roles_labels_and_bots() -> None:
    """Bot 0 throws, bot 1 catches, others watch, all on one seed; labels rebuild truth."""
    assert [role_motion(i) for i in range(4)] == [
        "throw-catch.thrower",
        "throw-catch.catcher",
        "throw-catch.watcher",
        "throw-catch.watcher",
    ]
    assert [motion_for_bot("throw-catch", i) for i in range(3)] == [
        ("synthetic:throw-catch.thrower", 0),
        ("synthetic:throw-catch.catcher", 0),
        ("synthetic:throw-catch.watcher", 0),
    ]
    assert scene_role("throw-catch.drill") == "drill" and scene_role("throw-catch") is None
    assert scene_epoch(9.5) == 8.0 and scene_epoch(8.0) == 8.0
    truth = MotionSpec.parse(drill_label(0, 8.0)).truth(until=8.0 + 2.5 * PERIOD)
    assert truth.streams == (DRILL,) and truth.times[0] == 8.0
    assert np.abs(truth.poses[360:720] - truth.poses[:360]).max() == 0.0  # it loops
    with pytest.raises(TraceError, match=r"throw-catch\.thrower"):
        synthetic_trace("throw-catch.juggler")


def test_score_drill_ideal_is_exact_and_10_hz_is_not() -> None:
    """Every sample as a keyframe at once: no error; 10 Hz keyframes: error in flight."""
    t0 = 100.0
    truth = MotionSpec.parse(drill_label(0, t0)).truth(until=t0 + 2 * PERIOD)
    s = scene_script(0)
    span = (t0, t0 + 2 * PERIOD - 0.2)

    def score(step: int) -> dict[str, float]:
        cap = truth.times[::step]
        log = KeyframeLog(cap, cap.copy(), truth.poses[::step])
        res = score_drill(truth, log, lambda tau: np.full_like(tau, 0.2), ["soa"], span, s, t0)
        return {cls: samples.stats()["tip_p95_mm"] for cls, samples in res["soa"].items()}

    ideal, slow = score(1), score(9)
    assert set(ideal) == set(slow) == {"object", "object-flight", "object-catch"}
    assert max(ideal.values()) < 1e-6
    assert min(slow.values()) > 1.0
