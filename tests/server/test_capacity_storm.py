"""A join storm's cost is kept apart from the members' in the relay's capacity.

Handshakes, hellos and refusals of a storm of clients cost the relay CPU and
delay its ticks, but one more member would not add to that: the adapter reports
that work (``Capacity.join_work``) and the decision keeps it out of the members'
scaling and out of the lag budget. Made-up measurements and times, no clock.
"""

from __future__ import annotations

import pytest

from posecast.server.capacity import LAG_MIN_MEMBERS, Capacity, CapacityBudget


def _measured(cpu: float, join_cpu: float, members: int) -> Capacity:
    """``cpu`` of a core over the window [0, 1] with ``members``, ``join_cpu`` of it
    spent on connections that were not members."""
    cap = Capacity(CapacityBudget(min_members=0))
    cap.sample(0.0, 100.0, 0, members)
    cap.join_work(0.2, 0.2 + join_cpu, join_cpu)
    cap.sample(1.0, 100.0 + cpu, 0, members)
    return cap


def test_join_work_is_not_scaled_as_the_members_cpu() -> None:
    """0.7 of a core with 20 members: as the members' alone, a 24th member is over 0.8
    (0.7 x 24 / 20 = 0.84); with 0.5 of it join work, the members' 0.2 scales and the
    join work stays: a 30th fits (0.2 x 30 / 20 + 0.5 = 0.8), a 31st does not."""
    plain = _measured(0.7, 0.0, 20)
    assert plain.join_share == 0.0
    assert plain.refusal(23, 1.0) is not None
    storm = _measured(0.7, 0.5, 20)
    assert storm.join_share == pytest.approx(0.5) and storm.join_cpu == pytest.approx(0.5)
    assert storm.usage(23, 1.0)["cpu"] == pytest.approx((0.2 * 24 / 20 + 0.5) / 0.8)
    assert storm.refusal(28, 1.0) is None
    assert storm.refusal(30, 1.0) is not None


def test_join_work_is_at_most_the_cpu_measured() -> None:
    """Join work reported over more CPU than the process used is capped at it."""
    cap = _measured(0.3, 0.5, 20)
    assert cap.join_share == pytest.approx(0.3)
    assert cap.usage(20, 1.0)["cpu"] == pytest.approx(0.3 / 0.8)


def test_a_tick_late_for_join_work_after_it_was_due_is_not_over_budget() -> None:
    """A tick 45 ms late of which 40 ms went to join work after it was due: on time for
    its members (5 ms), counted as late for joins; 70 ms late with the same join work:
    late (30 ms over a 25 ms budget). Join work before the tick was due excuses nothing."""
    members = LAG_MIN_MEMBERS
    cap = Capacity()
    cap.join_work(1.000, 1.040, 0.04)
    cap.tick_lag(1.045, 0.045)  # due at 1.000
    assert (cap.ticks_late, cap.ticks_late_for_joins) == (1, 1)
    assert cap.usage(members, 1.05)["lag"] == 0.0
    assert cap.refusal(members, 1.05) is None

    late = Capacity()
    late.join_work(1.000, 1.040, 0.04)
    late.tick_lag(1.070, 0.070)
    assert (late.ticks_late, late.ticks_late_for_joins) == (1, 0)
    assert late.refusal(members, 1.08) is not None

    before = Capacity()
    before.join_work(0.950, 0.990, 0.04)  # done before the tick came due at 1.000
    before.tick_lag(1.045, 0.045)
    assert (before.ticks_late, before.ticks_late_for_joins) == (1, 0)
    assert before.refusal(members, 1.05) is not None


def test_only_the_join_work_after_the_due_time_counts() -> None:
    """A span that began before the due time counts from the due time on."""
    cap = Capacity()
    cap.join_work(0.980, 1.020, 0.04)  # 20 ms of it after 1.000
    cap.tick_lag(1.040, 0.040)  # 40 ms late, 20 ms of it join work: 20 ms, on time
    assert cap.ticks_late_for_joins == 1
    cap.join_work(2.000, 2.010, 0.01)
    cap.tick_lag(2.040, 0.040)  # due 2.000: 10 ms of join work, 30 ms: late
    assert (cap.ticks_late, cap.ticks_late_for_joins) == (2, 1)
