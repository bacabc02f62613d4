"""The generated blocks of the results pages, rewritten from ``docs/results/`` outputs.

A page marks a block ``<!-- results:NAME -->`` ... ``<!-- /results:NAME -->``;
:data:`BLOCKS` maps each NAME to the function that writes its Markdown from
the outputs of :mod:`posecast.results`. Every block ends with a line naming
the command, the git revision and the traces split it came from.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

__all__ = ["BLOCKS", "rewrite_page", "rewrite_pages"]

_BLOCK = re.compile(r"(<!-- results:([a-z0-9-]+) -->\n)(.*?)(<!-- /results:\2 -->)", re.S)

#: ``name: (results folder) -> markdown``.
BLOCKS: dict[str, Callable[[Path], str]] = {}


def rewrite_page(text: str, results: Path) -> str:
    """``text`` with every generated block rewritten; ``ValueError`` for an unknown block."""

    def sub(m: re.Match[str]) -> str:
        name = m.group(2)
        if name not in BLOCKS:
            raise ValueError(f"unknown results block {name!r}; known: {', '.join(BLOCKS)}")
        return m.group(1) + BLOCKS[name](results).rstrip("\n") + "\n" + m.group(4)

    return _BLOCK.sub(sub, text)


def rewrite_pages(pages: Sequence[Path], results: Path) -> None:
    """Rewrite the generated blocks of each page in place."""
    for page in pages:
        old = page.read_text()
        new = rewrite_page(old, results)
        if new != old:
            page.write_text(new)


def _load(results: Path, name: str, file: str = "table1.json") -> dict[str, Any]:
    data: dict[str, Any] = json.loads((results / name / file).read_text())
    return data


def _source(prov: Mapping[str, Any] | None, where: str) -> str:
    p = prov or {}
    return (
        f"*Source: `{p.get('command', '?')}` (via `make results`), revision "
        f"`{p.get('revision', '?')}`, traces `{p.get('traces', '?')}`; data `{where}`.*"
    )


# ---------------------------------------------------------------- helpers

#: The methods of the closing tables, in the issue's order (those present are shown).
KEY_METHODS = (
    "soa",
    "dq-slerp",
    "motor-lerp",
    "motor-cubic",
    "motor-quintic",
    "soa-hermite",
    "motor-hermite",
)


def _f(x: Any, digits: int = 1, unit: str = "") -> str:
    if x is None:
        return "n/a"
    return f"{float(x):.{digits}f}{unit}"


def _r(rate: Any) -> str:
    return "null" if rate is None else str(rate)


def _pct(x: Any) -> str:
    return "n/a" if x is None else f"{float(x):.0f} %"


def _bytes(x: Any) -> str:
    return "none" if x is None else f"{float(x):,.0f}".replace(",", " ")


def _body(lines: Sequence[str]) -> list[str]:
    """A report section's lines without its ``## `` header and leading blank lines."""
    out = [ln for ln in lines if not ln.startswith("## ")]
    while out and not out[0]:
        out.pop(0)
    return out


def _methods(report: Mapping[str, Any]) -> list[str]:
    present = report["config"]["methods"]
    return [m for m in KEY_METHODS if m in present] + [m for m in present if m not in KEY_METHODS]


def _tail(report: Mapping[str, Any], name: str) -> list[str]:
    return ["", _source(report["config"].get("provenance"), f"docs/results/{name}/table1.json")]


# ---------------------------------------------------------------- Table 1 blocks


def _paper_table1(results: Path) -> str:
    """The paper's Table 1 beside the GA methods' measured rates (dev and eval)."""
    ev, dv = _load(results, "table1-eval"), _load(results, "table1-dev")
    lines = [
        "| tier | SoA rate | paper: GA rate (saving) | `dev`: GA rate, accuracy / smoothness "
        "| `eval`: GA rate, accuracy / smoothness | `eval` at the paper's rate vs SoA at the "
        "tier rate: p95 tip error | p95 velocity error |",
        "|---|---|---|---|---|---|---|",
    ]
    ga = ("dq-slerp", "motor-lerp")
    for re_, rd in zip(ev["tiers"], dv["tiers"], strict=True):
        p = re_["paper"]

        def rates(row: Mapping[str, Any]) -> str:
            cells = []
            for key in ("equal_qoe_rate", "equal_smoothness_rate"):
                rs = sorted({_r(row[key][m]) for m in ga})
                cells.append("-".join(rs))
            return " / ".join(cells)

        tip = " / ".join(_f(re_["headline_at_paper_rate_mm"][m], 0) for m in ga)
        vel = " / ".join(_f(re_["smoothness_at_paper_rate_mps"][m], 2) for m in ga)
        lines.append(
            f"| {re_['name']} | {re_['soa_rate']} | {p['ga_rate']} ({p['bandwidth_saving_pct']} %) "
            f"| {rates(rd)} | {rates(re_)} | {tip} vs {_f(re_['reference_headline_mm'], 0)} mm "
            f"| {vel} vs {_f(re_['smoothness_reference_mps'], 2)} m/s |"
        )
    lines += [
        "",
        "Cells with two GA methods show `dq-slerp / motor-lerp` (one figure when they agree).",
        *_tail(ev, "table1-eval"),
        _source(dv["config"].get("provenance"), "docs/results/table1-dev/table1.json"),
    ]
    return "\n".join(lines)


