"""``posecast table1 --live``: every tier through the real relay, beside the offline simulator.

For each tier, :func:`run_live_tier` starts a :class:`~server.app.RelayServer`
on ``127.0.0.1`` port 0 with the tier emulated in its egress
(``ServerConfig.link``), runs N trace-driven bots (:func:`client.bot.run_bot`)
in one room for a while, and collects what they measured (QoE per method and
class, scored with :mod:`scenarios.qoe` from each bot's own arrival log and
playout delays exactly as the bot scores itself; keyframes/s; playout delay D)
and what the server measured (the rate it chose for each subscriber,
bytes, delivered and lost snapshots on the emulated link, sampled while the
bots are connected). Then, off the event loop, the offline counterpart of
every bot (:func:`scenarios.live_agreement.simulate_receiver`) and the
verdict (:func:`scenarios.live_agreement.check_agreement`).

Bots publish every native sample of their trace (polled at 90 Hz, the
headsets' frame rate) and subscribe at the tier's rate, so the server's tick is
the one sampling stage, as in the offline Table 1 (keyframe = newest native
sample at each send time). The offline counterpart models the publisher's poll
grid, the room's tick grid and the tier's link, every timer firing late by the
host's measured event-loop lag, so the keyframes match without peeking at the
live arrivals or keyframes. Bots render at 10 Hz (QoE does not depend on it,
see :class:`LiveConfig`); an event-loop lag monitor tells whether the process
kept real time, without which the live figures would measure CPU starvation.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any

import numpy as np
from numpy.typing import NDArray

from posecast import interp
from posecast.client.bot import BotConfig, BotReport, remote_log, run_bot
from posecast.client.remote import ReceivedStream, score_received
from posecast.protocol import frame_size
from posecast.scenarios.live_agreement import (
    AMPLE_DELAY_S,
    ReceiverSim,
    SenderView,
    Tolerance,
    check_agreement,
    model_rate,
    simulate_receiver,
)
from posecast.scenarios.motion import MotionSpec
from posecast.scenarios.network import Tier, websocket_header_bytes
from posecast.scenarios.qoe import ErrorSamples, summarize
from posecast.scenarios.traces import DEVICE_NAMES, Trace, TraceError, find_traces
from posecast.server.app import RelayServer, ServerConfig
from posecast.server.room import room_phase

__all__ = ["LiveConfig", "LiveProgress", "live_motions", "run_live", "run_live_tier"]

F64 = NDArray[np.float64]
#: ``progress(stage, done, total)``: a tier's session seconds, then its scoring.
LiveProgress = Callable[[str, float, float], None]


@dataclass(frozen=True)
class LiveConfig:
    """What one live run does per tier."""

    #: Seconds each bot runs.
    duration: float = 20.0
    bots: int = 3
    #: How often a bot polls its trace and publishes the newest sample if it is new
    #: (Hz); 90 Hz, the headsets' frame rate, publishes every sample of the
    #: <= 90 Hz traces. None: the tier's rate (a second sampling stage before the
    #: server's, whose phase against the tick grid changes the keyframes' ages).
    send_rate: float | None = 90.0
    #: Render rate of the bots (Hz). QoE is scored at the traces' own sample
    #: times whatever this is; rendering only costs CPU, which on a shared
    #: machine would show up as event-loop lag in the network timing.
    render_rate: float = 10.0
    methods: tuple[str, ...] = ("soa", "dq-slerp", "motor-lerp")
    #: Seed of the offline link realisations.
    seed: int = 0
    tolerance: Tolerance = field(default_factory=Tolerance)
    #: Delay between bot starts (s), to avoid a burst of handshakes.
    stagger: float = 0.05
    #: How often the server's per-connection statistics are sampled (s).
    poll: float = 0.25
    #: Also run each tier once more with the bots asking rate "auto" (up to
    #: ``auto_max`` Hz): the relay chooses each one's rate from its emulated link.
    #: Live only (the offline counterpart models a fixed rate); one more session a tier.
    auto: bool = False
    auto_max: float = 30.0
    #: With ``auto``: the auto session's bots also join with this error budget
    #: (``join.budget_deg``, degrees): the relay sends each peer at the rate its view
    #: needs, within the link's rate. None: no budget.
    budget_deg: float | None = None

    def __post_init__(self) -> None:
        if not self.duration > 0:
            raise ValueError(f"live duration must be positive, got {self.duration}")
        if self.bots < 2:
            raise ValueError(
                f"a live run needs at least 2 bots (one to watch another), got {self.bots}"
            )
        if self.send_rate is not None and not self.send_rate > 0:
            raise ValueError(f"send rate must be positive, got {self.send_rate}")
        if self.budget_deg is not None and not 0 < self.budget_deg < 90:
            raise ValueError(f"budget must be in (0, 90) degrees, got {self.budget_deg:g}")
        if self.budget_deg is not None and not self.auto:
            raise ValueError("a budget applies to the auto session: ask for auto rates too")
        needs = [m for m in self.methods if interp.info(m).needs_velocity]
        if needs:
            raise ValueError(
                f"{', '.join(needs)} need keyframe velocities, which the live Table 1 "
                "comparison does not model yet (its offline counterpart has no velocity variant)"
            )


def live_motions(specs: Sequence[str]) -> list[tuple[str, int]]:
    """Bot motions for trace specs: ``(CSV path or synthetic:NAME, seed)``, in order.

    Trace files, folders and ``traces:dev``/``traces:eval`` give one motion per
    CSV; ``synthetic:NAME[:SEED]`` one synthetic motion. Synthetic suites have
    no live counterpart (bots play one motion each).
    """
    out: list[tuple[str, int]] = []
    for spec in specs:
        s = str(spec)
        if s.startswith("synthetic:"):
            _, name, seed = [*s.split(":"), "0"][:3]
            try:
                out.append((f"synthetic:{name}", int(seed)))
            except ValueError:
                raise TraceError(
                    f"malformed synthetic spec {s!r}; use synthetic:NAME[:SEED]"
                ) from None
        elif s == "synthetic" or s.endswith(".toml"):
            raise TraceError(
                f"--live needs trace files or synthetic:NAME motions; {s!r} is a synthetic suite"
            )
        else:
            out.extend((str(p), 0) for p in find_traces(s))
    if not out:
        raise TraceError("no traces given")
    return out


@dataclass
class _LinkSamples:
    """The server's view of one subscriber's emulated link over time."""

    times: list[float] = field(default_factory=list)
    frames: list[int] = field(default_factory=list)
    bytes: list[int] = field(default_factory=list)
    lost: list[int] = field(default_factory=list)
    cap_skips: list[int] = field(default_factory=list)
    rate: list[float] = field(default_factory=list)
    #: Whether the whole room was present at each sample.
    full: list[bool] = field(default_factory=list)


async def _watch(
    server: RelayServer,
    bots: int,
    samples: dict[int, _LinkSamples],
    poll: float,
    tick: Callable[[float], None],
) -> None:
    """Sample every connected subscriber's link figures until cancelled."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    while True:
        await asyncio.sleep(poll)
        now = server.clock()
        stats = server.statistics()["connection_stats"]
        assert isinstance(stats, list)
        linked = [s for s in stats if s.user is not None and s.link_rate_hz is not None]
        for s in linked:
            ls = samples.setdefault(s.user, _LinkSamples())
            ls.times.append(now)
            ls.frames.append(s.link_frames)
            ls.bytes.append(s.link_bytes)
            ls.lost.append(s.link_lost)
            ls.cap_skips.append(s.link_cap_skips)
            ls.rate.append(float(s.link_rate_hz))
            ls.full.append(len(linked) == bots)
        tick(loop.time() - start)


