"""``run_table1``: the Table 1 pipeline, stage after stage.

Resolve what to run (:func:`_plan`), sweep QoE against rate on the ideal
network, derive the tiers' equal-QoE rates, bench the receiver, sweep each
tier's link, search the error-versus-latency view, then assemble, write and
return the report (:mod:`scenarios.table1.report`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from posecast import interp
from posecast.scenarios.network import Tier, Transport, load_tiers, wire_bytes
from posecast.scenarios.table1.codec_bytes import CODECS, SizeCache, codec_report
from posecast.scenarios.table1.common import (
    CORRECTION_TIME_S,
    DEFAULT_METHODS,
    DEFAULT_ROOM_POSES,
    EXTRAPOLATE_HORIZON_S,
    FRONTIER_FRACTIONS,
    PAPER,
    Progress,
    Stats,
    _as_traces,
    tier_rate,
)
from posecast.scenarios.table1.frontier import _Network, frontier_networks, frontier_report
from posecast.scenarios.table1.plots import frontier_plot, write_plots
from posecast.scenarios.table1.report import (
    assemble_report,
    jsonable,
    run_config,
    write_json,
    write_markdown,
)
from posecast.scenarios.table1.runtime import bench_tier_rows
from posecast.scenarios.table1.sweep import (
    _curves_json,
    _ideal_log,
    _Sweep,
    _sweep,
    _Wire,
    _wire,
    ideal_tier_rows,
    link_rows,
    per_trace_report,
)
from posecast.scenarios.traces import Trace, device_class


def run_table1(
    traces: Sequence[str | Path | Trace],
    rates: Iterable[int] = range(5, 31),
    methods: Sequence[str] = DEFAULT_METHODS,
    tiers: Mapping[str, Tier] | Sequence[Tier] | str | Path | None = None,
    out_dir: str | Path | None = None,
    progress: Progress | None = None,
    *,
    seed: int = 0,
    room_poses: int = DEFAULT_ROOM_POSES,
    transport: Transport = "datagram",
    link: bool = True,
    bench: bool = True,
    bench_seconds: float = 1.0,
    bench_repeats: int = 11,
    plots: bool = True,
    command: str | None = None,
    provenance: Mapping[str, Any] | None = None,
    frontier: bool = True,
    frontier_rates: Iterable[int] | None = None,
    frontier_fractions: Sequence[float] = FRONTIER_FRACTIONS,
    extrapolate_horizon: float = EXTRAPOLATE_HORIZON_S,
    correction_time: float = CORRECTION_TIME_S,
    codecs: Sequence[str] = CODECS,
) -> dict[str, Any]:
    """Measure Table 1 on ``traces``; return the report (and write it if ``out_dir``).

    ``traces``: :class:`Trace` objects, CSV paths, or specs for
    :func:`resolve_traces` (``traces:dev``, ``synthetic``, ...). ``rates``:
    integer rates (Hz) searched for equal-QoE rates. ``methods``: interpolator
    names (``soa`` is always included as the reference). ``tiers``: tiers, a
    tier TOML file merged over the built-ins, or None for the built-ins.
    ``room_poses``: poses per snapshot for wire sizes (the bandwidth cap and the
    receiver running time). ``transport``: the link model's loss behaviour.
    ``link``/``bench``/``plots`` switch off parts (c), the running time, and
    the PNGs; ``provenance`` (revision, traces split) goes into ``config``.
    Writes ``table1.md``, ``table1.json`` (the returned dict) and PNGs to
    ``out_dir`` when given. Every method gets its own playout delay (one
    interval plus its look-ahead), velocity methods float16 keyframe velocities
    and the bigger wire frame; savings in updates/s and bytes/s.

    ``frontier`` adds the error-versus-latency view (key ``"frontier"``): hands
    only, every method at ``frontier_rates`` (default: :data:`FRONTIER_RATES`
    inside the rate range, plus the tiers' SoA rates), playout delays
    ``(f + look-ahead)/rate + lag`` for ``f`` in ``frontier_fractions``, each
    with the :data:`VARIANTS` (hold; dead reckoning up to
    ``extrapolate_horizon`` s, jump or blended over ``correction_time`` s), on
    the ideal network and (with ``link``) through every tier's link. With
    ``"compact"`` in ``codecs``, key ``"codecs"`` prices each equal-QoE rate with
    both codecs (:mod:`scenarios.table1.codec_bytes`).
    """
    clock = _Clock()
    opts = _Options(
        seed=seed,
        room_poses=room_poses,
        transport=transport,
        link=link,
        bench=bench,
        bench_seconds=bench_seconds,
        bench_repeats=bench_repeats,
        plots=plots,
        command=command,
        provenance=provenance,
        frontier=frontier,
        frontier_rates=frontier_rates,
        frontier_fractions=frontier_fractions,
        extrapolate_horizon=extrapolate_horizon,
        correction_time=correction_time,
        codecs=tuple(codecs),
    )
    unknown = sorted(set(codecs) - set(CODECS))
    if unknown:
        raise ValueError(f"unknown codec(s) {unknown}; known: {', '.join(CODECS)}")
    p = _plan(traces, rates, methods, tiers, room_poses)
    report, ideal, link_sweeps = _measure_or_interrupted(p, opts, clock, progress)
    if out_dir is not None:
        _write(Path(out_dir), report, p, ideal, link_sweeps, plots)
    return report


class Table1Interrupted(KeyboardInterrupt):
    """Ctrl-C during :func:`run_table1`, with what the run had measured (nothing is
    written). ``curves``: ``{rate: {method: {class: stats}}}`` on the ideal network,
    for the rates finished (of ``rates``); ``tiers``: Table 1's rows (equal-QoE
    rates on the ideal network, no running time) once the whole ideal sweep was
    done, else None."""

    def __init__(
        self,
        curves: dict[int, Stats],
        rates: list[int],
        tiers: list[dict[str, Any]] | None,
    ) -> None:
        super().__init__("Table 1 interrupted")
        self.curves, self.rates, self.tiers = curves, rates, tiers


@dataclass
class _Partial:
    """What an interrupted run keeps: each finished rate of the ideal sweep, and the
    whole ideal sweep once it is done."""

    finished: dict[int, Stats] = field(default_factory=dict)
    ideal: _Sweep | None = None

    def interrupted(self, p: _Plan) -> Table1Interrupted:
        tiers = None
        if self.ideal is not None:
            tiers = ideal_tier_rows(p.tiers, p.soa_rates, self.ideal, p.meths, p.rate_list, p.wire)
        return Table1Interrupted(dict(self.finished), list(p.all_rates), tiers)


@dataclass(frozen=True)
class _Options:
    """:func:`run_table1`'s keyword options, as given."""

    seed: int
    room_poses: int
    transport: Transport
    link: bool
    bench: bool
    bench_seconds: float
    bench_repeats: int
    plots: bool
    command: str | None
    provenance: Mapping[str, Any] | None
    frontier: bool
    frontier_rates: Iterable[int] | None
    frontier_fractions: Sequence[float]
    extrapolate_horizon: float
    correction_time: float
    codecs: tuple[str, ...]


