"""The attacker process of ``posecast bench hostile``: runs one attack, then reports.

Run as ``python -c BOOT CONFIG_JSON [NICE]`` by the controller
(:mod:`posecast.bench.hostile`): it reads the controller's signals from stdin,
attacks until stdin closes or the attack's bounds pass, and prints one
``{"event": "attack-result", ...}`` line. The attacks themselves live in
:mod:`~posecast.bench.hostile_attacks` (issue 14's), :mod:`~posecast.bench.hostile_room`
and :mod:`~posecast.bench.hostile_path` (issue 29's).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import sys
import threading
import time
from typing import Any

from posecast.bench.common import _raise_nofile, _run_loop
from posecast.bench.hostile_attacks import _RUNNERS, ATTACKS, AttackConfig, Tally, _set_signal
from posecast.bench.hostile_path import RUNNERS as PATH_RUNNERS
from posecast.bench.hostile_room import RUNNERS as ROOM_RUNNERS

__all__ = ["run_attack"]

#: The controller starts the attacker process with this (``python -c``).
_ATTACK_BOOT = "from posecast.bench.hostile_attacker import _attack_entry; _attack_entry()"


def _runners() -> dict[str, Any]:
    """Every attack's coroutine, by name."""
    return {**_RUNNERS, **ROOM_RUNNERS, **PATH_RUNNERS}


async def run_attack(cfg: AttackConfig, stop: asyncio.Event | None = None) -> dict[str, Any]:
    """Run attack ``cfg.kind`` until ``stop`` is set or ``cfg.seconds`` pass; its tally."""
    runners = _runners()
    if cfg.kind not in runners:
        raise ValueError(f"unknown attack {cfg.kind!r}: one of {', '.join(ATTACKS)}")
    stop = stop or asyncio.Event()
    tally = Tally()
    timer = asyncio.get_running_loop().call_later(cfg.seconds, stop.set)
    start = time.monotonic()
    try:
        await runners[cfg.kind](cfg, stop, tally)
    finally:
        timer.cancel()
    result = tally.as_dict()
    result["seconds"] = time.monotonic() - start
    return result


def _watch_stdin(loop: asyncio.AbstractEventLoop, stop: asyncio.Event) -> None:
    """Pass on the controller's signals; set ``stop`` when it closes our stdin (a
    thread: stdin blocks)."""
    for line in sys.stdin:
        with contextlib.suppress(ValueError, AttributeError):
            name = str(json.loads(line).get("signal"))
            loop.call_soon_threadsafe(_set_signal, name)
    loop.call_soon_threadsafe(stop.set)


async def _main(cfg: AttackConfig) -> dict[str, Any]:
    stop = asyncio.Event()
    threading.Thread(
        target=_watch_stdin, args=(asyncio.get_running_loop(), stop), daemon=True
    ).start()
    return await run_attack(cfg, stop)


def _attack_entry() -> None:
    """Entry of the attacker process: ``python -c BOOT CONFIG_JSON [NICE]``."""
    cfg = AttackConfig(**json.loads(sys.argv[1]))
    if len(sys.argv) > 2 and int(sys.argv[2]):
        # Real attackers run on other machines: on a shared 2-core box an attacker
        # at equal priority would measure the OS scheduler, not the relay.
        os.nice(int(sys.argv[2]))
    _raise_nofile(cfg.flood_connections + cfg.rooms + cfg.slowloris_connections + 256)
    result = _run_loop(_main(cfg))
    print(json.dumps({"event": "attack-result", **result}, default=dict), flush=True)
