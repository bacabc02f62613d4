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
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

import nats.errors

from protocol.events import Event
from protocol.messages import Join
from protocol.objects import ROOM_USER
from server.actions import Action
from server.cluster import Directory
from server.core import RelayCore
from server.forward import Edge, Members, alive
from server.limits import normalise_room
from server.room import IdAllocator

__all__ = ["MOVED", "ClusterNode", "cluster_clock", "join_room"]

log = logging.getLogger("posecast.cluster")

#: The close of a client whose room's node is gone, or whose room moved.
MOVED = (1012, "the room's node changed; reconnect")


def cluster_clock() -> Callable[[], float]:
    """The server clock of a cluster node: monotonic, anchored to the wall clock at
    start, so that every node reads the same time (to the hosts' clock sync) and a
    client synced with one node keeps its offset when its frames go to another."""
    anchor = time.time() - time.monotonic()
    return lambda: time.monotonic() + anchor


def join_room(event: Event) -> str | None:
    """The room a join event names (None: not a join, or a name the core refuses)."""
    if not isinstance(event, Join):
        return None
    try:
        return normalise_room(event.room)
    except ValueError:
        return None


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
        directory.on_lost = self._lost
        await members.start()
        await edge.start()
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

    async def close(self) -> None:
        """Give up this node's leases and leave NATS (bounded)."""
        await self.directory.close()

    # -- joins -----------------------------------------------------------------------

    def owns(self, room: str) -> bool:
        return self.directory.owns(room)

    async def claim(self, room: str) -> str:
        """The live node that owns ``room`` now: this one if it was free, or its owner
        was gone (then this node takes it over)."""
        for _ in range(3):
            owner = await self.directory.claim(room)
            if owner == self.name or await self._alive(owner):
                return owner
            if await self.directory.take_over(room, owner):
                return self.name
        return await self.directory.claim(room)

    def hand_off(
        self, conn: int, owner: str, agent: str, address: str, frames: list[bytes | str]
    ) -> bool:
        """Forward connection ``conn`` (welcomed here) to ``owner``, starting with
        ``frames`` (its join, and what followed it); False if the backlog is full."""
        peer = self.core.peer(conn)
        assert peer.user is not None
        self.core.hand_off(conn)
        self.joins_forwarded += 1
        self.edge.open(conn, owner, peer.user, agent, False, address)
        return self.edge.forward(conn, frames)

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
                log.warning("cluster: upkeep failed (%s); retrying", exc)

    async def _round(self) -> None:
        self.rtt = await self.directory.nc.rtt(timeout=max(1, int(self.directory.lease)))
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

    def _owner_gone(self, owner: str) -> None:
        clients = self.edge.clients_of(owner)
        self.owners_lost += 1
        log.warning("cluster: node %s is gone; its %d clients here reconnect", owner, len(clients))
        for econn in clients:
            self.edge.gone(econn, said_bye=False)
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
            ("posecast_cluster_nats_rtt_seconds", "gauge",
             "Round trip to NATS at the last upkeep round (NaN before it).", self.rtt),
        ]  # fmt: skip
        lines: list[str] = []
        for name, kind, help_, value in rows:
            text = "NaN" if value != value else f"{value:g}" if isinstance(value, float) else value
            lines += [f"# HELP {name} {help_}", f"# TYPE {name} {kind}", f"{name} {text}"]
        return "\n".join(lines) + "\n"
