"""Forwarding between cluster nodes: a room's members that came through other nodes.

In a cluster (``server/cluster.py``) one node owns each room. A client may
connect to any node: when it joins a room another node owns, the node it came
through (its *edge*) keeps the websocket and forwards, over NATS, every frame
the client sends to the owner, and writes to the websocket every frame the
owner sends back. On the owner the client is a connection of its relay core
like any other (:class:`Members`), so every rule, limit, error, token and
recording is the owner's, exactly as on one server; only the socket is
elsewhere. Its user id is the one its edge gave it at hello (each node has a
block of ids, ``Directory.user_ids``), so the welcome it already has stays
true.

Subjects and messages (msgpack arrays), ordered per publisher and subject as
NATS keeps them:

``posecast.node.<OWNER>.in`` (edge -> owner)
    ``["open", edge, econn, user, agent, resumable, address, token, hello]``: a
    client of the edge, already welcomed there (with resume ``token``), comes to
    one of the owner's rooms; with ``hello`` true it was not welcomed: it resumes
    a member of the owner, and its hello is the first of its frames;
    ``["frames", edge, econn, [frame, ...]]``: what it sent, in order;
    ``["gone", edge, econn, said_bye]``: its websocket ended.
``posecast.node.<EDGE>.out`` (owner -> edge)
    ``["frames", [[econn, ...], frame], ...]``: frames to write, each with the
    edge's connections it goes to: a snapshot that is the same bytes for a
    tick group is sent to each edge once, whatever its number of members
    there; ``["close", econn, code, reason]``: close that websocket.

The owner's :class:`Members` writes what its core hands out for remote
members in one batch per edge each time its loop runs (after a tick, after a
received frame), not one NATS message per frame.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

import msgpack
from nats.aio.client import Client as Nats
from nats.aio.msg import Msg

from posecast.protocol import Hello, encode_message
from posecast.server.actions import Action, Close, Wake
from posecast.server.core import RelayCore

__all__ = ["MAX_EDGE_BACKLOG", "Edge", "Members", "alive", "inbox", "outbox"]

log = logging.getLogger("posecast.cluster")


def inbox(node: str) -> str:
    """The subject a node's hosted members' frames come in on."""
    return f"posecast.node.{node}.in"


def outbox(node: str) -> str:
    """The subject a node receives its forwarded clients' frames on."""
    return f"posecast.node.{node}.out"


