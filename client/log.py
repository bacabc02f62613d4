"""What a bot keeps of its session for scoring: a consumer of the core's reports.

:class:`SessionLog` is the :class:`client.core.Observer` a bot hands its
:class:`client.core.ClientCore`: it logs every keyframe as it arrived (per remote
stream, a :class:`client.remote.RemoteStream`), every render frame's playout time
and D, the snapshots' ages and gaps, and how long nothing fresh was shown. At the
end it scores what was shown against each sender's motion (:meth:`SessionLog.score`,
DESIGN.md's QoE): every stream over the frames it was shown for (a peer that left
until it left). Nothing in the core depends on it.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from posecast.client.core import Key, Observer, Rendered
from posecast.client.remote import RemoteStream, evaluate_remote
from posecast.scenarios.qoe import ErrorSamples

__all__ = ["STALE_STRETCH", "RenderLogEntry", "SessionLog"]

F64 = NDArray[np.float64]

#: Stretches of render time with no fresh pose of anyone shorter than this (s) are
#: not counted as stale: a starved render loop that ran before the receive task
#: took in the next snapshot holds everything for a frame or two, a dead path for
#: seconds.
STALE_STRETCH = 1.0

#: (the room's playout time, the room's D, caller's clock at render,
#: {stream key: (pose of the first method, stalled)}).
RenderLogEntry = tuple[float, float, float, dict[Key, tuple[F64, bool]]]


class SessionLog(Observer):
    """A receiver's session as logged for scoring and the report.

    ``keep_render_log``: keep every frame's poses (first method) for inspection
    (memory grows); ``clock``-free: the render time of each entry is what the
    adapter passes to :meth:`note_local` before rendering.
    """

    def __init__(self, methods: Sequence[str], *, keep_render_log: bool = False) -> None:
        self.methods = tuple(methods)
        self.keep_render_log = keep_render_log
        #: Every remote stream received, by key (keys of a departed peer whose id came
        #: back are moved apart; see :meth:`stream_added`).
        self.streams: dict[Key, RemoteStream] = {}
        #: The present streams of each remote user.
        self.user_streams: dict[int, list[RemoteStream]] = {}
        #: Streams scored until a render frame only (their peer left).
        self.until: dict[Key, int] = {}
        self.play_t: list[float] = []
        self.play_d: list[float] = []
        self.render_stalls = self.render_samples = 0
        #: Render time (server clock, s) in stretches of over STALE_STRETCH during
        #: which every stream shown was held (see :attr:`stale_s`).
        self._stale = self._stretch = 0.0
        self.snapshot_bytes = self.poses_in = 0
        self.snapshot_times: list[tuple[float, float]] = []  # arrival, send: server clock
        self.render_log: list[RenderLogEntry] = []
        self._local = 0.0
        self._shown: list[Key] = []

    @property
    def stale_s(self) -> float:
        """Render time (s) with no fresh pose of anyone: every stream shown held past
        its newest keyframe, in stretches of at least :data:`STALE_STRETCH`."""
        open_stretch = self._stretch if self._stretch >= STALE_STRETCH else 0.0
        return self._stale + open_stretch

    # -- the core's reports -------------------------------------------------------

    def stream_added(self, key: Key, name: str, label: str | None, velocities: bool) -> None:
        if any(u == key[0] for u, _ in self.until):  # the id of one that left:
            self._rekey({key[0]})  # key its streams apart
        rs = self.streams[key] = RemoteStream(
            key[0], key[1], name, label, sends_velocities=velocities
        )
        self.user_streams.setdefault(key[0], []).append(rs)

    def velocities_known(self, user: int) -> None:
        for rs in self.user_streams.get(user, ()):
            rs.sends_velocities = True

    def keyframe(
        self,
        key: Key,
        capture: float,
        arrival: float,
        arrival_local: float,
        sent: float,
        pose: NDArray[np.float32],
        velocity: F64 | None,
    ) -> None:
        rs = self.streams[key]
        self.poses_in += 1
        rs.capture.append(capture)
        rs.arrival.append(arrival)
        rs.arrival_local.append(arrival_local)
        rs.sent.append(sent)
        rs.poses.append(pose)
        if velocity is not None:
            rs.velocities.append(velocity)

    def snapshot(
        self,
        arrival: float,
        arrival_local: float,
        sent: float,
        size: int,
        users: Mapping[int, tuple[int, int]],
    ) -> None:
        self.snapshot_bytes += size
        self.snapshot_times.append((arrival, sent))

    def peer_left(self, users: Sequence[int]) -> None:
        """Score ``users``' streams until this render frame only."""
        frame = len(self.play_t)
        gone = set(users)
        for key in self.streams:
            if key[0] in gone and key not in self.until:  # one that left before keeps its end
                self.until[key] = frame
        for user in gone:
            self.user_streams.pop(user, None)

    def note_local(self, local: float) -> None:
        """The caller's clock at the next render (for the render log)."""
        self._local = local

    def rendered(self, frame: Rendered) -> None:
        p = frame.playout
        stalled = frame.frame.stalled
        t_play = p.now - p.delay
        if self.play_t and stalled.size and bool(stalled.all()):
            self._stretch += max(0.0, t_play - self.play_t[-1])
        elif self._stretch:
            if self._stretch >= STALE_STRETCH:
                self._stale += self._stretch
            self._stretch = 0.0
        index = len(self.play_t)
        for user, d_own in p.own.items():
            for rs in self.user_streams.get(user, ()):
                rs.own_delays.append((index, d_own))
        self.play_t.append(t_play)
        self.play_d.append(p.delay)
        self.render_stalls += int(stalled.sum())
        self.render_samples += stalled.size
        if self.keep_render_log:
            first = frame.frame.poses[self.methods[0]]
            shown = {k: (first[j], bool(stalled[j])) for j, k in enumerate(self._shown)}
            self.render_log.append((t_play, p.delay, self._local, shown))

    def note_shown(self, keys: list[Key]) -> None:
        """The streams of the next frame, column by column (for the render log)."""
        self._shown = keys

    def left_relay(self, users: Sequence[int]) -> None:
        """The client rejoined elsewhere: ``users``' streams end now, keyed apart."""
        self.peer_left(users)
        self._rekey(set(users))

    def _rekey(self, users: set[int]) -> None:
        """Move ``users``' ended streams to keys above every key (new members may get
        their ids: the next relay's, or one reused)."""
        shift = ((max((u for u, _ in self.streams), default=0) >> 16) + 1) << 16
        out: dict[Key, RemoteStream] = {}
        for key, rs in self.streams.items():  # in order
            if key[0] in users and key in self.until:
                new = (key[0] + shift, key[1])
                self.until[new] = self.until.pop(key)
                key = new
            out[key] = rs
        self.streams = out

    # -- the end ------------------------------------------------------------------

    def score(self) -> dict[str, dict[str, ErrorSamples]]:
        """QoE of every stream over the frames it was shown for: to the end, or for a
        peer that left (and every peer of a relay the bot left) until then."""
        methods, n = self.methods, len(self.play_t)
        groups: dict[int, dict[Key, RemoteStream]] = {}
        for key, rs in self.streams.items():
            groups.setdefault(self.until.get(key, n), {})[key] = rs
        out: dict[str, dict[str, ErrorSamples]] = {m: {} for m in methods}
        for k, streams in groups.items():
            part = evaluate_remote(streams, self.play_t[:k], self.play_d[:k], methods)
            for m, classes in part.items():
                for cls, samples in classes.items():
                    out[m].setdefault(cls, ErrorSamples()).merge(samples)
        return out

    def keyframe_rate(self) -> float:
        """New keyframes received per remote stream per second: every stream's new
        keyframes over the time it was received (first to last arrival), pooled, so
        a stream seen only briefly (a peer that came and went, a resume) weighs its
        little time and not one stream's share."""
        spans = [
            (len(set(rs.capture)) - 1, rs.arrival[-1] - rs.arrival[0])
            for rs in self.streams.values()
            if len(rs.arrival) > 1 and rs.arrival[-1] > rs.arrival[0]
        ]
        seconds = sum(span for _, span in spans)
        return sum(n for n, _ in spans) / seconds if seconds > 0 else 0.0

    def late_delay_ms(self) -> dict[int, float]:
        """Peers shown late alone: their mean own D over those frames, ms."""
        return {
            user: 1000.0 * float(np.mean([d for _, d in streams[0].own_delays]))
            for user, streams in self.user_streams.items()
            if streams and streams[0].own_delays
        }
