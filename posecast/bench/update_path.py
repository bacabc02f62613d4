"""The walk of one pose update through a real relay: which of our files it visits.

    python -m posecast.bench.update_path [--codec compact] [--runs 5]

A relay (``server.app.RelayServer``) on loopback port 0, in this process, with two
websocket clients of the ``websockets`` library: a publisher and a subscriber in one
room. After a warm-up (the first updates, the key snapshot), one update is traced
with ``sys.settrace`` from the moment the publisher's frame is handed to its socket
to the moment the subscriber's socket yields the snapshot that carries it. The
clients' own encoding and decoding run outside the trace; what is traced is the
relay (its transport, adapter, core, room, codec) and the event loop between.

Every call and every return of a traced frame moves "where the update is" to a
file; files outside the repository (the standard library, ``websockets``) are left
out, and staying in one file is one visit. Of that sequence: **files** is how many
distinct files of ours the update crosses, **returns** how many times it comes back
to a file it had already left (the sequence's length less the files). A walk that
visits each file once has 0 returns. Runs differ by what else the relay does in the
window (another member's tick); the figures are each run's and their median.

That strict figure counts the way back of every call into another file, so it
cannot reach 0 for code that calls functions. Two more figures read the walk as a
reader follows calls (each call's caller is the nearest frame of ours below it):
**callbacks**, the calls (counted once per caller file and callee function) into a
file already on the call stack below the caller's file (a part calling up into
whoever called it, a generator of one file consumed by another), and **files in
more than one place**, the files entered by calls from more than one caller file
(the event loop, which starts each of the walk's callbacks, is no caller file). A
walk a reader follows down once, each file in one place, has 0 of both; ``--show``
names them.
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import Any

import numpy as np
from websockets.asyncio.client import ClientConnection, connect

from posecast.protocol import ClientSession, Hello, Join, Joined, PoseUpdate, Snapshot, Welcome
from posecast.server.app import RelayServer, ServerConfig, serving

__all__ = ["Walk", "main", "walk"]

#: The repository and its packages' folders: files in them (but not this one) are ours.
ROOT = Path(__file__).resolve().parent.parent.parent
FOLDERS = ("posecast", "server", "client", "protocol", "interp", "recorder", "scenarios")
STREAMS = ("head", "left", "right")


@dataclass
class Walk:
    """The files one update visited, in order (consecutive visits of one file merged)."""

    visits: list[str] = field(default_factory=list)
    #: Each call into a file of ours from another place: (caller file, None for the
    #: event loop; callee file; callee function; whether the callee's file was on
    #: the stack below the caller's).
    calls: list[tuple[str | None, str, str, bool]] = field(default_factory=list)

    @property
    def files(self) -> int:
        return len(set(self.visits))

    @property
    def returns(self) -> int:
        return len(self.visits) - self.files

    @property
    def callback_calls(self) -> list[str]:
        """The callbacks, each once: ``caller file -> callee file:function``."""
        seen = {f"{c} -> {f}:{fn}": None for c, f, fn, up in self.calls if up}
        return list(seen)

    @property
    def callbacks(self) -> int:
        return len(self.callback_calls)

    @property
    def places(self) -> dict[str, list[str]]:
        """The files entered from more than one caller file: file -> its callers."""
        callers: dict[str, dict[str, None]] = {}
        for caller, file, _, _ in self.calls:
            if caller is not None:  # (the event loop's calls start the walk's pieces)
                callers.setdefault(file, {})[caller] = None
        return {f: list(c) for f, c in callers.items() if len(c) > 1}

    @property
    def multi_place(self) -> int:
        return len(self.places)


class _Tracer:
    """``sys.settrace`` over our files: each call or return moves the walk to a file."""

    def __init__(self) -> None:
        self.walk = Walk()
        self.paused = False
        self._ours: dict[str, str | None] = {}

    def _file(self, frame: FrameType | None) -> str | None:
        if frame is None:
            return None
        name = frame.f_code.co_filename
        if name not in self._ours:
            path = Path(name)
            mine = path.is_relative_to(ROOT) and path != Path(__file__).resolve()
            mine = mine and path.relative_to(ROOT).parts[0] in FOLDERS
            self._ours[name] = str(path.relative_to(ROOT)) if mine else None
        return self._ours[name]

    def _visit(self, file: str | None) -> None:
        if file is not None and not self.paused:
            visits = self.walk.visits
            if not visits or visits[-1] != file:
                visits.append(file)

    def _call(self, frame: FrameType, event: str, arg: Any) -> Any:
        if event == "call":
            file = self._file(frame)
            self._visit(file)
            if file is not None and not self.paused:
                self._place(frame, file)
            frame.f_trace_lines = False
            return self._local
        return None

    def _place(self, frame: FrameType, file: str) -> None:
        """Note a call into ``file`` from another file: who called, and whether ``file``
        was on the stack already below its caller (a callback)."""
        below: list[str] = []  # the files of ours on the stack, innermost first
        back = frame.f_back
        while back is not None:
            mine = self._file(back)
            if mine is not None and (not below or below[-1] != mine):
                below.append(mine)
            back = back.f_back
        caller = below[0] if below else None
        if caller != file:
            self.walk.calls.append((caller, file, frame.f_code.co_name, file in below[1:]))

    def _local(self, frame: FrameType, event: str, arg: Any) -> Any:
        if event == "return":
            self._visit(self._file(frame.f_back))
        return self._local

    @contextmanager
    def tracing(self) -> Iterator[None]:
        sys.settrace(self._call)
        try:
            yield
        finally:
            sys.settrace(None)


async def _join(
    ws: ClientConnection, session: ClientSession, streams: tuple[str, ...], codec: str
) -> list[int]:
    await ws.send(session.send(Hello(agent="update-path")))
    ids: list[int] = []
    while not ids:
        data = await ws.recv()
        assert isinstance(data, bytes)
        for event in session.receive_data(data):
            if isinstance(event, Welcome):
                await ws.send(
                    session.send(Join(room="walk", streams=streams, rate=30.0, codec=codec))
                )
            elif isinstance(event, Joined):
                ids = list(event.streams.values())
    return ids


def _carries(session: ClientSession, data: bytes, user: int, x: float) -> bool:
    """Whether ``data`` is a snapshot with ``user``'s head at position x = ``x``."""
    for event in session.receive_data(data):
        if isinstance(event, Snapshot):
            mine = event.entries[event.entries["user"] == user]
            if len(mine) and abs(float(mine["pose"][:, 0].max()) - x) < 0.01:
                return True
    return False