@dataclass
class Members:
    """The owner's side: remote members as connections of this node's core.

    ``apply`` carries out the actions that are not about remote members (the
    adapter's); run :meth:`run` under the adapter's TaskGroup.
    """

    core: RelayCore
    nc: Nats
    node: str
    apply: Callable[[list[Action]], None]
    clock: Callable[[], float] = time.monotonic
    wall_clock: Callable[[], float] = time.time
    #: A recording relay's room opener (``RelayServer.prepare_room``): a join of a
    #: room not open yet waits for its recorder, as a local join does.
    prepare: Callable[[str], Awaitable[None]] | None = None
    #: Waits until rooms this node is taking over have their members in
    #: (``ClusterNode.settled``): a resume forwarded here waits for it.
    settle: Callable[[], Awaitable[None]] | None = None
    #: (edge, edge connection) -> core connection, and back.
    conns: dict[tuple[str, int], int] = field(default_factory=dict)
    remote: dict[int, tuple[str, int]] = field(default_factory=dict)
    _dirty: set[int] = field(default_factory=set)
    _closing: list[tuple[str, int, int, str]] = field(default_factory=list)
    _ready: asyncio.Event = field(default_factory=asyncio.Event)
    #: Frames and NATS messages sent to edges (``/metrics``: forwarded traffic).
    frames_out: int = 0
    messages_out: int = 0
    frames_in: int = 0

    async def start(self) -> None:
        """Subscribe to this node's inbox (the server has it when this returns)."""
        await self.nc.subscribe(inbox(self.node), cb=self._on_message)
        await self.nc.subscribe(alive(self.node), cb=self._on_alive)
        await self.nc.flush()

    async def _on_alive(self, msg: Msg) -> None:
        await msg.respond(b"1")

    async def _on_message(self, msg: Msg) -> None:
        try:
            item: list[Any] = msgpack.unpackb(msg.data)
            kind, edge, econn = item[0], str(item[1]), int(item[2])
        except Exception:
            log.warning("cluster: a malformed message on %s dropped", msg.subject)
            return
        key = (edge, econn)
        now = self.clock()
        if kind == "open" and key not in self.conns:
            if self.settle is not None:
                await self.settle()  # a room just taken over: its members come in first
                now = self.clock()
            self._open(key, item, now)
        elif kind == "frames" and key in self.conns:
            conn = self.conns[key]
            for data in item[3]:
                self.frames_in += 1
                frame = data if isinstance(data, str) else bytes(data)  # a text frame: refused
                if self.prepare is None:
                    self.route(self.core.receive(conn, frame, now, self.wall_clock()))
                    continue
                for event in self.core.frame(conn, frame):
                    room = self.core.room_to_open(conn, event, self.wall_clock())
                    if room is not None:  # a recorded room opens first, off the loop
                        await self.prepare(room)
                        now = self.clock()
                    self.route(self.core.handle(conn, event, now, self.wall_clock()))
        elif kind == "gone" and key in self.conns:
            conn = self.conns.pop(key)
            del self.remote[conn]
            self._dirty.discard(conn)
            self.route(self.core.disconnect(conn, now, bool(item[3])))

    def _open(self, key: tuple[str, int], item: list[Any], now: float) -> None:
        user, agent, resumable, address = int(item[3]), str(item[4]), bool(item[5]), item[6]
        token = item[7] if len(item) > 7 else None
        hello_follows = len(item) > 8 and bool(item[8])
        conn = self.core.connect(now, f"{key[0]}/{address}")
        self.conns[key], self.remote[conn] = conn, key
        peer = self.core.peer(conn)
        peer.preset_user = user
        self.route(self.core.pending())
        if hello_follows:
            return  # a resume: the client's own hello comes next, and this node answers it
        hello = encode_message(Hello(agent=agent, resumable=resumable))
        self.route(self.core.receive(conn, hello, now, self.wall_clock()))
        # The edge welcomed the client already (with this user id and resume token):
        # drop this welcome; a drop of its socket parks it under the edge's token.
        self.core.take(conn, now)
        self._dirty.discard(conn)
        if token and peer.resume_token is not None:
            peer.resume_token = str(token)

    def route(self, actions: list[Action]) -> None:
        """Keep the actions about remote members, hand the others to the adapter."""
        local: list[Action] = []
        for action in actions:
            if isinstance(action, Wake) and action.conn in self.remote:
                self._dirty.add(action.conn)
                self._ready.set()
            elif isinstance(action, Close) and action.conn in self.remote:
                edge, econn = self.remote[action.conn]
                self._closing.append((edge, econn, action.code, action.reason))
                self._dirty.add(action.conn)  # the error that explains it goes first
                self._ready.set()
            else:
                local.append(action)
        if local:
            self.apply(local)

    async def run(self) -> None:
        """Write the remote members' frames to their edges as they are ready."""
        while True:
            await self._ready.wait()
            self._ready.clear()
            await self.flush()

    async def flush(self) -> None:
        """One message per edge with every frame due to its clients."""
        now = self.clock()
        batches: dict[str, list[tuple[int, list[bytes]]]] = {}
        for conn in list(self._dirty):
            frames, _ = self.core.take(conn, now)
            key = self.remote.get(conn)
            if key is not None and frames:
                batches.setdefault(key[0], []).append((key[1], frames))
        self._dirty.clear()
        self.route(self.core.pending())
        for edge, seqs in batches.items():
            items = _batch_items(seqs)
            self.frames_out += sum(len(t) for t, _ in items)
            self.messages_out += 1
            await self.nc.publish(outbox(edge), msgpack.packb(["frames", *items]))
        closing, self._closing = self._closing, []
        for edge, econn, code, reason in closing:
            await self.nc.publish(outbox(edge), msgpack.packb(["close", econn, code, reason]))


def _batch_items(seqs: list[tuple[int, list[bytes]]]) -> list[list[Any]]:
    """One edge's frames as ``[targets, frame]`` items, in the order the edge writes them.

    ``seqs``: each edge connection's frames in order. The same bytes object (a tick
    group's snapshot, a presence notice) goes once with all its targets, and every
    connection still gets its frames in its own order: the items are a topological
    order of "comes before" over all the sequences (a member that joined since the
    last write has its ``joined`` before the snapshot it shares with the others).
    Should two connections hold shared frames in opposite orders, nothing is shared.
    """
    frames: dict[int, bytes] = {}
    targets: dict[int, list[int]] = {}
    after: dict[int, list[int]] = {}
    before: dict[int, int] = {}
    for econn, seq in seqs:
        prev = -1
        for data in seq:
            key = id(data)
            if key not in frames:
                frames[key], targets[key], after[key], before[key] = data, [], [], 0
            targets[key].append(econn)
            if prev != -1:
                after[prev].append(key)
                before[key] += 1
            prev = key
    ready = deque(key for key in frames if before[key] == 0)
    order: list[int] = []
    while ready:
        key = ready.popleft()
        order.append(key)
        for nxt in after[key]:
            before[nxt] -= 1
            if before[nxt] == 0:
                ready.append(nxt)
    if len(order) < len(frames):
        return [[[econn], data] for econn, seq in seqs for data in seq]
    return [[targets[key], frames[key]] for key in order]