def _server_figures(samples: dict[int, _LinkSamples]) -> dict[str, float]:
    """Per subscriber means over the time the whole room was present."""
    rates, means, spans, bps, fps, skips = [], [], [], [], [], []
    lost = offered = 0
    for ls in samples.values():
        full = [i for i, f in enumerate(ls.full) if f]
        if len(full) < 2:
            continue
        a, b = full[0], full[-1]
        dt = ls.times[b] - ls.times[a]
        if dt <= 0:
            continue
        rates.append(ls.rate[b])
        means.append(float(np.mean(ls.rate[a : b + 1])))
        spans += ls.rate[a : b + 1]
        bps.append((ls.bytes[b] - ls.bytes[a]) / dt)
        fps.append((ls.frames[b] - ls.frames[a]) / dt)
        offered += ls.frames[-1] + ls.lost[-1]
        lost += ls.lost[-1]
        skips.append(float(ls.cap_skips[-1]))
    if not rates:
        raise RuntimeError(
            "the server never saw the whole room at once: the bots' sessions did not overlap "
            "(raise --live-duration)"
        )
    return {
        "server_rate_hz": float(np.mean(rates)),
        "server_rate_min_hz": float(np.min(rates)),
        "server_rate_max_hz": float(np.max(rates)),
        # The rate over the whole room's time, per subscriber, then their mean (an auto
        # rate changes; a fixed one is its last).
        "server_rate_mean_hz": float(np.mean(means)),
        "server_rate_low_hz": float(np.min(spans)),
        "server_rate_high_hz": float(np.max(spans)),
        "bytes_per_s": float(np.mean(bps)),
        "snapshots_per_s": float(np.mean(fps)),
        "lost_fraction": lost / offered if offered else float("nan"),
        "offered": float(offered),
        "cap_skips": float(np.sum(skips)),
        "subscribers_measured": float(len(rates)),
    }


