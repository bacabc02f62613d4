"""What the load process and the controller of ``posecast bench relay`` share."""

from __future__ import annotations

import asyncio
import math
import re
from collections.abc import Coroutine
from typing import Any

import numpy as np

from protocol import PoseUpdate

#: The streams every bench client publishes.
STREAMS = ("head", "left", "right")

_SERVER_BOOT = "from posecast.cli import main; main()"
_LOAD_BOOT = "from posecast.bench.load import _load_entry; _load_entry()"
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