#: Frames an edge holds for its owners while NATS takes them (per node, at most).
MAX_EDGE_BACKLOG = 8192


def alive(node: str) -> str:
    """The subject a live node answers on (no responders: the node is gone)."""
    return f"posecast.node.{node}.alive"


@dataclass
class Edge:
    """The edge's side: its clients whose room another node owns.

    ``deliver(econn, frame)`` writes a frame to that client's websocket;
    ``close(econn, code, reason)`` closes it. What the clients send is queued
    here without waiting (``open``, ``forward``, ``gone`` are plain calls from the
    websocket's callbacks) and published in order by :meth:`run`; the queue holds
    at most ``max_backlog`` frames: ``forward`` returns False past it (NATS is not
    taking them), and the adapter closes that client.
    """

    nc: Nats
    node: str
    deliver: Callable[[int, bytes], None]
    close: Callable[[int, int, str], None]
    max_backlog: int = MAX_EDGE_BACKLOG
    #: Edge connection -> the node that owns its room.
    owners: dict[int, str] = field(default_factory=dict)
    _queue: list[tuple[str, bytes]] = field(default_factory=list)
    _frames_queued: int = 0
    _ready: asyncio.Event = field(default_factory=asyncio.Event)
    #: Frames forwarded to owners, and frames delivered from them (``/metrics``).
    frames_out: int = 0
    frames_in: int = 0

    async def start(self) -> None:
        """Subscribe to this node's outbox (the server has it when this returns)."""
        await self.nc.subscribe(outbox(self.node), cb=self._on_message)
        await self.nc.flush()

    def _push(self, owner: str, item: list[Any], frames: int = 0) -> None:
        self._queue.append((inbox(owner), msgpack.packb(item)))
        self._frames_queued += frames
        self._ready.set()

    def open(
        self,
        econn: int,
        owner: str,
        user: int,
        agent: str,
        resumable: bool,
        address: str,
        token: str | None = None,
        hello_follows: bool = False,
    ) -> None:
        """Client ``econn`` (welcomed here as ``user``, with resume ``token``) goes to a
        room of ``owner``; ``hello_follows``: it resumes, its hello is forwarded."""
        self.owners[econn] = owner
        item = ["open", self.node, econn, user, agent, resumable, address, token, hello_follows]
        self._push(owner, item)

    def forward(self, econn: int, frames: list[bytes | str]) -> bool:
        """Frames the client sent, in order; False if the backlog is full."""
        owner = self.owners.get(econn)
        if owner is None or not frames:
            return True
        if self._frames_queued + len(frames) > self.max_backlog:
            return False
        self.frames_out += len(frames)
        self._push(owner, ["frames", self.node, econn, frames], len(frames))
        return True

    def gone(self, econn: int, said_bye: bool) -> None:
        """The client's websocket ended."""
        owner = self.owners.pop(econn, None)
        if owner is not None:
            self._push(owner, ["gone", self.node, econn, said_bye])

    def clients_of(self, owner: str) -> list[int]:
        """This edge's clients in rooms of node ``owner``."""
        return [econn for econn, node in self.owners.items() if node == owner]

    async def run(self) -> None:
        """Publish what the clients sent, in order, as it comes."""
        while True:
            await self._ready.wait()
            self._ready.clear()
            queue, self._queue, self._frames_queued = self._queue, [], 0
            for subject, data in queue:
                await self.nc.publish(subject, data)

    async def _on_message(self, msg: Msg) -> None:
        try:
            item: list[Any] = msgpack.unpackb(msg.data)
        except Exception:
            log.warning("cluster: a malformed message on %s dropped", msg.subject)
            return
        if item[0] == "frames":
            for targets, data in item[1:]:
                frame = bytes(data)
                for econn in targets:
                    if econn in self.owners:
                        self.frames_in += 1
                        self.deliver(int(econn), frame)
        elif item[0] == "close":
            econn = int(item[1])
            if econn in self.owners:
                self.close(econn, int(item[2]), str(item[3]))
