"""Per-peer playout delay (``RoomPlayoutDelay(per_peer=True)``, issue 31): a peer the
relay sends every k snapshot intervals (view-aware rates) is shown k - 1 intervals
later than the room's D; peers at the snapshot rate keep exactly the D they had.
Fake times only."""

from __future__ import annotations

import numpy as np
import pytest

from posecast.client.core import ClientCore
from posecast.client.playout import RoomPlayoutDelay
from posecast.protocol import PeerJoined, Snapshot

RATE = 30.0
STREAMS = {"head": 0, "left": 1, "right": 2}


def _run(
    delays: list[RoomPlayoutDelay],
    every: dict[int, int],
    seconds: float,
    seed: int = 3,
    start: int = 0,
) -> list[dict[int, list[float]]]:
    """Snapshots at 30 Hz from tick ``start``; user u's three streams ride every
    ``every[u]``-th one, each with a jittered age. Frames at 90 Hz; per estimator,
    per user its D per frame."""
    rng = np.random.default_rng(seed)
    out: list[dict[int, list[float]]] = [{u: [] for u in every} for _ in delays]
    tick = start
    next_snap = tick / RATE
    for now in np.arange(next_snap, next_snap + seconds, 1.0 / 90.0):
        while next_snap <= now:
            for user, k in every.items():
                if tick % k == 0:
                    for age in 0.004 + rng.gamma(2.0, 0.005, 3):
                        for d in delays:
                            d.observe(user, float(age), next_snap)
            tick += 1
            next_snap = tick / RATE
        for d, got in zip(delays, out, strict=True):
            d.update(float(now))
            for u in every:
                got[u].append(d.delay(u))
    return out


def test_a_room_at_one_rate_gets_the_same_delay_as_before() -> None:
    """Every peer at the snapshot rate: per peer on or off, every user's D is the
    same at every frame, and no user is shown apart from the room."""
    before = RoomPlayoutDelay(interval=1 / RATE, rate=RATE)
    after = RoomPlayoutDelay(interval=1 / RATE, rate=RATE, per_peer=True)
    old, new = _run([before, after], {1: 1, 2: 1, 3: 1, 4: 1}, 6.0)
    for u in old:
        assert new[u] == old[u]
    assert after.own_delays() == {} and all(after.divisor(u) == 1 for u in old)
    assert after.room.value == before.room.value


def test_a_peer_sent_every_fourth_tick_gets_three_intervals_more() -> None:
    """A far peer at 7.5 Hz: its D is the room's plus 3 snapshot intervals once settled;
    the near peers at 30 Hz keep the D of a room without it."""
    plain = RoomPlayoutDelay(interval=1 / RATE, rate=RATE)
    per = RoomPlayoutDelay(interval=1 / RATE, rate=RATE, per_peer=True)
    old, new = _run([plain, per], {1: 1, 2: 1, 3: 4}, 8.0)
    assert per.divisor(3) == 4 and per.divisor(1) == 1
    assert new[3][-1] == pytest.approx(per.room.value + 3 / RATE, abs=1e-3)
    assert new[1][-1] == pytest.approx(per.room.value, abs=1e-12)
    assert per.own_delays() == {3: pytest.approx(new[3][-1])}
    # Without it the far peer is rendered at the room's D, which cannot bridge 133 ms.
    assert old[3][-1] < 1 / RATE * 4


def test_a_peer_that_slows_down_is_moved_smoothly() -> None:
    """From 30 Hz to 7.5 Hz mid-run: its D rises to the new target without a jump
    (each 90 Hz frame moves it by at most a frame's share of the gap, tau = 1 s)."""
    d = RoomPlayoutDelay(interval=1 / RATE, rate=RATE, per_peer=True)
    _run([d], {1: 1, 2: 1}, 3.0)
    start = d.delay(2)
    got = _run([d], {1: 1, 2: 4}, 5.0, seed=4, start=90)[0][2]
    steps = np.abs(np.diff([start, *got]))
    assert steps.max() < (3 / RATE) * (1 / 90.0) / d.tau + 0.005
    assert got[-1] == pytest.approx(d.room.value + 3 / RATE, abs=0.005)


def test_forget_drops_a_peers_interval() -> None:
    """A peer that left is forgotten: back, it starts at the room's D."""
    d = RoomPlayoutDelay(interval=1 / RATE, rate=RATE, per_peer=True)
    _run([d], {1: 1, 2: 3}, 2.0)
    assert d.divisor(2) == 3
    d.forget(2)
    assert d.divisor(2) == 1 and d.delay(2) == d.room.value


def _snap(user: int, t: float, tick: int) -> Snapshot:
    us = np.full(3, user)
    poses = np.tile(np.array([0.0, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0], np.float32), (3, 1))
    poses[:, 0] = t
    return Snapshot.from_arrays(tick, t, us, np.arange(3), np.full(3, t), poses)


def _stalls(per_peer: bool) -> tuple[int, int, dict[int, float]]:
    """A client core at 30 Hz with a near peer at 30 Hz and a far one at 6 Hz:
    stalled frames of the far peer's streams, of the near one's, its own Ds."""
    core = ClientCore(("soa",), RATE, per_peer=per_peer)
    for u in (1, 2):
        core.peer_joined(PeerJoined(u, STREAMS, label=None))
    far = near = 0
    frame, tick = 0.0, 0
    for tick in range(int(6 * RATE)):
        t = tick / RATE
        core.snapshot(_snap(1, t, tick), t + 0.01)
        if tick % 5 == 0:
            core.snapshot(_snap(2, t, tick), t + 0.01)
        while frame <= t + 0.01:
            out = core.render(core.playout(frame))
            if frame > 3.0:
                rows = list(zip(core.shown(), out.frame.stalled.tolist(), strict=True))
                far += sum(s for k, s in rows if k[0] == 2)
                near += sum(s for k, s in rows if k[0] == 1)
            frame += 1 / 90.0
    return far, near, dict(core.playout(frame).own)


def test_the_client_core_bridges_a_slower_peer_without_stalls() -> None:
    """Rendered through the client core: with per peer the far peer never stalls and
    is shown at its own D; without, it stalls between its keyframes."""
    far, near, own = _stalls(per_peer=True)
    assert far == 0 and near == 0 and set(own) == {2}
    far_old, near_old, own_old = _stalls(per_peer=False)
    assert far_old > 100 and near_old == 0 and own_old == {}