def _closing(name: str) -> Callable[[Path], str]:
    """Equal-accuracy and equal-smoothness rate per tier and method (hands), with bytes."""

    def block(results: Path) -> str:
        rep = _load(results, name)
        meths = _methods(rep)
        tiers = rep["tiers"]
        lines = [
            "| method | "
            + " | ".join(f"{t['name']} (SoA {t['soa_rate']} Hz)" for t in tiers)
            + " |",
            "|---|" + "---|" * len(tiers),
        ]
        for m in meths:
            cells = [
                f"{_r(t['equal_qoe_rate'][m])} / {_r(t['equal_smoothness_rate'][m])} Hz "
                f"({_pct(t['bytes_saving_pct'][m])} / {_pct(t['smoothness_bytes_saving_pct'][m])})"
                for t in tiers
            ]
            lines.append(f"| `{m}` | " + " | ".join(cells) + " |")
        refs = "; ".join(
            f"{t['name']}: {_f(t['reference_headline_mm'])} mm, "
            f"{_f(t['smoothness_reference_mps'], 2)} m/s"
            for t in tiers
        )
        lines += [
            "",
            "Cell: equal-accuracy / equal-smoothness rate (bytes/s saved against SoA at the "
            "tier rate, velocity methods' bigger frames counted). SoA's p95 tip error and "
            f"p95 velocity error of the hands at the tier rates: {refs}.",
            *_tail(rep, name),
        ]
        return "\n".join(lines)

    return block


def _split(name: str) -> Callable[[Path], str]:
    """Which part of each gain is the velocities, which the algebra."""

    def block(results: Path) -> str:
        from posecast.scenarios.table1.smoothness import gain_split_markdown

        rep = _load(results, name)
        return "\n".join([*_body(gain_split_markdown(rep)), *_tail(rep, name)])

    return block


def _velocity_error(
    name: str, rates: Sequence[int] = (5, 7, 10, 12, 15, 20, 30)
) -> Callable[[Path], str]:
    """Hands' p95 velocity error and p95 tip error against rate, every method."""

    def block(results: Path) -> str:
        rep = _load(results, name)
        meths = _methods(rep)
        lines = [
            "| rate | " + " | ".join(f"`{m}`" for m in meths) + " |",
            "|---|" + "---|" * len(meths),
        ]
        for r in rates:
            cells = []
            for m in meths:
                h = rep["curves"][m].get(str(r), {}).get("hands", {})
                cells.append(f"{_f(h.get('vel_p95_mps'), 2)} m/s, {_f(h.get('tip_p95_mm'), 0)} mm")
            lines.append(f"| {r} Hz | " + " | ".join(cells) + " |")
        lines += [
            "",
            "Cell: hands' p95 velocity error, p95 tip error (ideal network, one-interval "
            "playout plus look-ahead). Every rate 5-30 Hz is in the JSON and in "
            f"`{name}/table1.md`.",
            *_tail(rep, name),
        ]
        return "\n".join(lines)

    return block