async def _deliver(
    pub: tuple[ClientConnection, ClientSession, list[int], int],
    sub: tuple[ClientConnection, ClientSession],
    seq: int,
    tracer: _Tracer | None,
) -> None:
    """Publish one update (head at x = seq / 100) and wait for the subscriber to get it."""
    (pws, psession, ids, user), (sws, ssession) = pub, sub
    x = seq / 100
    poses = np.tile([x, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0], (len(ids), 1))
    update = PoseUpdate.from_arrays(seq, ids, np.full(len(ids), time.monotonic()), poses)
    frame = psession.send(update)
    with tracer.tracing() if tracer is not None else _nothing():
        await pws.send(frame)
        while True:
            data = await sws.recv()
            assert isinstance(data, bytes)
            if tracer is not None:
                tracer.paused = True
            got = _carries(ssession, data, user, x)
            if tracer is not None:
                tracer.paused = False
            if got:
                return


@contextmanager
def _nothing() -> Iterator[None]:
    yield


async def walk(codec: str = "compact", warmup: int = 5) -> Walk:
    """Trace one update of a publisher to a subscriber through a relay on loopback."""
    async with serving(RelayServer(ServerConfig(host="127.0.0.1", port=0))) as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        async with connect(url, compression=None) as pws, connect(url, compression=None) as sws:
            psession, ssession = ClientSession(), ClientSession()
            ids = await _join(pws, psession, STREAMS, codec)
            await _join(sws, ssession, ("head",), codec)
            assert psession.user is not None
            pub, sub = (pws, psession, ids, psession.user), (sws, ssession)
            for seq in range(1, warmup + 1):
                await _deliver(pub, sub, seq, None)
            tracer = _Tracer()
            await _deliver(pub, sub, warmup + 1, tracer)
            return tracer.walk


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--codec", default="compact", choices=("compact", "raw"))
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--show", action="store_true", help="print the first run's walk")
    args = parser.parse_args(argv)
    walks = [asyncio.run(walk(args.codec)) for _ in range(args.runs)]
    if args.show:
        print(" -> ".join(walks[0].visits))
        for call in walks[0].callback_calls:
            print(f"callback: {call}")
        for file, callers in walks[0].places.items():
            print(f"in more than one place: {file} (from {', '.join(callers)})")
    for i, w in enumerate(walks, 1):
        print(f"run {i}: {w.files} files, {w.returns} returns to a file already left")
        places = f"{w.multi_place} files in more than one place"
        print(f"run {i} as read: {w.callbacks} callbacks, {places}")
    files = statistics.median(w.files for w in walks)
    returns = statistics.median(w.returns for w in walks)
    print(f"median of {len(walks)} ({args.codec}): {files:g} files, {returns:g} returns")
    callbacks = statistics.median(w.callbacks for w in walks)
    multi = statistics.median(w.multi_place for w in walks)
    print(f"median of {len(walks)} ({args.codec}) as read: {callbacks:g} callbacks, "
          f"{multi:g} files in more than one place")  # fmt: skip


if __name__ == "__main__":
    main()
