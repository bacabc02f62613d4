"""Smoothness beside accuracy, and where each method's gain comes from.

Two views on the Table 1 report (the ``tiers`` rows of
:func:`scenarios.table1.sweep.ideal_tier_rows` and the frontier's verdicts):

- **Equal accuracy and equal smoothness**: each method's lowest rate whose
  hands' p95 tip error (accuracy, the headline) or p95 tip velocity error
  (smoothness, what the paper judged by eye) is no worse than SoA's at the
  tier rate, beside the paper's rate for its methods.
- **Velocities or algebra** (:func:`gain_split`): a velocity method's saving
  over SoA splits into what the keyframe velocities buy with the same plain
  algebra (``soa`` -> ``soa-hermite``: position Hermite + quaternion Hermite)
  and what the motor algebra adds on top of the same velocities
  (``soa-hermite`` -> ``motor-hermite``); the paper's methods differ from SoA
  in algebra only (``soa`` -> ``dq-slerp`` / ``motor-lerp``). Each step is the
  difference of the two methods' savings against SoA, in percentage points.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

__all__ = [
    "GAIN_STEPS",
    "MEASURES",
    "gain_split",
    "gain_split_markdown",
    "smoothness_markdown",
]

#: ``(from, to, what the step changes)``: the steps a gain is split into.
GAIN_STEPS = (
    ("soa", "soa-hermite", "velocities"),
    ("soa-hermite", "motor-hermite", "algebra"),
    ("soa", "dq-slerp", "algebra"),
    ("soa", "motor-lerp", "algebra"),
)
#: ``measure: (rate key, updates saving key, bytes saving key)`` of a tier row.
MEASURES = {
    "accuracy": ("equal_qoe_rate", "bandwidth_saving_pct", "bytes_saving_pct"),
    "smoothness": (
        "equal_smoothness_rate",
        "smoothness_bandwidth_saving_pct",
        "smoothness_bytes_saving_pct",
    ),
}


def _step(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else b - a


def gain_split(row: Mapping[str, Any], methods: Sequence[str]) -> list[dict[str, Any]]:
    """Each :data:`GAIN_STEPS` step of one tier row whose two methods ran, per measure.

    SoA's own saving is 0 by definition. A step is ``None`` where either method
    never reaches the reference.
    """
    out: list[dict[str, Any]] = []
    for a, b, what in GAIN_STEPS:
        if a not in methods or b not in methods:
            continue
        entry: dict[str, Any] = {"from": a, "to": b, "what": what}
        for measure, (rate_key, upd_key, byte_key) in MEASURES.items():
            if rate_key not in row:
                continue
            upd = {m: 0.0 if m == "soa" else row[upd_key][m] for m in (a, b)}
            byt = {m: 0.0 if m == "soa" else row[byte_key][m] for m in (a, b)}
            entry[measure] = {
                "rates": [row[rate_key][a], row[rate_key][b]],
                "updates_pp": _step(upd[a], upd[b]),
                "bytes_pp": _step(byt[a], byt[b]),
            }
        out.append(entry)
    return out


def _verdict_split(
    tier: Mapping[str, Any], methods: Sequence[str]
) -> list[tuple[str, str, str, float | None]]:
    """Steps of one frontier verdict: bytes saving at equal QoE and equal latency."""
    sav = dict(tier.get("bytes_saving_pct", {}))
    sav["soa"] = 0.0 if tier.get("cheapest", {}).get("soa") is not None else None
    return [
        (a, b, what, _step(sav.get(a), sav.get(b)))
        for a, b, what in GAIN_STEPS
        if a in methods and b in methods
    ]


def _pp(x: float | None) -> str:
    return "n/a" if x is None else f"{x:+.0f} pp"


def _rate(r: int | None) -> str:
    return "null" if r is None else f"{r}"


def smoothness_markdown(report: Mapping[str, Any]) -> list[str]:
    """Velocity error against rate, and equal-accuracy beside equal-smoothness rates."""
    cfg = report["config"]
    meths: list[str] = cfg["methods"]
    first = report["curves"][meths[0]]
    if not any("vel_p95_mps" in c.get("hands", {}) for c in first.values()):
        return []
    lines = [
        "## Smoothness: velocity error vs rate (ideal network)",
        "",
        "p95 velocity error of the hands' tip (m/s): the tip's velocity from differences "
        "over consecutive source samples, rendered against true (DESIGN.md); p50 in brackets.",
        "",
        "| rate | " + " | ".join(f"`{m}`" for m in meths) + " |",
        "|---|" + "---|" * len(meths),
    ]
    for r in sorted(int(r) for r in first):
        cells = []
        for m in meths:
            h = report["curves"][m][str(r)].get("hands", {})
            cells.append(f"{_num(h.get('vel_p95_mps'), 2)} ({_num(h.get('vel_p50_mps'), 2)})")
        lines.append(f"| {r} | " + " | ".join(cells) + " |")
    lines += ["", *_equal_rates_markdown(report, meths)]
    return lines


def _num(x: Any, digits: int) -> str:
    return "n/a" if x is None else f"{float(x):.{digits}f}"


def _equal_rates_markdown(report: Mapping[str, Any], meths: Sequence[str]) -> list[str]:
    rows = [r for r in report["tiers"] if "equal_smoothness_rate" in r]
    if not rows:
        return []
    others = [m for m in meths if m != "soa"]
    lines = [
        "## Equal accuracy and equal smoothness per tier (ideal network)",
        "",
        "Cell: equal-accuracy rate (hands p95 tip error) / equal-smoothness rate (hands p95 "
        "velocity error), each the lowest rate no worse than SoA at the tier rate; `null` = "
        "none swept. Bytes/s savings against SoA at the tier rate in brackets (velocity "
        "methods pay their bigger frames). Paper: its rate for `dq-slerp` and `motor-lerp`, "
        "judged by eye.",
        "",
        "| tier | SoA: rate, p95 tip, p95 velocity error | "
        + " | ".join(f"`{m}`" for m in others)
        + " | paper |",
        "|---|---|" + "---|" * len(others) + "---|",
    ]
    for row in rows:
        cells = []
        for m in others:
            a, s = row["equal_qoe_rate"][m], row["equal_smoothness_rate"][m]
            ba, bs = row["bytes_saving_pct"][m], row["smoothness_bytes_saving_pct"][m]
            cells.append(f"{_rate(a)} / {_rate(s)} ({_pct(ba)} / {_pct(bs)})")
        paper = row.get("paper", {}).get("ga_rate", "-")
        lines.append(
            f"| {row['name']} | {row['soa_rate']} Hz, {_num(row['reference_headline_mm'], 1)} mm, "
            f"{_num(row['smoothness_reference_mps'], 2)} m/s | "
            + " | ".join(cells)
            + f" | {paper} |"
        )
    lines += ["", *_paper_verdict_markdown(rows)]
    return lines


def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.0f} %"


def _paper_verdict_markdown(rows: Sequence[Mapping[str, Any]]) -> list[str]:
    """Does the paper's claim hold in its own terms (smoothness) and in ours (accuracy)?"""
    rows = [r for r in rows if "reproduced_smoothness" in r]
    if not rows:
        return []
    lines = [
        "The paper's claim per tier: its rate for the GA methods against the measured "
        "equal-accuracy / equal-smoothness rates ('yes' where the measured rate is no higher).",
        "",
        "| tier | paper | " + " | ".join(f"`{m}`" for m in rows[0]["reproduced"]) + " |",
        "|---|---|" + "---|" * len(rows[0]["reproduced"]),
    ]
    for row in rows:
        cells = []
        for m in row["reproduced"]:
            acc = "yes" if row["reproduced"][m] else "no"
            smo = "yes" if row["reproduced_smoothness"][m] else "no"
            cells.append(
                f"accuracy {acc} ({_rate(row['equal_qoe_rate'][m])} Hz), smoothness {smo} "
                f"({_rate(row['equal_smoothness_rate'][m])} Hz)"
            )
        lines.append(
            f"| {row['name']} | {row['paper']['ga_rate']} Hz | " + " | ".join(cells) + " |"
        )
    return [*lines, ""]


