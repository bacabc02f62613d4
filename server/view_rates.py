"""View-aware rates (``join.budget_deg``): each peer at the rate its distance allows.

A subscriber that joins with an error budget in degrees of visual angle asks the
relay to send each peer's streams at the lowest rate whose expected interpolation
error, seen from the subscriber's head, stays within that budget. Sans I/O: time
and poses are arguments, nothing here reads a clock.

The model of expected error (checked on traces in ``docs/lab/results.md``, "The
model of expected error, checked"): between keyframes ``dt`` apart, linear
interpolation of a point whose acceleration stays within ``A`` is off by at most
``A dt^2 / 8``. The relay receives every update of a stream, so it estimates
``A`` causally (:class:`Acceleration`, the same numbers as
:func:`causal_acceleration` on a whole trace): the largest ``|a|`` over the last
``WINDOW_S`` seconds, from second differences over ``STRIDE`` updates. The point
it follows is the stream's *tip* (``TIP_OFFSET_M`` along the device's -z), the
point whose error DESIGN.md's angular error measures, so rotation counts too.

The choice (:func:`divisor`): a peer seen at distance ``d`` from the subscriber's
head may be sent every ``dt`` seconds while ``margin A dt^2 / 8 <= d tan(budget)``;
its rate is the subscriber's snapshot rate divided by a whole ``k`` (so it falls
on the subscriber's own tick grid), the largest ``k`` that keeps that bound and
keeps the rate at or above the server's ``min_rate``. A peer is the slowest of its
streams' needs (its fastest one decides). A stream whose acceleration is not known
yet (fewer than ``2 STRIDE + 1`` updates) goes at the full rate.

:class:`ViewState` is one subscriber's per-peer schedule (which peers are due at a
tick, the store versions each peer's streams were last sent at); ``server.room``
uses it to encode only the due peers' streams. :class:`ViewRates` is the server's
setting and the chosen rates' histogram (``/metrics``: ``posecast_view_rate_hz``).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

from posecast.interp.expected_error import Acceleration, divisor, tip_of
from posecast.protocol import pack_snapshot, pack_velocity_snapshot
from posecast.protocol.codec import Volume
from posecast.protocol.codec_relay import GroupSnapshot, RelayEntry, encode_group
from posecast.server.histogram import bucket, histogram_lines

__all__ = [
    "MARGIN",
    "VIEW_RATE_BUCKETS",
    "Motion",
    "ViewRates",
    "ViewState",
    "encode_peers",
    "peer_divisor",
]

#: Safety factor on the predicted error (chosen on ``dev`` traces, see results.md).
MARGIN = 1.0
#: Upper bounds (Hz) of the per-peer rate histogram's buckets.
VIEW_RATE_BUCKETS = (5.0, 6.0, 7.5, 10.0, 15.0, 20.0, 30.0, 45.0, 60.0)


@dataclass
class Motion:
    """What the relay follows of a room's streams for view-aware rates: each stream's
    tip (newest) and its acceleration estimate. Fed by ``Room.ingest``."""

    tips: dict[int, tuple[float, float, float]] = field(default_factory=dict)
    accel: dict[int, Acceleration] = field(default_factory=dict)

    def observe(self, sid: int, t: float, pose: bytes) -> None:
        tip = tip_of(pose)
        self.tips[sid] = tip
        est = self.accel.get(sid)
        if est is None:
            est = self.accel[sid] = Acceleration()
        est.observe(t, tip)

    def forget(self, sid: int) -> None:
        self.tips.pop(sid, None)
        self.accel.pop(sid, None)


@dataclass
class ViewRates:
    """The server's view-aware setting and the histogram of the per-peer rates it chose:
    one observation per subscriber, peer and subscriber tick (over subscriber time),
    per bucket of ``VIEW_RATE_BUCKETS`` then +Inf (not cumulative), and their sum."""

    min_rate: float = 5.0
    margin: float = MARGIN
    counts: list[int] = field(default_factory=lambda: [0] * (len(VIEW_RATE_BUCKETS) + 1))
    total: float = 0.0

    def observe(self, rate: float) -> None:
        self.counts[bucket(rate, VIEW_RATE_BUCKETS)] += 1
        self.total += rate

    def metric_lines(self, members: int) -> list[str]:
        """Prometheus text: the histogram and the gauge of members with a budget."""
        lines = histogram_lines(
            "posecast_view_rate_hz",
            "Rate the relay chose for each peer of each subscriber with an error budget"
            " (join budget_deg), observed at every tick of the subscriber.",
            VIEW_RATE_BUCKETS,
            self.counts,
            self.total,
        )
        lines += [
            "# HELP posecast_view_rate_members Members whose peers' rates the relay "
            "chooses from their error budget now.",
            "# TYPE posecast_view_rate_members gauge",
            f"posecast_view_rate_members {members}",
        ]
        return lines


@dataclass
class ViewState:
    """One subscriber's per-peer schedule. Peers are publishers (user ids, the room's
    objects under ``ROOM_USER``); versions are the room store's."""

    budget_deg: float
    #: Peer -> store version its streams were covered to by the newest snapshot
    #: offered (-1: its next entries go absolute, a key).
    last: dict[int, int] = field(default_factory=dict)
    #: The same, as of the snapshots the subscriber's writer took (delta baselines).
    delivered: dict[int, int] = field(default_factory=dict)
    #: Peer -> the subscriber's tick index when its streams last went.
    sent_tick: dict[int, int] = field(default_factory=dict)
    #: Peer -> its divisor as last chosen (its rate: the snapshot rate / k).
    k: dict[int, int] = field(default_factory=dict)
    #: Peers whose next entries go absolute (a compact subscriber's key, per peer).
    absolute: set[int] = field(default_factory=set)

    @property
    def budget_rad(self) -> float:
        return math.radians(self.budget_deg)

    def reset(self) -> None:
        """Forget the schedule (a rate change): every peer is due, absolute, next tick."""
        self.last.clear()
        self.delivered.clear()
        self.sent_tick.clear()
        self.absolute.clear()

    def due(self, peer: int, tick: int, k: int) -> bool:
        """Whether ``peer`` goes at subscriber tick ``tick`` with divisor ``k``: its
        interval has elapsed, or the tick is on its grid (``tick % k == 0``, where
        subscribers of one rate that chose the same ``k`` meet and share encodes), or
        a snapshot that carried it is about to be replaced unsent."""
        last = self.sent_tick.get(peer)
        return (
            last is None
            or tick - last >= k
            or tick % k == 0
            or self.last.get(peer, -1) != self.delivered.get(peer, -1)
        )


