"""Per-user playout delay: a late user is shown late alone and does not move the room's D.

:class:`~client.playout.RoomPlayoutDelay` judges each remote user by the
median of its keyframe ages against the majority's; :func:`render_buffers` takes
one playout time per row; :func:`score_received` scores a stream with the D it
was rendered with.
"""

from __future__ import annotations

import numpy as np
import pytest

from posecast.client.buffers import RoomBuffers
from posecast.client.playout import PlayoutDelay, RoomPlayoutDelay
from posecast.client.remote import ReceivedStream, score_received
from posecast.client.render import render_buffers
from posecast.scenarios.motion import MotionSpec
from posecast.scenarios.qoe import KeyframeLog

INTERVAL = 1.0 / 15.0
HONEST = (0, 1, 2)
LATE = 9


def _feed(
    delays: list[RoomPlayoutDelay],
    users: dict[int, float],
    t0: float,
    t1: float,
    seed: int,
    only: set[int] | None = None,
) -> list[tuple[float, float, dict[int, float]]]:
    """Snapshots at 15 Hz: each user's 3 streams with age ``base + jitter``; 90 Hz
    updates. Every estimator sees the same jittered ages, but the second and later
    ones only ``only``'s. Returns, for the first, (now, room D, own Ds) per update."""
    rng = np.random.default_rng(seed)
    out = []
    snap = t0
    for now in np.arange(t0, t1, 1.0 / 90.0):
        while snap <= now:
            for user, base in users.items():
                for age in base + rng.gamma(2.0, 0.004, 3):
                    for k, d in enumerate(delays):
                        if k == 0 or only is None or user in only:
                            d.observe(user, float(age))
            snap += INTERVAL
        rooms = [d.update(float(now)) for d in delays]
        out.append((float(now), rooms[0], dict(delays[0].own)))
    return out


def test_a_late_user_does_not_move_the_rooms_delay() -> None:
    """Three honest users and one 0.8 s late: the room's D is the clean room's, exactly."""
    with_late, clean = RoomPlayoutDelay(INTERVAL), RoomPlayoutDelay(INTERVAL)
    users = {u: 0.03 for u in HONEST} | {LATE: 0.8}
    trace = _feed([with_late, clean], users, 0.0, 6.0, seed=1, only=set(HONEST))
    assert with_late.late == {LATE} and not clean.late
    assert with_late.room.value == pytest.approx(clean.room.value, abs=1e-12)
    # The room's D covers the honest ages (about interval + 30-60 ms), not 0.8 s.
    assert INTERVAL + 0.03 < with_late.room.value < INTERVAL + 0.1
    # The late user is shown late alone: its own D covers its ages, the others have none.
    assert set(with_late.own) == {LATE}
    assert with_late.delay(LATE) > 0.8 + INTERVAL
    assert all(with_late.delay(u) == with_late.room.value for u in HONEST)
    # Never shown at the room's D (late from its first snapshot): its own D from the
    # start, then it follows its ages without a jump (< 10 % of the gap a frame).
    own = [o[LATE] for _, _, o in trace if LATE in o]
    assert own[0] > 0.8 + INTERVAL
    assert np.abs(np.diff(own)).max() < 0.1 * 0.8


def test_the_later_of_two_users_is_the_late_one() -> None:
    """With two peers the reference is the lower median: the late one is flagged."""
    d = RoomPlayoutDelay(INTERVAL)
    _feed([d], {0: 0.03, LATE: 0.7}, 0.0, 3.0, seed=2)
    assert d.late == {LATE}
    assert d.room.value < INTERVAL + 0.1 < 0.7 < d.delay(LATE)


def test_a_room_of_widely_spread_paths_keeps_one_delay() -> None:
    """Medians 20-300 ms evenly spread: no user is an outlier (the MAD bound), one D."""
    d = RoomPlayoutDelay(INTERVAL)
    users = {u: base for u, base in enumerate((0.02, 0.09, 0.16, 0.23, 0.30))}
    _feed([d], users, 0.0, 3.0, seed=3)
    assert not d.late and not d.own
    assert d.room.value > INTERVAL + 0.3  # it covers everyone, as PlayoutDelay would


def test_a_single_user_gets_the_delay_playout_delay_would_give() -> None:
    """One peer: never late; its D is :class:`PlayoutDelay`'s over the same ages."""
    d = RoomPlayoutDelay(INTERVAL)
    ref = PlayoutDelay(INTERVAL)
    rng = np.random.default_rng(4)
    for k in range(200):
        for age in 0.5 + rng.gamma(2.0, 0.004, 3):
            d.observe(7, float(age))
            ref.observe(float(age))
        assert d.update(k / 15.0) == pytest.approx(ref.update(k / 15.0), abs=1e-12)
    assert not d.late