def gain_split_markdown(report: Mapping[str, Any]) -> list[str]:
    """Which part of each gain is the velocities, which the algebra (ideal, and verdicts)."""
    meths: list[str] = report["config"]["methods"]
    rows = [(r["name"], gain_split(r, meths)) for r in report["tiers"]]
    if not any(steps for _, steps in rows):
        return []
    lines = [
        "## Which part of each gain is the velocities, which the algebra",
        "",
        "Each step: the second method's saving against SoA at the tier rate minus the "
        "first's, in percentage points of SoA's updates/s and bytes/s (ideal network, "
        "one-interval playout); rates in brackets.",
        "",
        "| tier | step | what changes | accuracy: updates / bytes | smoothness: updates / bytes |",
        "|---|---|---|---|---|",
    ]
    for name, steps in rows:
        for st in steps:
            cells = []
            for measure in MEASURES:
                e = st.get(measure)
                if e is None:
                    cells.append("-")
                    continue
                ra, rb = e["rates"]
                cells.append(
                    f"{_pp(e['updates_pp'])} / {_pp(e['bytes_pp'])} ({_rate(ra)} -> {_rate(rb)} Hz)"
                )
            lines.append(
                f"| {name} | `{st['from']}` -> `{st['to']}` | {st['what']} | "
                + " | ".join(cells)
                + " |"
            )
    lines += ["", *_verdict_split_markdown(report, meths)]
    return lines


def _verdict_split_markdown(report: Mapping[str, Any], meths: Sequence[str]) -> list[str]:
    tiers = report.get("frontier", {}).get("verdicts", {}).get("tiers", [])
    if not tiers:
        return []
    lines = [
        "The same split of the verdicts (fewest bytes/s at equal headline and no more "
        "latency than SoA at the tier rate, over rates, playout delays and stall policies):",
        "",
        "| tier (network) | "
        + " | ".join(f"`{a}` -> `{b}` ({w})" for a, b, w, _ in _verdict_split(tiers[0], meths))
        + " |",
        "|---|" + "---|" * len(_verdict_split(tiers[0], meths)),
    ]
    for t in tiers:
        steps = _verdict_split(t, meths)
        lines.append(
            f"| {t['tier']} ({t['network']}) | " + " | ".join(_pp(x) for *_, x in steps) + " |"
        )
    return [*lines, ""]
