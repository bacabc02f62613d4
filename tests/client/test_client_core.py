"""The client core (client/core.py) and its reconnect policy (client/reconnect.py),
driven with protocol messages and fake times: no socket, no clock, no sleep."""

from __future__ import annotations

import numpy as np
import pytest

from posecast.client.core import ClientCore, Observer, Rendered
from posecast.client.log import SessionLog
from posecast.client.reconnect import STALE_SHARE, Reconnect, SessionEnd, ran_to_the_end
from posecast.protocol import PeerJoined, PeerLeft, Snapshot

STREAMS = {"head": 0, "left": 1, "right": 2}
IDENTITY = np.array([0.0, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0], dtype=np.float32)


def snapshot(users: list[int], t: float, tick: int = 1) -> Snapshot:
    """A snapshot with each user's three streams captured at ``t`` (sent at ``t``)."""
    us = np.repeat(users, 3)
    ids = np.tile([0, 1, 2], len(users))
    poses = np.tile(IDENTITY, (us.size, 1))
    poses[:, 0] = t  # moving along x
    return Snapshot.from_arrays(tick, t, us, ids, np.full(us.size, t), poses)


def fed(core: ClientCore, users: list[int], start: float, n: int, rate: float = 20.0) -> float:
    """Feed ``n`` snapshots of ``users`` at ``rate`` from ``start`` (arrival 30 ms after
    capture, clock offset 0); returns the last capture time."""
    t = start
    for k in range(n):
        t = start + k / rate
        core.snapshot(snapshot(users, t, k + 1), t + 0.03)
    return t


def test_a_frame_renders_every_present_stream_between_its_keyframes() -> None:
    """Two peers, fed at 20 Hz: a frame at playout time between keyframes brackets
    them, and nothing stalls."""
    core = ClientCore(("soa",), 20.0)
    for u in (1, 2):
        core.peer_joined(PeerJoined(u, STREAMS, label=None))
    last = fed(core, [1, 2], 100.0, 20)
    out = core.render(core.playout(last + 0.03))
    assert out.frame.stalled.size == 6 and not out.frame.stalled.any()
    assert len(core.shown()) == 6
    t = out.playout.time
    assert np.allclose(out.frame.poses["soa"][:, 0], t, atol=1e-6)  # x follows time


def test_render_cost_after_a_thousand_joins_and_leaves_equals_the_peers_present() -> None:
    """A peer that leaves gives its buffer rows back (#29): after 1,000 peers joined,
    sent and left, a frame touches the rows of the two peers present, no more."""
    core = ClientCore(("soa",), 20.0)
    t = 0.0
    for u in (1, 2):
        core.peer_joined(PeerJoined(u, STREAMS))
    for k in range(1000):
        user = 10 + k % 60_000
        core.peer_joined(PeerJoined(user, STREAMS))
        t = fed(core, [1, 2, user], t + 0.05, 2)
        core.render(core.playout(t))
        core.receive(PeerLeft(user), t)
    out = core.render(core.playout(t + 0.05))
    # Rows touched by the render: the rows in use, and the streams of the frame.
    assert len(core.buffers) == 6
    assert out.frame.stalled.size == 6
    assert {k[0] for k in core.shown()} == {1, 2}
    # The control: a core where nobody left renders every row it ever had.
    kept = ClientCore(("soa",), 20.0)
    for k in range(50):
        fed(kept, [1, 2, 10 + k], k * 0.2, 2)
    assert len(kept.buffers) == 3 * 52


def test_a_released_row_takes_the_last_one_and_renders_the_same() -> None:
    """Freeing a middle row moves the last one into it: the streams left render the
    same poses as before, by key."""
    core = ClientCore(("soa",), 20.0)
    last = fed(core, [1, 2, 3], 10.0, 10)
    before = core.render(core.playout(last))
    by_key = {k: before.frame.poses["soa"][j] for j, k in enumerate(core.shown())}
    core.peer_left(1)
    after = core.render(core.playout(last))
    assert len(core.buffers) == 6
    for j, k in enumerate(core.shown()):
        assert k[0] != 1
        np.testing.assert_allclose(after.frame.poses["soa"][j], by_key[k], atol=1e-6)


def test_a_repeated_keyframe_is_taken_once() -> None:
    """A key snapshot resends an unchanged stream within the codec's 1 ms: not new."""
    core = ClientCore(("soa",), 20.0)
    assert core.snapshot(snapshot([1], 5.0), 5.03) == 3
    poses = np.tile(IDENTITY, (3, 1))
    poses[:, 0] = 5.0
    again = Snapshot.from_arrays(2, 5.1, [1, 1, 1], [0, 1, 2], [5.0005] * 3, poses)
    assert core.snapshot(again, 5.13) == 0


def test_the_observer_sees_keyframes_frames_and_leaves() -> None:
    """Scoring is a consumer: the log gets each new keyframe, each frame, each leave."""
    log = SessionLog(("soa",))
    core = ClientCore(("soa",), 20.0, observer=log)
    core.peer_joined(PeerJoined(4, STREAMS, label="synthetic:orbit|seed=1|t0=0"))
    last = fed(core, [4], 1.0, 5)
    core.render(core.playout(last))
    assert log.poses_in == 15 and len(log.play_t) == 1
    assert {rs.label for rs in log.streams.values()} == {"synthetic:orbit|seed=1|t0=0"}
    core.peer_left(4)
    assert all(log.until[k] == 1 for k in log.streams)
    # The id comes back: the old streams are keyed apart, the new ones start afresh.
    core.peer_joined(PeerJoined(4, STREAMS))
    fed(core, [4], 3.0, 2)
    assert len(log.streams) == 6 and len([k for k in log.streams if k[0] == 4]) == 3