def test_a_user_that_catches_up_rejoins_the_rooms_delay_smoothly() -> None:
    """Once its ages are honest again, a late user's D slews back and merges."""
    d = RoomPlayoutDelay(INTERVAL)
    _feed([d], {0: 0.03, 1: 0.03, LATE: 0.6}, 0.0, 3.0, seed=5)
    assert LATE in d.own
    # The window (256 ages, ~5.7 s of 3 streams at 15 Hz) forgets the late ages.
    trace = _feed([d], {0: 0.03, 1: 0.03, LATE: 0.03}, 3.0, 20.0, seed=6)
    assert not d.late and not d.own
    own = [o[LATE] for _, _, o in trace if LATE in o]
    assert own and np.abs(np.diff(own)).max() < 0.1 * 0.6
    assert d.delay(LATE) == d.room.value
    # Its window held late ages until it rejoined: the room's D never covered them.
    assert max(room for _, room, _ in trace) < INTERVAL + 0.1


def test_a_late_first_peer_keeps_its_delay_when_honest_peers_come() -> None:
    """The room's D was the late peer's; honest peers come: it is set to theirs at
    once, and the late peer keeps being shown from where it was, alone."""
    d = RoomPlayoutDelay(INTERVAL)
    _feed([d], {LATE: 0.7}, 0.0, 2.0, seed=9)
    assert not d.late and d.room.value > 0.7
    shown = d.room.value
    trace = _feed([d], {LATE: 0.7, 0: 0.03, 1: 0.03}, 2.0, 4.0, seed=10)
    assert d.late == {LATE}
    assert trace[0][1] < INTERVAL + 0.1  # set, not slewed: nobody watched it before
    assert trace[0][2][LATE] == pytest.approx(shown, abs=0.01)
    assert np.abs(np.diff([o[LATE] for _, _, o in trace])).max() < 0.01


def test_forget_drops_a_users_ages() -> None:
    """A peer that left no longer counts, late or not."""
    d = RoomPlayoutDelay(INTERVAL)
    _feed([d], {0: 0.03, 1: 0.03, LATE: 0.6}, 0.0, 2.0, seed=7)
    d.forget(LATE)
    d.update(2.1)
    assert not d.late and not d.own and LATE not in d._users


def _room(n: int) -> RoomBuffers:
    room = RoomBuffers(capacity=16)
    rng = np.random.default_rng(8)
    for j in range(n):
        buf = room.stream()
        for k in range(12):
            q = rng.normal(size=4)
            q /= np.linalg.norm(q)
            pose = np.r_[rng.normal(size=3), q].astype(np.float32)
            buf.push(0.1 * k + 0.013 * j, pose)
    room.stream()  # an empty row: skipped, its time too
    return room


def test_render_at_one_time_per_row_equals_rows_rendered_alone() -> None:
    """Per-row playout times: each row as if the whole room were rendered at its time."""
    room = _room(5)
    methods = ["soa", "dq-slerp", "motor-cubic"]
    t = np.array([0.55, 0.2, 0.55, 1.3, 0.4001, 9.0])  # a stall, a hold, an empty row
    frame = render_buffers(room, t, methods)
    assert frame.poses["soa"].shape == (5, 7)
    for j in range(5):
        alone = render_buffers(room, float(t[j]), methods)
        assert frame.stalled[j] == alone.stalled[j]
        for m in methods:
            np.testing.assert_array_equal(frame.poses[m][j], alone.poses[m][j])
    assert frame.stalled[3] and not frame.stalled[0]
    with pytest.raises(ValueError, match=r"Expected `t` to have shape \(6,\), got \(5,\)"):
        render_buffers(room, t[:5], methods)


def _late_stream(arrival_lag: float) -> ReceivedStream:
    """The head of synthetic orbit at 15 Hz, arriving ``arrival_lag`` after capture."""
    spec = MotionSpec("synthetic:orbit", 0, 0.0)
    truth = spec.truth(until=12.0).select(["head"])
    cap = np.arange(0.0, 10.0, INTERVAL)
    idx = np.searchsorted(truth.times, cap)
    cap = truth.times[idx]
    log = KeyframeLog(cap, cap + arrival_lag, truth.poses[idx].reshape(-1, 1, 7), None)
    return ReceivedStream(spec.label(), "head", lambda: log)


def test_a_stream_is_scored_with_the_delay_it_was_rendered_with() -> None:
    """Own delays score as that stream's own render loop would; the room's D stalls it."""
    pt = np.arange(2.0, 9.0, 1.0 / 90.0)
    pd = np.full(pt.shape, 0.1)
    sd = np.full(pt.shape, 0.95)
    room_d = _late_stream(0.8)
    own = ReceivedStream(room_d.label, room_d.name, room_d.log, sd)
    (by_room,) = score_received([room_d], pt, pd, ["soa"])
    (by_own,) = score_received([own], pt, pd, ["soa"])
    # Its own playout times (pt + pd - sd) with its own D: the same numbers.
    (alone,) = score_received([room_d], pt + pd - sd, sd, ["soa"])
    assert by_own["soa"]["head"].stats() == alone["soa"]["head"].stats()
    # At the room's 0.1 s nothing had arrived in time: every sample a stall.
    assert by_room["soa"]["head"].stats()["stall_fraction"] == 1.0
    assert by_own["soa"]["head"].stats()["stall_fraction"] < 0.05
