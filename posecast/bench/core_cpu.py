"""Relay-core CPU per delivered pose, in one process: raw, compact compiled, compact pure.

    python -m posecast.bench.core_cpu [--rooms 3] [--seconds 6] [--rounds 3]

Rooms of 10 at 20 Hz on the sans-I/O ``RelayCore`` (no sockets, no event loop),
each member replaying a bundled trace (``traces:sample``) as ``posecast bench
relay`` does. Only the relay's work is timed, with ``time.process_time``: its
``receive`` of every update (decode, checks, ingest), ``tick`` (snapshots: one
group encode and a splice per subscriber for compact) and ``take``. The clients'
sessions (encoding updates, decoding snapshots) run outside the timed region.
Figures are CPU per remote pose delivered (a subscriber's own streams left out),
medians over interleaved rounds, so a busy machine slows all three alike; each
is split into its receive, tick and take phases (medians of each). No
websocket framing or socket writes: for those, and the bare baseline, see
``posecast bench relay``.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import dataclass, field

import numpy as np

from posecast.protocol import ClientSession, Hello, Join, Joined, PoseUpdate, Snapshot, _accel
from posecast.scenarios.traces import Trace, find_traces, load_trace
from posecast.server.core import RelayCore

__all__ = ["main", "measure"]

RATE = 20.0
ROOM = 10
PHASES = ("receive", "tick", "take")
STREAMS = ("head", "left", "right")


@dataclass
class _Member:
    conn: int
    session: ClientSession
    trace: Trace
    start: float
    phase: float
    ids: list[int] = field(default_factory=list)
    seq: int = 0


def _join(
    core: RelayCore, room: str, codec: str, trace: Trace, start: float, phase: float, now: float
) -> _Member:
    conn = core.connect(now)
    member = _Member(conn, ClientSession(), trace, start, phase)
    for message in (
        Hello(agent="core-cpu"),
        Join(room=room, streams=STREAMS, rate=RATE, codec=codec),
    ):
        core.receive(conn, member.session.send(message), now)
        for data in core.take(conn, now)[0]:
            for ev in member.session.receive_data(data):
                if isinstance(ev, Joined):
                    member.ids = list(ev.streams.values())
    return member


def _update(m: _Member, now: float) -> bytes:
    t = m.start + now
    i = int(np.searchsorted(m.trace.times, t, side="right")) - 1
    m.seq += 1
    capture = np.full(3, now - (t - m.trace.times[i]))
    return m.session.send(PoseUpdate.from_arrays(m.seq, m.ids, capture, m.trace.poses[i]))


def _remote_poses(m: _Member, frames: list[bytes]) -> int:
    n = 0
    for data in frames:
        for ev in m.session.receive_data(data):
            if isinstance(ev, Snapshot):
                n += int((ev.entries["user"] != m.session.user).sum())
    return n


def measure(codec: str, rooms: int, seconds: float, traces: list[Trace]) -> float:
    """Relay CPU (us) per remote pose delivered, for rooms of 10 on ``codec``."""
    return sum(measure_phases(codec, rooms, seconds, traces).values())


def measure_phases(codec: str, rooms: int, seconds: float, traces: list[Trace]) -> dict[str, float]:
    """:func:`measure` by phase: relay CPU (us) per remote pose delivered in
    ``receive`` (updates: decode, checks, ingest), ``tick`` (snapshots encoded and
    offered) and ``take`` (frames taken for writing)."""
    core, t0 = RelayCore(), 1000.0
    members = []
    for i in range(rooms * ROOM):
        tr = traces[i % len(traces)]
        start = tr.times[0] + (i // 4) * 7.0 + 0.9 * (i % ROOM) - t0
        members.append(_join(core, f"r{i // ROOM}", codec, tr, start, (i * 0.37) % 1.0, t0))
    next_pub = [t0 + m.phase / RATE for m in members]
    now, poses = t0, 0
    cpu = dict.fromkeys(PHASES, 0.0)
    while now < t0 + seconds:
        now = min(min(next_pub), core.next_deadline() or now + 1)
        for k, m in enumerate(members):
            if next_pub[k] <= now + 1e-12:
                data = _update(m, now)
                c = time.process_time()
                core.receive(m.conn, data, now)
                cpu["receive"] += time.process_time() - c
                next_pub[k] += 1 / RATE
        due = core.next_deadline()
        if due is not None and due <= now + 1e-12:
            c = time.process_time()
            core.tick(now)
            c2 = time.process_time()
            out = [core.take(m.conn, now)[0] for m in members]
            cpu["tick"] += c2 - c
            cpu["take"] += time.process_time() - c2
            poses += sum(_remote_poses(m, frames) for m, frames in zip(members, out, strict=True))
    if not poses:
        raise RuntimeError("the relay delivered no pose")
    return {phase: 1e6 * t / poses for phase, t in cpu.items()}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--rooms", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=6.0)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args(argv)
    traces = [load_trace(p) for p in find_traces("traces:sample")]
    runs = {
        "raw": ("raw", True),
        "compact compiled": ("compact", False),
        "compact pure": ("compact", True),
    }
    if _accel.compiled() is None:
        del runs["compact compiled"]
    got: dict[str, list[dict[str, float]]] = {name: [] for name in runs}
    was_pure = _accel.speedups is None
    try:
        for _ in range(args.rounds):
            for name, (codec, pure) in runs.items():
                _accel.use(pure)
                got[name].append(measure_phases(codec, args.rooms, args.seconds, traces))
    finally:
        _accel.use(was_pure)
    print(f"relay core CPU per delivered remote pose, {args.rooms} rooms of {ROOM} at {RATE:g} Hz:")
    medians = {}
    for name, runs_ in got.items():
        values = [sum(r.values()) for r in runs_]
        medians[name] = statistics.median(values)
        rounds = ", ".join(f"{v:.2f}" for v in values)
        phases = "  ".join(f"{p} {statistics.median(r[p] for r in runs_):.2f}" for p in PHASES)
        print(f"  {name:17} {medians[name]:6.2f} us  ({phases}; rounds: {rounds})")
    if "compact compiled" in medians:
        ratio = medians["compact compiled"] / medians["raw"]
        print(f"  compact compiled / raw: {ratio:.2f}x")


if __name__ == "__main__":
    main()
