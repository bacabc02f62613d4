"""Table 1's report: the JSON (``table1.json``) and the Markdown (``table1.md``).

Every function takes the report dict (what ``table1.json`` holds) or parts of
it; the live report (``posecast table1 --live``) adds its own section to the
same files, so these stay public.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from posecast.scenarios.network import VELOCITY_BYTES_PER_POSE
from posecast.scenarios.table1.codec_bytes import codec_markdown
from posecast.scenarios.table1.common import (
    PAPER,
    VARIANTS,
    VELOCITY_SOURCE,
    _contiguous,
    describe_rates,
    snapped_range,
)
from posecast.scenarios.table1.smoothness import gain_split_markdown, smoothness_markdown
from posecast.scenarios.traces import CAUSAL_DEGREE, CAUSAL_SAMPLES, Trace

# ---------------------------------------------------------------- JSON


def jsonable(x: Any) -> Any:
    """``x`` as JSON takes it: string keys, lists, floats rounded to 6 decimals (``None`` if
    not finite), numpy integers and booleans as Python ones."""
    if isinstance(x, Mapping):
        return {str(k): jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [jsonable(v) for v in x]
    if isinstance(x, float | np.floating):
        return None if not math.isfinite(float(x)) else round(float(x), 6)
    if isinstance(x, np.integer | np.bool_):
        return x.item()
    return x


def assemble_report(
    curves: Mapping[str, Any],
    tier_rows: Sequence[Mapping[str, Any]],
    link_rows: Sequence[Mapping[str, Any]],
    per_trace: Mapping[str, Any],
    frontier: Mapping[str, Any] | None,
    config: Mapping[str, Any],
) -> dict[str, Any]:
    """The report (what ``table1.json`` holds) from the stages' results, made JSON-able."""
    report: dict[str, Any] = {
        "curves": curves,
        "tiers": tier_rows,
        "paper": PAPER,
        "link": link_rows,
        "per_trace": per_trace,
        **({"frontier": frontier} if frontier is not None else {}),
        "config": config,
    }
    out: dict[str, Any] = jsonable(report)
    return out


def run_config(
    trs: Sequence[Trace],
    rate_list: Sequence[int],
    all_rates: Sequence[int],
    meths: Sequence[str],
    *,
    lookahead: Mapping[str, int],
    wire_bytes_by_method: Mapping[str, int],
    room_poses: int,
    snapshot_wire_bytes: int,
    seed: int,
    transport: str,
    bench: Mapping[str, float],
    command: str | None,
    elapsed: float,
    timings: Mapping[str, float],
) -> dict[str, Any]:
    """The report's ``config`` key: what was run, and how long each stage took."""
    contiguous = _contiguous(rate_list)
    return {
        "traces": [tr.name for tr in trs],
        "rates": list(rate_list),
        "rates_contiguous": contiguous,
        "equal_qoe_search": "the lowest of `rates` meeting the bar"
        + (
            ""
            if contiguous
            else "; with gaps between them the 1 Hz-step rate may lie between listed "
            "rates (`equal_qoe_rate_snapped`: the range it lies in)"
        ),
        "reference_rates": [r for r in all_rates if r not in rate_list],
        "methods": list(meths),
        "headline": "p95 tip error of the hands (mm), tip 0.20 m along -z",
        "keyframes": "latest native sample at each send time t0 + k/rate",
        "ideal_playout": "D = (1 + look-ahead)/rate + 1/native_rate (one interval, plus one "
        "per keyframe of look-ahead the method needs)",
        "lookahead": dict(lookahead),
        "room_poses": room_poses,
        "snapshot_wire_bytes": snapshot_wire_bytes,
        "wire_bytes_by_method": dict(wire_bytes_by_method),
        "velocity_variant": _velocity_variant(),
        "seed": seed,
        "transport": transport,
        "bench": dict(bench),
        "command": command,
        "elapsed_s": elapsed,
        "timings_s": dict(timings),
    }


