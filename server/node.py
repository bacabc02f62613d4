"""One relay as a node of a cluster: the directory, forwarding, and their upkeep.

``posecast serve --cluster nats://HOST:PORT --node NAME`` runs a
:class:`ClusterNode` beside the relay's adapter (``server/app.py``). It holds
the three parts of ``server/cluster.py`` and ``server/forward.py`` together:

- a join names a room: the node claims it in the directory (:meth:`claim`).
  If this node owns it, the join is the local core's as on one server;
  otherwise the client's connection is *handed off*: its frames, from the join
  on, are forwarded to the owner (:class:`~server.forward.Edge`) and what the
  owner sends back is written to its websocket;
- the owner side (:class:`~server.forward.Members`) runs the forwarded clients
  of other nodes as connections of this node's core;
- the members of its rooms, written to NATS four times a second, so that a
  member can resume through any node, also after this one is lost;
- upkeep, every third of a lease: renew the leases, give up rooms that stayed
  empty for a whole round, check that the owners this node forwards to are
  alive (a node killed with SIGKILL has no subscriber left, and NATS says so at
  once: "no responders"), and measure the NATS round trip for ``/metrics``.

When an owner is gone, its rooms are free again: the next join claims them
(taking a dead owner's lease over at once, before it runs out), and the
clients this node forwarded there are closed with 1012 (service restart) so
that they reconnect and join again, now on a live node.
"""

from __future__ import annotations

import asyncio
import logging
import re
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

import msgpack
import nats.errors
from nats.aio.msg import Msg

from posecast.protocol.objects import ROOM_USER
from posecast.server import resume
from posecast.server.actions import Action
from posecast.server.cluster import Directory, member_key
from posecast.server.core import RelayCore
from posecast.server.forward import Edge, Members, alive
from posecast.server.member import IdAllocator, Member, Outbox

__all__ = ["MOVED", "ClusterNode", "cluster_clock"]

log = logging.getLogger("posecast.cluster")

#: The close of a client whose room's node is gone, or whose room moved.
MOVED = (1012, "the room's node changed; reconnect")
#: The subject a node that took a room over from a lost node says so on.
GONE = "posecast.cluster.gone"
#: Seconds a member record lives unless its owner writes it again (every third).
RECORD_TTL = 30.0
#: How often the owner writes new, changed and gone member records (s).
RECORD_INTERVAL = 0.25
#: What a resume token looks like (``Parking.new_token``): a safe NATS key token.
_TOKEN = re.compile(r"[A-Za-z0-9_-]{8,64}")


def cluster_clock() -> Callable[[], float]:
    """The server clock of a cluster node: monotonic, anchored to the wall clock at
    start, so that every node reads the same time (to the hosts' clock sync) and a
    client synced with one node keeps its offset when its frames go to another."""
    anchor = time.time() - time.monotonic()
    return lambda: time.monotonic() + anchor


def _stop_if_cancelled() -> None:
    """Raise CancelledError if the running task was cancelled. nats-py waits for its
    replies with ``asyncio.wait_for``, which on Python 3.11 returns a reply that comes
    together with a cancellation and drops the cancellation (or turns it into an error
    of its own): a loop around NATS calls that does not check this after each runs on
    for ever, and the relay's stop waits for it for ever."""
    task = asyncio.current_task()
    if task is not None and task.cancelling():
        raise asyncio.CancelledError


