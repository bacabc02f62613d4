"""Test helpers: ``SessionPair`` (two sessions joined by a fake wire) and ``raw_frame``.

Each ``client_send``/``server_send`` encodes through the sending session and
feeds the bytes to the other one, returning what it received. No sockets, no
event loop. ``raw_frame`` packs any map, valid or not, to play a hostile peer.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import msgpack

from posecast.protocol.events import Event, Message
from posecast.protocol.messages import Hello, Join, Joined
from posecast.protocol.session import ClientSession, ServerSession

__all__ = ["SessionPair", "raw_frame"]


def raw_frame(type_: object, **fields: object) -> bytes:
    """One msgpack map {"type": type_, **fields}, with no validation at all."""
    data: bytes = msgpack.packb({"type": type_, **fields})
    return data


class SessionPair:
    """A ClientSession and a ServerSession talking through bytes."""

    def __init__(
        self, client: ClientSession | None = None, server: ServerSession | None = None
    ) -> None:
        self.client = client if client is not None else ClientSession()
        self.server = server if server is not None else ServerSession()

    def client_send(self, message: Message) -> list[Event]:
        """Send from the client; return the server's events."""
        return self.server.receive_data(self.client.send(message))

    def server_send(self, message: Message) -> list[Event]:
        """Send from the server; return the client's events."""
        return self.client.receive_data(self.server.send(message))

    def handshake(
        self,
        *,
        user: int = 1,
        room: str = "lab",
        streams: Sequence[str] = ("head", "left", "right"),
        ids: Mapping[str, int] | None = None,
        rate: float = 20.0,
        server_time: float = 0.0,
        sends_velocities: bool = False,
        wants_velocities: bool = False,
        codec: str = "raw",
    ) -> Joined:
        """hello, welcome, join, joined; stream ids default to 0, 1, 2, ... in order."""
        self.client_send(Hello(agent="session-pair"))
        self.server_send(self.server.make_welcome(user, server_time))
        join = Join(
            room=room,
            streams=tuple(streams),
            rate=rate,
            sends_velocities=sends_velocities,
            wants_velocities=wants_velocities,
            codec=codec,
        )
        self.client_send(join)
        assigned = dict(ids) if ids is not None else {name: i for i, name in enumerate(streams)}
        joined = Joined(room=room, streams=assigned, rate=rate)
        self.server_send(joined)
        return joined
