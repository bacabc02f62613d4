"""Everything ``posecast serve`` can set: :class:`ServerConfig` (one frozen dataclass).

Each field is a ``posecast serve`` flag and a ``POSECAST_*`` variable; the
limits are explained in ``docs/guides/security.md``. ``server.core`` re-exports it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

from posecast.protocol.codec import DEFAULT_VOLUME, Volume
from posecast.server.link import LinkTier

if TYPE_CHECKING:
    from pathlib import Path

__all__ = ["DEFAULT_EVENT_QUEUE", "ServerConfig"]

#: Control messages (events, peer notices, pongs) a connection may have queued.
DEFAULT_EVENT_QUEUE = 256


@dataclass(frozen=True)
class ServerConfig:
    """Everything ``posecast serve`` can set."""

    host: str = "127.0.0.1"
    port: int = 8765
    #: Serve ``wss://`` with this certificate chain and private key (PEM files).
    certfile: Path | None = None
    keyfile: Path | None = None
    #: Keepalive: a ping every ``ping_interval`` s; a peer that has not answered
    #: within ``ping_timeout`` s is dead and closed (1011): gone within 5 s.
    ping_interval: float = 2.5
    ping_timeout: float = 2.5
    rate: float = 20.0
    min_rate: float = 5.0
    max_rate: float = 30.0
    secret: str | None = None
    max_event_queue: int = DEFAULT_EVENT_QUEUE
    #: A subscriber with more than this many bytes unsent gets no new snapshot.
    congested_bytes: int = 64 * 1024
    #: Pose updates per second one connection may publish (bucket of one second).
    max_update_rate: float = 120.0
    close_timeout: float = 2.0
    #: Record every room session into this folder (``posecast serve --record``).
    record_dir: Path | None = None
    #: Where the recorder's MCAP writer runs: ``process`` (a child process fed the
    #: raw update frames through a pipe; the relay's own cost per update is two
    #: list appends) or ``thread`` (a thread of the server's process).
    record_writer: Literal["process", "thread"] = "process"
    #: Emulate this network tier on every subscriber's downlink (``--link``).
    link: LinkTier | None = None
    #: Snapshots held in one subscriber's emulated link at most (older ones drop).
    link_max_in_flight: int = 64
    #: Honour ``join.budget_deg`` (view-aware per-peer rates, ``server.view_rates``;
    #: ``serve --no-view-rates``: every peer at the snapshot rate), and the safety
    #: factor on the expected error it uses.
    view_rates: bool = True
    view_margin: float = 1.0
    #: What a peer causes (its protocol errors, the errors it reports) is logged
    #: at most once per this many seconds per connection, with a count of the
    #: records held back, so that a misbehaving peer cannot fill the disk.
    peer_log_interval: float = 1.0
    # -- limits (docs/guides/security.md); 0 turns a count limit off --------------------------
    #: An update captured longer ago than this (s, server clock) is refused.
    max_capture_age: float = 1.0
    #: ... and one captured later than now plus this (the clock-sync error allowance).
    max_capture_ahead: float = 0.25
    #: A stream whose capture times are older than its link explains (its smallest age
    #: on arrival over half its round trip) by more than this (s) has them moved later
    #: by that much (``server/stamps.py``: a lagging liar); 0: off.
    stamp_lag: float = 0.025
    #: Positions must lie within this box (m): the room volume, stated at welcome,
    #: in which compact codes quantise positions (0.5 mm steps at most).
    volume: Volume = DEFAULT_VOLUME
    #: If set, the volume is the cube +-this (m) on each axis instead.
    room_extent: float | None = None

    #: Misbehaviour budget: tokens a connection holds, and refills a second; each
    #: protocol error or refused update or join costs one; none left: close 1008.
    misbehaviour_burst: int = 20
    misbehaviour_refill: float = 5.0
    #: A connection that has not joined a room this long after it opened is closed.
    join_timeout: float = 5.0
    #: A TCP connection whose websocket handshake (or plain HTTP request) is not done
    #: this long after it was accepted is dropped (``server/handshakes.py``).
    handshake_timeout: float = 2.0
    #: Across connections, per source address (and per token user for joins and events):
    #: connections, joins and events a second (bursts of 10 s worth); 0: off
    #: (``server/guard.py``).
    max_connect_rate: float = 100.0
    max_join_rate: float = 60.0
    max_event_rate: float = 1000.0
    #: A resumable client's dropped connection keeps its place this long (s); 0: off.
    resume_window: float = 10.0
    #: A member whose updates stop this long (s) while its connection stays up (a
    #: frozen browser tab answers pings) is announced ``peer_stalled`` to its
    #: peers, and ``peer_resumed`` when its updates come back; 0: off.
    stall_after: float = 1.0
    max_connections: int = 1024
    max_connections_per_address: int = 64
    max_rooms: int = 256
    max_members: int = 64
    #: Shared objects a room may hold (``object_create`` over it is refused).
    max_objects: int = 64
    #: Rooms recorded at once (``--record``); a join opening one more is refused.
    max_recorded_rooms: int = 32
    #: The relay's capacity budget (``server.capacity``, docs/guides/deployment.md): over
    #: it a hello or join is refused ``server-full`` (1013). Share of one core its process
    #: may use; p99 tick lag (s); bytes unsent over all connections. 0 turns one off.
    capacity_cpu: float = 0.8
    capacity_lag: float = 0.025
    capacity_backlog: int = 32 << 20
    #: Members from which CPU and lag count (fewer: only the backlog can refuse).
    capacity_min_members: int = 16
    #: Join the cluster of relays sharing this NATS (``nats://HOST:PORT``; None: alone).
    cluster: str | None = None
    #: This node's name in the cluster (unique among live nodes; None: the host name).
    node: str | None = None
    #: Seconds a node's and a room's lease live without renewal.
    cluster_lease: float = 3.0
    #: Browser origins allowed to connect (``--allow-origin``; normalised as in
    #: ``server.http``); others get HTTP 403. None: any origin. Handshakes
    #: without an Origin header (non-browser clients) are never refused for it.
    allow_origins: tuple[str, ...] | None = None

    @property
    def room_volume(self) -> Volume:
        """The volume in force: ``volume``, or the cube of ``room_extent``."""
        e = self.room_extent
        return self.volume if e is None else Volume((-e, -e, -e), (e, e, e))
