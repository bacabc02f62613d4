"""The relay's stamp rule (server/stamps.py) on simulated links, with an injected clock.

Each test plays a publisher through a model of its path: its clock synchronised the
NTP way (the lowest round trip of 16 pings: the offset error is half the asymmetry
of that ping), its capture-to-send delay, its uplink's delay and jitter, and the
relay's keepalive pings every 2.5 s (the first at 0.5 s).
"""

from __future__ import annotations

import numpy as np
import pytest

from posecast.protocol import PoseUpdate
from posecast.server.stamps import StampCheck, StampRule

POSE = [0.0, 1.5, 0.0, 1.0, 0.0, 0.0, 0.0]


def _path(rng: np.random.Generator, one_way: float, jitter: float, n: int) -> np.ndarray:
    """``n`` one-way delays: ``one_way`` plus a right-skewed jitter of scale ``jitter``."""
    return one_way + rng.gamma(2.0, jitter / 2.0, n)


def play(
    seed: int,
    *,
    one_way: float = 0.0002,
    jitter: float = 0.0,
    send_delay: float = 0.0,
    frame: float = 0.0,
    lag: float | dict[int, float] = 0.0,
    seconds: float = 30.0,
    rate: float = 30.0,
    rule: StampRule | None = None,
    pings: bool = True,
) -> tuple[StampCheck, list[tuple[PoseUpdate, PoseUpdate]], list[float]]:
    """Publish head, left and right (ids 0-2) at ``rate`` for ``seconds``; returns the
    check, every (sent, stored) update pair and their arrival times.

    ``send_delay``: fixed capture-to-send delay; ``frame``: plus a uniform share of
    one render frame; ``lag``: the liar's stamps are this much older (per stream)."""
    rng = np.random.default_rng(seed)
    up = lambda k: _path(rng, one_way, jitter, k)  # noqa: E731
    # Clock sync: of 16 pings, the one with the lowest round trip sets the offset error.
    ups, downs = up(16), up(16)
    best = int(np.argmin(ups + downs))
    error = (ups[best] - downs[best]) / 2.0
    check = StampCheck(rule or StampRule())
    lags = lag if isinstance(lag, dict) else dict.fromkeys(range(3), lag)
    pairs, arrivals = [], []
    next_ping = 0.5
    n = int(seconds * rate)
    delays = up(n)
    for k in range(n):
        capture = 1000.0 + k / rate
        sent = capture + send_delay + frame * rng.random()
        arrival = sent + delays[k]
        while pings and next_ping <= arrival:
            check.round_trip(float(up(1)[0] + up(1)[0]))
            next_ping += 2.5
        stamps = np.array([capture + error - lags.get(s, 0.0) for s in range(3)])
        update = PoseUpdate.from_arrays(
            k, [0, 1, 2], stamps, [POSE] * 3, base_time=float(stamps.max())
        )
        pairs.append((update, check.check(update, arrival)))
        arrivals.append(arrival)
    return check, pairs, arrivals


def _untouched(check: StampCheck, pairs: list[tuple[PoseUpdate, PoseUpdate]]) -> None:
    assert check.corrected == 0
    assert all(stored is sent for sent, stored in pairs)


def _captures(update: PoseUpdate) -> np.ndarray:
    return update.base_time + update.entries["dt"].astype(np.float64)


@pytest.mark.parametrize("seed", range(10))
def test_an_honest_client_on_a_jittered_link_is_untouched(seed: int) -> None:
    """40 ms each way with a jitter of 30 ms (gamma: a long tail), a render frame of
    capture-to-send: every update stored is the very update received."""
    check, pairs, _ = play(seed, one_way=0.04, jitter=0.03, frame=1 / 60)
    _untouched(check, pairs)


@pytest.mark.parametrize("seed", range(5))
def test_an_honest_client_on_a_slow_link_is_untouched(seed: int) -> None:
    """300 ms round trip (and 10 ms jitter): its ages are its link's, never moved."""
    check, pairs, _ = play(seed, one_way=0.15, jitter=0.01)
    _untouched(check, pairs)


