"""A bot's schedule in the throw-catch scene (``client/scene.py``), on server time."""

from __future__ import annotations

import pytest

from posecast.client.scene import LEAD, ThrowCatchActor
from posecast.scenarios.throw_catch import PERIOD, scene_script

T0 = 1000.0


def test_thrower_brings_the_drill_in_at_the_first_cycle_after_its_lead() -> None:
    """Joined 0.5 s into a cycle: the first hold is the next cycle's start (LEAD = 1 s)."""
    s = scene_script(0)
    actor = ThrowCatchActor("thrower", 0, T0, T0 + 0.5)
    assert LEAD > 0.5
    # A throw of a drill it does not hold comes first, and does nothing when done.
    assert actor.next_at() == pytest.approx(T0 + s.release)
    due = actor.due(T0 + PERIOD + 0.01)
    assert [(round(at - T0, 6), a.kind) for at, a in due] == [
        (round(s.release, 6), "throw"),
        (round(s.grab, 6), "grab"),
        (PERIOD, "hold"),
    ]
    assert due[0][1].velocity is not None and due[0][1].keyframe
    assert actor.next_at() == pytest.approx(T0 + PERIOD + s.release)


def test_catcher_and_watcher_schedules() -> None:
    """The catcher catches then hands back, every cycle; a watcher never acts."""
    s = scene_script(0)
    catcher = ThrowCatchActor("catcher", 0, T0, T0 + s.catch + 0.01)  # just missed one
    due = catcher.due(T0 + 2 * PERIOD)
    assert [(round(at - T0, 6), a.kind) for at, a in due] == [
        (round(s.hand_back, 6), "hand-back"),
        (round(PERIOD + s.catch, 6), "catch"),
        (round(PERIOD + s.hand_back, 6), "hand-back"),
    ]
    assert not [a for _, a in due if a.kind == "catch" and a.keyframe]
    watcher = ThrowCatchActor("watcher", 0, T0, T0)
    assert watcher.next_at() == float("inf") and watcher.due(T0 + 10 * PERIOD) == []
    assert catcher.label == watcher.label == f"synthetic:throw-catch.drill|seed=0|t0={T0!r}"
