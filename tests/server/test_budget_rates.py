"""View-aware rates without sockets: the estimator, the choice, and a room's per-peer
frames on an injected clock (raw and compact, decoded by the client's own decoders)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from posecast.interp import quat_rotate
from posecast.interp.expected_error import (
    Acceleration,
    causal_acceleration,
    divisor,
    expected_error,
    tip_of,
)
from posecast.protocol import PoseUpdate, Snapshot, decode_message
from posecast.protocol._compact import SnapshotDecoder
from posecast.protocol.codec import DEFAULT_VOLUME
from posecast.server.room import Member, Outbox, Room
from posecast.server.view_rates import ViewRates, ViewState

STREAMS = ("head", "left", "right")


def test_incremental_acceleration_is_the_whole_trace_estimate() -> None:
    """Acceleration fed one sample at a time gives causal_acceleration's numbers."""
    rng = np.random.default_rng(3)
    times = np.cumsum(rng.uniform(0.008, 0.014, 400))
    pos = np.stack([np.sin(3 * times), np.cos(5 * times), 0.01 * rng.standard_normal(400)], 1)
    whole = causal_acceleration(times, pos)
    est = Acceleration()
    got = []
    for t, p in zip(times, pos, strict=True):
        est.observe(float(t), (float(p[0]), float(p[1]), float(p[2])))
        got.append(est.value())
    assert got[:6] == [None] * 6  # fewer than 2 strides + 1 samples: not known
    np.testing.assert_allclose(np.array(got[6:], dtype=float), whole[6:], rtol=1e-9)


def test_tip_is_the_point_a_fifth_of_a_metre_along_minus_z() -> None:
    """tip_of(pose) = p + R (0, 0, -0.2), for wire bytes and floats alike."""
    rng = np.random.default_rng(1)
    for _ in range(20):
        q = rng.standard_normal(4)
        q /= np.linalg.norm(q)
        pose = np.concatenate([rng.uniform(-2, 2, 3), q])
        want = pose[:3] + quat_rotate(q, np.array([0.0, 0.0, -0.2]))
        np.testing.assert_allclose(tip_of(tuple(pose)), want, atol=1e-12)
        np.testing.assert_allclose(tip_of(pose.astype("<f4").tobytes()), want, atol=1e-6)


def test_divisor_keeps_the_expected_error_within_the_budget() -> None:
    """The chosen interval's error A dt^2/8 stays within d tan(budget), and the next
    longer one would not; still or far peers get the lowest rate, unknown motion the
    full one."""
    budget = math.radians(1.0)
    assert divisor(budget, None, 5.0, 30.0, 6, 1.0) == 1
    assert divisor(budget, 0.0, 0.5, 30.0, 6, 1.0) == 6
    for accel, d in [(40.0, 0.6), (10.0, 2.0), (3.0, 4.0), (1.0, 8.0)]:
        k = divisor(budget, accel, d, 30.0, 6, 1.0)
        assert 1 <= k <= 6
        if k > 1:
            assert expected_error(accel, k / 30.0) <= d * math.tan(budget) + 1e-12
        if k < 6:
            assert expected_error(accel, (k + 1) / 30.0) > d * math.tan(budget)
    near = divisor(budget, 40.0, 0.6, 30.0, 6, 1.0)
    far = divisor(budget, 40.0, 8.0, 30.0, 6, 1.0)
    assert near < far
    assert divisor(budget, 40.0, 8.0, 30.0, 6, 4.0) <= far  # a margin sends more often


# -- a room on an injected clock --------------------------------------------------------


def _pose(x: float, y: float, z: float) -> list[float]:
    return [x, y, z, 1.0, 0.0, 0.0, 0.0]


def _motion(who: str, t: float) -> list[list[float]]:
    """Poses of the three streams of a user: ``near`` swings its hands 0.6 m in front
    of the subscriber, ``far`` stands still 7 m away, ``me`` stands at the origin."""
    if who == "near":
        s = 0.3 * math.sin(2 * math.pi * 2.0 * t)
        return [_pose(0.0, 1.6, -0.6), _pose(-0.2 + s, 1.2, -0.5), _pose(0.2 - s, 1.2, -0.5)]
    x = 7.0 if who == "far" else 0.0
    return [_pose(x, 1.6, 0.0), _pose(x - 0.2, 1.2, 0.0), _pose(x + 0.2, 1.2, 0.0)]


def _member(room: Room, user: int, rate: float, **kw: object) -> Member:
    m = Member(user, f"u{user}", room.allocate_streams(STREAMS), rate, Outbox(), **kw)  # type: ignore[arg-type]
    return m


