"""Table 1's PNG plots (matplotlib, Agg backend): QoE against rate, error CDFs, the frontier."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from posecast.scenarios.table1.common import PAPER
from posecast.scenarios.table1.sweep import _Sweep


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt: Any, fig: Any, out: Path, name: str) -> str:
    """Lay ``fig`` out, write it to ``out/name`` and close it; return ``name``."""
    fig.tight_layout()
    fig.savefig(out / name)
    plt.close(fig)
    return name


def write_plots(
    out: Path,
    report: Mapping[str, Any],
    ideal: _Sweep,
    link_sweeps: Mapping[str, _Sweep],
    meths: Sequence[str],
    soa_rates: Mapping[str, int],
) -> list[str]:
    """``qoe_vs_rate.png``, ``error_cdf.png`` and (with link sweeps) ``qoe_vs_rate_link.png``."""
    plt = _pyplot()
    colours = {m: f"C{i}" for i, m in enumerate(meths)}
    files = [
        _qoe_vs_rate(plt, out, report, ideal, meths, soa_rates, colours),
        _error_cdf(plt, out, report, ideal, meths, colours),
    ]
    if link_sweeps:
        files.append(_qoe_vs_rate_link(plt, out, link_sweeps, meths, soa_rates, colours))
    return files


def _qoe_vs_rate(
    plt: Any,
    out: Path,
    report: Mapping[str, Any],
    ideal: _Sweep,
    meths: Sequence[str],
    soa_rates: Mapping[str, int],
    colours: Mapping[str, str],
) -> str:
    """Headline (hands) and head p95 tip error against rate, ideal network."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4), dpi=100)
    for ax, cls in zip(axes, ("hands", "head"), strict=True):
        for m in meths:
            rs = sorted(ideal.pooled)
            ys = [ideal.pooled[r][m].get(cls, {}).get("tip_p95_mm", np.nan) for r in rs]
            ax.plot(rs, ys, marker=".", color=colours[m], label=m)
        for name, r in soa_rates.items():
            ax.axvline(r, color="grey", ls=":", lw=0.8)
            ax.text(
                r,
                1.0,
                name,
                rotation=90,
                va="top",
                ha="right",
                fontsize=7,
                transform=ax.get_xaxis_transform(),
                color="grey",
            )
        ax.set_yscale("log")
        ax.set_xlabel("update rate (Hz)")
        ax.set_ylabel(f"p95 tip error, {cls} (mm)")
        ax.grid(True, which="both", alpha=0.3)
    for row in report["tiers"]:
        ref = row["reference_headline_mm"]
        if ref is not None:
            axes[0].axhline(ref, color="grey", ls="--", lw=0.5)
        for m, r in row["equal_qoe_rate"].items():
            if r is not None and m != "soa":
                axes[0].plot(
                    [r], [row["headline_at_equal_rate_mm"][m]], "o", mfc="none", color=colours[m]
                )
    axes[0].legend(fontsize=8)
    fig.suptitle(
        "QoE vs update rate, ideal network (dotted: tier rates; circles: equal-QoE)", fontsize=9
    )
    return _save(plt, fig, out, "qoe_vs_rate.png")