_Groups = list[dict[str, dict[str, ErrorSamples]]]


def _score(
    reports: Sequence[BotReport],
    tier: Tier,
    tier_index: int,
    cfg: LiveConfig,
    send_rate: float,
    rate: float,
    phase: float,
    frame_bytes: int,
    host_lag: F64,
) -> tuple[_Groups, _Groups, list[ReceiverSim], list[float]]:
    """Each bot's QoE (at its D, at an ample D), its offline counterpart, its median D (s).

    Blocking (loads traces, scores): run it off the event loop. The live QoE is
    scored from the bot's own arrival log and playout delays with
    :func:`client.remote.score_received`, exactly as the bot scores itself, over
    the windows where its sender was still publishing (a bot that left early
    leaves no keyframes to bracket the rest of the receiver's session: those
    samples would count as stalls that no network caused).
    """
    truths: dict[str, Trace] = {}
    live: _Groups = []
    live_ample: _Groups = []
    sims: list[ReceiverSim] = []
    live_d: list[float] = []
    for i, rep in enumerate(reports):
        if not rep.render_log:
            continue
        pt = np.array([r[0] for r in rep.render_log])
        pd = np.array([r[1] for r in rep.render_log])
        got, ample, senders = _score_bot(rep, pt, pd, cfg, send_rate, truths)
        if not senders:
            continue
        live.append(got)
        live_ample.append(ample)
        live_d.append(float(np.median(pd)))

        def delay_at(taus: F64, pt: F64 = pt, pd: F64 = pd) -> F64:
            d: F64 = np.interp(taus, pt, pd)
            return d

        sims.append(
            simulate_receiver(
                senders,
                tier=tier,
                rate=rate,
                phase=phase,
                frame_bytes=frame_bytes,
                methods=cfg.methods,
                delay=delay_at,
                seed=(cfg.seed, tier_index, i),
                host_lag=host_lag,
            )
        )
    return live, live_ample, sims, live_d