def _session(
    views: ViewRates | None, budgets: dict[int, float | None], compact: bool, seconds: float = 3.0
) -> tuple[Room, dict[int, list[bytes]]]:
    """Users 1 (me), 2 (near), 3 (far) publish at 90 Hz; every member's frames at 30 Hz,
    its writer taking each one at once."""
    room = Room("r", views=views)
    who = {1: "me", 2: "near", 3: "far"}
    members = {}
    for user in (1, 2, 3):
        m = _member(room, user, 30.0, compact=compact, velocities=user == 3 and not compact)
        budget = budgets.get(user)
        m.view = None if budget is None else ViewState(budget)
        room.add(m, 0.0)
        members[user] = m
    frames: dict[int, list[bytes]] = {u: [] for u in members}
    t, seq = 0.0, 0
    while t < seconds:
        t = round(t + 1 / 90, 9)
        seq += 1
        for user, m in members.items():
            ids = list(m.streams.values())
            room.ingest(user, PoseUpdate.from_arrays(seq, ids, [t] * 3, _motion(who[user], t)))
        due = room.next_due()
        while due is not None and due <= t:
            room.tick(due)
            for user, m in members.items():
                data = m.outbox.take()
                if data is not None:
                    frames[user].append(data)
            due = room.next_due()
    return room, frames


@pytest.mark.parametrize("compact", [False, True])
def test_without_a_budget_the_frames_are_the_same_bytes(compact: bool) -> None:
    """A server that honours budgets sends members without one the very bytes of one
    that does not (same frames, same ticks)."""
    _, on = _session(ViewRates(), {}, compact)
    _, off = _session(None, {}, compact)
    assert on == off and sum(map(len, on.values())) > 200


def _decoded(frames: list[bytes], compact: bool) -> list[Snapshot]:
    if not compact:
        out = [decode_message(f) for f in frames]
        assert all(isinstance(s, Snapshot) for s in out)
        return out  # type: ignore[return-value]
    dec = SnapshotDecoder(DEFAULT_VOLUME)
    return [dec.decode(f) for f in frames]


@pytest.mark.parametrize("compact", [False, True])
def test_a_far_still_peer_goes_less_often_than_a_near_moving_one(compact: bool) -> None:
    """With a 1 degree budget, the near swinging peer is in (almost) every snapshot, the
    far still one at the lowest rate (5 Hz of 30); every frame decodes with the client's
    decoder, and each entry is the pose its peer published at that capture time."""
    room, frames = _session(ViewRates(), {1: 1.0}, compact)
    snaps = _decoded(frames[1], compact)
    seen = {2: 0, 3: 0}
    for snap in snaps:
        users = {int(u) for u in snap.users}
        for u in seen:
            seen[u] += u in users
        for u, t, p in zip(snap.users, snap.capture_times, snap.poses, strict=True):
            if int(u) == 1:
                continue
            want = np.array(_motion({2: "near", 3: "far"}[int(u)], float(t)), np.float32)
            assert min(np.abs(want[:, :3] - p[:3]).max(axis=1)) < 1e-3  # one of its streams
    assert len(snaps) > 60
    assert seen[2] >= 0.9 * len(snaps)
    assert seen[3] <= 0.3 * len(snaps) and seen[3] > 0
    sub = room.members[1]
    assert sub.view is not None and sub.view.k[3] == 6 and sub.view.k[2] <= 2
    # The member without a budget still gets both peers every tick.
    plain = _decoded(frames[2], compact)
    assert sum(3 in {int(u) for u in s.users} for s in plain) >= 0.9 * len(plain)


def test_a_snapshot_replaced_unsent_leaves_nothing_behind() -> None:
    """When the writer has not taken a budget member's snapshot by its next tick, the
    new one also carries the peers only the replaced one had (latest wins, no loss)."""
    room = Room("r", views=ViewRates())
    sub = _member(room, 1, 30.0)
    sub.view = ViewState(1.0)
    far = _member(room, 3, 30.0)
    room.add(sub, 0.0)
    room.add(far, 0.0)
    t = 0.0
    for seq in range(1, 60):
        t = seq / 90
        room.ingest(1, PoseUpdate.from_arrays(seq, list(sub.streams.values()), [t] * 3,
                                              _motion("me", t)))  # fmt: skip
        room.ingest(3, PoseUpdate.from_arrays(seq, list(far.streams.values()), [t] * 3,
                                              _motion("far", t)))  # fmt: skip
        if (due := room.next_due()) is not None and due <= t:
            room.tick(due)
            far.outbox.take()
            if seq < 40:
                sub.outbox.take()
    # From seq 40 on, sub's writer took nothing: its slot holds the newest frame, which
    # must carry user 3 (it went at least once since, and whatever went is kept).
    pending = sub.outbox.take()
    assert pending is not None and 3 in {int(u) for u in _decoded([pending], False)[0].users}