def _verdicts(results: Path) -> str:
    """Fewest bytes/s at equal headline and no more latency than SoA, per tier and network."""
    rep = _load(results, "table1-eval")
    v = rep["frontier"]["verdicts"]
    meths = [m for m in _methods(rep) if m != "soa"]
    lines = [
        "| tier (network) | SoA reference | " + " | ".join(f"`{m}`" for m in meths) + " |",
        "|---|---|" + "---|" * len(meths),
    ]
    for t in v["tiers"]:
        ref = t["reference"]
        cells = []
        for m in meths:
            c = t["cheapest"].get(m)
            if c is None:
                cells.append("none")
                continue
            cells.append(
                f"{_bytes(c['bytes_per_s'])} ({c['rate']} Hz, f {c['fraction']:g}, "
                f"{c['variant']}; {_pct(t['bytes_saving_pct'][m])})"
            )
        lines.append(
            f"| {t['tier']} ({t['network']}) | {_f(ref['headline_mm'])} mm @ "
            f"{_f(ref['latency_ms'], 0)} ms, {_bytes(ref['bytes_per_s'])} B/s | "
            + " | ".join(cells)
            + " |"
        )
    lines += [
        "",
        "Cell: the fewest bytes/s at which the method's hands p95 tip error is no worse than "
        "SoA's at the tier rate at no more capture-to-display latency, over rates, playout "
        "delays D = (f + look-ahead)/rate + lag and stall policies (hold, extrapolate = dead "
        "reckoning with a jump, smooth = dead reckoning blended); saving against SoA's bytes/s.",
        *_tail(rep, "table1-eval"),
    ]
    return "\n".join(lines)


def _headline(results: Path) -> str:
    """The lowest rate at which each method matches SoA at 30 Hz (ideal network)."""
    rep = _load(results, "table1-eval")
    ht = rep["frontier"]["verdicts"]["headline_target"]
    ref = ht["reference"]
    lines = [
        "| method | lowest matching rate | p95 tip error | latency | bytes/s | saving (bytes) |",
        "|---|---|---|---|---|---|",
    ]
    for m in _methods(rep):
        p = ht["lowest_matching_rate"].get(m)
        if p is None:
            lines.append(f"| `{m}` | none | | | | |")
            continue
        lines.append(
            f"| `{m}` | {p['rate']} Hz (f {p['fraction']:g}, {p['variant']}) "
            f"| {_f(p['headline_mm'])} mm | {_f(p['latency_ms'], 1)} ms "
            f"| {_bytes(p['bytes_per_s'])} "
            f"| {_pct(100 * (1 - p['bytes_per_s'] / ref['bytes_per_s']))} |"
        )
    lines += [
        "",
        f"Reference: SoA at 30 Hz, {_f(ref['headline_mm'])} mm at {_f(ref['latency_ms'], 1)} ms, "
        f"{_bytes(ref['bytes_per_s'])} B/s. A method's row is its lowest-rate point of the "
        "error-versus-latency view that matches it (at that rate, its lowest latency).",
        *_tail(rep, "table1-eval"),
    ]
    return "\n".join(lines)


def _runtime30(results: Path) -> str:
    """Receiver CPU time per second of session at the excellent tier's rate, per method."""
    rep = _load(results, "table1-eval")
    row = rep["tiers"][0]
    lines = [
        f"| receiver time at {row['soa_rate']} Hz | decode | render | total | decode share |",
        "|---|---|---|---|---|",
    ]
    for m in _methods(rep):
        c = row["running_time_s"][m]["at_soa_rate"]
        lines.append(
            f"| `{m}` | {1000 * c['decode_s']:.1f} ms | {1000 * c['render_s']:.1f} ms "
            f"| {1000 * c['total_s']:.1f} ms | {100 * c['decode_s'] / c['total_s']:.0f} % |"
        )
    streams = row["running_time_s"]["soa"]["at_soa_rate"]["streams"]
    lines += [
        "",
        f"CPU time per second of session: {streams:.0f} remote streams, 90 Hz render, "
        "median of the interleaved runs.",
        *_tail(rep, "table1-eval"),
    ]
    return "\n".join(lines)


def _frontier(results: Path) -> str:
    """Best headline within each latency budget, per network (the error-vs-latency view)."""
    rep = _load(results, "table1-eval")
    lines = [
        "| network | latency | p95 tip, hands | method, rate, f, stall policy | stalls | B/s |",
        "|---|---|---|---|---|---|",
    ]
    for net, points in rep["frontier"]["frontiers"].items():
        for p in points:
            lines.append(
                f"| {net} | {_f(p['latency_ms'])} ms | {_f(p['headline_mm'])} mm "
                f"| `{p['method']}` {p['rate']} Hz, f {p['fraction']:g}, {p['variant']} "
                f"| {_f(100 * p['stall_fraction'])} % | {_bytes(p['bytes_per_s'])} |"
            )
    lines += [
        "",
        "Each row beats every point of lower latency on that network (all methods, rates, "
        "playout delays and stall policies of the view).",
        *_tail(rep, "table1-eval"),
    ]
    return "\n".join(lines)


