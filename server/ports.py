"""The relay core's ports: what its parts may ask of it, and what it asks of its cluster.

The core (``server.core.RelayCore``) keeps the connections, users and rooms; its
parts hold one rule set each and act on the core only through :class:`Relay`:

==============  =================================================================
part            rules
==============  =================================================================
``joins``       admission, the join deadline, what waits before a join, join,
                leave, spectators (``joins.Joins``: it keeps its own state)
``objects``     shared objects: ownership, flights, their records
``resume``      parking a dropped member, resuming it, the window closing
``tokens``      access tokens at join, renewed, expired; join and event rates
``capacity``    the relay's budget: joins shed when one more member is over it
==============  =================================================================

The parts import this module, never ``server.core``: the core implements
:class:`Relay` by its shape (``typing.Protocol``: mypy checks every call that
passes the core where a ``Relay`` is asked), so dependencies point one way,
core -> parts -> ports, and a part can be read (and tested) without the core.
The surface is what the parts use and no more: sending and refusing, who is
connected, the room table and the user ids, the parking and silence tables, the
settings, and the few hooks that move a deadline or a tick.

The other way, :class:`ClusterView` is what the core asks of the cluster it is a
node of (``server.node.ClusterNode`` implements it; the core never imports it).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING, Protocol

if TYPE_CHECKING:
    from posecast.protocol import ErrorCode, Volume
    from posecast.protocol.events import Message
    from posecast.server.config import ServerConfig
    from posecast.server.handshakes import Handshakes
    from posecast.server.member import IdAllocator, Member
    from posecast.server.parking import Parking
    from posecast.server.peer import Peer
    from posecast.server.room import Room
    from posecast.server.silence import Silence

__all__ = ["ClusterView", "Relay"]


class Relay(Protocol):
    """The relay core as its parts see it (``server.core.RelayCore`` is the one)."""

    # -- state the parts read (each table has its own public methods) -------------------

    @property
    def config(self) -> ServerConfig: ...

    @property
    def volume(self) -> Volume:
        """The rooms' volume: positions outside it are refused."""
        ...

    @property
    def rooms(self) -> Mapping[str, Room]:
        """Room name -> room, every room of this relay."""
        ...

    @property
    def users(self) -> IdAllocator:
        """User ids: taken at hello, given back when no connection or parking holds one."""
        ...

    @property
    def parking(self) -> Parking:
        """Members parked after a drop, under their resume tokens."""
        ...

    @property
    def silence(self) -> Silence:
        """Publishers whose updates stopped (``peer_stalled``)."""
        ...

    @property
    def handshakes(self) -> Handshakes:
        """Admission before and at the handshake, and the join and event rates."""
        ...

    # -- who is connected ----------------------------------------------------------------

    def connected(self, user: int) -> Peer | None:
        """The live connection of ``user`` (None: none, e.g. it is parked)."""
        ...

    def bind_user(self, user: int, peer: Peer) -> None:
        """``user`` is ``peer``'s from its hello on."""
        ...

    def is_spectator(self, user: int | None) -> bool:
        """Whether ``user`` joined as a spectator (publishes nothing, unannounced)."""
        ...

    def new_conn(self) -> int:
        """A new connection id (also for parked members no socket holds)."""
        ...

    # -- what the parts send ------------------------------------------------------------

    def send(self, peer: Peer, message: Message) -> None:
        """Queue a reliable message; overflow closes that connection."""
        ...

    def to_member(self, member: Member, message: Message) -> None:
        """Send to a member's connection (a parked member keeps events only)."""
        ...

    def tell_peers(self, room: Room, member: Member, notice: Message) -> None:
        """Queue ``notice`` (about ``member``) to every other member but spectators."""
        ...

    def refuse(
        self, peer: Peer, code: ErrorCode, message: str, what: str, now: float, charge: bool = True
    ) -> None:
        """A non-fatal error answering ``what``; ``charge``: it costs a misbehaviour token."""
        ...

    def close_peer(self, peer: Peer, code: int, reason: str) -> None:
        """Close ``peer``'s connection with ``code`` (the first close wins)."""
        ...

    def admit_update(self, peer: Peer, now: float) -> bool:
        """Whether an update or event of ``peer`` fits its bucket (a flood closes it)."""
        ...

    # -- hooks that move deadlines and ticks ----------------------------------------------

    def emit_rearm(self) -> None:
        """A deadline of the core's expiries was added or moved."""
        ...

    def rescheduled(self, room: Room) -> None:
        """A member of ``room`` joined, left or changed its rate: its ticks moved."""
        ...

    def forget_room_if_empty(self, room: Room, now: float) -> None:
        """Remove ``room`` once its last member is gone (its recording is finished)."""
        ...


class ClusterView(Protocol):
    """What the core asks of the cluster it is a node of (``server.node.ClusterNode``)."""

    def must_claim(self, room: str) -> bool:
        """Whether a join of ``room`` waits for a claim in the cluster first."""
        ...