def test_velocities_announced_after_the_first_snapshot_apply_to_its_streams() -> None:
    """peer_joined with velocities after a snapshot marks the streams already there."""

    class Seen(Observer):
        def __init__(self) -> None:
            self.users: list[int] = []

        def velocities_known(self, user: int) -> None:
            self.users.append(user)

    seen = Seen()
    core = ClientCore(("soa",), 20.0, observer=seen)
    fed(core, [7], 1.0, 1)
    core.peer_joined(PeerJoined(7, STREAMS, velocities=True))
    assert seen.users == [7]
    assert all(b.has_velocities for b in core.buffers.buffers())


def test_stale_time_counts_frames_with_every_stream_held() -> None:
    """The log counts render time with no fresh pose of anyone (a dead path)."""
    log = SessionLog(("soa",))
    core = ClientCore(("soa",), 20.0, observer=log)
    last = fed(core, [1], 0.0, 20)
    local = last + 0.03
    while local < last + 5.0:  # nothing arrives for 5 s: every frame holds
        core.render(core.playout(local))
        local += 0.1
    assert log.stale_s == pytest.approx(5.0 - core.delay.room.value, abs=0.3)
    # Fresh poses again: the stretch is kept; a short one later is not counted.
    stale = log.stale_s
    last = fed(core, [1], local, 20)
    local = last + 0.03
    core.render(core.playout(local))
    for k in range(5):  # 0.5 s with nothing new: a starved loop's hiccup, not a dead path
        core.render(core.playout(local + 0.1 * (k + 1)))
    core.snapshot(snapshot([1], local + 0.6, 99), local + 0.63)
    core.render(core.playout(local + 0.7))
    assert log.stale_s == stale


def test_rendered_reports_the_frame_index() -> None:
    """Frames are numbered from 0, one per render."""
    got: list[int] = []

    class Frames(Observer):
        def rendered(self, frame: Rendered) -> None:
            got.append(frame.index)

    core = ClientCore(("soa",), 10.0, observer=Frames())
    for k in range(3):
        core.render(core.playout(float(k)))
    assert got == [0, 1, 2] and core.frames == 3


# -- the reconnect policy -----------------------------------------------------------


def test_a_drop_with_a_resume_token_reconnects_within_the_window() -> None:
    """No close frame + a resume token: reconnect until min(stop, now + window)."""
    p = Reconnect(("ws://a",), window=10.0)
    assert p.ended(None, "", 3.0, joined=True, resume_token=True)
    assert p.state == "reconnecting"
    assert p.start(100.0, stop=105.0) == 105.0
    assert p.start(100.0, stop=200.0) == 110.0
    p.reconnected(0, True, 55.0)
    assert p.state == "connected" and p.resumed_at == [55.0]


@pytest.mark.parametrize(
    ("code", "relays", "token", "goes_on"),
    [
        (None, 1, False, False),  # a drop, nothing to resume, nowhere else to go
        (None, 2, False, True),  # a drop: other relays
        (1012, 1, False, True),  # a cluster node asks its clients back
        (1001, 1, True, False),  # the one relay going away
        (1001, 2, False, True),  # going away, others exist
        (1000, 2, True, False),  # a normal close ends it
    ],
)
def test_which_ends_reconnect(code: int | None, relays: int, token: bool, goes_on: bool) -> None:
    """The table of client/reconnect.py: who goes on after an end."""
    p = Reconnect(tuple(f"ws://r{i}" for i in range(relays)))
    assert p.ended(code, "why", 2.0, joined=True, resume_token=token) is goes_on
    if not goes_on:
        assert p.ending is not None and p.ending.kind == ("lost" if code is None else "closed")


def test_not_joined_or_not_enabled_never_reconnects() -> None:
    """A session that never joined, or that asked for no resume, ends where it drops."""
    assert not Reconnect(("a", "b")).ended(None, "", 1.0, joined=False, resume_token=True)
    off = Reconnect(("a", "b"), enabled=False)
    assert not off.ended(None, "", 1.0, joined=True, resume_token=True)
    assert off.ending == SessionEnd("lost", 1.0)


def test_a_refused_join_moves_on_then_gives_up_as_it_dropped() -> None:
    """With several relays a refusal tries the next; with one it ends the session;
    a window that closes ends it as the drop was (a close keeps its code)."""
    p = Reconnect(("a", "b", "c"))
    assert p.ended(1012, "restart", 1.0, joined=True, resume_token=False)
    assert p.refused(2) and p.relay == 0
    assert p.gave_up(7.5) == SessionEnd("closed", 7.5, 1012, "restart")
    one = Reconnect(("a",))
    one.ended(None, "", 1.0, joined=True, resume_token=True)
    assert not one.refused(0)
    assert one.gave_up(2.0) == SessionEnd("lost", 2.0)


def test_the_first_ending_wins() -> None:
    """An interrupted session stays interrupted when its connection then closes."""
    p = Reconnect(("a",))
    p.finish(SessionEnd("interrupted", 4.0))
    assert not p.ended(1000, "bye", 5.0, joined=True, resume_token=True)
    assert p.ending == SessionEnd("interrupted", 4.0)


def test_complete_means_it_ran_its_duration_with_fresh_poses() -> None:
    """Over STALE_SHARE of the time with nothing fresh is ``stalled``, not complete."""
    assert ran_to_the_end(20.0, 0.2).kind == "complete"
    stalled = ran_to_the_end(20.0, 20.0 * 0.73)
    assert stalled.kind == "stalled" and not stalled.graceful
    assert "no fresh poses for 14.6 s of 20.0 s" in stalled.describe()
    assert ran_to_the_end(10.0, 10.0 * STALE_SHARE).kind == "complete"
