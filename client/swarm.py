"""Many bots at once, and the report they add up to.

:func:`run_bots` starts N bots under one ``TaskGroup`` against a server URL;
:func:`swarm_report` pools their QoE with :func:`scenarios.qoe.summarize` and
adds the wire figures, in the JSON shape ``posecast bots/demo --json`` write.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any

from client.bot import BotConfig, BotReport, motion_for_bot, run_bot
from scenarios.qoe import summarize

__all__ = ["run_bots", "swarm_report"]


async def run_bots(
    base: BotConfig,
    n: int,
    *,
    token_for: Callable[[int], str | None] | None = None,
    stagger: float = 0.05,
) -> list[BotReport]:
    """Run ``n`` bots built from ``base`` (bot i gets motion i of ``base.motion``)."""
    cfgs = []
    for i in range(n):
        motion, seed = motion_for_bot(base.motion, i)
        cfgs.append(
            replace(
                base,
                motion=motion,
                seed=seed,
                name=f"{base.name}{i}",
                token=token_for(i) if token_for else base.token,
            )
        )

    async def one(i: int, cfg: BotConfig) -> BotReport:
        await asyncio.sleep(i * stagger)  # avoid a thundering herd of handshakes
        return await run_bot(cfg)

    async with asyncio.TaskGroup() as tg:
        tasks = [tg.create_task(one(i, c)) for i, c in enumerate(cfgs)]
    return [t.result() for t in tasks]


def swarm_report(reports: Sequence[BotReport]) -> dict[str, Any]:
    """``{"methods": ..., "wire": ..., "bots": [...]}`` (the documented JSON shape)."""
    methods = summarize(r.qoe for r in reports)
    snap_bytes = sum(r.snapshot_bytes for r in reports)
    poses = sum(r.poses_received for r in reports)
    seconds = sum(r.duration for r in reports)
    return {
        "methods": methods,
        "wire": {
            # Snapshot bytes per remote pose delivered (a subscriber's own
            # streams ride along in the shared snapshot and are paid for here).
            "bytes_per_pose": snap_bytes / poses if poses else float("nan"),
            "bytes_per_s": snap_bytes / seconds if seconds else float("nan"),
            "bytes_in_total": sum(r.bytes_in for r in reports),
            "bytes_out_total": sum(r.bytes_out for r in reports),
            # Velocity keyframes (12 B more a pose, 6 x float16) are in the figures above.
            "velocity_keyframes": any(r.velocities for r in reports),
        },
        "bots": [
            {
                "id": r.user,
                "name": r.name,
                "rate_hz": r.rate_hz,
                "delay_ms": r.delay_ms,
                "render_stall_fraction": r.render_stall_fraction,
                "frames_rendered": r.frames_rendered,
                "render_cpu_ms_per_frame": 1000.0 * r.render_cpu_s / max(1, r.frames_rendered),
                "clock_rtt_ms": r.clock_rtt_ms,
            }
            for r in reports
        ],
    }
