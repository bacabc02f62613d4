"""A bot's playout delay follows the rate an auto-rate relay chose (RoomPlayoutDelay.retime)."""

from __future__ import annotations

import pytest

from posecast.client.playout import RoomPlayoutDelay


def test_retime_scales_every_interval_with_the_new_rate() -> None:
    """From 30 to 10 Hz the interval D covers triples, for the room and each user."""
    delay = RoomPlayoutDelay(interval=2.0 / 30.0, rate=30.0)
    for age in (0.05, 0.06, 0.07):
        delay.observe(1, age)
    delay.update(0.0)
    delay.retime(10.0)
    assert delay.rate == 10.0
    assert delay.interval == pytest.approx(0.2)
    assert delay.room.interval == pytest.approx(0.2)
    assert delay._users[1].interval == pytest.approx(0.2)
    before = delay.update(0.01)
    assert delay.update(10.0) > before  # D slews up towards the longer target


def test_retime_without_a_rate_changes_nothing() -> None:
    """A delay built without its rate (a fixed-rate client) ignores retime."""
    delay = RoomPlayoutDelay(interval=0.1)
    delay.retime(5.0)
    assert delay.interval == 0.1 and delay.rate is None
