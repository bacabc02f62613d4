"""A publisher's capture times against its link: the relay's answer to a lagging liar, sans I/O.

A member may stamp its poses with capture times older than they are (a "lagging
liar"). Within ``max_capture_age`` the relay accepts them, and every receiver
sizes its playout delay D from the ages it sees: a lag under one publish interval
looks to a receiver like an honest phase offset (``client/playout.py``), so it
raises everyone's D. The relay can tell, because it sees each update arrive.

For an honest client that synchronised its clock the NTP way (``docs/protocol.md``
section 7), an update's age on arrival at the relay (arrival minus claimed capture,
server clock) is its capture-to-send delay plus half its round trip plus the
uplink's queueing of the moment: the clock-sync error and the one-way delay add up
to half the round trip, whatever the asymmetry of the path. The smallest age over a
few seconds therefore exceeds half the round trip by the client's capture-to-send
delay alone (queueing only adds, the minimum sheds it). A liar's smallest age
exceeds it by its lag as well.

:class:`StampCheck` (one per connection) keeps, per stream it publishes, the
smallest age of its updates over ``window`` seconds (in four blocks; judged from
the first on, 0.5 s), and the
connection's round trip as the relay's keepalive pings measure it (the lowest of
the last ``RTT_SAMPLES``). Once a stream's window holds ``min_updates`` updates
and a round trip is known, its *unexplained lag* is ``min(age) - rtt / 2``. Over
``threshold`` (``ServerConfig.stamp_lag``, ``posecast serve --stamp-lag``, 25 ms by
default: one 60 Hz render frame between capture and send, with room to spare), the
relay moves that stream's capture times later by the whole unexplained lag, so
receivers see its keyframes as fresh as an honest client's; it keeps doing so while
the lag stays over half the threshold. A correction grows at once and shrinks by at
most ``SLEW`` of the time that passed, so a stream's capture times never go back.
A stream under the threshold is never touched: its update goes on as it came (the
same object, the same bytes).

What it cannot see: a lag under ``threshold`` (which raises D by at most that much);
a client that delays its answers to the relay's pings (an honest slow link looks the
same: its own D is what that costs the room); forwarded members of a cluster (their
pings are another node's), whose stamps are never moved.
"""

from __future__ import annotations

import math
import struct
from collections import deque
from dataclasses import dataclass

import numpy as np

from posecast.protocol import UPDATE_DTYPE, UPDATE_VELOCITY_DTYPE, PoseUpdate

__all__ = ["RTT_SAMPLES", "SLEW", "StampCheck", "StampRule"]

#: Round trips kept per connection (the lowest counts): 8 keepalive pings, 20 s.
RTT_SAMPLES = 8
#: A correction shrinks by at most this share of the time that passed (capture times
#: then still move forward at 90 % of the clock's pace: never backwards).
SLEW = 0.1
#: Blocks of a window: the window slides by a quarter of itself.
BLOCKS = 4
#: Stream id (u16) and dt (f32) of each update record, by record size (``protocol.poses``).
_HEADS = {
    size: struct.Struct(f"<Hf{size - 6}x")
    for size in (UPDATE_DTYPE.itemsize, UPDATE_VELOCITY_DTYPE.itemsize)
}


@dataclass(frozen=True, slots=True)
class StampRule:
    """The rule's parameters (``ServerConfig`` holds the first; the others are fixed)."""

    #: Unexplained lag (s) over which a stream's capture times are moved; 0: never.
    threshold: float = 0.025
    #: Seconds of updates whose smallest age is judged.
    window: float = 2.0
    #: Updates of a stream the window must hold before it is judged.
    min_updates: int = 10


class _Track:
    """One stream's smallest ages, block by block, and the correction in force."""

    __slots__ = ("blocks", "counts", "cur", "end", "lag", "n", "shift", "target")

    def __init__(self, end: float) -> None:
        self.blocks: deque[float] = deque(maxlen=BLOCKS)
        self.counts: deque[int] = deque(maxlen=BLOCKS)
        self.cur = math.inf  # the current block's smallest age
        self.n = 0  # and its updates
        self.end = end  # when the current block ends
        self.shift = 0.0  # the correction applied now (s)
        self.target = 0.0  # the correction the window asks for
        self.lag = math.nan  # the unexplained lag last judged (NaN: not judged yet)