def _runtime(results: Path) -> str:
    rep = _load(results, "table1-eval")
    meths = [m for m in _methods(rep) if m != "soa"]
    lines = [
        "| tier | " + " | ".join(f"`{m}`" for m in meths) + " |",
        "|---|" + "---|" * len(meths),
    ]
    for t in rep["tiers"]:
        rt = t["running_time_saving_pct"]
        lines.append(f"| {t['name']} | " + " | ".join(_pct(rt.get(m)) for m in meths) + " |")
    lines += [
        "",
        "Receiver CPU time saved against SoA at the tier rate, each method at its equal-QoE "
        "rate (negative: more CPU). The paper claims +16.5 % for its methods. Median of "
        f"{rep['config']['bench']['repeats']} interleaved runs on a shared machine (noise about "
        "+-10 %).",
        *_tail(rep, "table1-eval"),
    ]
    return "\n".join(lines)


def _report_section(name: str, section: str) -> Callable[[Path], str]:
    """A section of a table1.md (without its header), from the report module."""

    def block(results: Path) -> str:
        from posecast.scenarios.table1 import report as rp

        rep = _load(results, name)
        fn = {"link": rp.link_markdown, "per-trace": rp.per_trace_markdown}[section]
        return "\n".join([*_body(fn(rep)), *_tail(rep, name)])

    return block


def _codecs(name: str) -> Callable[[Path], str]:
    """Bytes/s at equal QoE with the raw and the compact codec (table1's ``codecs``)."""

    def block(results: Path) -> str:
        from posecast.scenarios.table1.codec_bytes import codec_markdown

        rep = _load(results, name)
        if "codecs" not in rep:
            return f"*No codec prices in `{name}` (run without the compact codec).*"
        return "\n".join([*_body(codec_markdown(rep)), *_tail(rep, name)])

    return block


def _paper_scene(results: Path) -> str:
    """The synthetic scene closest to the paper's: accuracy and smoothness per class."""
    rep = _load(results, "table1-paper-scene")
    meths = _methods(rep)
    lines = [
        "| tier | SoA (hands): p95 tip, p95 velocity error | "
        + " | ".join(f"`{m}`" for m in meths if m != "soa")
        + " |",
        "|---|---|" + "---|" * (len(meths) - 1),
    ]
    for t in rep["tiers"]:
        cells = []
        for m in meths[1:]:
            obj = t["equal_qoe_rate_by_class"].get("objects", {}).get(m)
            cells.append(
                f"{_r(t['equal_qoe_rate'][m])} / {_r(t['equal_smoothness_rate'][m])} / {_r(obj)}"
            )
        lines.append(
            f"| {t['name']} ({t['soa_rate']} Hz) | {_f(t['reference_headline_mm'])} mm, "
            f"{_f(t['smoothness_reference_mps'], 2)} m/s | " + " | ".join(cells) + " |"
        )
    c = rep["curves"]
    at = " ".join(
        f"`{m}` {_f(c[m]['10']['hands']['tip_p95_mm'])} mm / "
        f"{_f(c[m]['10']['hands']['vel_p95_mps'], 3)} m/s;"
        for m in meths
    )
    lines += [
        "",
        "Cell: equal-accuracy rate (hands) / equal-smoothness rate (hands) / equal-accuracy "
        "rate judged on the objects (the tool and the drill). At 10 Hz, hands p95 tip error / "
        f"p95 velocity error: {at}",
        *_tail(rep, "table1-paper-scene"),
    ]
    return "\n".join(lines)


def _velocity_sources(results: Path) -> str:
    data = _load(results, "velocity-sources-eval", "velocity_sources.json")
    hands = data["hands"]
    sources = list(hands)
    rates = list(hands[sources[0]])
    lines = [
        "| rate | " + " | ".join(f"`{s}`" for s in sources) + " |",
        "|---|" + "---|" * len(sources),
    ]
    for r in rates:
        lines.append(
            f"| {float(r):g} Hz | "
            + " | ".join(_f(hands[s][r]["tip_p95_mm"]) + " mm" for s in sources)
            + " |"
        )
    lines += [
        "",
        f"`{data['method']}`, hands p95 tip error per velocity source (ideal network, "
        "one-interval playout, float16 velocities).",
        "",
        _source(data.get("provenance"), "docs/results/velocity-sources-eval/velocity_sources.json"),
    ]
    return "\n".join(lines)


