"""Compact snapshots on the sans-I/O core: deltas per subscriber, keys, splicing.

Clients join with ``codec="compact"`` (or raw, in mixed rooms) and publish a
random walk; every pose a compact subscriber decodes must equal the codec's
codes of what the sender published, exactly, whatever the skips, rates, joins
and leaves in between (a delta against a baseline the subscriber does not hold
would be refused by its session as ``bad-baseline``).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from test_core import Client

from posecast.protocol import (
    Hello,
    Join,
    Joined,
    PoseUpdate,
    ProtocolError,
    SetRate,
    Snapshot,
    Welcome,
)
from posecast.protocol.codec import DEFAULT_VOLUME, dequantise, quantise
from posecast.protocol.codec_relay import snapshot_counts
from posecast.server.core import RelayCore, ServerConfig
from posecast.server.room import KEY_INTERVAL


class Walker(Client):
    """A client that publishes a seeded random walk and checks what it receives."""

    def __init__(self, core: RelayCore, conn: int, seed: int) -> None:
        super().__init__(core, conn)
        self.rng = np.random.default_rng(seed)
        self.pos = self.rng.uniform(-1.0, 1.0, (3, 3)) + np.array([0.0, 1.2, 0.0])
        self.rot = self.rng.normal(size=(3, 4))
        self.frames: list[bytes] = []

    def step(self, now: float) -> np.ndarray:
        self.pos += self.rng.normal(0.0, 0.01, (3, 3))
        self.rot += self.rng.normal(0.0, 0.05, (3, 4))
        self.rot /= np.linalg.norm(self.rot, axis=1)[:, None]
        poses = np.hstack([self.pos, self.rot])
        self.seq += 1
        ids = list(self.streams.values())
        self.send(PoseUpdate.from_arrays(self.seq, ids, np.full(3, now), poses), now)
        return poses

    def read(self, now: float) -> list[object]:
        frames, _ = self.core.take(self.conn, now)
        got: list[object] = []
        for data in frames:
            self.frames.append(bytes(data))
            got.extend(self.session.receive_data(data))
        for event in got:
            assert not isinstance(event, ProtocolError), event
            if isinstance(event, Welcome):
                self.user = event.user
            elif isinstance(event, Joined):
                self.streams = dict(event.streams)
        self.inbox.extend(got)
        return got


def join(
    core: RelayCore,
    now: float,
    seed: int,
    codec: str = "compact",
    rate: float = 10.0,
    echo: bool = False,
) -> Walker:
    c = Walker(core, core.connect(now), seed)
    c.send(Hello(agent="t"), now)
    c.read(now)
    streams = ("head", "left", "right")
    c.send(Join(room="lobby", streams=streams, rate=rate, codec=codec, echo=echo), now)
    c.read(now)
    return c


def codes_of(poses: np.ndarray) -> list[list[int]]:
    out: list[list[int]] = quantise(poses, DEFAULT_VOLUME).tolist()
    return out


History = dict[tuple[int, int], list[tuple[float, list[int]]]]


def run(
    core: RelayCore,
    clients: list[Walker],
    t0: float,
    t1: float,
    dt: float,
    read: Callable[[Walker, int], bool] | None = None,
) -> History:
    """Publish every ``dt`` and tick; returns (user, stream) -> [(capture, codes)]."""
    history: History = {}
    t = t0
    k = 0
    while t < t1:
        for c in clients:
            poses = c.step(t)
            for sid, row in zip(c.streams.values(), codes_of(poses), strict=True):
                history.setdefault((c.user, sid), []).append((t, row))
        due = core.next_deadline()
        while due is not None and due <= t + dt:
            core.tick(due)
            for c in clients:
                if read is None or read(c, k):
                    c.read(due)
            due = core.next_deadline()
        t += dt
        k += 1
    return history


def check_received(c: Walker, history: History) -> int:
    """Every pose of every snapshot is exactly the codes published with its capture time."""
    n = 0
    for snap in c.inbox:
        if not isinstance(snap, Snapshot):
            continue
        e = snap.entries
        for user, sid, dt, pose in zip(e["user"], e["stream"], e["dt"], e["pose"], strict=True):
            t = snap.send_time + float(dt)
            matches = [row for tt, row in history[(int(user), int(sid))] if abs(tt - t) < 0.0011]
            assert len(matches) == 1, (user, sid, t)
            want = dequantise(np.array(matches, np.int64), DEFAULT_VOLUME)[0][0]
            assert np.array_equal(pose, want)
            n += 1
    return n


def test_compact_subscribers_get_exact_codes_without_their_own_streams() -> None:
    core = RelayCore()
    clients = [join(core, 1.0, seed) for seed in range(4)]
    history = run(core, clients, 1.0, 6.0, 1 / 30)
    for c in clients:
        assert check_received(c, history) > 100
        users = {int(u) for s in c.inbox if isinstance(s, Snapshot) for u in s.entries["user"]}
        assert c.user not in users and len(users) == 3
        # Codec frames on the wire, never msgpack, once joined.
        snaps = [f for f in c.frames if f[:1] == b"\xc1"]
        assert len(snaps) >= 40


def test_one_group_encode_per_tick_spliced_per_member() -> None:
    """Members of one rate share one encode; their frames differ only by their own streams."""
    core = RelayCore()
    clients = [join(core, 1.0, seed) for seed in range(3)]
    run(core, clients, 1.0, 2.0, 1 / 30)
    room = core.rooms["lobby"]
    stats = room.statistics()
    # One key group and one delta group at most per tick, never one per member.
    assert stats.snapshots_encoded <= 2 * stats.ticks / len(clients) + 2
    assert stats.frames_out >= stats.ticks - len(clients)


def test_keys_at_join_and_at_least_every_interval() -> None:
    core = RelayCore()
    a, b = join(core, 1.0, 1), join(core, 1.0, 2)
    run(core, [a, b], 1.0, 1.0 + 3 * KEY_INTERVAL, 1 / 20)
    times_keys = []
    for f, snap in zip(
        [f for f in b.frames if f[:1] == b"\xc1"],
        [s for s in b.inbox if isinstance(s, Snapshot)],
        strict=True,
    ):
        times_keys.append((snap.send_time, frame_is_key(f)))
        assert len(snap.entries) == 3  # a's streams, never b's own
    keys = [t for t, key in times_keys if key]
    assert keys[0] == times_keys[0][0]  # the first snapshot is a key
    # A key at least every KEY_INTERVAL (the first tick of each slot of the
    # interval less one tick).
    gaps = np.diff(keys)
    assert len(keys) >= 3 and gaps.max() <= KEY_INTERVAL + 1e-6
    assert sum(not key for _, key in times_keys) > 2 * len(keys)


def frame_is_key(data: bytes) -> bool:
    """Whether a relay frame has no delta entry (n_delta == 0)."""
    return snapshot_counts(data)[3] == 0


def test_skips_never_break_the_chain() -> None:
    """A subscriber that reads only now and then (its snapshots replaced unsent) still
    decodes every frame exactly: each is coded against what its writer last took."""
    core = RelayCore()
    clients = [join(core, 1.0, seed) for seed in range(3)]
    slow = clients[2]
    history = run(core, clients, 1.0, 4.0, 1 / 30, read=lambda c, k: c is not slow or k % 7 == 0)
    assert core.peer(slow.conn).statistics().skips > 5
    assert check_received(slow, history) > 20
    assert check_received(clients[0], history) > 50


def test_rates_joins_leaves_and_a_mixed_room() -> None:
    """Raw and compact members side by side, other rates, late joins, a rate change and
    a leave (whose stream ids are reused by the next join)."""
    core = RelayCore()
    a = join(core, 1.0, 1, rate=30.0)
    b = join(core, 1.0, 2, rate=7.0)
    raw = join(core, 1.0, 3, codec="raw", rate=15.0)
    h1 = run(core, [a, b, raw], 1.0, 2.5, 1 / 30)
    a.send(SetRate(rate=12.0), 2.5)
    c = join(core, 2.5, 4, rate=20.0)
    h2 = run(core, [a, b, raw, c], 2.5, 4.0, 1 / 30)
    core.disconnect(b.conn, 4.0)
    d = join(core, 4.0, 5, rate=20.0)  # b's stream ids come back
    h3 = run(core, [a, raw, c, d], 4.0, 5.5, 1 / 30)
    history: History = {}
    for h in (h1, h2, h3):  # a user id may come back too (b's, to d): keep both
        for key, rows in h.items():
            history.setdefault(key, []).extend(rows)
    for x in (a, c, d):
        assert check_received(x, history) > 30
    # The raw member still gets float records, its own streams included.
    raw_snaps = [s for s in raw.inbox if isinstance(s, Snapshot)]
    assert raw_snaps and all(f[:1] != b"\xc1" for f in raw.frames)
    assert any(raw.user in s.entries["user"] for s in raw_snaps)


def test_echo_asks_for_the_own_streams() -> None:
    core = RelayCore()
    a = join(core, 1.0, 1, echo=True)
    b = join(core, 1.0, 2)
    history = run(core, [a, b], 1.0, 2.0, 1 / 30)
    users_a = {int(u) for s in a.inbox if isinstance(s, Snapshot) for u in s.entries["user"]}
    assert users_a == {a.user, b.user}
    check_received(a, history)


@pytest.mark.parametrize("extent", [None, 50.0])
def test_positions_outside_the_volume_are_refused_for_every_codec(extent: float | None) -> None:
    core = RelayCore(ServerConfig(room_extent=extent))
    raw = join(core, 1.0, 1, codec="raw")
    far = np.array([[0.0, 1.0, 60.0, 1.0, 0.0, 0.0, 0.0]] * 3)
    raw.send(PoseUpdate.from_arrays(1, list(raw.streams.values()), np.full(3, 1.0), far), 1.0)
    errors = [e for e in raw.read(1.0) if getattr(e, "code", None) == "bad-pose"]
    assert len(errors) == 1 and "outside the room volume" in errors[0].message  # type: ignore[attr-defined]


def test_velocity_snapshots_carry_quantised_velocities() -> None:
    """A compact subscriber that wants velocities gets the senders' velocities within
    the codec's steps (from a raw velocity sender: its float16 values)."""
    core = RelayCore()
    sender = Walker(core, core.connect(1.0), 1)
    sender.send(Hello(agent="t"), 1.0)
    sender.read(1.0)
    streams = ("head", "left", "right")
    sender.send(Join(room="lobby", streams=streams, rate=10.0, sends_velocities=True), 1.0)
    sender.read(1.0)
    sub = Walker(core, core.connect(1.0), 2)
    sub.send(Hello(agent="t"), 1.0)
    sub.read(1.0)
    sub.send(
        Join(room="lobby", streams=streams, rate=10.0, codec="compact", wants_velocities=True),
        1.0,
    )
    sub.read(1.0)
    rng = np.random.default_rng(0)
    sent: dict[float, np.ndarray] = {}
    t = 1.0
    while t < 2.0:
        poses = np.hstack([sender.pos, sender.rot / np.linalg.norm(sender.rot, axis=1)[:, None]])
        vel = rng.normal(0.0, 1.5, (3, 6))
        ids = list(sender.streams.values())
        sender.seq += 1
        update = PoseUpdate.from_arrays(sender.seq, ids, np.full(3, t), poses, velocities=vel)
        sender.send(update, t)
        sent[round(t, 4)] = update.velocities
        due = core.next_deadline()
        while due is not None and due <= t + 0.05:
            core.tick(due)
            sub.read(due)
            due = core.next_deadline()
        t += 0.05
    snaps = [s for s in sub.inbox if isinstance(s, Snapshot)]
    assert len(snaps) >= 8 and all(s.has_velocities for s in snaps)
    for s in snaps:
        capture = round(s.send_time + float(s.entries["dt"][0]), 2)
        want = sent[min(sent, key=lambda k: abs(k - capture))].astype(np.float64)
        got = s.entries["velocity"].astype(np.float64)
        # Half a codec step (2**-9 m/s, 2**-8 rad/s), plus float16's rounding on the wire.
        f16 = np.abs(want) * 2.0**-11
        assert (np.abs(got[:, :3] - want[:, :3]) <= 2.0**-10 + f16[:, :3] + 1e-9).all()
        assert (np.abs(got[:, 3:] - want[:, 3:]) <= 2.0**-9 + f16[:, 3:] + 1e-9).all()