class StampCheck:
    """One connection's capture times judged against its link (see the module)."""

    __slots__ = ("_last", "_rtts", "_tracks", "corrected", "rtt", "rule")

    def __init__(self, rule: StampRule) -> None:
        self.rule = rule
        #: The lowest recent round trip (s; NaN before the first pong).
        self.rtt = math.nan
        #: Updates whose capture times this connection had moved (the metric's count).
        self.corrected = 0
        self._rtts: deque[float] = deque(maxlen=RTT_SAMPLES)
        self._tracks: dict[int, _Track] = {}
        self._last = -math.inf

    def round_trip(self, rtt: float) -> None:
        """A keepalive pong came back ``rtt`` s after its ping."""
        if math.isfinite(rtt) and rtt >= 0.0:
            self._rtts.append(rtt)
            self.rtt = min(self._rtts)

    def lags(self) -> dict[int, float]:
        """The unexplained lag (s) last judged per stream (the judged ones only)."""
        return {sid: t.lag for sid, t in self._tracks.items() if not math.isnan(t.lag)}

    def shifts(self) -> dict[int, float]:
        """The correction (s) in force per stream (only the moved ones)."""
        return {sid: t.shift for sid, t in self._tracks.items() if t.shift > 0.0}

    def check(self, update: PoseUpdate, now: float) -> PoseUpdate:
        """``update`` as the room should store it, arrived at ``now`` (server clock):
        itself, untouched, unless a stream of it is corrected (then a copy whose
        corrected entries have later capture times)."""
        entries = update.entries
        head = _HEADS.get(entries.itemsize)
        if head is None or self.rule.threshold <= 0.0:
            return update
        base, tracks = update.base_time, self._tracks
        since, self._last = now - self._last, now
        moved: dict[int, float] | None = None
        for sid, dt in head.iter_unpack(entries.tobytes()):
            track = tracks.get(sid)
            if track is None:
                track = tracks[sid] = _Track(now + self.rule.window / BLOCKS)
            elif now >= track.end:
                self._roll(track, now)
            age = now - (base + dt)
            if age < track.cur:
                track.cur = age
            track.n += 1
            if track.target > 0.0 or track.shift > 0.0:
                shift = self._slew(track, since)
                if shift > 0.0:
                    moved = moved or {}
                    moved[sid] = shift
        if moved is None:
            return update
        self.corrected += 1
        return _moved(update, moved)

    def _roll(self, track: _Track, now: float) -> None:
        """Close the current block (and judge the window) at ``now``."""
        block = self.rule.window / BLOCKS
        if now - track.end >= block:  # a silence of a block or more: start again
            track.blocks.clear()
            track.counts.clear()
        else:
            track.blocks.append(track.cur)
            track.counts.append(track.n)
        track.cur, track.n = math.inf, 0
        track.end = now + block
        track.target = self._judge(track)

    def _judge(self, track: _Track) -> float:
        """The correction a full window asks for: its unexplained lag, or 0."""
        rule = self.rule
        if len(track.blocks) < 1 or sum(track.counts) < rule.min_updates:
            return 0.0
        if not math.isfinite(self.rtt):
            return 0.0
        lag = track.lag = min(track.blocks) - self.rtt / 2.0
        keep = track.target > 0.0 and lag > rule.threshold / 2.0
        return lag if lag > rule.threshold or keep else 0.0

    @staticmethod
    def _slew(track: _Track, since: float) -> float:
        """The correction now: up to its target at once, down by ``SLEW`` of ``since``."""
        if track.target >= track.shift:
            track.shift = track.target
        else:
            track.shift = max(track.target, track.shift - SLEW * max(0.0, since))
        return track.shift


def _moved(update: PoseUpdate, moved: dict[int, float]) -> PoseUpdate:
    """``update`` with the capture times of the streams in ``moved`` later by their shift
    (all of them moved alike: its base time; else each one's ``dt``)."""
    entries = update.entries
    shifts = set(moved.values())
    if len(shifts) == 1 and len(moved) == len(entries):
        base = float(update.base_time + shifts.pop())
        return PoseUpdate(seq=update.seq, base_time=base, entries=entries)
    entries = entries.copy()
    streams, dts = entries["stream"], entries["dt"]
    for sid, shift in moved.items():
        at = streams == sid
        dts[at] = (dts[at].astype(np.float64) + shift).astype(np.float32)
    return PoseUpdate(seq=update.seq, base_time=update.base_time, entries=entries)