def _velocity_variant() -> dict[str, Any]:
    return {
        "bytes_per_pose": VELOCITY_BYTES_PER_POSE,
        "encoding": "6 x float16 (linear m/s, angular rad/s, world frame) after each pose",
        "source": f"trace velocities ({VELOCITY_SOURCE}: "
        + (
            f"degree-{CAUSAL_DEGREE} fit over the last {CAUSAL_SAMPLES} native samples"
            if VELOCITY_SOURCE == "causal"
            else "central differences at the native rate"
        )
        + "), rounded to float16",
    }


def write_json(out: Path, report: Mapping[str, Any]) -> None:
    """Write ``out/table1.json``."""
    (out / "table1.json").write_text(json.dumps(report, indent=1) + "\n")


def write_markdown(
    out: Path, report: Mapping[str, Any], trs: Sequence[Trace], plots: Sequence[str]
) -> None:
    """Write ``out/table1.md``."""
    (out / "table1.md").write_text(markdown(report, trs, plots))


# ---------------------------------------------------------------- cells


def fmt(x: Any, digits: int = 1, unit: str = "") -> str:
    """``x`` to ``digits`` decimals with ``unit``; ``null`` for a missing or non-finite value."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "null"
    if isinstance(x, int):
        return f"{x}{unit}"
    return f"{x:.{digits}f}{unit}"


#: Marks an equal-QoE rate snapped up to a listed rate (the 1 Hz-step rate is at
#: most it), and the saving that follows from it (at least that).
SNAPPED_RATE, SNAPPED_SAVING = "≤", "≥"


def eq_cell(rate: int | None, rates: Sequence[int]) -> str:
    """An equal-QoE rate, ``≤20`` when it was snapped up to a listed rate."""
    return ("" if snapped_range(rate, rates) is None else SNAPPED_RATE) + fmt(rate)


def saving_cell(pct: float | None, rate: int | None, rates: Sequence[int], unit: str = " %") -> str:
    """A saving from an equal-QoE rate, ``≥50 %`` when the rate was snapped."""
    mark = "" if pct is None or snapped_range(rate, rates) is None else SNAPPED_SAVING
    return mark + fmt(pct, 0, unit)


def rates_text(cfg: Mapping[str, Any]) -> str:
    """What rates were swept, and what a sparse list means for equal-QoE rates."""
    rates: list[int] = cfg["rates"]
    contiguous = cfg.get("rates_contiguous", _contiguous(rates))
    text = f"Rates {describe_rates(rates)}"
    if not contiguous:
        text += (
            " (listed rates, not a 1 Hz range: equal-QoE rates are the lowest listed rate "
            "meeting the bar; the true rate may lie between listed rates, so a rate snapped "
            f"up to a listed one is marked {SNAPPED_RATE} and its savings {SNAPPED_SAVING})"
        )
    refs = cfg.get("reference_rates") or []
    if refs:
        text += (
            f"; also measured as the tiers' and the paper's reference rates, not searched: "
            f"{describe_rates(refs)}"
        )
    return text


# ---------------------------------------------------------------- markdown


def markdown(report: Mapping[str, Any], trs: Sequence[Trace], plots: Sequence[str]) -> str:
    """``table1.md`` for ``report``, the ``trs`` it was measured on and the ``plots`` written."""
    lines = [
        *intro_markdown(report, trs),
        *paper_table_markdown(report),
        *running_time_markdown(report),
        *link_markdown(report),
        *curves_markdown(report),
        *smoothness_markdown(report),
        *gain_split_markdown(report),
        *codec_markdown(report),
        *by_class_markdown(report),
        *per_trace_markdown(report),
    ]
    if "frontier" in report:
        lines += frontier_markdown(report)
    if plots:
        lines += ["## Plots", ""] + [f"![{p}]({p})" for p in plots] + [""]
    lines += [
        "Paper: " + report["paper"]["source"] + ". Full numbers: `table1.json`.",
        "",
    ]
    return "\n".join(lines)


def intro_markdown(report: Mapping[str, Any], trs: Sequence[Trace]) -> list[str]:
    """Title, command, traces, rates and methods, and the run time."""
    cfg = report["config"]
    meths: list[str] = cfg["methods"]
    lines: list[str] = ["# Table 1: equal-QoE update rates per network tier", ""]
    if cfg.get("command"):
        lines += ["Command:", "", f"    {cfg['command']}", ""]
    if cfg.get("provenance"):
        lines += [
            "Provenance: "
            + "; ".join(f"{k.replace('_', ' ')} `{v}`" for k, v in cfg["provenance"].items())
            + ".",
            "",
        ]
    total_s = sum(tr.duration for tr in trs)
    lines += [
        f"Traces ({len(trs)}, {total_s:.0f} s in all): "
        + ", ".join(f"`{tr.name}` ({tr.duration:.0f} s, {tr.native_rate:.0f} Hz)" for tr in trs)
        + ".",
        "",
        rates_text(cfg)
        + "; methods "
        + ", ".join(f"`{m}`" for m in meths)
        + f". Headline: {cfg['headline']}. Keyframes: {cfg['keyframes']}. "
        f"Ideal network playout: {cfg['ideal_playout']}. Wire size of a snapshot: "
        f"{cfg['snapshot_wire_bytes']} B ({cfg['room_poses']} poses, a 16-user room). "
        f"Run time {cfg['elapsed_s']:.0f} s ("
        + ", ".join(f"{k.replace('_', ' ')} {v:.0f} s" for k, v in cfg["timings_s"].items())
        + ").",
        "",
    ]
    return lines


def paper_table_markdown(report: Mapping[str, Any]) -> list[str]:
    """The equal-QoE rates and savings beside the paper's, per tier and method."""
    cfg = report["config"]
    meths: list[str] = cfg["methods"]
    others = [m for m in meths if m != "soa"]
    rates: list[int] = cfg["rates"]
    lines = [
        "## Measured beside the paper (ideal network)",
        "",
        "Equal-QoE rate: the lowest rate swept whose headline is no worse than SoA's at the "
        "tier rate; `null` = no rate swept reaches SoA's quality"
        + (
            ""
            if cfg.get("rates_contiguous", _contiguous(rates))
            else f" ({SNAPPED_RATE}: snapped up to a listed rate; the true rate lies between "
            "the listed rate below and it, and the saving is at least the one shown)"
        )
        + ". Running time: receiver "
        "CPU time (decode + interpolate the same number of 90 Hz frames), method at its "
        "equal-QoE rate vs SoA at the tier rate; last column: the method at the paper's rate "
        "for it (granting the paper's equal-QoE rate) vs SoA at the tier rate. Bandwidth "
        "saving in updates/s (the paper's measure) and in bytes/s (velocity methods send "
        f"{cfg['velocity_variant']['bytes_per_pose']} B more per pose: "
        f"{cfg['velocity_variant']['encoding']}). Latency: the method's playout delay at its "
        "equal-QoE rate, one interval plus its look-ahead (SoA's at the tier rate in brackets).",
        "",
        "| tier | SoA rate | SoA p95 tip (mm) | method | rate paper "
        "| p95 tip at the paper's rate (mm) | rate measured "
        "| p95 tip at it (mm) | bandwidth saving paper | measured (updates) | (bytes) "
        "| latency (ms) | running-time saving paper | measured | at the paper's rate |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    paper_rt = report["paper"]["running_time_saving_pct"]
    for row in report["tiers"]:
        paper = row.get("paper", {})
        for m in others:
            eq = row["equal_qoe_rate"][m]
            lines.append(
                f"| {row['name']} | {row['soa_rate']} | {fmt(row['reference_headline_mm'])} "
                f"| `{m}` | {paper.get('ga_rate', '-')} "
                f"| {fmt(row.get('headline_at_paper_rate_mm', {}).get(m))} "
                f"| {eq_cell(eq, rates)} "
                f"| {fmt(row['headline_at_equal_rate_mm'][m])} "
                f"| {paper.get('bandwidth_saving_pct', '-')} % "
                f"| {saving_cell(row['bandwidth_saving_pct'][m], eq, rates)} "
                f"| {saving_cell(row.get('bytes_saving_pct', {}).get(m), eq, rates)} "
                f"| {fmt(row.get('latency_at_equal_rate_ms', {}).get(m), 0)} "
                f"({fmt(row.get('latency_at_soa_rate_ms'), 0)}) "
                f"| {paper_rt if paper else '-'} % "
                f"| {fmt(row['running_time_saving_pct'][m], 1, ' %')} "
                f"| {fmt(row.get('running_time_saving_at_paper_rate_pct', {}).get(m), 1, ' %')} |"
            )
    lines += [""]
    return lines


def running_time_markdown(report: Mapping[str, Any]) -> list[str]:
    """The receiver's CPU time per tier, method and rate (if benchmarked)."""
    cfg = report["config"]
    lines: list[str] = []
    if report["tiers"] and "running_time_s" in report["tiers"][0]:
        b = cfg["bench"]
        lines += [
            f"Receiver CPU time (ms; median of {b['repeats']} round-robin runs "
            f"of {b['seconds']:g} s of session: {cfg['room_poses']} streams, "
            f"{b['render_hz']:.0f} Hz render): decode / render / total, every method at the "
            "tier's SoA rate, at its equal-QoE rate and at the paper's rate.",
            "",
            "| tier | method | rate | decode | render | total |",
            "|---|---|---|---|---|---|",
        ]
        seen: set[tuple[str, str, int]] = set()
        for row in report["tiers"]:
            for m, both in row["running_time_s"].items():
                for c in (both["at_soa_rate"], both["at_equal_rate"], both.get("at_paper_rate")):
                    if c is None or (row["name"], m, c["rate"]) in seen:
                        continue
                    seen.add((row["name"], m, c["rate"]))
                    lines.append(
                        f"| {row['name']} | `{m}` | {c['rate']} | {1000 * c['decode_s']:.1f} "
                        f"| {1000 * c['render_s']:.1f} | {1000 * c['total_s']:.1f} |"
                    )
        lines += [""]
    return lines


def link_markdown(report: Mapping[str, Any]) -> list[str]:
    """The rows through each tier's link model (if swept)."""
    cfg = report["config"]
    meths: list[str] = cfg["methods"]
    rates: list[int] = cfg["rates"]
    lines: list[str] = []
    if report["link"]:
        lines += [
            "## Through each tier's link model",
            "",
            f"Transport `{cfg['transport']}`; playout delay fixed per run: D = (1 + look-ahead)"
            "/rate + p95 of the keyframe age (arrival - capture); velocity methods send the "
            "bigger velocity frames through the same link (same seed). "
            "Latency = D + mean network delay (DESIGN.md); "
            "D alone is already the capture-to-display delay, since ages count from capture. "
            "Stall: share of hand samples with no bracketing keyframe by their deadline. "
            "Here the equal-QoE rate is searched only up to the tier's rate (the tier allows no "
            "more); `null`: no rate the tier allows reaches SoA's quality through the link. "
            "Rows show SoA at the tier rate and each method at its equal-QoE rate.",
            "",
            "| tier | method | rate | p95 tip (mm) | stall | D (ms) | net delay (ms) "
            "| latency (ms) | lost | equal-QoE rate | bandwidth saving (updates) | (bytes) |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for row in report["link"]:
            for m in meths:
                a = row["at_soa_rate"][m] if m == "soa" else row["at_equal_rate"][m]
                eq = row["equal_qoe_rate"][m]
                if a is None:
                    lines.append(
                        f"| {row['name']} | `{m}` | null | | | | | | | null | null | null |"
                    )
                    continue
                lines.append(
                    f"| {row['name']} | `{m}` | {a['rate']} | {fmt(a['headline_mm'])} "
                    f"| {fmt(100 * a['stall_fraction'] if a['stall_fraction'] is not None else None, 2, ' %')} "  # noqa: E501
                    f"| {fmt(a['playout_delay_ms'])} | {fmt(a['network_delay_ms'])} "
                    f"| {fmt(a['latency_ms'])} "
                    f"| {fmt(100 * a['loss_fraction'] if a['loss_fraction'] is not None else None, 2, ' %')} "  # noqa: E501
                    f"| {eq_cell(eq, rates)} "
                    f"| {saving_cell(row['bandwidth_saving_pct'][m], eq, rates)} "
                    f"| {saving_cell(row.get('bytes_saving_pct', {}).get(m), eq, rates)} |"
                )
        lines += [""]
    return lines


def curves_markdown(report: Mapping[str, Any]) -> list[str]:
    """The headline against rate, every method (ideal network)."""
    cfg = report["config"]
    meths: list[str] = cfg["methods"]
    lines: list[str] = []
    lines += [
        "## Headline QoE vs rate (ideal network)",
        "",
        "p95 tip error of the hands (mm); the head's in brackets.",
        "",
        "| rate | " + " | ".join(f"`{m}`" for m in meths) + " |",
        "|---|" + "---|" * len(meths),
    ]
    refs = set(cfg.get("reference_rates") or [])
    for r in sorted(int(r) for r in report["curves"][meths[0]]):
        cells = []
        for m in meths:
            c = report["curves"][m][str(r)]
            cells.append(
                f"{fmt(c.get('hands', {}).get('tip_p95_mm'))} "
                f"({fmt(c.get('head', {}).get('tip_p95_mm'))})"
            )
        label = f"{r} (ref.)" if r in refs else str(r)
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines += [""]
    if refs:
        lines += ["(ref.): a tier's or the paper's rate, measured but not searched.", ""]
    return lines


def by_class_markdown(report: Mapping[str, Any]) -> list[str]:
    """Equal-QoE rates judged on each device class (ideal network)."""
    cfg = report["config"]
    meths: list[str] = cfg["methods"]
    others = [m for m in meths if m != "soa"]
    rates: list[int] = cfg["rates"]
    lines: list[str] = []
    tier_names = [row["name"] for row in report["tiers"]]
    by_class = [row.get("equal_qoe_rate_by_class", {}) for row in report["tiers"]]
    classes = [c for c in ("hands", "head", "objects") if any(c in b for b in by_class)]
    if classes:
        lines += [
            "## Equal-QoE rate judged on each device class (ideal network)",
            "",
            "As above, but with each class's own p95 tip error in place of the hands'; cells "
            "are " + " / ".join(f"`{m}`" for m in others) + " (SoA at the tier rate).",
            "",
            "| class | "
            + " | ".join(
                f"{t} ({row['soa_rate']} Hz)"
                for t, row in zip(tier_names, report["tiers"], strict=True)
            )
            + " |",
            "|---|" + "---|" * len(tier_names),
        ]
        for cls in classes:
            cells = [
                " / ".join(eq_cell(b.get(cls, {}).get(m), rates) for m in others) for b in by_class
            ]
            lines.append(f"| {cls} | " + " | ".join(cells) + " |")
        lines += [""]
    return lines


def per_trace_markdown(report: Mapping[str, Any]) -> list[str]:
    """Equal-QoE rates per trace and device class (ideal network)."""
    cfg = report["config"]
    meths: list[str] = cfg["methods"]
    others = [m for m in meths if m != "soa"]
    rates: list[int] = cfg["rates"]
    lines: list[str] = []
    tier_names = [row["name"] for row in report["tiers"]]
    if len(report["per_trace"]) > 1:
        lines += [
            "## Equal-QoE rate per trace and device class (ideal network)",
            "",
            "Each trace on its own, against SoA on the same trace, judged on the class's p95 "
            "tip error; cells are "
            + " / ".join(f"`{m}`" for m in others)
            + ". Last column: p95 tip error (mm) at 15 Hz, "
            + " / ".join(f"`{m}`" for m in meths)
            + ".",
            "",
            "| trace | class | " + " | ".join(tier_names) + " | p95 tip @15 Hz |",
            "|---|---|" + "---|" * (len(tier_names) + 1),
        ]
        for name, pt in report["per_trace"].items():
            for cls, curves in pt["tip_p95_mm_by_class"].items():
                cells = [
                    " / ".join(
                        eq_cell(pt["equal_qoe_rate_by_class"][t].get(cls, {}).get(m), rates)
                        for m in others
                    )
                    for t in tier_names
                ]
                at15 = " / ".join(fmt(curves[m].get("15")) for m in meths)
                lines.append(f"| `{name}` | {cls} | " + " | ".join(cells) + f" | {at15} |")
        lines += [""]
    return lines


# ---------------------------------------------------------------- error vs latency


def frontier_markdown(report: Mapping[str, Any]) -> list[str]:
    """The "Error versus latency" section for the report's ``frontier`` key."""
    fr = report["frontier"]
    ver = fr["verdicts"]
    lines = frontier_intro_markdown(fr["config"])
    ht = ver.get("headline_target")
    if ht is not None and ht["reference"] is not None:
        lines += headline_target_markdown(ht)
    if ver["tiers"]:
        lines += frontier_tiers_markdown(ver["tiers"])
    lines += frontier_table_markdown(fr["frontiers"])
    lines += frontier_ideal_markdown(fr)
    return lines


def frontier_intro_markdown(cfg: Mapping[str, Any]) -> list[str]:
    """What the view measured: playout delays, latency, variants, bandwidth."""
    lines = [
        "## Error versus latency",
        "",
        "Hands only. Playout delay "
        + cfg["playout"]
        + "; f in "
        + ", ".join(f"{f:g}" for f in cfg["fractions"])
        + ". Latency = "
        + cfg["latency"]
        + " (DESIGN.md's 'D plus the mean network "
        "delay' would count the network twice here). Variants: "
        + "; ".join(f"`{k}`: {v}" for k, v in cfg["variants"].items())
        + f". Horizon {1000 * cfg['extrapolate_horizon_s']:.0f} ms, correction time "
        f"{1000 * cfg['correction_time_s']:.0f} ms. Dead reckoning: "
        + "; ".join(f"`{m}` {v.split(' (')[0]}" for m, v in cfg["extrapolation"].items())
        + ". Bandwidth: "
        + cfg["bytes_per_s"]
        + ". Corrections: p95 of the tip jump (mm) "
        "between the stalled pose continued and the new pose at the first frame after a "
        "keyframe arrives (for `smooth` this is the size of the correction it blends in).",
        "",
    ]
    return lines


def headline_target_markdown(ht: Mapping[str, Any]) -> list[str]:
    """Question (1): a posecast method at <= 10 Hz as good as SoA at 30 Hz."""
    ref = ht["reference"]
    lines: list[str] = [
        "### Headline target: a posecast method at <= 10 Hz as good as SoA at 30 Hz",
        "",
        f"Reference: SoA at 30 Hz, one-interval playout: {fmt(ref['headline_mm'])} mm at "
        f"{fmt(ref['latency_ms'])} ms, {fmt(ref['bytes_per_s'], 0)} B/s.",
        "",
    ]
    if ht["met"]:
        b = ht["best"]
        lines += [
            f"**Met**: `{b['method']}` at {b['rate']} Hz, f = {b['fraction']:g}, "
            f"`{b['variant']}`: {fmt(b['headline_mm'])} mm at {fmt(b['latency_ms'])} ms "
            f"(+{fmt(ht['added_latency_ms'])} ms), {fmt(b['bytes_per_s'], 0)} B/s "
            f"({fmt(ht['bytes_saving_pct'], 0, ' %')} fewer bytes, "
            f"{fmt(ht['updates_saving_pct'], 0, ' %')} fewer updates).",
            "",
        ]
    else:
        lines += [
            "**Not met** on these traces. Closest at <= 10 Hz, and the lowest rate "
            "that matches at any playout delay:",
            "",
        ]
    lines += [
        "| method | best at <= 10 Hz (mm) | at (Hz, f, variant, latency) "
        "| lowest matching rate | its latency (ms) | its bytes/s |",
        "|---|---|---|---|---|---|",
    ]
    for m, c in ht["closest_at_10hz_or_less"].items():
        lo = ht["lowest_matching_rate"].get(m)
        cell = (
            "-"
            if c is None
            else f"{c['rate']} Hz, f {c['fraction']:g}, {c['variant']}, {fmt(c['latency_ms'])} ms"
        )
        lines.append(
            f"| `{m}` | {fmt(None if c is None else c['headline_mm'])} | {cell} "
            f"| {'none' if lo is None else str(lo['rate']) + ' Hz'} "
            f"| {fmt(None if lo is None else lo['latency_ms'])} "
            f"| {fmt(None if lo is None else lo['bytes_per_s'], 0)} |"
        )
    lines += [""]
    return lines


def frontier_tiers_markdown(tiers: Sequence[Mapping[str, Any]]) -> list[str]:
    """Question (2): bandwidth at equal QoE and equal latency, per tier."""
    meths = list(tiers[0]["cheapest"])
    lines: list[str] = [
        "### Bandwidth at equal QoE and equal latency, per tier",
        "",
        "Reference: SoA at the tier's rate with one-interval playout (hold), on the "
        "tier's link and on the ideal network. Each cell: the fewest bytes/s of the "
        "method at no more latency and no more headline error than the reference "
        "(rate, f, variant; saving vs the reference in bytes/s).",
        "",
        "| tier | network | SoA ref (mm @ ms, B/s) | "
        + " | ".join(f"`{m}`" for m in meths)
        + " | posecast beats both paper methods | ... and SoA |",
        "|---|---|---|" + "---|" * len(meths) + "---|---|",
    ]
    for row in tiers:
        ref = row["reference"]
        cells = []
        for m in meths:
            c = row["cheapest"][m]
            cells.append(
                "none"
                if c is None
                else f"{fmt(c['bytes_per_s'], 0)} ({c['rate']} Hz, f {c['fraction']:g}, "
                f"{c['variant']}; {fmt(row['bytes_saving_pct'][m], 0, ' %')})"
            )
        lines.append(
            f"| {row['tier']} | {row['network']} | {fmt(ref['headline_mm'])} @ "
            f"{fmt(ref['latency_ms'])}, {fmt(ref['bytes_per_s'], 0)} | "
            + " | ".join(cells)
            + f" | {'yes' if row['posecast_beats_both_paper_methods'] else 'no'}"
            + ("" if row["paper_methods_reach_reference"] else " (paper methods: none)")
            + f" | {'yes' if row['posecast_beats_soa'] else 'no'} |"
        )
    lines += [""]
    return lines


def frontier_table_markdown(frontiers: Mapping[str, Sequence[Mapping[str, Any]]]) -> list[str]:
    """The frontier of every network: the best headline within each latency budget."""
    lines: list[str] = [
        "### Frontier: the best headline within each latency budget",
        "",
        "| network | latency (ms) | p95 tip, hands (mm) | method | rate | f | variant "
        "| stall | corr. p95 (mm) | B/s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for net, front in frontiers.items():
        for p in front:
            lines.append(
                f"| {net} | {fmt(p['latency_ms'])} | {fmt(p['headline_mm'])} | `{p['method']}` "
                f"| {p['rate']} | {p['fraction']:g} | {p['variant']} "
                f"| {fmt(100 * p['stall_fraction'], 1, ' %')} "
                f"| {fmt(p['correction_tip_p95_mm'])} | {fmt(p['bytes_per_s'], 0)} |"
            )
    lines += [""]
    return lines


def frontier_ideal_markdown(fr: Mapping[str, Any]) -> list[str]:
    """The ideal network's headline per rate and playout delay, every variant."""
    cfg = fr["config"]
    lines: list[str] = []
    ideal = [p for p in fr["points"] if p["network"] == "ideal"]
    if ideal:
        fracs = list(cfg["fractions"])
        lines += [
            "### Ideal network: headline (mm) per playout delay",
            "",
            "Cells: hold / extrapolate / smooth p95 tip error of the hands (mm) @ latency (ms).",
            "",
            "| method | rate | " + " | ".join(f"f = {f:g}" for f in fracs) + " |",
            "|---|---|" + "---|" * len(fracs),
        ]
        index = {(p["method"], p["rate"], p["fraction"], p["variant"]): p for p in ideal}
        for m in dict.fromkeys(p["method"] for p in ideal):
            for r in sorted({p["rate"] for p in ideal if p["method"] == m}):
                cells = []
                for f in fracs:
                    trio = [index.get((m, r, f, v)) for v in VARIANTS]
                    if trio[0] is None:
                        cells.append("")
                        continue
                    cells.append(
                        " / ".join(fmt(None if t is None else t["headline_mm"], 0) for t in trio)
                        + f" @ {fmt(trio[0]['latency_ms'], 0)}"
                    )
                lines.append(f"| `{m}` | {r} | " + " | ".join(cells) + " |")
        lines += [""]
    return lines