def _measure_or_interrupted(
    p: _Plan, o: _Options, clock: _Clock, progress: Progress | None
) -> tuple[dict[str, Any], _Sweep, dict[str, _Sweep]]:
    """:func:`_measure`; Ctrl-C raises :class:`Table1Interrupted` with what it measured."""
    partial = _Partial()
    try:
        return _measure(p, o, clock, progress, partial)
    except KeyboardInterrupt as exc:
        raise partial.interrupted(p) from exc


def _measure(
    p: _Plan, o: _Options, clock: _Clock, progress: Progress | None, partial: _Partial
) -> tuple[dict[str, Any], _Sweep, dict[str, _Sweep]]:
    """Stages (a)-(d) and the report: ``(report, ideal sweep, link sweeps)``; ``partial``
    follows stage (a) as it goes."""
    f_nets = _frontier_nets(p, o)
    ticks = _Ticks(_total_ticks(p, o.link, f_nets), progress)

    # (a) ideal-network curves
    ideal = _sweep(
        p.trs,
        p.all_rates,
        p.meths,
        _ideal_log,
        ticks.stage("ideal"),
        p.wire,
        keep_samples=o.plots,
        finished=partial.finished,
    )
    partial.ideal = ideal
    clock.lap("ideal_sweep")

    # (b) equal-QoE rates, savings, running time
    tier_rows = _tier_rows(p, o, ideal, progress)
    clock.lap("bench")

    # (c) the same through each tier's link model
    link_part, link_sweeps = link_rows(
        p.trs,
        p.tiers if o.link else [],
        p.soa_rates,
        p.all_rates,
        p.rate_list,
        p.meths,
        p.wire,
        seed=o.seed,
        transport=o.transport,
        stage=ticks.stage,
    )
    clock.lap("link_sweeps")

    # (d) error versus latency: playout delay sweep, hold vs dead reckoning
    frontier_part = None
    if o.frontier:
        frontier_part = _frontier(p, o, f_nets, ticks.stage("error vs latency"))
        clock.lap("frontier")
    per_trace = per_trace_report(
        p.trs, ideal, p.meths, p.all_rates, p.rate_list, p.tiers, p.soa_rates
    )
    curves = _curves_json(ideal.pooled, p.meths)
    codec_part = None
    if "compact" in o.codecs:
        codec_part = _codec_part(p, o, tier_rows, frontier_part)
        clock.lap("codecs")
    config = _config(p, o, clock)
    report = assemble_report(curves, tier_rows, link_part, per_trace, frontier_part, config)
    if codec_part is not None:
        report["codecs"] = jsonable(codec_part)
    return report, ideal, link_sweeps