def _score_bot(
    rep: BotReport,
    pt: F64,
    pd: F64,
    cfg: LiveConfig,
    send_rate: float,
    truths: dict[str, Trace],
) -> tuple[
    dict[str, dict[str, ErrorSamples]], dict[str, dict[str, ErrorSamples]], list[SenderView]
]:
    """One bot's live QoE at its D and at an ample D, and the senders it watched.

    ``pt``, ``pd``: the bot's render times and playout delays; ``truths`` caches
    the senders' traces across bots.
    """
    by_label: dict[str, dict[str, tuple[float, float]]] = {}
    streams = [
        ReceivedStream(rs.label, rs.name, partial(remote_log, rs))
        for rs in rep.streams.values()
        if rs.capture
    ]
    got, ample = (
        {m: classes for m, classes in scored.items() if classes}
        for scored in score_received(
            streams,
            pt,
            pd,
            cfg.methods,
            delays=(None, AMPLE_DELAY_S),
            until_sender_left=True,
            as_rendered=False,
            truths=truths,
            windows=by_label,
        )
    )
    senders = []
    for label, windows in by_label.items():
        t0 = MotionSpec.parse(label).t0
        senders.append(SenderView(truths[label], windows, t0, send_rate, end=t0 + cfg.duration))
    return got, ample, senders


async def _loop_lag(lags: list[float], period: float = 0.01) -> None:
    """Record how late the event loop wakes a 10 ms sleeper, until cancelled."""
    loop = asyncio.get_running_loop()
    while True:
        t = loop.time()
        await asyncio.sleep(period)
        lags.append(max(0.0, loop.time() - t - period))


async def run_live_tier(
    tier: Tier,
    motions: Sequence[tuple[str, int]],
    cfg: LiveConfig,
    *,
    tier_index: int = 0,
    progress: LiveProgress | None = None,
) -> dict[str, Any]:
    """One tier through the real relay and its offline counterpart (see the module doc)."""
    room = f"table1-{tier.name}"
    poses = len(DEVICE_NAMES) * cfg.bots
    payload = frame_size(poses, "snapshot")
    frame_bytes = payload + websocket_header_bytes(payload)
    asked = tier.max_rate_hz
    send_rate = asked if cfg.send_rate is None else cfg.send_rate
    reports, samples, lags = await _session(
        tier, motions, cfg, room=room, send_rate=send_rate, progress=progress
    )
    if progress is not None:
        progress(f"score {tier.name}", 0, 1)
    server_fig = _server_figures(samples)
    rate = model_rate(tier, asked, frame_bytes)
    lag = np.array(lags) if lags else np.zeros(1)
    groups, groups_ample, sims, live_d = await asyncio.to_thread(
        _score,
        reports,
        tier,
        tier_index,
        cfg,
        send_rate,
        rate,
        room_phase(room),
        frame_bytes,
        lag,
    )
    if not sims:
        raise RuntimeError(f"tier {tier.name}: no bot received anything to score")
    live = _live_figures(reports, groups, groups_ample, live_d, server_fig, lag)
    offline = _offline_figures(sims, tier, rate, frame_bytes)
    if progress is not None:
        progress(f"score {tier.name}", 1, 1)
    auto = None
    if cfg.auto:
        auto = await _run_auto(tier, motions, cfg, room=room, send_rate=send_rate,
                               progress=progress)  # fmt: skip
    return {
        "tier": tier.name,
        "tier_params": tier.as_dict(),
        "asked_rate_hz": asked,
        "send_rate_hz": send_rate,
        "room_poses": poses,
        "bots": [
            {
                "name": r.name,
                "user": r.user,
                "rate_hz": r.rate_hz,
                "delay_ms": r.delay_ms,
                "duration_s": r.duration,
                "render_stall_fraction": r.render_stall_fraction,
                "frames_rendered": r.frames_rendered,
            }
            for r in reports
        ],
        "live": live,
        "offline": offline,
        "agreement": check_agreement(live, offline, cfg.tolerance),
        # --live-auto: the same tier with auto rates, live only (no agreement check).
        **({"auto": auto} if auto is not None else {}),
    }


