"""Velocity keyframes through the real relay: a velocity sender, a plain sender, and
subscribers of both kinds in one room, over websockets on loopback."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from relaykit import random_poses, settle
from websockets.exceptions import ConnectionClosed

from posecast.client.connection import ClientConnection
from posecast.protocol import (
    VELOCITY_MAX,
    ErrorCode,
    ErrorMessage,
    PeerJoined,
    ProtocolError,
    Snapshot,
    encode_update,
)
from posecast.server.app import RelayServer

ServerFactory = Callable[..., Any]


@dataclass
class Peer:
    """A joined connection and everything it received."""

    conn: ClientConnection
    events: list[object] = field(default_factory=list)
    closed: ConnectionClosed | None = None

    async def collect(self) -> None:
        try:
            while True:
                self.events.append((await self.conn.recv()).event)
        except ConnectionClosed as exc:
            self.closed = exc

    def of(self, kind: type[Any]) -> list[Any]:
        return [e for e in self.events if isinstance(e, kind)]

    def entries_from(self, user: int) -> dict[tuple[int, float], tuple[bytes, bytes | None]]:
        """(stream, capture) -> (pose bytes, velocity bytes or None) of user's received poses."""
        out: dict[tuple[int, float], tuple[bytes, bytes | None]] = {}
        for snap in self.of(Snapshot):
            vel = snap.velocities
            for i in np.flatnonzero(snap.users == user):
                key = (int(snap.streams[i]), float(snap.capture_times[i]))
                out[key] = (snap.poses[i].tobytes(), None if vel is None else vel[i].tobytes())
        return out


@contextlib.asynccontextmanager
async def collecting(peers: list[Peer]) -> AsyncIterator[None]:
    async with asyncio.TaskGroup() as tg:
        tasks = [tg.create_task(p.collect()) for p in peers]
        try:
            yield
        finally:
            for t in tasks:
                t.cancel()


async def _open(srv: RelayServer, streams: tuple[str, ...], **flags: bool) -> Peer:
    conn = await ClientConnection.open(
        f"ws://127.0.0.1:{srv.port}", room="vel", streams=streams, rate=30.0, **flags
    )
    peer = Peer(conn)
    peer.events.extend(conn.early_peers)
    return peer


# Capture times cross the relay as float32 offsets twice (update, snapshot): they
# come back within a microsecond, while distinct captures here are >= 2 ms apart.
TOL = 1e-5


def lookup(table: dict[tuple[int, float], Any], stream: int, capture: float) -> Any:
    """The entry of ``stream`` whose capture time is within TOL of ``capture``, else None."""
    for (sid, cap), value in table.items():
        if sid == stream and abs(cap - capture) <= TOL:
            return value
    return None


def _ids(peer: Peer) -> list[int]:
    assert peer.conn.joined is not None
    return list(peer.conn.joined.streams.values())