def _codec_part(
    p: _Plan, o: _Options, tier_rows: Sequence[dict[str, Any]], frontier: dict[str, Any] | None
) -> dict[str, Any]:
    """Bytes/s at equal QoE with each codec (:func:`codec_report`)."""
    velocities = p.wire.velocities if any(v is not None for v in p.wire.velocities) else None
    cache = SizeCache(
        p.trs, None if velocities is None else [v for v in velocities if v is not None],
        o.room_poses,
    )  # fmt: skip
    needs = {m: interp.info(m).needs_velocity for m in p.meths}
    return codec_report(cache, tier_rows, frontier, dict(p.wire.frame_bytes), needs)


def _frontier_nets(p: _Plan, o: _Options) -> list[_Network]:
    """The networks of the error-versus-latency view (none without ``frontier``)."""
    if not o.frontier:
        return []
    return frontier_networks(
        p.tiers,
        p.soa_rates,
        p.rate_list,
        o.frontier_rates,
        link=o.link,
        seed=o.seed,
        transport=o.transport,
    )


def _tier_rows(
    p: _Plan, o: _Options, ideal: _Sweep, progress: Progress | None
) -> list[dict[str, Any]]:
    """Stage (b): the tiers' equal-QoE rows, with the running time unless ``bench`` is off."""
    rows = ideal_tier_rows(p.tiers, p.soa_rates, ideal, p.meths, p.rate_list, p.wire)
    if not o.bench:
        return rows
    return bench_tier_rows(
        rows,
        p.meths,
        p.trs[0],
        room_poses=o.room_poses,
        seconds=o.bench_seconds,
        repeats=o.bench_repeats,
        progress=progress,
    )


def _frontier(
    p: _Plan, o: _Options, f_nets: Sequence[_Network], tick: Callable[[], None]
) -> dict[str, Any]:
    """Stage (d): the report's ``frontier`` key."""
    return frontier_report(
        p.trs,
        f_nets,
        p.meths,
        p.wire,
        p.soa_rates,
        p.rate_list[0],
        fractions=o.frontier_fractions,
        horizon=o.extrapolate_horizon,
        correction_time=o.correction_time,
        tick=tick,
    )


def _config(p: _Plan, o: _Options, clock: _Clock) -> dict[str, Any]:
    """The report's ``config`` key (``elapsed_s`` measured now)."""
    cfg = run_config(
        p.trs,
        p.rate_list,
        p.all_rates,
        p.meths,
        lookahead=p.wire.lookahead,
        wire_bytes_by_method=p.wire.frame_bytes,
        room_poses=o.room_poses,
        snapshot_wire_bytes=p.frame_bytes,
        seed=o.seed,
        transport=o.transport,
        bench={"seconds": o.bench_seconds, "repeats": o.bench_repeats, "render_hz": 90.0},
        command=o.command,
        elapsed=clock.elapsed(),
        timings=clock.timings,
    )
    if o.provenance is not None:
        cfg["provenance"] = dict(o.provenance)
    return cfg


@dataclass(frozen=True)
class _Plan:
    """What a run measures, resolved and checked before any work."""

    trs: list[Trace]
    #: the searched rates (sorted, 1 Hz steps)
    rate_list: list[int]
    #: ``soa`` first, then the other methods asked for
    meths: list[str]
    tiers: list[Tier]
    #: wire bytes of a plain room snapshot
    frame_bytes: int
    #: SoA's rate in each tier
    soa_rates: dict[str, int]
    #: searched rates, the tiers' SoA rates and the paper's rates
    all_rates: list[int]
    wire: _Wire