async def _run_auto(
    tier: Tier,
    motions: Sequence[tuple[str, int]],
    cfg: LiveConfig,
    *,
    room: str,
    send_rate: float,
    progress: LiveProgress | None,
) -> dict[str, Any]:
    """``tier`` once more, every bot asking rate "auto" (up to ``cfg.auto_max``): the
    live figures of :func:`_live_figures` (QoE at the bots' own D, keyframes/s, the
    server's chosen rates and link bytes), with no offline counterpart."""
    reports, samples, lags = await _session(
        tier, motions, cfg, room=room, send_rate=send_rate, progress=progress, auto=True
    )
    stage = f"score {tier.name} auto"
    if progress is not None:
        progress(stage, 0, 1)
    server_fig = _server_figures(samples)
    lag = np.array(lags) if lags else np.zeros(1)

    def score() -> tuple[_Groups, _Groups, list[float]]:
        truths: dict[str, Trace] = {}
        live: _Groups = []
        ample: _Groups = []
        live_d: list[float] = []
        for rep in reports:
            if not rep.render_log:
                continue
            pt = np.array([r[0] for r in rep.render_log])
            pd = np.array([r[1] for r in rep.render_log])
            got, got_ample, senders = _score_bot(rep, pt, pd, cfg, send_rate, truths)
            if senders:
                live.append(got)
                ample.append(got_ample)
                live_d.append(float(np.median(pd)))
        return live, ample, live_d

    groups, groups_ample, live_d = await asyncio.to_thread(score)
    if not groups:
        raise RuntimeError(f"tier {tier.name} (auto): no bot received anything to score")
    if progress is not None:
        progress(stage, 1, 1)
    figures = _live_figures(reports, groups, groups_ample, live_d, server_fig, lag)
    figures["asked"] = f"auto (up to {cfg.auto_max:g} Hz)"
    if cfg.budget_deg is not None:
        figures["asked"] += f", budget {cfg.budget_deg:g} deg"
    return figures


async def _session(
    tier: Tier,
    motions: Sequence[tuple[str, int]],
    cfg: LiveConfig,
    *,
    room: str,
    send_rate: float,
    progress: LiveProgress | None,
    auto: bool = False,
) -> tuple[list[BotReport], dict[int, _LinkSamples], list[float]]:
    """A relay emulating ``tier`` and ``cfg.bots`` bots in ``room``, to the bots' end;
    ``auto``: the bots ask rate "auto" (up to ``cfg.auto_max``), not the tier's rate.

    Returns the bots' reports, the server's link samples per subscriber and the
    event loop's lags (s) while the bots ran.
    """
    asked = tier.max_rate_hz
    server = RelayServer(
        ServerConfig(
            host="127.0.0.1",
            port=0,
            rate=asked,
            min_rate=min(5.0, asked),
            max_rate=max(30.0, asked, cfg.auto_max),
            link=tier,
            # Bots and relay share this process: its CPU is not the relay's alone.
            capacity_cpu=0.0,
            capacity_lag=0.0,
        )
    )
    stage = f"live {tier.name}" + (" auto" if auto else "")
    samples: dict[int, _LinkSamples] = {}
    lags: list[float] = []

    def tick(elapsed: float) -> None:
        if progress is not None:
            progress(stage, min(elapsed, cfg.duration), cfg.duration)

    async with asyncio.timeout(cfg.duration + cfg.bots * cfg.stagger + 120.0):
        async with asyncio.TaskGroup() as tg:
            tg.create_task(server.run())
            try:
                await asyncio.wait_for(server.ready.wait(), 10)
                base = BotConfig(
                    url=f"ws://127.0.0.1:{server.port}",
                    room=room,
                    rate=cfg.auto_max if auto else asked,
                    auto_rate=auto,
                    budget_deg=cfg.budget_deg if auto else None,
                    send_rate=send_rate,
                    methods=cfg.methods,
                    duration=cfg.duration,
                    render_rate=cfg.render_rate,
                    keep_render_log=True,
                    # The offline model prices raw snapshot frames: compare like with like.
                    codec="raw",
                )
                helpers = [
                    tg.create_task(_watch(server, cfg.bots, samples, cfg.poll, tick)),
                    tg.create_task(_loop_lag(lags)),
                ]

                async def one(i: int) -> BotReport:
                    motion, seed = motions[i % len(motions)]
                    await asyncio.sleep(i * cfg.stagger)
                    return await run_bot(
                        replace(base, motion=motion, seed=seed, name=f"{tier.name}-bot{i}")
                    )

                try:
                    async with asyncio.TaskGroup() as bots:
                        tasks = [bots.create_task(one(i)) for i in range(cfg.bots)]
                finally:
                    for h in helpers:
                        h.cancel()
            finally:
                server.stop()
    return [t.result() for t in tasks], samples, lags