def peer_divisor(
    views: ViewRates | None,
    motion: Motion | None,
    view: ViewState,
    rate: float,
    own: bool,
    eye: tuple[float, ...] | None,
    sids: Sequence[int],
) -> int:
    """A peer's divisor for a subscriber at snapshot ``rate`` whose head is at ``eye``:
    its fastest stream's need (:func:`divisor`). ``own``: the subscriber's own
    streams (an echo, no sight of anyone: the lowest rate). Without a known head or
    motion: 1, the full rate."""
    lo = views.min_rate if views is not None else rate
    k_max = max(1, int(rate / lo + 1e-9))
    if own:
        return k_max
    if views is None or motion is None or eye is None:
        return 1
    hx, hy, hz = eye
    budget, margin = view.budget_rad, views.margin
    k = k_max
    for sid in sids:
        tip, est = motion.tips.get(sid), motion.accel.get(sid)
        if tip is None or est is None:
            return 1
        d = math.sqrt((tip[0] - hx) ** 2 + (tip[1] - hy) ** 2 + (tip[2] - hz) ** 2)
        k = min(k, divisor(budget, est.value(), d, rate, k_max, margin))
    return k


class StoredStream(Protocol):
    """What :func:`encode_peers` reads of a room's stored stream (``server.room``)."""

    user: int
    capture: float
    pose: bytes
    velocity: bytes
    version: int

    def coded(self, volume: Volume) -> list[int]: ...
    def baseline(self, since: int) -> list[int] | None: ...


#: A frame's key: (compact, velocities, ((peer, since version), ...)).
FrameKey = tuple[bool, bool, tuple[tuple[int, int], ...]]


def encode_peers(
    tick: int,
    now: float,
    key: FrameKey,
    publishers: Mapping[int, Sequence[tuple[int, StoredStream]]],
    volume: Volume,
) -> GroupSnapshot | tuple[bytes, int] | None:
    """One encode of the streams of the peers in ``key`` newer than each one's
    ``since`` (compact: delta against the codes as of ``since``; ``since < 0``:
    absolute). None: nothing to send."""
    compact, velocities, wanted = key
    width = 13 if velocities else 7
    raw: list[tuple[int, int, float, bytes, bytes]] = []
    entries: list[RelayEntry] = []
    for user, since in wanted:
        for sid, s in publishers[user]:
            if s.version <= since:
                continue
            if not compact:
                raw.append((s.user, sid, s.capture, s.pose, s.velocity))
                continue
            row = s.coded(volume)
            base = s.baseline(since) if since >= 0 else None
            entries.append(
                (s.user, sid, s.capture, row[:width], None if base is None else base[:width])
            )
    if compact:
        if not entries:
            return None
        return encode_group(tick, now, entries, volume, velocities, trusted=True)
    if not raw:
        return None
    if velocities:
        return pack_velocity_snapshot(tick, now, raw), len(raw)
    return pack_snapshot(tick, now, (e[:4] for e in raw)), len(raw)