def _plan(
    traces: Sequence[str | Path | Trace],
    rates: Iterable[int],
    methods: Sequence[str],
    tiers: Mapping[str, Tier] | Sequence[Tier] | str | Path | None,
    room_poses: int,
) -> _Plan:
    """Traces, rates, methods and tiers of a run; ``ValueError`` for bad rates or methods."""
    trs = _as_traces(traces)
    rates_in = list(rates)
    if not rates_in or any(r != int(r) or r <= 0 for r in rates_in):
        raise ValueError(f"rates must be positive integers (1 Hz steps), got {rates_in}")
    rate_list = sorted({int(r) for r in rates_in})
    meths = list(dict.fromkeys(["soa", *methods]))
    unknown = [m for m in meths if m not in interp.names()]
    if unknown:
        raise ValueError(f"unknown interpolator(s) {unknown}; known: {', '.join(interp.names())}")
    tier_list = _resolve_tiers(tiers)
    frame_bytes = wire_bytes(room_poses)
    soa_rates = {t.name: tier_rate(t, frame_bytes) for t in tier_list}
    paper_rates = {p["ga_rate"] for p in PAPER["tiers"] if p["name"] in soa_rates}
    all_rates = sorted(set(rate_list) | set(soa_rates.values()) | paper_rates)
    return _Plan(
        trs=trs,
        rate_list=rate_list,
        meths=meths,
        tiers=tier_list,
        frame_bytes=frame_bytes,
        soa_rates=soa_rates,
        all_rates=all_rates,
        wire=_wire(trs, meths, room_poses),
    )


def _resolve_tiers(tiers: Mapping[str, Tier] | Sequence[Tier] | str | Path | None) -> list[Tier]:
    if tiers is None:
        return list(load_tiers().values())
    if isinstance(tiers, str | Path):
        return list(load_tiers(tiers).values())
    if isinstance(tiers, Mapping):
        return list(tiers.values())
    return list(tiers)


def _total_ticks(p: _Plan, link: bool, f_nets: Sequence[_Network]) -> int:
    """Progress ticks of the run: one per trace and rate of each sweep."""
    n_link = sum(r <= p.soa_rates[t.name] for t in p.tiers for r in p.all_rates) if link else 0
    n_hands = sum(any(device_class(s) == "hands" for s in tr.streams) for tr in p.trs)
    n_frontier = sum(len(r) for _, _, r in f_nets) * n_hands
    return (len(p.all_rates) + n_link) * len(p.trs) + n_frontier


class _Ticks:
    """``progress(stage, done, total)`` after each trace of each sweep, counted over the run."""

    def __init__(self, total: int, progress: Progress | None) -> None:
        self.total = total
        self.done = 0
        self.progress = progress

    def stage(self, name: str) -> Callable[[], None]:
        def tick() -> None:
            self.done += 1
            if self.progress is not None:
                self.progress(name, self.done, self.total)

        return tick


class _Clock:
    """Wall-clock time of each stage (``timings``) since the run started."""

    def __init__(self) -> None:
        self.start = time.perf_counter()
        self.timings: dict[str, float] = {}

    def elapsed(self) -> float:
        return time.perf_counter() - self.start

    def lap(self, name: str) -> None:
        self.timings[name] = self.elapsed() - sum(self.timings.values())


def _write(
    out: Path,
    report: dict[str, Any],
    p: _Plan,
    ideal: _Sweep,
    link_sweeps: Mapping[str, _Sweep],
    plots: bool,
) -> None:
    """``table1.json``, the plots (timed into the report) and ``table1.md`` in ``out``."""
    out.mkdir(parents=True, exist_ok=True)
    write_json(out, report)
    plot_files: list[str] = []
    if plots:
        t_plot = time.perf_counter()
        plot_files = write_plots(out, report, ideal, link_sweeps, p.meths, p.soa_rates)
        if "frontier" in report:
            plot_files.append(frontier_plot(out, report, p.meths, p.soa_rates))
        report["config"]["timings_s"]["plots"] = round(time.perf_counter() - t_plot, 3)
        write_json(out, report)
    write_markdown(out, report, p.trs, plot_files)
