"""Measure compact snapshots through the relay core on the real traces; prints figures.

Run: ``.venv/bin/python -m pytest -q -p no:cacheprovider -s tests/server/test_compact_measure.py``

A room of 10 users on the sans-I/O relay core replays the bundled traces (user u:
trace u % 4, from (u // 4) * 7 + 0.9 u s in), each publishing its newest sample
every 1/30 s (compact updates) with its own phase; every member asks for 30 Hz
snapshots and reads them at once. An observer (member 0) counts the bytes of
every snapshot frame it receives and the poses in them: keys every 2 s, the
frame header and padding, everything. Asserts behaviour only (the poses decode
to the senders' codes in tests/server/test_compact_relay.py); the figures are
printed.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from posecast.protocol import ClientSession, Hello, Join, Joined, PoseUpdate, Snapshot, Welcome
from posecast.protocol.codec_relay import snapshot_counts
from posecast.scenarios.traces import Trace, find_traces, load_trace
from posecast.server.core import RelayCore
from posecast.server.room import Room

ROOM = 10
RATE = 30.0
DURATION = 12.0


class Member:
    def __init__(
        self, core: RelayCore, now: float, trace: Trace, start: float, phase: float, codec: str
    ):
        self.core = core
        self.conn = core.connect(now)
        self.session = ClientSession()
        self.trace, self.start, self.phase = trace, start, phase
        self.user = -1
        self.streams: dict[str, int] = {}
        self.frames: list[tuple[int, int, bool]] = []  # bytes, poses, key
        self.seq = 0
        self.send(Hello(agent="measure"), now)
        self.read(now)
        streams = ("head", "left", "right")
        self.send(Join(room="m", streams=streams, rate=RATE, codec=codec), now)
        self.read(now)

    def send(self, message: object, now: float) -> None:
        self.core.receive(self.conn, self.session.send(message), now)  # type: ignore[arg-type]

    def read(self, now: float) -> None:
        frames, _ = self.core.take(self.conn, now)
        for data in frames:
            for ev in self.session.receive_data(data):
                if isinstance(ev, Welcome):
                    self.user = ev.user
                elif isinstance(ev, Joined):
                    self.streams = dict(ev.streams)
                elif isinstance(ev, Snapshot):
                    key = data[:1] == b"\xc1" and _n_delta(data) == 0
                    self.frames.append((len(data), len(ev.entries), key))
                else:
                    assert not hasattr(ev, "code"), ev

    def publish(self, now: float) -> None:
        tr = self.trace
        t = self.start + now
        i = int(np.searchsorted(tr.times, t, side="right")) - 1
        self.seq += 1
        ids = list(self.streams.values())
        capture = now - (t - tr.times[i])
        update = PoseUpdate.from_arrays(self.seq, ids, np.full(3, capture), tr.poses[i])
        self.send(update, now)


def _n_delta(data: bytes) -> int:
    return snapshot_counts(data)[3]


@pytest.mark.parametrize("codec", ["compact", "raw"])
def test_room_of_ten_at_30_hz_on_the_real_traces(codec: str) -> None:
    paths = find_traces("traces:sample")
    if not paths:
        pytest.skip("traces:sample not found")
    traces = [load_trace(p) for p in paths]
    core = RelayCore()
    t0 = 1000.0
    members = []
    for u in range(ROOM):
        tr = traces[u % len(traces)]
        start = tr.times[0] + (u // 4) * 7.0 + 0.9 * u - t0
        members.append(Member(core, t0, tr, start, (u * 0.37) % 1.0, codec))
    room: Room = core.rooms["m"]
    encode_s = 0.0
    encodes = 0
    name = "_encode_group" if codec == "compact" else "_encode"
    real_encode = getattr(room, name)

    def timed(*args: object) -> object:
        nonlocal encode_s, encodes
        t = time.perf_counter()
        out = real_encode(*args)  # type: ignore[arg-type]
        encode_s += time.perf_counter() - t
        encodes += 1
        return out

    setattr(room, name, timed)
    next_pub = [t0 + m.phase / RATE for m in members]
    now = t0
    tick_s = 0.0
    while now < t0 + DURATION:
        step = min(min(next_pub), core.next_deadline() or now + 1)
        now = step
        for k, m in enumerate(members):
            if next_pub[k] <= now + 1e-12:
                m.publish(now)
                next_pub[k] += 1 / RATE
        due = core.next_deadline()
        if due is not None and due <= now + 1e-12:
            t = time.perf_counter()
            core.tick(now)
            tick_s += time.perf_counter() - t
            for m in members:
                m.read(now)
    obs = members[0].frames
    assert len(obs) > 0.9 * RATE * DURATION
    nbytes = sum(b for b, _, _ in obs)
    poses = sum(n for _, n, _ in obs)
    keys = [(b, n) for b, n, k in obs if k]
    delta = [(b, n) for b, n, k in obs if not k]
    per_frame = np.array([b / n for b, n, _ in obs])
    delivered = sum(len(m.frames) for m in members)
    delivered_poses = sum(sum(n for _, n, _ in m.frames) for m in members)
    p50, p95 = np.percentile(per_frame, [50, 95])
    print(
        f"\n{codec}: room of {ROOM} at {RATE:g} Hz, {DURATION:g} s, observer member 0:"
        f"\n  all frames: {nbytes / poses:.2f} B/pose mean ({len(obs)} frames,"
        f" {poses / len(obs):.1f} poses each); per frame p50 {p50:.2f}, p95 {p95:.2f}"
    )
    if codec == "compact":
        assert len(keys) >= DURATION / 2 - 1
        print(
            f"  key frames: {sum(b for b, _ in keys) / sum(n for _, n in keys):.2f} B/pose"
            f" ({len(keys)} of them); delta frames:"
            f" {sum(b for b, _ in delta) / sum(n for _, n in delta):.2f} B/pose"
        )
    print(
        f"  relay: {encodes} encodes for {delivered} member frames;"
        f" {1e6 * encode_s / max(encodes, 1):.0f} us an encode,"
        f" {1e6 * tick_s / max(delivered, 1):.1f} us of tick a member frame,"
        f" {1e6 * tick_s / delivered_poses:.2f} us a delivered pose"
    )
    # One encode a tick for the room, never one a member (members share baselines).
    assert encodes <= 1.1 * len(obs) + 2
