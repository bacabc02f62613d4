"""One in-process relay-core measurement that runs in any checkout's venv, old or new.

    <checkout>/.venv/bin/python -I posecast/bench/sidebyside_probe.py --codec raw|compact
        [--pure] [--rooms 3] [--seconds 6] [--traces FILE.npz]

Run as a file by :mod:`posecast.bench.sidebyside` with another checkout's
interpreter (``-I``: this folder is not put on that interpreter's path), so it
imports nothing of this checkout: the relay and protocol under ``posecast.``
where they install so (since b50f95a), as top-level ``server``/``protocol``
before that.

The same method as ``python -m posecast.bench.core_cpu`` (replayed alone): rooms
of 10 at 20 Hz on the sans-I/O ``RelayCore``, each member replaying a trace; the
clients run first against one core and every call is logged, then a fresh core
replays the log alone and only its ``receive``, ``tick`` and ``take`` are timed
(``time.process_time``). ``--traces`` reads the traces from an ``.npz`` written
by :func:`save_traces`, so two checkouts whose trace loaders differ are fed the
same poses. Prints one JSON line: relay CPU (us) per remote pose delivered, by
phase, and a CRC-32 per connection of the frames the relay took for it, in order
(``conn_crcs``; ``crc`` combines them): equal CRCs on two checkouts mean their
relays sent each connection the same bytes for the same input (the order in
which connections are served in one call may differ).
"""

from __future__ import annotations

import argparse
import importlib
import json
import sys
import time
import zlib
from collections.abc import Callable
from types import ModuleType, SimpleNamespace
from typing import Any

import numpy as np

RATE = 20.0
ROOM = 10
STREAMS = ("head", "left", "right")
PHASES = ("receive", "tick", "take")
T0 = 1000.0


def modules() -> tuple[ModuleType, ModuleType, ModuleType, str]:
    """The protocol, traces and relay-core modules of the running venv, and their layout."""
    for prefix in ("posecast.", ""):
        try:
            protocol = importlib.import_module(prefix + "protocol")
            traces = importlib.import_module(prefix + "scenarios.traces")
            core = importlib.import_module(prefix + "server.core")
        except ImportError:
            continue
        return protocol, traces, core, prefix.rstrip(".") or "top-level"
    raise ImportError("neither posecast.protocol nor a top-level protocol package is installed")


def save_traces(path: str) -> None:
    """Write ``traces:sample`` as loaded by the running venv to ``path`` (.npz)."""
    _, traces, _, _ = modules()
    arrays: dict[str, Any] = {}
    for i, p in enumerate(traces.find_traces("traces:sample")):
        trace = traces.load_trace(p)
        arrays[f"times{i}"], arrays[f"poses{i}"] = trace.times, trace.poses
    np.savez(path, **arrays)


def load_traces(path: str | None) -> list[Any]:
    """Traces (``times``, ``poses``) from an .npz of :func:`save_traces`, or ``traces:sample``."""
    if path is None:
        _, traces, _, _ = modules()
        return [traces.load_trace(p) for p in traces.find_traces("traces:sample")]
    z = np.load(path)
    count = sum(1 for k in z.files if k.startswith("times"))
    return [SimpleNamespace(times=z[f"times{i}"], poses=z[f"poses{i}"]) for i in range(count)]


def _take_all(core: Any, conns: list[int], now: float) -> list[list[bytes]]:
    return [core.take(conn, now)[0] for conn in conns]


