"""Relay-core CPU per delivered pose, in one process: raw, compact compiled, compact pure.

    python -m posecast.bench.core_cpu [--rooms 3] [--seconds 6] [--rounds 3] [--interleaved]

Rooms of 10 at 20 Hz on the sans-I/O ``RelayCore`` (no sockets, no event loop),
each member replaying a bundled trace (``traces:sample``) as ``posecast bench
relay`` does. Only the relay's work is timed, with ``time.process_time``: its
``receive`` of every update (decode, checks, ingest), ``tick`` (snapshots: one
group encode and a splice per subscriber for compact) and ``take``.

The clients' sessions (encoding updates, decoding snapshots) run first, against
one relay core, and every call they make of it is logged; a fresh core then
replays that log alone, timed (it must take the same frames, byte for byte, or
the run fails). With ``--interleaved`` the first core is timed instead, the
clients' work running between its calls: the figure then also holds what the
relay loses to the clients' use of the caches (a compact client decodes its
snapshots in pure Python, a raw one mostly in msgpack's C), which a relay
process does not pay.

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
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

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
    core: _Logged, room: str, codec: str, trace: Trace, start: float, phase: float, now: float
) -> _Member:
    conn = core.connect(now)
    member = _Member(conn, ClientSession(), trace, start, phase)
    for message in (
        Hello(agent="core-cpu"),
        Join(room=room, streams=STREAMS, rate=RATE, codec=codec),
    ):
        core.receive(conn, member.session.send(message), now)
        for data in core.take_all([conn], now)[0]:
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


def measure(
    codec: str, rooms: int, seconds: float, traces: list[Trace], interleaved: bool = False
) -> float:
    """Relay CPU (us) per remote pose delivered, for rooms of 10 on ``codec``."""
    return sum(measure_phases(codec, rooms, seconds, traces, interleaved).values())


class _Logged:
    """A relay core whose calls are logged (``log``: phase, timed, arguments) and whose
    frames taken are summed into a CRC (``crc``); timed by phase into ``cpu`` if
    ``interleaved``. Calls are not timed while ``setup`` (the joins)."""

    def __init__(self, interleaved: bool) -> None:
        self.core = RelayCore()
        self.log: list[tuple[str, bool, tuple[Any, ...]]] = []
        self.cpu = dict.fromkeys(PHASES, 0.0)
        self.interleaved = interleaved
        self.setup = True
        self.crc = 0

    def _call(self, phase: str, call: Callable[..., Any], *args: Any) -> Any:
        self.log.append((phase, not self.setup, args))
        if self.setup or not self.interleaved:
            return call(*args)
        c = time.process_time()
        out = call(*args)
        self.cpu[phase] += time.process_time() - c
        return out

    def connect(self, now: float) -> int:
        return self._call("connect", self.core.connect, now)  # type: ignore[no-any-return]

    def receive(self, conn: int, data: bytes, now: float) -> None:
        self._call("receive", self.core.receive, conn, data, now)

    def tick(self, now: float) -> None:
        self._call("tick", self.core.tick, now)

    def take_all(self, conns: list[int], now: float) -> list[list[bytes]]:
        out: list[list[bytes]] = self._call("take", self._take, conns, now)
        for frames in out:
            for data in frames:
                self.crc = zlib.crc32(data, self.crc)
        return out

    def _take(self, conns: list[int], now: float) -> list[list[bytes]]:
        return _take_all(self.core, conns, now)


def _take_all(core: RelayCore, conns: list[int], now: float) -> list[list[bytes]]:
    return [core.take(conn, now)[0] for conn in conns]


def _replay(log: list[tuple[str, bool, tuple[Any, ...]]]) -> tuple[dict[str, float], int]:
    """The CPU by phase of a fresh core making the calls of ``log`` (the timed ones
    timed), and the CRC of the frames it took."""
    core = RelayCore()
    calls: dict[str, Callable[..., Any]] = {
        "connect": core.connect,
        "receive": core.receive,
        "tick": core.tick,
        "take": lambda *args: _take_all(core, *args),
    }
    cpu = dict.fromkeys(PHASES, 0.0)
    crc = 0
    clock = time.process_time
    for phase, timed, args in log:
        call = calls[phase]
        c = clock()
        out = call(*args)
        if timed:
            cpu[phase] += clock() - c
        if phase == "take":
            for frames in out:
                for data in frames:
                    crc = zlib.crc32(data, crc)
    return cpu, crc


def measure_phases(
    codec: str, rooms: int, seconds: float, traces: list[Trace], interleaved: bool = False
) -> dict[str, float]:
    """:func:`measure` by phase: relay CPU (us) per remote pose delivered in
    ``receive`` (updates: decode, checks, ingest), ``tick`` (snapshots encoded and
    offered) and ``take`` (frames taken for writing). The relay's calls are
    replayed alone on a fresh core and timed there, unless ``interleaved``."""
    core, t0 = _Logged(interleaved), 1000.0
    members = []
    for i in range(rooms * ROOM):
        tr = traces[i % len(traces)]
        start = tr.times[0] + (i // 4) * 7.0 + 0.9 * (i % ROOM) - t0
        members.append(_join(core, f"r{i // ROOM}", codec, tr, start, (i * 0.37) % 1.0, t0))
    core.setup = False
    next_pub = [t0 + m.phase / RATE for m in members]
    conns = [m.conn for m in members]
    now, poses = t0, 0
    while now < t0 + seconds:
        now = min(min(next_pub), core.core.next_deadline() or now + 1)
        for k, m in enumerate(members):
            if next_pub[k] <= now + 1e-12:
                core.receive(m.conn, _update(m, now), now)
                next_pub[k] += 1 / RATE
        due = core.core.next_deadline()
        if due is not None and due <= now + 1e-12:
            core.tick(now)
            out = core.take_all(conns, now)
            poses += sum(_remote_poses(m, frames) for m, frames in zip(members, out, strict=True))
    if not poses:
        raise RuntimeError("the relay delivered no pose")
    cpu = core.cpu
    if not interleaved:
        cpu, crc = _replay(core.log)
        if crc != core.crc:
            raise RuntimeError("the replayed relay took other frames than the first")
    return {phase: 1e6 * t / poses for phase, t in cpu.items()}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--rooms", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=6.0)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument(
        "--interleaved",
        action="store_true",
        help="time the relay between its clients' work, not replayed alone",
    )
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
                got[name].append(
                    measure_phases(codec, args.rooms, args.seconds, traces, args.interleaved)
                )
    finally:
        _accel.use(was_pure)
    how = "interleaved with its clients" if args.interleaved else "replayed alone"
    print(
        f"relay core CPU per delivered remote pose, {args.rooms} rooms of {ROOM} at "
        f"{RATE:g} Hz ({how}):"
    )
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