@dataclass
class ClusterNode:
    """The cluster side of one relay process (build it with :meth:`open`)."""

    directory: Directory
    core: RelayCore
    apply: Callable[[list[Action]], None]
    members: Members
    edge: Edge
    clock: Callable[[], float] = time.monotonic
    #: Rooms this node owns that were empty at the last upkeep round.
    _empty: set[str] = field(default_factory=set)
    #: Claims under way (each takes its room's members in before it ends).
    _adopting: set[asyncio.Future[None]] = field(default_factory=set)
    #: Rooms this node took over from a lost node: room -> that node.
    taken_from: dict[str, str] = field(default_factory=dict)
    #: Member records this node wrote: key -> (value, when).
    _written: dict[str, tuple[bytes, float]] = field(default_factory=dict)
    #: Last NATS round trip (s), NaN before the first.
    rtt: float = float("nan")
    joins_forwarded: int = 0
    owners_lost: int = 0

    @classmethod
    async def open(
        cls,
        servers: str,
        node: str,
        core: RelayCore,
        apply: Callable[[list[Action]], None],
        deliver: Callable[[int, bytes], None],
        close: Callable[[int, int, str], None],
        *,
        url: str = "",
        lease: float = 3.0,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
        prepare: Callable[[str], Awaitable[None]] | None = None,
    ) -> ClusterNode:
        """Join the cluster at ``servers`` as ``node`` (:class:`ClusterError` if not)."""
        directory = await Directory.open(servers, node, url=url, lease=lease)
        ids = directory.user_ids()
        core.users = IdAllocator(min(ids.stop, ROOM_USER), start=ids.start)
        members = Members(core, directory.nc, node, apply, clock, wall_clock, prepare)
        edge = Edge(directory.nc, node, deliver, close)
        self = cls(directory, core, apply, members, edge, clock)
        core.cluster = self
        members.settle = self.settled
        directory.on_lost = self._lost
        await members.start()
        await edge.start()
        await directory.nc.subscribe(GONE, cb=self._on_gone)
        log.info("cluster: node %s (index %d) joined", node, directory.index)
        return self

    @property
    def name(self) -> str:
        return self.directory.node

    async def run(self) -> None:
        """Forwarding and upkeep, for ever (under the adapter's TaskGroup)."""
        async with asyncio.TaskGroup() as tg:
            tg.create_task(self.members.run(), name="cluster-members")
            tg.create_task(self.edge.run(), name="cluster-edge")
            tg.create_task(self.directory.keep_alive(), name="cluster-leases")
            tg.create_task(self._upkeep(), name="cluster-upkeep")
            tg.create_task(self._keep_records(), name="cluster-records")

    async def close(self) -> None:
        """Give up this node's leases and leave NATS (bounded)."""
        await self.directory.close()

    # -- joins -----------------------------------------------------------------------

    def owns(self, room: str) -> bool:
        return self.directory.owns(room)

    def must_claim(self, room: str) -> bool:
        """Whether a join of ``room`` waits for :meth:`claim`: this node does not own
        it, or a claim under way may be taking members in."""
        return self.busy or not self.directory.owns(room)

    async def claim(self, room: str) -> str:
        """The live node that owns ``room`` now: this one if it was free, or its owner
        was gone (then this node takes it over). When this node becomes its owner it
        takes in the members a lost owner recorded before anything else of the room
        is handled here: resumes forwarded by other nodes wait for it (:meth:`settled`)."""
        if self.directory.owns(room):
            await self.settled()
            return self.name
        adopting: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._adopting.add(adopting)
        try:
            owner = await self._claim(room)
            if owner == self.name:
                await self._take_in(room)
            return owner
        finally:
            self._adopting.discard(adopting)
            adopting.set_result(None)

    @property
    def busy(self) -> bool:
        """Whether a claim is under way (joins and resumes here wait for it)."""
        return bool(self._adopting)

    async def settled(self) -> None:
        """Wait until no room this node just claimed is still taking its members in."""
        while self._adopting:
            await asyncio.gather(*self._adopting)

    async def _take_in(self, room: str) -> None:
        """Open ``room`` (its recording) and park the members its lost owner recorded."""
        try:
            if self.members.prepare is not None:
                await self.members.prepare(room)
            await self.adopt(room)
        except Exception as exc:  # NATS away: the room starts empty here
            log.warning("cluster: cannot take room %r's members in: %s", room, exc)

    async def _claim(self, room: str) -> str:
        for _ in range(3):
            owner = await self.directory.claim(room)
            if owner == self.name or await self._alive(owner):
                return owner
            if await self.directory.take_over(room, owner):
                self.taken_from[room] = owner
                # Every node's clients forwarded to it reconnect now, not at their
                # node's next upkeep round.
                self._owner_gone(owner)
                await self.directory.nc.publish(GONE, owner.encode())
                return self.name
        return await self.directory.claim(room)

    def hand_off(self, conn: int, owner: str, address: str, frames: list[bytes | str]) -> bool:
        """Forward connection ``conn`` (welcomed here) to ``owner``, starting with
        ``frames`` (its join, and what followed it); False if the backlog is full.
        Its resume token goes along: a drop parks it on the owner under that token."""
        peer = self.core.peer(conn)
        assert peer.user is not None
        token = peer.resume_token
        self.core.hand_off(conn)
        self.joins_forwarded += 1
        self.edge.open(conn, owner, peer.user, peer.name, token is not None, address, token)
        return self.edge.forward(conn, frames)

    def hand_off_resume(
        self, conn: int, owner: str, user: int, address: str, frames: list[bytes | str]
    ) -> bool:
        """Forward connection ``conn``, whose hello (the first of ``frames``) resumes
        ``user`` of a room ``owner`` holds: the owner answers the hello itself."""
        self.core.hand_off(conn)
        self.joins_forwarded += 1
        self.edge.open(conn, owner, user, "", True, address, None, True)
        return self.edge.forward(conn, frames)

    async def place_join(self, room: str) -> str | None:
        """The node a join of ``room`` goes to (claimed in the cluster, see :meth:`claim`);
        None: the cluster cannot place it now (NATS away, or the room changes hands too
        fast: the adapter closes the client with 1013, to try again)."""
        try:
            return await self.claim(room)
        except Exception as exc:
            log.warning("cluster: cannot claim room %r: %s", room, exc)
            return None

    async def place_resume(self, token: str) -> tuple[str, int] | None:
        """(owner node, user) of the member resumable with ``token``, its room claimed
        (taking in the members of a lost owner when this node takes it over); None: not
        in the cluster, or NATS away (then this node answers the hello: not resumed)."""
        try:
            record = await self.lookup(token)
            if record is not None:
                return await self.claim(str(record["room"])), int(record["user"])
        except Exception as exc:
            log.warning("cluster: cannot look up a resume: %s", exc)
        return None

    # -- resume anywhere: members' records in NATS -----------------------------------

    async def lookup(self, token: str) -> dict[str, Any] | None:
        """The record of the member resumable with ``token`` (None: not in the cluster)."""
        if not _TOKEN.fullmatch(token):
            return None
        found = await self.directory.values(f"member.*.{token}")
        for value in found.values():
            record: dict[str, Any] = msgpack.unpackb(value)
            return record
        return None

    def restore_room(self, room: str, records: list[dict[str, Any]], now: float) -> int:
        """Park the members of ``room`` recorded by its lost owner, for their clients to
        resume here (``server.resume.restore``); returns how many were parked."""
        target = self.core.rooms.get(room)
        if target is None:
            target = self.core.room_for(room)
        parked = 0
        for r in records:
            member = Member(
                int(r["user"]), str(r["name"]), {str(k): int(v) for k, v in r["streams"].items()},
                float(r["rate"]), Outbox(self.core.config.max_event_queue), label=r["label"],
                velocities=bool(r["v"]), sends_velocities=bool(r["sv"]),
                compact=bool(r["compact"]), echo=bool(r["echo"]),
            )  # fmt: skip
            member.asked_rate = member.rate
            parked += resume.restore(self.core, target, member, str(r["token"]), now)
        self.apply(self.core.pending())
        if parked:
            log.warning("cluster: room %r came here with %d members to resume", room, parked)
        return parked

    async def adopt(self, room: str) -> None:
        """This node owns ``room`` now and has no state of it: take in the members its
        last owner recorded (if it was lost with them)."""
        held = self.core.rooms.get(room)
        if held is not None and held.members:
            return
        values = await self.directory.values(member_key(room))
        records = [msgpack.unpackb(v) for v in values.values()]
        if records:
            self.restore_room(room, records, self.clock())

    def _records(self) -> dict[str, bytes]:
        """Key -> record of every resumable member of the rooms this node owns."""
        core = self.core
        parked = core.parking.tokens()
        out: dict[str, bytes] = {}
        for name, room in core.rooms.items():
            if not self.directory.owns(name):
                continue
            for member in room.members.values():
                peer = core.connected(member.user)
                token = (
                    parked.get(member.user)
                    if member.parked or peer is None
                    else (peer.resume_token)
                )
                if token is None:
                    continue
                record = {
                    "room": name, "user": member.user, "name": member.name,
                    "streams": member.streams, "rate": member.asked_rate or member.rate,
                    "label": member.label, "v": member.velocities,
                    "sv": member.sends_velocities, "compact": member.compact,
                    "echo": member.echo, "token": token,
                }  # fmt: skip
                out[member_key(name, token)] = msgpack.packb(record)
        return out

    async def _sync_records(self) -> None:
        """Write new and changed member records, refresh old ones, delete those gone."""
        now = self.clock()
        records = self._records()
        for key, value in records.items():
            written = self._written.get(key)
            if written is None or written[0] != value or now - written[1] > RECORD_TTL / 3:
                await self.directory.put(key, value, RECORD_TTL)
                self._written[key] = (value, now)
        for key in [k for k in self._written if k not in records]:
            del self._written[key]
            await self.directory.delete(key)

    def recording_metadata(self, room: str) -> dict[str, str]:
        """What a recording of ``room`` made here says of the cluster: this node, and
        the lost node whose recording of the room it continues."""
        out = {"cluster_node": self.name}
        lost = self.taken_from.pop(room, None)
        if lost is not None:
            out["continues_from_node"] = lost
        return out

    # -- upkeep ----------------------------------------------------------------------

    async def _alive(self, node: str) -> bool:
        """Whether ``node`` answers (False only when NATS says nobody listens)."""
        try:
            await self.directory.nc.request(alive(node), b"", timeout=self.directory.lease / 3)
        except nats.errors.NoRespondersError:
            return False
        except Exception:  # a timeout, NATS away: not proof that it is gone
            return True
        return True

    async def _upkeep(self) -> None:
        while True:
            await asyncio.sleep(self.directory.lease / 3)
            try:
                await self._round()
            except Exception as exc:  # NATS away: the rooms here keep running
                _stop_if_cancelled()
                # (while NATS is away the lease keeper has said so, once)
                level = logging.DEBUG if self.directory.unreachable else logging.WARNING
                log.log(level, "cluster: upkeep failed (%s); retrying", exc)
            _stop_if_cancelled()

    async def _keep_records(self) -> None:
        """Member records to NATS within ``RECORD_INTERVAL`` of a join or a leave (a
        node lost sooner loses that member's resume: it rejoins)."""
        while True:
            await asyncio.sleep(RECORD_INTERVAL)
            try:
                await self._sync_records()
            except Exception as exc:  # NATS away: said by the lease keeper
                _stop_if_cancelled()
                log.debug("cluster: member records not written (%s)", exc)
            _stop_if_cancelled()

    async def _round(self) -> None:
        began = time.perf_counter()
        await self.directory.nc.rtt(timeout=max(1, int(self.directory.lease)))
        self.rtt = time.perf_counter() - began
        # Rooms that stayed empty a whole round are given up (a join forwarded here
        # meanwhile would have filled them again).
        owned = self.directory.rooms()
        empty = {room for room in owned if room not in self.core.rooms}
        for room in empty & self._empty:
            await self.directory.release(room)
        self._empty = empty
        for owner in sorted(set(self.edge.owners.values())):
            if not await self._alive(owner):
                self._owner_gone(owner)

    async def _on_gone(self, msg: Msg) -> None:
        self._owner_gone(msg.data.decode(errors="replace"))

    def _owner_gone(self, owner: str) -> None:
        """``owner`` is gone: its rooms' clients here reconnect (and resume where a
        live node took their room over); their ids here are free for the members
        restored from its records."""
        clients = self.edge.clients_of(owner)
        if not clients:
            return
        self.owners_lost += 1
        log.warning("cluster: node %s is gone; its %d clients here reconnect", owner, len(clients))
        for econn in clients:
            self.edge.gone(econn, said_bye=False)
            self.core.release_user(econn)
            self.edge.close(econn, *MOVED)

    def _lost(self, room: str) -> None:
        """Another node owns ``room`` now: its members here reconnect (to it)."""
        held = self.core.rooms.get(room)
        if held is None:
            return
        actions: list[Action] = []
        for member in list(held.members.values()):
            peer = self.core.peer_of(member.user)
            actions += self.core.close(peer.conn, *MOVED)
        self.members.route(actions)

    # -- /metrics --------------------------------------------------------------------

    def metrics_text(self) -> str:
        """Prometheus lines of the cluster's figures."""
        rows = [
            ("posecast_cluster_rooms_owned", "gauge", "Rooms this node owns the lease of.",
             len(self.directory.rooms())),
            ("posecast_cluster_remote_members", "gauge",
             "Members of this node's rooms connected through other nodes.",
             len(self.members.conns)),
            ("posecast_cluster_forwarded_clients", "gauge",
             "Clients of this node whose room another node owns.", len(self.edge.owners)),
            ("posecast_cluster_forwarded_frames_total", "counter",
             "Frames this node's clients sent that were forwarded to their rooms' nodes.",
             self.edge.frames_out),
            ("posecast_cluster_received_frames_total", "counter",
             "Frames other nodes forwarded to this node's rooms.", self.members.frames_in),
            ("posecast_cluster_sent_frames_total", "counter",
             "Frames sent to members on other nodes (one NATS message per node and flush).",
             self.members.frames_out),
            ("posecast_cluster_joins_forwarded_total", "counter",
             "Joins handed off to the room's owner node.", self.joins_forwarded),
            ("posecast_cluster_owners_lost_total", "counter",
             "Times an owner node this node forwarded to was found gone.", self.owners_lost),
            ("posecast_cluster_nats_up", "gauge",
             "1 while this node renews its leases in NATS, 0 while NATS is unreachable.",
             int(not self.directory.unreachable)),
            ("posecast_cluster_nats_rtt_seconds", "gauge",
             "Round trip to NATS at the last upkeep round (NaN before it).", self.rtt),
        ]  # fmt: skip
        lines: list[str] = []
        for name, kind, help_, value in rows:
            text = "NaN" if value != value else f"{value:g}" if isinstance(value, float) else value
            lines += [f"# HELP {name} {help_}", f"# TYPE {name} {kind}", f"{name} {text}"]
        return "\n".join(lines) + "\n"