@pytest.mark.parametrize("seed", [3, 5, 6])
def test_random_joins_leaves_rates_and_unread_frames_never_break_a_chain(seed: int) -> None:
    """Members of mixed rates come and go (their ids are reused) while others read
    only now and then: no compact frame is ever coded against a baseline its
    receiver lacks. A snapshot encoded before a user left can reach a receiver
    after that user's peer_left (events overtake the pose slot): a receiver that
    dropped the baselines on peer_left failed here."""
    rng = np.random.default_rng(seed)
    core = RelayCore()
    clients: list[Walker] = []
    t = 1.0
    for _ in range(2000):
        t += 1 / 60
        if rng.random() < 0.01 and len(clients) < 8:
            rate = float(rng.choice([5.0, 10.0, 20.0, 30.0]))
            clients.append(join(core, t, int(rng.integers(1000)), rate=rate))
        if rng.random() < 0.005 and clients:
            gone = clients.pop(int(rng.integers(len(clients))))
            core.disconnect(gone.conn, t)
        for c in clients:
            if rng.random() < 0.5:
                c.step(t)
        due = core.next_deadline()
        while due is not None and due <= t:
            core.tick(due)
            for c in clients:
                if rng.random() < 0.7:
                    c.read(due)  # asserts that nothing decodes to a protocol error
            due = core.next_deadline()
    assert core.rooms and sum(len(c.frames) for c in clients) > 100
