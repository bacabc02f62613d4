"""What a bot keeps of each remote stream, and how it scores it (DESIGN.md's QoE).

:class:`RemoteStream` holds a remote stream's arrival log; :func:`evaluate_remote`
scores every stream a bot received against its sender's motion
(:func:`score_received`). A shared room
object (user :data:`~protocol.ROOM_USER`) whose label is the live throw-catch
scene's drill is scored in the ``object`` classes instead
(:func:`scenarios.throw_catch.score_drill`: all of it, in flight, at the catch);
other room objects are rendered but not scored (nobody knows their truth).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import cast

import numpy as np
from numpy.typing import NDArray

from posecast.client.render import rendered_method
from posecast.protocol import ROOM_USER
from posecast.scenarios.motion import MotionSpec
from posecast.scenarios.qoe import ErrorSamples, KeyframeLog, evaluate_group
from posecast.scenarios.throw_catch import DRILL, scene_role, scene_script, score_drill
from posecast.scenarios.traces import Trace, TraceError

__all__ = [
    "ReceivedStream",
    "RemoteStream",
    "evaluate_remote",
    "longest_gap",
    "p50_p99_ms",
    "remote_log",
    "score_object",
    "score_received",
    "stream_delays",
]

F64 = NDArray[np.float64]


@dataclass
class RemoteStream:
    """One remote stream as a receiver logged it, for the QoE evaluation (its render
    buffer is the client core's: :class:`client.core.ClientCore`)."""

    user: int
    stream: int
    name: str
    label: str | None
    capture: list[float] = field(default_factory=list)
    #: Arrival times in server time (with the clock offset known on arrival).
    arrival: list[float] = field(default_factory=list)
    #: The same arrivals on the bot's own clock.
    arrival_local: list[float] = field(default_factory=list)
    #: The server's send time (its clock at the tick) of the snapshot that brought each.
    sent: list[float] = field(default_factory=list)
    poses: list[NDArray[np.float32]] = field(default_factory=list)
    #: With velocity snapshots: the velocity received with each pose, (6,) float64
    #: from float16 (linear m/s, angular rad/s, world frame).
    velocities: list[NDArray[np.float64]] = field(default_factory=list)
    #: Whether the sender reports velocities (else the received ones are zeros,
    #: and velocity methods render and score it with ``VELOCITY_FALLBACK``).
    sends_velocities: bool = False
    #: (render frame index, D) of every frame that showed it late alone, at its
    #: sender's own D instead of the room's (see :func:`stream_delays`).
    own_delays: list[tuple[int, float]] = field(default_factory=list)


def remote_log(rs: RemoteStream) -> KeyframeLog:
    """The stream's arrival log as a KeyframeLog (sorted by capture, deduplicated).

    With the received velocities when the sender reports them and every keyframe
    came with one (a sender that reports none gets zeros: no velocities here).
    """
    cap = np.asarray(rs.capture, dtype=np.float64)
    arr = np.asarray(rs.arrival, dtype=np.float64)
    poses = np.asarray(rs.poses, dtype=np.float64).reshape(-1, 1, 7)
    order = np.lexsort((arr, cap))
    cap, arr, poses = cap[order], arr[order], poses[order]
    keep = np.ones(cap.shape, dtype=bool)
    keep[1:] = cap[1:] != cap[:-1]  # a duplicate: the first arrival counts
    vel = None
    if rs.sends_velocities and rs.velocities and len(rs.velocities) == len(rs.capture):
        vel = np.asarray(rs.velocities, dtype=np.float64).reshape(-1, 1, 6)[order][keep]
    return KeyframeLog(cap[keep], arr[keep], poses[keep], vel)


def stream_delays(rs: RemoteStream, play_d: Sequence[float]) -> F64 | None:
    """The D ``rs`` was rendered with at each frame, or None: the room's (``play_d``)."""
    if not rs.own_delays:
        return None
    d = np.array(play_d, dtype=np.float64)
    frames, own = zip(*rs.own_delays, strict=True)
    d[list(frames)] = own
    return d


def evaluate_remote(
    remote: dict[tuple[int, int], RemoteStream],
    play_t: Sequence[float],
    play_d: Sequence[float],
    methods: Sequence[str],
) -> dict[str, dict[str, ErrorSamples]]:
    """QoE of everything received, with the delay D that was in effect at each tau."""
    if not play_t:
        return {m: {} for m in methods}
    streams = [
        ReceivedStream(rs.label, rs.name, partial(remote_log, rs), stream_delays(rs, play_d))
        for rs in remote.values()
        if rs.capture and rs.user != ROOM_USER
    ]
    (out,) = score_received(streams, np.asarray(play_t), np.asarray(play_d), methods)
    for rs in remote.values():
        if rs.user == ROOM_USER and rs.capture:
            for m, classes in score_object(rs, play_t, play_d, methods).items():
                for cls, samples in classes.items():
                    out[m].setdefault(cls, ErrorSamples()).merge(samples)
    return out


def score_object(
    rs: RemoteStream, play_t: Sequence[float], play_d: Sequence[float], methods: Sequence[str]
) -> dict[str, dict[str, ErrorSamples]]:
    """A room object in the ``object`` classes, if it is the throw-catch scene's drill
    (its label says so); else nothing. Scored as rendered: from its first keyframe
    to the last render, each tau at the D it was rendered with."""
    if rs.label is None or rs.name != DRILL:
        return {}
    try:
        spec = MotionSpec.parse(rs.label)
    except TraceError:
        return {}
    if scene_role(spec.source.partition(":")[2]) != "drill":
        return {}
    st, sd = np.asarray(play_t, dtype=np.float64), np.asarray(play_d, dtype=np.float64)
    own = stream_delays(rs, play_d)
    if own is not None:  # its own playout times (kept monotonic for interp)
        st, sd = np.maximum.accumulate(st + sd - own), own
    log = remote_log(rs)
    span = (max(float(log.capture[0]), float(st[0])), float(st[-1]))
    if span[1] <= span[0]:
        return {}
    truth = spec.truth(until=span[1] + 1.0)
    at = cast(Callable[[F64], F64], partial(np.interp, xp=st, fp=sd))
    shown = {m: rendered_method(m, log.velocities is not None) for m in methods}
    unique = list(dict.fromkeys(shown.values()))
    res = score_drill(truth, log, at, unique, span, scene_script(spec.seed), spec.t0)
    return {m: res[shown[m]] for m in methods}


def p50_p99_ms(values: list[float]) -> tuple[float, float]:
    """The 50th and 99th percentiles of ``values`` (s), in ms (NaN if none)."""
    if not values:
        return float("nan"), float("nan")
    p50, p99 = np.percentile(np.asarray(values), [50, 99])
    return 1000.0 * float(p50), 1000.0 * float(p99)


def longest_gap(times: list[float]) -> float:
    """The longest interval between consecutive ``times`` (s; NaN if fewer than two)."""
    return float(np.max(np.diff(np.asarray(times)))) if len(times) > 1 else float("nan")


@dataclass(frozen=True)
class ReceivedStream:
    """A remote stream as a receiver saw it, for :func:`score_received`.

    ``label`` is the sender's motion spec (None: unknown, not scored); ``log``
    builds its arrival log, and is only called for a stream that is scored.
    """

    label: str | None
    name: str
    log: Callable[[], KeyframeLog]
    #: The D it was rendered with at each render, when not the room's (shown late).
    delays: F64 | None = None


def score_received(
    streams: Iterable[ReceivedStream],
    play_t: F64,
    play_d: F64,
    methods: Sequence[str],
    *,
    delays: Sequence[float | None] = (None,),
    until_sender_left: bool = False,
    as_rendered: bool = True,
    truths: dict[str, Trace] | None = None,
    windows: dict[str, dict[str, tuple[float, float]]] | None = None,
) -> list[dict[str, dict[str, ErrorSamples]]]:
    """QoE of what one receiver got, against each sender's motion, one result per delay.

    ``play_t``, ``play_d`` (non-empty): the render loop's playout times and the
    delay D in effect at each (a stream's own ``delays`` instead, if it has them:
    its playout times are then ``play_t + play_d - delays``). Each entry of
    ``delays`` is a fixed D in seconds, or None for the D the render loop used at
    each tau. A stream is scored over its first keyframe (or the first render) to
    its last render, or, with
    ``until_sender_left``, to its last keyframe where that is earlier (streams
    with nothing in that window are skipped). With ``as_rendered`` a velocity
    method is scored as what the render loop showed on a stream without
    velocities (:func:`rendered_method`). ``truths`` caches the motions by
    label; ``windows`` collects ``{label: {name: window}}`` of scored streams.
    Returns ``[{method: {device_class: ErrorSamples}}]``, one per delay.
    """
    pt = np.asarray(play_t)
    pd = np.asarray(play_d)

    out: list[dict[str, dict[str, ErrorSamples]]] = [{m: {} for m in methods} for _ in delays]
    truths = {} if truths is None else truths
    for rs in streams:
        if rs.label is None:
            continue
        if rs.label not in truths:
            try:
                truths[rs.label] = MotionSpec.parse(rs.label).truth(until=float(pt[-1]) + 1.0)
            except TraceError:
                continue
        truth = truths[rs.label]
        if rs.name not in truth.streams:
            continue
        log = rs.log()
        st, sd = pt, pd
        if rs.delays is not None:  # its own playout times (kept monotonic for interp)
            sd = np.asarray(rs.delays)
            st = np.maximum.accumulate(pt + pd - sd)
        end = float(st[-1])
        if until_sender_left:
            end = min(end, float(log.capture[-1]))
        window = (max(float(log.capture[0]), float(st[0])), end)
        if until_sender_left and window[1] <= window[0]:
            continue
        if windows is not None:
            windows.setdefault(rs.label, {})[rs.name] = window
        # What the render loop showed: velocity methods fall back on streams without.
        has_velocities = log.velocities is not None
        shown = {m: rendered_method(m, has_velocities) if as_rendered else m for m in methods}
        unique = list(dict.fromkeys(shown.values()))
        one = truth.select([rs.name])
        for into, fixed in zip(out, delays, strict=True):
            at = cast(Callable[[F64], F64], partial(np.interp, xp=st, fp=sd))
            res = evaluate_group(one, log, at if fixed is None else fixed, unique, window)
            for m in methods:
                for cls, samples in res[shown[m]].items():
                    into[m].setdefault(cls, ErrorSamples()).merge(samples)
    return out