class _Run:
    """The clients' side: members joined to one relay core whose calls are logged."""

    def __init__(self, codec: str, rooms: int, traces: list[Any]) -> None:
        self.p, _, core_module, _ = modules()
        self.core = core_module.RelayCore()
        self.log: list[tuple[str, bool, tuple[Any, ...]]] = []
        self.timed = False
        self.members: list[SimpleNamespace] = []
        for i in range(rooms * ROOM):
            trace = traces[i % len(traces)]
            start = float(trace.times[0]) + (i // 4) * 7.0 + 0.9 * (i % ROOM) - T0
            self._join(f"r{i // ROOM}", codec, trace, start, (i * 0.37) % 1.0)
        self.timed = True

    def call(self, phase: str, fn: Callable[..., Any], *args: Any) -> Any:
        self.log.append((phase, self.timed, args))
        return fn(*args)

    def _join(self, room: str, codec: str, trace: Any, start: float, phase: float) -> None:
        p = self.p
        conn = self.call("connect", self.core.connect, T0)
        m = SimpleNamespace(conn=conn, session=p.ClientSession(), trace=trace, start=start)
        m.phase, m.ids, m.seq = phase, [], 0
        for message in (
            p.Hello(agent="core-cpu"),
            p.Join(room=room, streams=STREAMS, rate=RATE, codec=codec),
        ):
            self.call("receive", self.core.receive, conn, m.session.send(message), T0)
            for data in self.call("take", _take_all, self.core, [conn], T0)[0]:
                for ev in m.session.receive_data(data):
                    if isinstance(ev, p.Joined):
                        m.ids = list(ev.streams.values())
        self.members.append(m)

    def _update(self, m: SimpleNamespace, now: float) -> bytes:
        t = m.start + now
        i = int(np.searchsorted(m.trace.times, t, side="right")) - 1
        m.seq += 1
        capture = np.full(3, now - (t - m.trace.times[i]))
        update = self.p.PoseUpdate.from_arrays(m.seq, m.ids, capture, m.trace.poses[i])
        return m.session.send(update)  # type: ignore[no-any-return]

    def play(self, seconds: float) -> tuple[int, list[int]]:
        """Publish and tick for ``seconds``; the remote poses delivered, each connection's CRC."""
        members, core = self.members, self.core
        next_pub = [T0 + m.phase / RATE for m in members]
        conns = [m.conn for m in members]
        now, poses, crcs = T0, 0, [0] * len(conns)
        while now < T0 + seconds:
            now = min(min(next_pub), core.next_deadline() or now + 1)
            for k, m in enumerate(members):
                if next_pub[k] <= now + 1e-12:
                    self.call("receive", core.receive, m.conn, self._update(m, now), now)
                    next_pub[k] += 1 / RATE
            due = core.next_deadline()
            if due is not None and due <= now + 1e-12:
                self.call("tick", core.tick, now)
                out = self.call("take", _take_all, core, conns, now)
                for k, (m, frames) in enumerate(zip(members, out, strict=True)):
                    for data in frames:
                        crcs[k] = zlib.crc32(data, crcs[k])
                        for ev in m.session.receive_data(data):
                            if isinstance(ev, self.p.Snapshot):
                                poses += int((ev.entries["user"] != m.session.user).sum())
        return poses, crcs


def _replay(log: list[tuple[str, bool, tuple[Any, ...]]]) -> tuple[dict[str, float], list[int]]:
    """CPU seconds by phase of a fresh core making the logged calls, and the CRC of the
    frames it took for each connection (in order of the connections)."""
    core = modules()[2].RelayCore()
    fns: dict[str, Callable[..., Any]] = {
        "connect": core.connect,
        "receive": core.receive,
        "tick": core.tick,
        "take": lambda _old, *args: _take_all(core, *args),
    }
    cpu = dict.fromkeys(PHASES, 0.0)
    crcs: dict[int, int] = {}
    clock = time.process_time
    for phase, timed, args in log:
        c = clock()
        out = fns[phase](*args)
        if timed:
            cpu[phase] += clock() - c
            if phase == "take":
                for conn, frames in zip(args[1], out, strict=True):
                    crc = crcs.get(conn, 0)
                    for data in frames:
                        crc = zlib.crc32(data, crc)
                    crcs[conn] = crc
    return cpu, [crcs[conn] for conn in sorted(crcs)]


def measure(codec: str, rooms: int, seconds: float, traces: list[Any]) -> dict[str, Any]:
    """Relay CPU (us) per remote pose delivered, total and by phase; the frames' CRC."""
    run = _Run(codec, rooms, traces)
    poses, crcs = run.play(seconds)
    if not poses:
        raise RuntimeError("the relay delivered no pose")
    cpu, replayed = _replay(run.log)
    if replayed != crcs:
        raise RuntimeError("the replayed relay took other frames than the first")
    us = {phase: 1e6 * cpu[phase] / poses for phase in PHASES}
    out: dict[str, Any] = {"us_per_pose": sum(us.values())}
    out.update({f"us_{phase}": v for phase, v in us.items()})
    out.update(crc=f"{zlib.crc32(b''.join(c.to_bytes(4, 'big') for c in crcs)):08x}")
    out.update(conn_crcs=[f"{c:08x}" for c in crcs], poses=poses)
    return out


def _implementation(pure: bool) -> str:
    """Select the codec (pure Python or the compiled accelerator, where built); say which ran."""
    try:
        accel = importlib.import_module("posecast.protocol._accel")
    except ImportError:
        return "pure (no accelerator in this checkout)"
    accel.use(pure)
    return "pure" if accel.speedups is None else "compiled"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--codec", choices=("raw", "compact"), default="raw")
    parser.add_argument("--pure", action="store_true", help="the pure-Python codec")
    parser.add_argument("--rooms", type=int, default=3)
    parser.add_argument("--seconds", type=float, default=6.0)
    parser.add_argument("--traces", help="an .npz of save_traces: the same poses everywhere")
    parser.add_argument("--save-traces", metavar="FILE", help="write that .npz and exit")
    args = parser.parse_args(argv)
    if args.save_traces:
        save_traces(args.save_traces)
        return
    implementation = _implementation(args.pure)
    out = measure(args.codec, args.rooms, args.seconds, load_traces(args.traces))
    out.update(codec=args.codec, implementation=implementation, layout=modules()[3])
    out["python"] = sys.version.split()[0]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
