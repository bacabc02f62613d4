"""What the stamp rule buys the room: the relay's :class:`StampCheck` and the client's
:class:`RoomPlayoutDelay` on one simulated room, with an injected clock.

Four honest publishers at 30 Hz (each its own phase, 1 ms +- jitter each way) and,
in the attacked room, a liar stamping its poses ``lag`` s late; the relay stores the
newest keyframe per publisher and ticks 20 Hz snapshots; a receiver, which joins
1.5 s after the publishers started (as the bench's bots join after its attacker),
feeds the ages of the keyframes it gets to its ``RoomPlayoutDelay`` and renders
with the room's D.
The figure is the receiver's mean D over the run against the clean room's (what
``posecast bench hostile`` reports of live bots).

Run as a script for the table: ``python tests/server/test_stamps_playout.py``.
"""

from __future__ import annotations

import sys
from functools import lru_cache

import numpy as np
import pytest

from posecast.client.playout import RoomPlayoutDelay
from posecast.protocol import PoseUpdate
from posecast.server.stamps import StampCheck, StampRule

POSE = [0.0, 1.5, 0.0, 1.0, 0.0, 0.0, 0.0]
SEND, TICK, SECONDS = 30.0, 20.0, 10.0
#: The receiver joins this long after the publishers (and the liar) started, as the
#: bench's bots join after its attacker; it renders for ``SECONDS`` then.
JOIN = 1.5


@lru_cache(maxsize=64)
def room_delay(seed: int, lag: float | None, rule: StampRule) -> float:
    """The receiver's mean D (s) over the run; ``lag`` None: no liar (the clean room)."""
    rng = np.random.default_rng(seed)
    users = 5 if lag is None else 6  # user 0 receives; 1-4 honest; 5 the liar
    phases = rng.uniform(0.0, 1.0 / SEND, users)
    checks = {u: StampCheck(rule) for u in range(1, users)}
    for check in checks.values():
        check.round_trip(0.002 + float(rng.gamma(2.0, 0.0005)))
    # Every publisher's updates, in order of arrival at the relay: (arrival, user, stored capture).
    arrivals: list[tuple[float, int, float]] = []
    for u in range(1, users):
        k = np.arange(int((JOIN + SECONDS) * SEND))
        captures = 100.0 + k / SEND + phases[u]
        sent = captures + rng.uniform(0.0, 0.002, k.size)
        arrived = sent + 0.001 + rng.gamma(2.0, 0.001, k.size)
        stamps = captures - (lag if u == 5 and lag is not None else 0.0)
        for a, s in zip(arrived, stamps, strict=True):
            arrivals.append((float(a), u, float(s)))
    arrivals.sort()
    stored = []
    for a, u, s in arrivals:
        update = PoseUpdate.from_arrays(0, [u], [s], [POSE])
        kept = checks[u].check(update, a)
        stored.append((a, u, float(kept.base_time + float(kept.entries["dt"][0]))))
    playout = RoomPlayoutDelay(interval=1.0 / TICK, rate=TICK)
    latest: dict[int, float] = {}
    sent_to_receiver: dict[int, float] = {}
    i, delays = 0, []
    for j in range(int((JOIN + SECONDS) * TICK)):
        tick = 100.0 + j / TICK + 0.013
        while i < len(stored) and stored[i][0] <= tick:
            _, u, capture = stored[i]
            latest[u] = max(latest.get(u, -np.inf), capture)
            i += 1
        if tick < 100.0 + JOIN:
            continue
        arrival = tick + 0.001 + float(rng.gamma(2.0, 0.001))
        for u, capture in latest.items():
            if sent_to_receiver.get(u) != capture:
                sent_to_receiver[u] = capture
                playout.observe(u, arrival - capture)
        d = playout.update(arrival)
        if tick >= 100.0 + JOIN + 1.0:  # from its first second on, as the bots render
            delays.append(d)
    return float(np.mean(delays))


def ratios(lag: float, rule: StampRule, seeds: range) -> list[float]:
    return [room_delay(s, lag, rule) / room_delay(s, None, rule) for s in seeds]


@pytest.mark.parametrize("lag", [0.03, 0.09, 0.3])
def test_a_re_stamped_liar_leaves_the_rooms_delay_within_10_percent(lag: float) -> None:
    """With the rule, honest D stays within 1.10x of the clean room's at 30, 90 and 300 ms."""
    assert max(ratios(lag, StampRule(), range(5))) < 1.10


def test_without_the_rule_a_30_ms_liar_raises_the_rooms_delay() -> None:
    """The rule off: a 30 ms liar raises honest D by over 10 % (what the rule is for)."""
    assert np.mean(ratios(0.03, StampRule(threshold=0.0), range(5))) > 1.10


if __name__ == "__main__":
    seeds = range(int(sys.argv[1]) if len(sys.argv) > 1 else 10)
    for lag in (0.03, 0.09, 0.3):
        for name, rule in (("off", StampRule(threshold=0.0)), ("on", StampRule())):
            r = ratios(lag, rule, seeds)
            print(f"lag {1e3 * lag:3.0f} ms rule {name:3}: D ratio min {min(r):.2f} "
                  f"mean {np.mean(r):.2f} max {max(r):.2f}")  # fmt: skip