# ---------------------------------------------------------------- Tables 2-3 blocks

#: The paper's Tables 2-3 (its extended version): mean relative error (%) of the
#: interpolated translations and rotations; "1-frame" drops every 2nd frame (keep 1
#: in 2), "2-frame" keeps 1 in 3. Its "3D CGA" motors are our ``motor-lerp``.
PAPER_TABLES: dict[str, dict[str, dict[str, float]]] = {
    "2": {
        "translation": {"dq-slerp": 0.02, "soa": 0.006, "motor-lerp": 0.006},
        "rotation": {"dq-slerp": 0.02, "soa": 0.01, "motor-lerp": 0.01},
    },
    "3": {
        "translation": {"dq-slerp": 0.009, "soa": 0.009, "motor-lerp": 0.009},
        "rotation": {"dq-slerp": 0.02, "soa": 0.02, "motor-lerp": 0.02},
    },
}


def _tables23(name: str) -> Callable[[Path], str]:
    """Our Tables 2 and 3 (paper's metric) beside the paper's values, with the factor."""

    def block(results: Path) -> str:
        res = _load(results, name, "analyze.json")
        lines = [
            "| table | method | translation rel. %: paper | ours: all / hands / head | factor "
            "| rotation rel. %: paper | ours (Euler): all / hands / head | factor "
            "| tip p95 mm: hands / head |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for k in ("2", "3"):
            for m, entry in res["tables"][k]["methods"].items():
                cls = entry.get("classes")
                if cls is None:
                    continue
                paper = PAPER_TABLES[k]
                pt, pr = paper["translation"].get(m), paper["rotation"].get(m)
                ours_t = [
                    cls.get(c, {}).get("translation_rel_pct") for c in ("all", "hands", "head")
                ]
                ours_e = [cls.get(c, {}).get("euler_rel_pct") for c in ("all", "hands", "head")]
                tips = [cls.get(c, {}).get("tip_p95_mm") for c in ("hands", "head")]
                lines.append(
                    f"| {k} (keep 1 in {k}) | `{m}` | {_f(pt, 3) if pt else '-'} "
                    f"| {' / '.join(_f(x, 3) for x in ours_t)} "
                    f"| {_factor(ours_t[0], pt)} | {_f(pr, 2) if pr else '-'} "
                    f"| {' / '.join(_f(x, 3) for x in ours_e)} | {_factor(ours_e[0], pr)} "
                    f"| {' / '.join(_f(x, 1) for x in tips)} |"
                )
        lines += [
            "",
            "Factor: ours (all devices) over the paper's. `-`: the paper has no such method.",
            "",
            _source(res.get("provenance"), f"docs/results/{name}/analyze.json"),
        ]
        return "\n".join(lines)

    return block


def _factor(ours: Any, paper: Any) -> str:
    if ours is None or not paper:
        return "-"
    return f"{float(ours) / float(paper):.0f}x"


def _budget(results: Path) -> str:
    """What SoA's mean relative translation error (keep 1 in 2) is made of."""
    lines = [
        "| source | class | frames | rel. error % | mean abs. error | mean accel. "
        "| median accel. | mean distance from origin | frame rate "
        "| factor over the paper's 0.006 % |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    provs = []
    for name, label in (
        ("recording-eval", "`eval` traces"),
        ("recording-paper-scene", "paper scene"),
    ):
        res = _load(results, name, "analyze.json")
        provs.append(_source(res.get("provenance"), f"docs/results/{name}/analyze.json"))
        for cls, b in res["budget"].items():
            lines.append(
                f"| {label} | {cls} | {b['frames']} | {_f(b['translation_rel_pct'], 4)} "
                f"| {_f(b['abs_error_mean_mm'], 3)} mm | {_f(b['accel_mean_mps2'], 2)} m/s² "
                f"| {_f(b['accel_p50_mps2'], 2)} m/s² "
                f"| {_f(b['distance_from_origin_mean_m'], 2)} m "
                f"| {_f(b['frame_rate_mean_hz'], 1)} Hz "
                f"| {_f(b['translation_rel_pct'] / 0.006, 1)}x |"
            )
    lines += [
        "",
        "SoA keeping 1 frame in 2: the LERP midpoint misses by exactly |a| dt² / 2 (a: the "
        "finite-difference acceleration, dt: the frame interval), so the paper's translation "
        "metric is the mean of |a| dt² / (2 |p|).",
        "",
        *provs,
    ]
    return "\n".join(lines)


def _recording_table(name: str, keep: str) -> Callable[[Path], str]:
    """One of Tables 2-3 per method and class: the paper's metric and absolute errors."""

    def block(results: Path) -> str:
        res = _load(results, name, "analyze.json")
        table = res["tables"][keep]["methods"]
        first = next(e for e in table.values() if "classes" in e)
        frames = first["classes"].get("hands", {}).get("frames")
        lines = [
            f"{frames} reconstructed hand samples per method (both hands), fractions "
            f"{', '.join(f'{a:.2g}' for a in res['tables'][keep]['fractions'])}.",
            "",
            "| method | class | translation rel. % | Euler rel. % | (wrapped) | median transl. / "
            "Euler % | pos p50 / p95 mm | rot p50 / p95 deg | tip p50 / p95 mm |",
            "|---|---|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for m, entry in table.items():
            for cls, st in entry.get("classes", {}).items():
                lines.append(
                    f"| `{m}` | {cls} | {_f(st['translation_rel_pct'], 3)} "
                    f"| {_f(st['euler_rel_pct'], 3)} | {_f(st['euler_rel_wrapped_pct'], 3)} "
                    f"| {_f(st['translation_rel_p50_pct'], 3)} / {_f(st['euler_rel_p50_pct'], 3)} "
                    f"| {_f(st['pos_p50_mm'], 2)} / {_f(st['pos_p95_mm'], 2)} "
                    f"| {_f(st['rot_p50_deg'], 2)} / {_f(st['rot_p95_deg'], 2)} "
                    f"| {_f(st['tip_p50_mm'], 2)} / {_f(st['tip_p95_mm'], 2)} |"
                )
        lines += ["", _source(res.get("provenance"), f"docs/results/{name}/analyze.json")]
        return "\n".join(lines)

    return block


def _recording_per_source(results: Path) -> str:
    res = _load(results, "recording-eval", "analyze.json")
    meths = [m for m in ("soa", "dq-slerp", "motor-lerp") if m in res["methods"]]
    rates = {src["name"]: src["rate_hz"] for src in res["sources"]}
    lines = [
        "| trace (native rate) | "
        + " | ".join(f"keep {k}: `{m}`" for k in ("2", "3") for m in meths)
        + " |",
        "|---|" + "---|" * (2 * len(meths)),
    ]
    for name, per in res["per_source"].items():
        cells = [
            f"{_f(per[k][m]['all']['translation_rel_pct'], 3)} / "
            f"{_f(per[k][m]['all']['euler_rel_pct'], 3)}"
            for k in ("2", "3")
            for m in meths
        ]
        lines.append(f"| {name.split('_')[0]} ({rates[name]:.0f} Hz) | " + " | ".join(cells) + " |")
    lines += [
        "",
        "Cell: translation rel. % / Euler rel. %, all devices.",
        "",
        _source(res.get("provenance"), "docs/results/recording-eval/analyze.json"),
    ]
    return "\n".join(lines)


BLOCKS.update(
    {
        "paper-table1": _paper_table1,
        "closing-eval": _closing("table1-eval"),
        "closing-dev": _closing("table1-dev"),
        "split-eval": _split("table1-eval"),
        "split-dev": _split("table1-dev"),
        "velocity-error-eval": _velocity_error("table1-eval"),
        "verdicts-eval": _verdicts,
        "headline-eval": _headline,
        "runtime-eval": _runtime,
        "runtime30-eval": _runtime30,
        "frontier-eval": _frontier,
        "codecs-eval": _codecs("table1-eval"),
        "link-eval": _report_section("table1-eval", "link"),
        "link-dev-stream": _report_section("table1-dev-stream", "link"),
        "per-trace-eval": _report_section("table1-eval", "per-trace"),
        "synthetic": _report_section("table1-synthetic", "per-trace"),
        "fixtures": _report_section("table1-fixtures", "per-trace"),
        "paper-scene": _paper_scene,
        "velocity-sources-eval": _velocity_sources,
        "tables23-eval": _tables23("recording-eval"),
        "tables23-paper-scene": _tables23("recording-paper-scene"),
        "tables23-budget": _budget,
        "recording-table2-eval": _recording_table("recording-eval", "2"),
        "recording-table3-eval": _recording_table("recording-eval", "3"),
        "recording-per-trace-eval": _recording_per_source,
    }
)