@pytest.mark.parametrize("seed", range(5))
def test_a_render_frame_between_capture_and_send_is_untouched(seed: int) -> None:
    """A whole 60 Hz frame (16.7 ms) between capture and send, on loopback, plus a
    frame's scheduling jitter: under the 25 ms threshold."""
    check, pairs, _ = play(seed, send_delay=1 / 60, frame=1 / 240, jitter=0.002)
    _untouched(check, pairs)


def test_nothing_is_judged_before_a_round_trip_is_known() -> None:
    """Without a pong the relay cannot tell a slow link from a liar: it moves nothing."""
    check, pairs, _ = play(0, lag=0.3, pings=False)
    _untouched(check, pairs)
    assert check.shifts() == {}


def test_threshold_zero_turns_the_rule_off() -> None:
    check, pairs, _ = play(0, lag=0.3, rule=StampRule(threshold=0.0))
    _untouched(check, pairs)


@pytest.mark.parametrize("lag", [0.03, 0.09, 0.3])
@pytest.mark.parametrize("seed", range(3))
def test_a_lagging_liar_is_moved_to_the_age_its_link_explains(lag: float, seed: int) -> None:
    """30, 90 and 300 ms of lag on a 0.4 ms link with 2 ms jitter: within 2 s the stored
    capture times are the lie undone (the smallest age within 1 ms of the link's)."""
    check, pairs, arrivals = play(seed, lag=lag, jitter=0.002)
    assert set(check.shifts()) == {0, 1, 2}
    assert all(abs(s - lag) < 0.003 for s in check.shifts().values())
    late = [i for i, a in enumerate(arrivals) if a > arrivals[0] + 2.0]
    assert all(pairs[i][1] is not pairs[i][0] for i in late)
    ages = [arrivals[i] - _captures(pairs[i][1]).max() for i in late]
    assert 0.0 <= min(ages) < 0.001 + 0.0004
    assert check.corrected >= len(late)


def test_only_the_lagging_streams_are_moved() -> None:
    """A liar that keeps its head fresh and lags its hands 60 ms: the hands alone move,
    and the head's stamps are byte for byte what it sent."""
    check, pairs, _ = play(1, lag={1: 0.06, 2: 0.06}, jitter=0.002)
    assert set(check.shifts()) == {1, 2}
    sent, stored = pairs[-1]
    assert stored.entries["dt"][0] == sent.entries["dt"][0]
    for name in ("stream", "pose"):
        assert stored.entries[name].tobytes() == sent.entries[name].tobytes()
    assert np.all(_captures(stored)[1:] - _captures(sent)[1:] > 0.055)


def test_capture_times_never_go_back_when_the_lie_stops() -> None:
    """A liar lagging 300 ms for 10 s that then stamps honestly: its correction shrinks
    slowly, every stream's stored capture times keep increasing, and it ends at 0."""
    rule = StampRule()
    check = StampCheck(rule)
    check.round_trip(0.0004)
    last = -np.inf
    for k in range(60 * 30):
        now = 1000.0 + k / 30
        lag = 0.3 if now < 1010.0 else 0.0
        stamp = now - 0.0002 - lag
        stored = check.check(PoseUpdate.from_arrays(k, [0], [stamp], [POSE]), now)
        capture = float(_captures(stored)[0])
        assert capture > last
        last = capture
    assert check.shifts() == {}


def test_a_silence_starts_the_window_again() -> None:
    """A stream silent for over a block is judged afresh: its old ages do not count."""
    check = StampCheck(StampRule())
    check.round_trip(0.0)
    for k in range(60):
        check.check(PoseUpdate.from_arrays(k, [0], [100.0 + k / 30 - 0.1], [POSE]), 100.0 + k / 30)
    assert check.shifts() == {0: pytest.approx(0.1, abs=1e-6)}
    # back after 10 s, honest: the correction slews down, never judged on the old window
    for k in range(200):
        now = 112.0 + k / 30
        check.check(PoseUpdate.from_arrays(100 + k, [0], [now], [POSE]), now)
    assert check.shifts() == {}


def test_round_trips_keep_the_lowest_of_the_recent_ones() -> None:
    check = StampCheck(StampRule())
    for rtt in (0.2, 0.05, float("nan"), -1.0, 0.3):
        check.round_trip(rtt)
    assert check.rtt == 0.05
    for _ in range(8):
        check.round_trip(0.1)
    assert check.rtt == 0.1