async def test_velocity_and_plain_subscribers_in_one_room(server_factory: ServerFactory) -> None:
    """Velocity subscribers get the sender's velocities bit for bit (zeros for a plain
    sender); plain subscribers get plain snapshots with the same poses; a NaN velocity
    is refused with bad-velocity without disturbing anyone; an undeclared velocity
    update closes only its sender."""
    rng = np.random.default_rng(5)
    async with server_factory() as srv:
        sender = await _open(srv, ("head", "left"), sends_velocities=True)
        plain_sender = await _open(srv, ("head",))
        vsub = await _open(srv, ("head",), wants_velocities=True)
        psub = await _open(srv, ("head",))
        peers = [sender, plain_sender, vsub, psub]
        async with collecting(peers):
            ids, plain_ids = _ids(sender), _ids(plain_sender)
            sent: dict[tuple[int, float], tuple[bytes, bytes]] = {}
            last_capture = 0.0

            def delivered_last(peer: Peer) -> bool:
                got = peer.entries_from(sender.conn.user)
                return lookup(got, ids[0], last_capture) is not None

            for seq in range(1, 13):
                now = srv.clock()
                poses = random_poses(rng, len(ids))
                vel = rng.normal(scale=5.0, size=(len(ids), 6))
                if seq == 3:
                    vel[0, 1] = 1e6  # beyond float16: clamped to 65504
                    vel[1, 4] = -7e4
                caps = np.array([now, now - 0.002])
                frame = encode_update(seq, ids, caps, poses, base_time=now, velocities=vel)
                await sender.conn.send_bytes(frame)
                clamped = np.clip(vel, -VELOCITY_MAX, VELOCITY_MAX).astype("<f2")
                for j, sid in enumerate(ids):
                    sent[(sid, float(caps[j]))] = (poses[j].tobytes(), clamped[j].tobytes())
                await plain_sender.conn.send_bytes(
                    encode_update(seq, plain_ids, [now], random_poses(rng, 1), base_time=now)
                )
                last_capture = now
                # Each update reaches both subscribers before the next (none merged).
                await settle(lambda: delivered_last(vsub) and delivered_last(psub))

            # Velocity subscriber: velocity snapshots only, velocities and poses bit-exact.
            snaps = vsub.of(Snapshot)
            assert snaps and all(s.has_velocities for s in snaps)
            got = vsub.entries_from(sender.conn.user)
            assert len(got) >= 8
            for (sid, cap), (pose, velocity) in got.items():
                assert lookup(sent, sid, cap) == (pose, velocity), (sid, cap)
            clamped_seen = {
                v
                for _, v in got.values()
                if v is not None and (b"\xff\x7b" in v or b"\xff\xfb" in v)
            }
            assert clamped_seen, "the clamped velocities of update 3 were delivered"
            zeros = vsub.entries_from(plain_sender.conn.user)
            assert zeros and all(v == bytes(12) for _, v in zeros.values())

            # Plain subscriber: plain snapshots, the same poses, no velocities, no errors.
            psnaps = psub.of(Snapshot)
            assert psnaps and not any(s.has_velocities for s in psnaps)
            pgot = psub.entries_from(sender.conn.user)
            assert len(pgot) >= 8
            for (sid, cap), (pose, velocity) in pgot.items():
                assert velocity is None and pose == lookup(sent, sid, cap)[0]
            assert not psub.of(ProtocolError) and not vsub.of(ProtocolError)

            # Everyone learns who sends velocities.
            for peer in (vsub, psub):
                flags = {p.user: p.velocities for p in peer.of(PeerJoined)}
                assert flags[sender.conn.user] is True
                assert flags[plain_sender.conn.user] is False

            # A NaN velocity: refused with bad-velocity, the sender stays connected.
            now = srv.clock()
            bad = encode_update(
                100, ids[:1], [now], random_poses(rng, 1), velocities=[[0, np.nan, 0, 0, 0, 0]]
            )
            await sender.conn.send_bytes(bad)
            await settle(lambda: bool(sender.of(ErrorMessage)))
            (err,) = sender.of(ErrorMessage)
            assert err.code == ErrorCode.BAD_VELOCITY and not err.fatal
            assert err.message == "non-finite velocity"

            # A velocity update from a client that did not declare it: its session ends.
            await plain_sender.conn.send_bytes(
                encode_update(100, plain_ids, [now], random_poses(rng, 1), velocities=[[0.0] * 6])
            )
            await settle(lambda: plain_sender.closed is not None)
            assert plain_sender.closed is not None and plain_sender.closed.rcvd is not None
            assert plain_sender.closed.rcvd.code == 1002
            (fatal,) = plain_sender.of(ErrorMessage)
            assert fatal.code == ErrorCode.BAD_MESSAGE and fatal.fatal

            # The others carry on: a later velocity update still reaches both subscribers.
            now = srv.clock()
            pose = random_poses(rng, 1)
            vel = np.array([[1.5, -2.5, 0.25, 3.0, -4.0, 0.5]])
            await sender.conn.send_bytes(
                encode_update(101, ids[:1], [now], pose, base_time=now, velocities=vel)
            )

            def latest(peer: Peer) -> Any:
                return lookup(peer.entries_from(sender.conn.user), ids[0], now)

            await settle(lambda: latest(vsub) is not None and latest(psub) is not None)
            assert latest(vsub) == (pose[0].tobytes(), vel[0].astype("<f2").tobytes())
            assert latest(psub) == (pose[0].tobytes(), None)
            assert sender.closed is None and vsub.closed is None and psub.closed is None
        for peer in peers:
            with contextlib.suppress(ConnectionClosed):
                await peer.conn.close()
