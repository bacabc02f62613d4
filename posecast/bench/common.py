"""What the load process and the controller of ``posecast bench relay`` share."""

from __future__ import annotations

import asyncio
import math
import re
from collections.abc import Coroutine
from typing import Any

import numpy as np

from posecast.protocol import PoseUpdate

#: The streams every bench client publishes.
STREAMS = ("head", "left", "right")

_SERVER_BOOT = "from posecast.cli import main; main()"
_LOAD_BOOT = "from posecast.bench.load import _load_entry; _load_entry()"
_BASELINE_BOOT = "from posecast.bench.baseline import _baseline_entry; _baseline_entry()"
_LISTENING = re.compile(r"posecast listening on ws://([^:\s]+):(\d+)")

#: Snapshot scalars and bodies are turned into numpy arrays this many at a time.
_FLUSH_EVERY = 4096


# ----------------------------------------------------------------------------------
# Shared helpers
# ----------------------------------------------------------------------------------


def update_template(stream_ids: list[int], position: tuple[float, float, float]) -> dict[str, Any]:
    """The protocol's wire map of an update with ``stream_ids`` and dt = 0.

    Re-packing it with ``msgpack.packb`` after setting ``seq`` and ``time`` gives
    exactly ``protocol.encode_update(seq, ids, [time] * n, poses, base_time=time)``
    at a twentieth of the cost.
    """
    n = len(stream_ids)
    poses = np.tile([*position, 1.0, 0.0, 0.0, 0.0], (n, 1))
    return PoseUpdate.from_arrays(0, stream_ids, np.zeros(n), poses, base_time=0.0).to_wire()


#: Frames in a client's motion cycle: 2 s at 20 Hz.
MOTION_FRAMES = 40
#: ``--motion`` value for fixed poses (every delta zero in the compact codec).
STATIC = "static"
#: The default ``--motion``: the real head and hand traces bundled with posecast.
DEFAULT_MOTION = "traces:sample"


class Motion:
    """What each bench client publishes: a cycle of frames ``(K, 3, 7)`` at the bench rate.

    ``spec`` is ``static`` (one fixed pose per stream, K = 1) or a trace set
    (``traces:sample``, ``traces:dev``, a folder or a file): client ``i`` plays
    ``MOTION_FRAMES`` samples of trace ``i % len(traces)`` (its head, left and
    right streams), taken at ``rate`` Hz from a start spread over the trace,
    then loops (one jump a cycle).
    """

    def __init__(self, spec: str, rate: float, frames: int = MOTION_FRAMES) -> None:
        if rate <= 0 or frames < 1:
            raise ValueError("rate and frames must be positive")
        self.spec, self.rate, self.frames = spec, rate, frames
        self.traces = [] if spec == STATIC else _bench_traces(spec)

    def cycle(self, index: int) -> np.ndarray:
        """Client ``index``'s frames, float64 ``(K, len(STREAMS), 7)``."""
        if not self.traces:
            pose = [0.01 * (index % 1000), 1.6, 0.0, 1.0, 0.0, 0.0, 0.0]
            return np.tile(pose, (1, len(STREAMS), 1))
        trace = self.traces[index % len(self.traces)]
        span = trace.duration - (self.frames - 1) / self.rate
        # Golden-ratio steps: the clients of one trace start far apart.
        start = (index // len(self.traces) * 0.6180339887 % 1.0) * max(span, 0.0)
        wanted = trace.times[0] + start + np.arange(self.frames) / self.rate
        rows = np.searchsorted(trace.times, wanted).clip(0, len(trace.times) - 1)
        cycle: np.ndarray = trace.poses[rows]
        return cycle


def _bench_traces(spec: str) -> list[Any]:
    """The traces of ``spec`` that have every stream of :data:`STREAMS`; ValueError if none."""
    from posecast.scenarios.traces import find_traces, load_trace

    traces = [load_trace(path) for path in find_traces(spec)]
    usable = [t.select(STREAMS) for t in traces if set(STREAMS) <= set(t.streams)]
    if not usable:
        raise ValueError(f"no trace in {spec!r} has the streams {', '.join(STREAMS)}")
    return usable


def _ws_header(n: int) -> int:
    """Bytes of an unmasked (server -> client) websocket frame header for ``n`` bytes."""
    return 2 if n <= 125 else 4 if n <= 0xFFFF else 10


def _pct(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if len(values) else math.nan


def _run_loop(coro: Coroutine[Any, Any, Any]) -> Any:
    try:
        import uvloop
    except ImportError:
        return asyncio.run(coro)
    return uvloop.run(coro)


def _raise_nofile(needed: int) -> None:
    try:
        import resource

        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        if soft != resource.RLIM_INFINITY and soft < needed:
            target = needed if hard == resource.RLIM_INFINITY else min(needed, hard)
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
    except (ImportError, ValueError, OSError):
        pass
