"""One connection as the relay sees it: its session, outbox, buckets and counters.

:class:`Peer` is :class:`server.core.RelayCore`'s record of a connection;
:class:`ConnectionStatistics` is what the server reports of it (statistics,
``/metrics``), and ``COUNTERS`` are the statistics that only ever grow.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from posecast.protocol import Limits, ServerSession, Volume
from posecast.server.actions import INFO, Log
from posecast.server.config import ServerConfig
from posecast.server.limits import Budget
from posecast.server.link import Downlink
from posecast.server.logs import LogLimiter
from posecast.server.member import Member, Outbox
from posecast.server.parked import Parked
from posecast.server.room import Room
from posecast.server.stamps import StampCheck, StampRule

__all__ = ["COUNTERS", "ConnectionStatistics", "Peer", "PeerHost"]


class PeerHost(Protocol):
    """What a :class:`Peer` needs of the relay core that keeps it (``RelayCore`` is one):
    its settings (a peer calls nothing of the core: what it decides, it returns)."""

    @property
    def config(self) -> ServerConfig: ...

    @property
    def limits(self) -> Limits: ...

    @property
    def volume(self) -> Volume: ...


#: ConnectionStatistics fields that only ever grow, summed over ended connections.
COUNTERS = (
    "frames_in",
    "bytes_in",
    "frames_out",
    "bytes_out",
    "snapshots_offered",
    "skips",
    "congestion_skips",
    "event_drops",
    "flood_drops",
    "protocol_errors",
    "stale_captures",
    "future_captures",
    "out_of_bounds",
    "stamps_moved",
)


@dataclass(frozen=True, slots=True)
class ConnectionStatistics:
    user: int | None
    room: str | None
    frames_in: int
    bytes_in: int
    frames_out: int
    bytes_out: int
    snapshots_offered: int
    skips: int
    congestion_skips: int
    event_drops: int
    flood_drops: int
    protocol_errors: int
    #: Updates refused: capture time too old / ahead of the server clock (see
    #: ``max_capture_age``, ``max_capture_ahead``), a position out of the room volume.
    stale_captures: int = 0
    future_captures: int = 0
    out_of_bounds: int = 0
    #: Updates whose capture times the relay moved later (``server/stamps.py``).
    stamps_moved: int = 0
    #: With an emulated link: the rate the server chose for this subscriber (Hz),
    #: snapshots delivered / skipped at the cap / lost, and bytes on the link.
    link_rate_hz: float | None = None
    link_frames: int = 0
    link_cap_skips: int = 0
    link_lost: int = 0
    link_bytes: int = 0


class Peer:
    """One connection as the relay sees it: session state, outbox, bucket, counters."""

    def __init__(
        self,
        conn: int,
        core: PeerHost,
        now: float,
        address: str | None = None,
    ) -> None:
        cfg = core.config
        self.conn = conn
        #: The source address (host) the adapter reported; None in tests.
        self.address = address
        #: Whether :class:`server.limits.Admission` counted it (it was not refused).
        self.admitted = False
        self.session = ServerSession(core.limits, core.volume)
        self.outbox = Outbox(cfg.max_event_queue, 0, cfg.congested_bytes)
        self.outbox.conn = conn
        self.user: int | None = None
        #: The user id given by the cluster node this member came through (its hello
        #: takes it instead of a new one; ``server.forward``).
        self.preset_user: int | None = None
        #: In a cluster: its room is another node's, where its frames are forwarded.
        self.forwarded = False
        self.name = ""
        self.room: Room | None = None
        self.member: Member | None = None
        self.close_request: tuple[int, str] | None = None
        #: When its access token expires, server clock (None: no secret, no expiry).
        self.token_deadline: float | None = None
        #: Its resume token (``hello.resumable``), and the parked member its hello
        #: claimed, until its join re-binds it (see ``server.resume``).
        self.resume_token: str | None = None
        self.parked: Parked | None = None
        self.frames_in = self.bytes_in = self.frames_out = self.bytes_out = 0
        self.event_drops = self.flood_drops = self.protocol_errors = 0
        self.stale_captures = self.future_captures = self.out_of_bounds = 0
        #: When its last stale-capture error went out (``server.capacity.stale_error_due``).
        self.stale_error_at = float("-inf")
        #: Its hello asked for ``error.retry_after`` (``server.capacity.shed``).
        self.wants_retry_after = False
        #: Each refused frame or update costs a token; none left: closed 1008.
        self.budget = Budget(cfg.misbehaviour_burst, cfg.misbehaviour_refill, now)
        #: The emulated downlink (``ServerConfig.link``), set at join.
        self.downlink: Downlink | None = None
        self._bucket = cfg.max_update_rate
        self._bucket_time = now
        self.log_limit = LogLimiter(cfg.peer_log_interval)
        #: Its capture times against its link (a lagging liar's are moved).
        self.stamps = StampCheck(StampRule(cfg.stamp_lag))

    def admit(self, rate: float, now: float) -> bool:
        """Token bucket over pose updates and events: ``rate`` a second, holding one
        second's worth (bursts are fine); what exceeds it is dropped and counted."""
        self._bucket = min(rate, self._bucket + (now - self._bucket_time) * rate)
        self._bucket_time = now
        if self._bucket < 1.0:
            self.flood_drops += 1
            if self.room is not None and self.user is not None:
                self.room.note_drop("flood", self.user)
            return False
        self._bucket -= 1.0
        return True

    def would_admit(self, rate: float, now: float) -> bool:
        """Whether :meth:`admit` would take one now (nothing spent, nothing counted)."""
        return min(rate, self._bucket + (now - self._bucket_time) * rate) >= 1.0

    def count_refused(self, kind: str) -> None:
        """Count an update refused for ``kind`` (a :class:`server.limits.Refusal` kind)."""
        if kind == "stale-capture":
            self.stale_captures += 1
        elif kind == "future-capture":
            self.future_captures += 1
        else:
            self.out_of_bounds += 1

    def log(self, now: float, msg: str, *args: object) -> Log | None:
        """The line to log of what this peer caused, at most one per
        ``peer_log_interval`` (None: held back, counted for the next)."""
        held = self.log_limit.admit(now)
        if held is None:
            return None
        return Log(INFO, msg + "%s", (*args, self.log_limit.note(held)))

    def statistics(self) -> ConnectionStatistics:
        m = self.member
        link = None if self.downlink is None else self.downlink.link
        return ConnectionStatistics(
            user=self.user,
            room=self.room.name if self.room else None,
            frames_in=self.frames_in,
            bytes_in=self.bytes_in,
            frames_out=self.frames_out,
            bytes_out=self.bytes_out,
            snapshots_offered=self.outbox.snapshots_offered,
            skips=self.outbox.skips,
            congestion_skips=m.congestion_skips if m else 0,
            event_drops=self.event_drops,
            flood_drops=self.flood_drops,
            protocol_errors=self.protocol_errors,
            stale_captures=self.stale_captures,
            future_captures=self.future_captures,
            out_of_bounds=self.out_of_bounds,
            stamps_moved=self.stamps.corrected,
            link_rate_hz=m.rate if (m is not None and link is not None) else None,
            link_frames=link.frames if link else 0,
            link_cap_skips=link.cap_skips if link else 0,
            link_lost=link.lost if link else 0,
            link_bytes=link.bytes if link else 0,
        )
