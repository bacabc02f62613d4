"""The expected interpolation error at a keyframe interval, checked against traces.

The model the view-aware rates use (issue 31, ``server.view_rates``): between two
keyframes ``dt`` apart, linear interpolation of a position whose acceleration
stays within ``A`` is off by at most ``A dt^2 / 8`` (the chord of a parabola, at
mid-interval), with ``A`` estimated causally from the stream's recent motion
(``interp.expected_error``, shared with the relay, which receives every native
update: the largest ``|a|`` over the last 0.3 s, from second differences over a
stride of 3 native samples).

:func:`check` measures, for every keyframe interval of every stream at each rate,
the largest position error of linear interpolation over the native samples inside
it (an ideal network), beside that prediction; ``python -m posecast.scenarios.error_model``
prints the comparison per rate and device class and draws it.
"""

from __future__ import annotations

import argparse
import itertools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from posecast.interp.expected_error import causal_acceleration, expected_error
from posecast.scenarios.qoe import sample_keyframes
from posecast.scenarios.traces import DEVICE_NAMES, Trace, find_traces, load_trace

__all__ = ["IntervalErrors", "causal_acceleration", "check", "main"]

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class IntervalErrors:
    """Per keyframe interval: the measured largest error and the predicted one (mm)."""

    rate: float
    device: str
    measured_mm: F64
    predicted_mm: F64


def _intervals(times: F64, pos: F64, acc: F64, rate: float) -> tuple[F64, F64]:
    """Measured and predicted largest errors (mm) of every keyframe interval at ``rate``."""
    _, idx = sample_keyframes(times, rate)
    measured, predicted = [], []
    for k0, k1 in itertools.pairwise(idx):
        if k1 - k0 < 2:
            continue
        t0, t1 = times[k0], times[k1]
        s = (times[k0 + 1 : k1] - t0) / (t1 - t0)
        lerp = pos[k0] + s[:, None] * (pos[k1] - pos[k0])
        err = np.linalg.norm(lerp - pos[k0 + 1 : k1], axis=1).max()
        measured.append(1000.0 * err)
        predicted.append(1000.0 * expected_error(acc[k0], t1 - t0))
    return np.array(measured), np.array(predicted)


def check(traces: Sequence[Trace], rates: Sequence[float]) -> list[IntervalErrors]:
    """Every interval of every stream of ``traces`` at each rate, pooled per device class."""
    pooled: dict[tuple[float, str], tuple[list[F64], list[F64]]] = {}
    for tr in traces:
        for j, name in enumerate(tr.streams):
            device = "head" if name == "head" else "hands"
            pos = tr.poses[:, j, :3]
            acc = causal_acceleration(tr.times, pos)
            for rate in rates:
                m, p = _intervals(tr.times, pos, acc, rate)
                ms, ps = pooled.setdefault((rate, device), ([], []))
                ms.append(m)
                ps.append(p)
    return [
        IntervalErrors(rate, device, np.concatenate(ms), np.concatenate(ps))
        for (rate, device), (ms, ps) in sorted(pooled.items())
    ]


def _rows(results: Sequence[IntervalErrors]) -> list[str]:
    lines = [
        "| rate Hz | device | measured p50 / p95 mm | predicted p50 / p95 mm "
        "| measured <= predicted | log-log correlation |",
        "|---|---|---|---|---|---|",
    ]
    for r in results:
        m, p = r.measured_mm, r.predicted_mm
        ok = (m > 0) & (p > 0)
        corr = float(np.corrcoef(np.log(m[ok]), np.log(p[ok]))[0, 1]) if ok.sum() > 2 else np.nan
        lines.append(
            f"| {r.rate:g} | {r.device} | {np.percentile(m, 50):.1f} / {np.percentile(m, 95):.1f} "
            f"| {np.percentile(p, 50):.1f} / {np.percentile(p, 95):.1f} "
            f"| {100.0 * np.mean(m <= p):.0f} % | {corr:.2f} |"
        )
    return lines


def _plot(results: Sequence[IntervalErrors], path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5), sharex=True, sharey=True)
    for ax, device in zip(axes, ("hands", "head"), strict=True):
        for r in results:
            if r.device != device:
                continue
            ok = (r.measured_mm > 0.01) & (r.predicted_mm > 0.01)
            ax.scatter(
                r.predicted_mm[ok], r.measured_mm[ok], s=2, alpha=0.25, label=f"{r.rate:g} Hz"
            )
        ax.plot([0.01, 1e4], [0.01, 1e4], "k--", lw=1, label="measured = predicted")
        ax.set(xscale="log", yscale="log", xlim=(0.1, 3e3), ylim=(0.1, 3e3), title=device)
        ax.set_xlabel("predicted |a| dt^2 / 8 (mm)")
        ax.set_ylabel("measured largest LERP error in the interval (mm)")
        ax.legend(loc="upper left", markerscale=4, fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m posecast.scenarios.error_model")
    ap.add_argument("--traces", default="traces:eval")
    ap.add_argument("--rates", default="5,10,15,20,30")
    ap.add_argument("--plot", default=None, help="write the scatter plot (PNG) here")
    args = ap.parse_args(argv)
    traces = [load_trace(p).select(DEVICE_NAMES) for p in find_traces(args.traces)]
    results = check(traces, [float(r) for r in args.rates.split(",")])
    print(f"{len(traces)} traces ({args.traces}); position, linear interpolation, ideal network")
    print("\n".join(_rows(results)))
    if args.plot:
        _plot(results, args.plot)


if __name__ == "__main__":
    main()