def _error_cdf(
    plt: Any,
    out: Path,
    report: Mapping[str, Any],
    ideal: _Sweep,
    meths: Sequence[str],
    colours: Mapping[str, str],
) -> str:
    """Per tier: CDF of the hands tip error at SoA's rate and at each equal-QoE rate."""
    tiers = report["tiers"]
    fig, axes = plt.subplots(1, len(tiers), figsize=(3.2 * len(tiers), 3.4), dpi=100, squeeze=False)
    for ax, row in zip(axes[0], tiers, strict=True):
        r_soa = row["soa_rate"]
        at_soa = ideal.hands_tip.get(r_soa, {})
        for m in meths:
            x = np.sort(at_soa.get(m, np.empty(0)))
            if x.size:
                ax.plot(
                    x, np.arange(1, x.size + 1) / x.size, color=colours[m], label=f"{m} @{r_soa}"
                )
            r_m = row["equal_qoe_rate"].get(m)
            if m != "soa" and r_m is not None and r_m != r_soa:
                y = np.sort(ideal.hands_tip.get(r_m, {}).get(m, np.empty(0)))
                if y.size:
                    ax.plot(
                        y,
                        np.arange(1, y.size + 1) / y.size,
                        color=colours[m],
                        ls="--",
                        label=f"{m} @{r_m}",
                    )
        ax.axhline(0.95, color="grey", lw=0.5)
        ax.set_xscale("log")
        ax.set_xlim(left=1)
        ax.set_title(f"{row['name']} (SoA {r_soa} Hz)", fontsize=9)
        ax.set_xlabel("hands tip error (mm)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6)
    axes[0][0].set_ylabel("CDF")
    return _save(plt, fig, out, "error_cdf.png")


def _qoe_vs_rate_link(
    plt: Any,
    out: Path,
    link_sweeps: Mapping[str, _Sweep],
    meths: Sequence[str],
    soa_rates: Mapping[str, int],
    colours: Mapping[str, str],
) -> str:
    """Headline against rate through each tier's link."""
    fig, axes = plt.subplots(
        1, len(link_sweeps), figsize=(3.2 * len(link_sweeps), 3.4), dpi=100, squeeze=False
    )
    for ax, (name, sw) in zip(axes[0], link_sweeps.items(), strict=True):
        rs = sorted(sw.pooled)
        for m in meths:
            ys = [sw.pooled[r][m].get("hands", {}).get("tip_p95_mm", np.nan) for r in rs]
            ax.plot(rs, ys, marker=".", color=colours[m], label=m)
        ax.axvline(soa_rates[name], color="grey", ls=":", lw=0.8)
        ax.set_yscale("log")
        ax.set_title(f"link: {name}", fontsize=9)
        ax.set_xlabel("update rate (Hz)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel("p95 tip error, hands (mm)")
    axes[0][0].legend(fontsize=7)
    return _save(plt, fig, out, "qoe_vs_rate_link.png")


def frontier_plot(
    out: Path, report: Mapping[str, Any], meths: Sequence[str], soa_rates: Mapping[str, int]
) -> str:
    """``frontier.png``: headline vs latency per network, one curve per method and tier rate."""
    plt = _pyplot()
    fr = report["frontier"]
    nets = list(fr["frontiers"])
    colours = {m: f"C{i}" for i, m in enumerate(meths)}
    markers = "osD^v<>P*X"
    tier_rates = sorted(set(soa_rates.values()), reverse=True)
    ncols = min(3, len(nets))
    nrows = -(-len(nets) // ncols)
    fig, axes = plt.subplots(
        nrows, ncols, figsize=(4.6 * ncols, 3.9 * nrows), dpi=100, squeeze=False, sharey=True
    )
    flat = list(axes.flat)
    for ax in flat[len(nets) :]:
        ax.axis("off")
    for ax, net in zip(flat, nets, strict=False):
        pts = [p for p in fr["points"] if p["network"] == net]
        present = {p["rate"] for p in pts}
        rates = sorted(
            (set(tier_rates) | {p["ga_rate"] for p in PAPER["tiers"]}) & present, reverse=True
        )
        for m in meths:
            for k, r in enumerate(rates):
                by_f: dict[float, tuple[float, float]] = {}
                for p in pts:
                    if p["method"] != m or p["rate"] != r or p["headline_mm"] is None:
                        continue
                    f, cur = p["fraction"], by_f.get(p["fraction"])
                    if cur is None or p["headline_mm"] < cur[1]:
                        by_f[f] = (p["latency_ms"], p["headline_mm"])
                xy = [by_f[f] for f in sorted(by_f)]
                if not xy:
                    continue
                ax.plot(
                    [a for a, _ in xy],
                    [b for _, b in xy],
                    marker=markers[k % len(markers)],
                    ms=3,
                    lw=0.8,
                    alpha=0.75,
                    color=colours[m],
                    label=m if k == 0 else None,
                )
        front = fr["frontiers"][net]
        if front:
            xs = [p["latency_ms"] for p in front]
            ys = [p["headline_mm"] for p in front]
            ax.step(xs, ys, where="post", color="black", lw=1.8, label="frontier")
        for row in fr["verdicts"]["tiers"]:
            if row["network"] == net and row["reference"] is not None:
                ref = row["reference"]
                ax.plot([ref["latency_ms"]], [ref["headline_mm"]], "*", color="k", ms=9)
        ax.set_yscale("log")
        ax.set_title(
            f"{net}: best variant per D; rates "
            + ",".join(str(r) for r in rates)
            + f" Hz ({'/'.join(markers[: len(rates)])})",
            fontsize=8,
        )
        ax.set_xlabel("capture-to-display latency (ms)")
        ax.grid(True, which="both", alpha=0.3)
    for row in axes:
        row[0].set_ylabel("p95 tip error, hands (mm)")
    flat[0].legend(fontsize=7)
    fig.suptitle(
        "Error vs latency (stars: SoA at the tier rate, one-interval playout; black: frontier)",
        fontsize=9,
    )
    return _save(plt, fig, out, "frontier.png")