def _live_figures(
    reports: Sequence[BotReport],
    groups: _Groups,
    groups_ample: _Groups,
    live_d: list[float],
    server_fig: dict[str, float],
    lag: F64,
) -> dict[str, Any]:
    """What the live session measured: QoE, rate, D, the server's link, the loop's lag."""
    rates = [r.rate_hz for r in reports if r.rate_hz > 0]
    return {
        "methods": summarize(groups),
        "methods_ample": summarize(groups_ample),
        "rate_hz": float(np.mean(rates)) if rates else float("nan"),
        "delay_ms": 1000.0 * float(np.mean(live_d)),
        **server_fig,
        "bot_bytes_per_s": float(np.mean([r.snapshot_bytes / r.duration for r in reports])),
        "render_stall_fraction": float(np.mean([r.render_stall_fraction for r in reports])),
        "clock_rtt_ms": float(np.mean([r.clock_rtt_ms for r in reports])),
        "loop_lag_p50_ms": 1000.0 * float(np.percentile(lag, 50)),
        "loop_lag_p95_ms": 1000.0 * float(np.percentile(lag, 95)),
        "loop_lag_max_ms": 1000.0 * float(lag.max()),
        # What the bots reported themselves (their windows run to their own end,
        # past the end of senders that left earlier).
        "bots_own_methods": summarize(r.qoe for r in reports),
    }


def _offline_figures(
    sims: Sequence[ReceiverSim], tier: Tier, rate: float, frame_bytes: int
) -> dict[str, Any]:
    """What the offline counterparts of the bots give, in the live figures' keys."""
    delivered = sum(s.delivered for s in sims)
    lost = sum(s.lost for s in sims)
    return {
        "methods": summarize([s.equal_d for s in sims]),
        "methods_rule_d": summarize([s.rule_d for s in sims]),
        "methods_ample": summarize([s.ample_d for s in sims]),
        "rate_hz": float(np.nanmean([s.rate_hz for s in sims])),
        "server_rate_hz": rate,
        "bytes_per_s": float(np.mean([s.bytes_per_s for s in sims])),
        "delay_ms": 1000.0 * float(np.mean([s.rule_delay_s for s in sims])),
        "lost_fraction": lost / (delivered + lost) if delivered + lost else float("nan"),
        "offered": float(delivered + lost),
        "tier_loss": tier.loss_pct / 100.0,
        "frame_bytes": frame_bytes,
    }


async def run_live(
    traces: Sequence[str],
    tiers: Sequence[Tier],
    cfg: LiveConfig,
    progress: LiveProgress | None = None,
) -> dict[str, Any]:
    """Every tier in turn (one relay each); the ``live`` key of ``table1.json``."""
    if not tiers:
        raise ValueError("no tiers to run")
    motions = await asyncio.to_thread(live_motions, traces)
    rows = []
    for i, tier in enumerate(tiers):
        rows.append(await run_live_tier(tier, motions, cfg, tier_index=i, progress=progress))
    return {
        "config": {
            "bots": cfg.bots,
            "duration_s": cfg.duration,
            "send_rate_hz": "the tier's rate" if cfg.send_rate is None else cfg.send_rate,
            "render_rate_hz": cfg.render_rate,
            "methods": list(cfg.methods),
            "seed": cfg.seed,
            "motions": [m.rsplit("/", 1)[-1] for m, _ in motions[: cfg.bots]],
            "tolerance": cfg.tolerance.as_dict(),
            **({"auto_max_hz": cfg.auto_max} if cfg.auto else {}),
            "compared": "offline counterpart of each bot at the bot's own playout delay D(tau); "
            "D itself against Table 1's rule 1/rate + p95(age)",
        },
        "tiers": rows,
        "pass": all(r["agreement"]["pass"] for r in rows),
    }
