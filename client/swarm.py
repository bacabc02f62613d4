"""Many bots at once, and the report they add up to.

:func:`run_bots` starts N bots under one ``TaskGroup`` against a server URL (or
several: bot i starts on relay i, round-robin, and fails over to the others);
:func:`swarm_report` pools their QoE with :func:`scenarios.qoe.summarize` and
adds the wire figures, in the JSON shape ``posecast bots/demo --json`` write.

Judgements on a finished swarm, pure functions of its reports:

- :func:`starvation`: did the machine starve the session? The figures of a starved
  session read worse than the method is. It is starved when the bots' mean
  keyframe rate is under 90 % of the rate they could get (the asked snapshot
  rate, or the senders' publish rate if lower), or when over 10 % of all render
  frames were late (started more than one render period, 1/90 s, after their
  scheduled time: a headset would have missed showing them).
- :func:`session_ending`: how the session ended (every bot ran its duration, the
  server closed it, or the connection was lost), as lines to print and an exit
  code: 0 when every bot completed or the server closed with 1000/1001, else 1.
- :func:`reconnections`: which bots resumed or rejoined after a drop, and where
  they ended, as lines to print.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

from posecast.client.bot import Bot, BotConfig, BotReport, motion_for_bot, run_bot
from posecast.scenarios.qoe import summarize
from posecast.scenarios.spawn import layout_points

__all__ = [
    "STARVED_KEYFRAME_SHARE",
    "STARVED_RENDER_LATE",
    "Starvation",
    "handovers",
    "reconnections",
    "run_bots",
    "session_ending",
    "starvation",
    "swarm_report",
]

#: Starved when the measured keyframe rate is under this share of the expected one.
STARVED_KEYFRAME_SHARE = 0.9
#: Starved when over this share of the render frames were late (over a period behind).
STARVED_RENDER_LATE = 0.1


async def run_bots(
    base: BotConfig,
    n: int,
    *,
    token_for: Callable[[int], str | None] | None = None,
    stagger: float = 0.05,
    spawn: str = "none",
    stop: asyncio.Event | None = None,
) -> list[BotReport]:
    """Run ``n`` bots built from ``base`` (bot i gets motion i of ``base.motion``, and
    spawn point i of the layout ``spawn``: ``scenarios.spawn.layout_points``).

    With several relays (``base.relays``), bot i starts on relay ``i % len`` and
    fails over to the next ones in order. Setting ``stop`` (Ctrl-C) ends every bot's
    session there; each reports the time it ran.
    """
    cfgs, relays = [], base.relays
    points = layout_points(spawn, n)
    for i in range(n):
        motion, seed = motion_for_bot(base.motion, i)
        cfg = replace(
            base,
            motion=motion,
            seed=seed,
            spawn=base.spawn if points is None else points[i],
            name=f"{base.name}{i}",
            token=token_for(i) if token_for else base.token,
        )
        if len(relays) > 1:
            cfg = replace(cfg, url=relays[i % len(relays)], urls=relays)
        cfgs.append(cfg)

    async def one(i: int, cfg: BotConfig) -> BotReport:
        await asyncio.sleep(i * stagger)  # avoid a thundering herd of handshakes
        if stop is None:
            return await run_bot(cfg)
        bot = Bot(cfg, time.monotonic)
        async with asyncio.TaskGroup() as tg:
            watcher = tg.create_task(_interrupt(bot, stop))
            report = await bot.run()
            watcher.cancel()
        return report

    async with asyncio.TaskGroup() as tg:
        tasks = [tg.create_task(one(i, c)) for i, c in enumerate(cfgs)]
    return [t.result() for t in tasks]


async def _interrupt(bot: Bot, stop: asyncio.Event) -> None:
    """When ``stop`` is set, end ``bot``'s session as ``interrupted``: its render loop
    ends at its next frame, and it reports the time it ran."""
    await stop.wait()
    bot.stop()


@dataclass(frozen=True)
class Starvation:
    """Whether a session was starved of CPU, from what its bots measured.

    ``keyframe_hz``: mean over the bots that received anything of their keyframe
    rate (None if none did); ``expected_hz``: what they could get, the asked
    snapshot rate or the publish rate if lower; ``asked_hz``: the asked rate;
    ``render_late_fraction``: late render frames over all rendered (None if none).
    """

    keyframe_hz: float | None
    expected_hz: float
    asked_hz: float
    render_late_fraction: float | None

    @property
    def keyframes_short(self) -> bool:
        return (
            self.keyframe_hz is not None
            and self.keyframe_hz < STARVED_KEYFRAME_SHARE * self.expected_hz
        )

    @property
    def render_late(self) -> bool:
        return (
            self.render_late_fraction is not None
            and self.render_late_fraction > STARVED_RENDER_LATE
        )

    @property
    def starved(self) -> bool:
        return self.keyframes_short or self.render_late

    def warning(self) -> str | None:
        """The one line to print for a starved session, else None."""
        if not self.starved:
            return None
        parts = []
        if self.keyframe_hz is not None:
            of = "asked" if self.expected_hz == self.asked_hz else "possible"
            parts.append(f"keyframe rate {self.keyframe_hz:.1f} Hz of {self.expected_hz:g} {of}")
        if self.render_late_fraction is not None:
            parts.append(f"render loop late {100 * self.render_late_fraction:.0f} % of frames")
        return (
            f"warning: this machine starved the session ({'; '.join(parts)}): "
            "figures may read worse than the method is"
        )

    def as_dict(self) -> dict[str, Any]:
        return {
            "starved": self.starved,
            "keyframe_hz": self.keyframe_hz,
            "expected_keyframe_hz": self.expected_hz,
            "asked_hz": self.asked_hz,
            "render_late_fraction": self.render_late_fraction,
            "warning": self.warning(),
        }


def starvation(reports: Sequence[BotReport]) -> Starvation:
    """Judge whether the machine starved the session the bots of ``reports`` ran."""
    rates = [r.rate_hz for r in reports if r.streams and r.rate_hz > 0]
    frames = sum(r.frames_rendered for r in reports)
    asked = min((r.granted_hz or r.asked_hz for r in reports), default=0.0)
    sends = [r.send_hz for r in reports if r.send_hz > 0]
    expected = min([asked, *sends]) if sends else asked
    return Starvation(
        keyframe_hz=sum(rates) / len(rates) if rates else None,
        expected_hz=expected,
        asked_hz=asked,
        render_late_fraction=sum(r.frames_late for r in reports) / frames if frames else None,
    )


def session_ending(reports: Sequence[BotReport]) -> tuple[list[str], int]:
    """Lines that say how the session ended (none if every bot completed), and the exit code.

    One line per way of ending, e.g. ``session ended early: server closed: going
    away (1001) after 2.0 s (3 of 3 bots); the report covers that time``, or
    ``session stalled: no fresh poses for 14.6 s of 20.0 s (1 of 4 bots)`` for bots
    that ran their duration mostly without fresh poses. Exit code 0 if every bot
    completed or was closed on purpose by the server (1000, 1001), else 1 (a lost
    connection, a close for an error, a stalled session).
    """
    early = [r for r in reports if r.ending.kind != "complete"]
    lines = []
    groups: dict[tuple[str, int | None, str], list[BotReport]] = {}
    for r in early:
        groups.setdefault((r.ending.kind, r.ending.code, r.ending.reason), []).append(r)
    for group in groups.values():
        # The bot that lasted longest tells how much of the session there is.
        last = max(group, key=lambda r: r.ending.after_s)
        if last.ending.kind == "stalled":
            lines.append(f"session {last.ending.describe()} ({len(group)} of {len(reports)} bots)")
            continue
        lines.append(
            f"session ended early: {last.ending.describe()} "
            f"({len(group)} of {len(reports)} bots); the report covers that time"
        )
    code = 0 if all(r.ending.graceful for r in reports) else 1
    return lines, code


def reconnections(reports: Sequence[BotReport]) -> list[str]:
    """Lines that say which bots reconnected after a drop (none if no bot did), e.g.
    ``reconnected after a drop: bot0 rejoined 1 (now on ws://b:8765); bot1 resumed 1``,
    and, when the bots ended on several relays, how many ended on each."""
    moved = []
    for r in reports:
        counts = [
            f"{what} {k}" for what, k in (("resumed", r.resumed), ("rejoined", r.rejoined)) if k
        ]
        if counts:
            where = f" (now on {r.relay})" if r.rejoined else ""
            moved.append(f"{r.name} {' and '.join(counts)}{where}")
    lines = [f"reconnected after a drop: {'; '.join(moved)}"] if moved else []
    ends: dict[str, int] = {}
    for r in reports:
        if r.relay:
            ends[r.relay] = ends.get(r.relay, 0) + 1
    if len(ends) > 1:
        lines.append("bots per relay at the end: " + ", ".join(f"{u} {k}" for u, k in ends.items()))
    return lines


def _object_classes(report: BotReport) -> dict[str, dict[str, dict[str, float]]]:
    """One bot's figures of the shared-object classes: ``{method: {class: stats}}``."""
    return {
        method: {cls: st for cls, st in classes.items() if cls.startswith("object")}
        for method, classes in summarize([report.qoe]).items()
        if any(cls.startswith("object") for cls in classes)
    }


def handovers(reports: Sequence[BotReport]) -> dict[str, int]:
    """Shared objects' changes of owner by reason (``throw``, ``catch``, ...), as the bot
    that saw the most of them received them (every member is told every change)."""
    seen = max((r.ownership for r in reports), key=len, default=[])
    out: dict[str, int] = {}
    for change in seen:
        out[change.reason] = out.get(change.reason, 0) + 1
    return out


def swarm_report(reports: Sequence[BotReport]) -> dict[str, Any]:
    """``{"methods": ..., "wire": ..., "bots": [...]}`` (the documented JSON shape)."""
    methods = summarize(r.qoe for r in reports)
    snap_bytes = sum(r.snapshot_bytes for r in reports)
    poses = sum(r.poses_received for r in reports)
    seconds = sum(r.duration for r in reports)
    up_bytes = sum(r.update_bytes for r in reports)
    sent = sum(r.poses_sent for r in reports)
    codecs = "+".join(sorted({r.codec for r in reports}))
    lines, exit_code = session_ending(reports)
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
            # Upstream: how the bots coded their updates ("raw", "compact", or
            # "compact+raw" for a mix), and bytes of update frames sent per pose sent.
            "codec": codecs,
            "up_bytes_per_pose": up_bytes / sent if sent else float("nan"),
        },
        "bots": [
            {
                "id": r.user,
                "name": r.name,
                "rate_hz": r.rate_hz,
                # The snapshot rate asked (an auto rate's ceiling) and the last granted.
                "asked_hz": r.asked_hz,
                "granted_hz": r.granted_hz,
                "auto_rate": r.auto_rate,
                "delay_ms": r.delay_ms,
                "render_stall_fraction": r.render_stall_fraction,
                "frames_rendered": r.frames_rendered,
                "render_cpu_ms_per_frame": 1000.0 * r.render_cpu_s / max(1, r.frames_rendered),
                "clock_rtt_ms": r.clock_rtt_ms,
                "snapshot_age_ms_p50": r.snapshot_age_ms[0],
                "snapshot_age_ms_p99": r.snapshot_age_ms[1],
                "snapshot_gap_s": r.snapshot_gap_s,
                "render_late_fraction": r.frames_late / max(1, r.frames_rendered),
                "codec": r.codec,
                "up_bytes_per_pose": r.update_bytes / r.poses_sent if r.poses_sent else None,
                "ended": r.ending.describe(),
                # Render time with no fresh pose of anyone (every remote stream held).
                "stale_s": r.stale_s,
                "resumed": r.resumed,
                "rejoined": r.rejoined,
                "relay": r.relay,
                "role": r.role,
                # What this bot saw of a shared object (the throw-catch drill), if any.
                "object": _object_classes(r),
            }
            for r in reports
        ],
        "objects": {"handovers": handovers(reports)},
        "reconnects": {
            "resumed": sum(r.resumed for r in reports),
            "rejoined": sum(r.rejoined for r in reports),
            "lines": reconnections(reports),
        },
        "starvation": starvation(reports).as_dict(),
        "ending": {
            "complete": all(r.ending.kind == "complete" for r in reports),
            "lines": lines,
            "exit_code": exit_code,
        },
    }
