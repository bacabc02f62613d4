"""``make results``: regenerate every published result with the current code.

Run: ``make results`` (or ``python -m posecast.results``; ``--only NAME,...``
for some outputs, ``--docs-only`` to rewrite the pages from the outputs already
there, ``--list`` for the outputs). Each output (a folder under
``docs/results/``, see :data:`JOBS`) is recomputed from the traces by the same
code the commands run (``posecast table1``, ``posecast analyze``,
``posecast velocity-sources``), with its command, the git revision and the
traces split written into it. Then the generated blocks of ``docs/lab/results.md``
and ``docs/lab/results-recording.md`` (between ``<!-- results:NAME -->`` and
``<!-- /results:NAME -->``, see :mod:`posecast.results_docs`) are rewritten from
the outputs, and the runner prints which files changed (JSON compared without
its timings, which change on every run).

Not part of ``make test``: the whole run takes 12-20 minutes on a shared 2-core
machine. It reads the full trace sets (bundled; ``POSECAST_TRACES`` for another copy). Live
measurements (``table1 --live``, the recorded demo session, the relay and
recorder benchmarks) depend on the host and are not re-run; the pages say
where they came from.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import subprocess
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["JOBS", "Job", "main", "provenance", "run_results"]

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "docs" / "results"
PAGES = (ROOT / "docs" / "lab" / "results.md", ROOT / "docs" / "lab" / "results-recording.md")

#: Every interpolator of the published tables.
ALL_METHODS = (
    "soa",
    "dq-slerp",
    "motor-lerp",
    "motor-cubic",
    "motor-quintic",
    "soa-hermite",
    "motor-hermite",
)
PAPER_METHODS = ("soa", "dq-slerp", "motor-lerp")
#: Tables 2-3: the paper's methods and ours (velocity methods on traces use
#: ``Trace.velocities()``, see ``recorder.analyze``).
RECORDING_METHODS = ("soa", "dq-slerp", "motor-lerp", "motor-cubic", "soa-hermite", "motor-hermite")
#: The synthetic motions closest to the paper's medical-training scene.
PAPER_SCENE = (
    "synthetic:hand-over:0",
    "synthetic:hand-over:1",
    "synthetic:drill-toss:0",
    "synthetic:drill-toss:1",
)


@dataclass(frozen=True)
class Job:
    """One published output: a folder under ``docs/results/``."""

    name: str
    #: the traces it was computed on (``traces:eval``, ``synthetic``, ...)
    split: str
    #: the equivalent command line
    command: str
    run: Callable[[Path, Mapping[str, Any]], None]


def _table1_job(
    name: str, traces: Sequence[str], split: str, methods: Sequence[str], **opts: Any
) -> Job:
    flags = " ".join(f"--traces {t}" for t in traces)
    extra = "".join(
        f" --{k.replace('_', '-')}" if v is True else f" --no-{k.replace('_', '-')}"
        for k, v in opts.items()
        if isinstance(v, bool)
    )
    extra += "".join(f" --{k} {v}" for k, v in opts.items() if not isinstance(v, bool))
    command = (
        f"posecast table1 {flags} --methods {','.join(methods)}{extra} --out docs/results/{name}"
    )

    def run(out: Path, prov: Mapping[str, Any]) -> None:
        from posecast.scenarios.table1 import run_table1

        run_table1(
            list(traces), methods=methods, out_dir=out, command=command, provenance=prov, **opts
        )

    return Job(name, split, command, run)


def _analyze_job(name: str, sources: Sequence[str], split: str) -> Job:
    if all(src.startswith("traces:") for src in sources):
        command = (
            f"posecast analyze --trace {' --trace '.join(sources)} --keep-every 2,3 "
            f"--interp {','.join(RECORDING_METHODS)} --json docs/results/{name}/analyze.json"
        )
    else:  # `posecast analyze` reads trace files; synthetic motions go through Python
        command = (
            f"python -m posecast.results --only {name} (recorder.analyze.analyze on "
            f"{', '.join(sources)}; keep 2,3; {','.join(RECORDING_METHODS)})"
        )

    def run(out: Path, prov: Mapping[str, Any]) -> None:
        from posecast.recorder.analyze import analyze, format_analysis
        from posecast.scenarios.table1 import resolve_traces

        traces = [tr for s in sources for tr in resolve_traces(s)]
        result = analyze(traces, (2, 3), RECORDING_METHODS)
        result["provenance"] = dict(prov)
        result["budget"] = relative_error_budget(traces)
        _write_json(out / "analyze.json", result)
        (out / "analyze.md").write_text(format_analysis(result) + "\n")

    return Job(name, split, command, run)


def _velocity_sources_job() -> Job:
    rates, sources = (10, 15, 16, 17, 20, 30), ("central", "causal", "causal:2,1")
    command = (
        "posecast velocity-sources --traces traces:eval --rates "
        f'{",".join(map(str, rates))} --sources "{";".join(sources)}"'
    )

    def run(out: Path, prov: Mapping[str, Any]) -> None:
        from posecast.scenarios.table1 import resolve_traces
        from posecast.scenarios.velocity_sources import compare_velocity_sources

        res = compare_velocity_sources(resolve_traces("traces:eval"), rates, sources)
        data = {"provenance": dict(prov), "method": "motor-hermite", "hands": res}
        _write_json(out / "velocity_sources.json", data)

    return Job("velocity-sources-eval", "traces:eval", command, run)


JOBS: tuple[Job, ...] = (
    _table1_job("table1-eval", ["traces:eval"], "traces:eval", ALL_METHODS),
    _table1_job("table1-dev", ["traces:dev"], "traces:dev", ALL_METHODS),
    _table1_job(
        "table1-paper-scene", PAPER_SCENE, "synthetic (hand-over, drill-toss)", ALL_METHODS,
        link=False, bench=False, frontier=False,
    ),
    _table1_job(
        "table1-synthetic", ["synthetic"], "synthetic (suite)", PAPER_METHODS, frontier=False
    ),
    _table1_job(
        "table1-fixtures", ["synthetic:screw", "synthetic:spin-drift"], "synthetic (fixtures)",
        PAPER_METHODS, link=False, bench=False, frontier=False,
    ),
    _table1_job(
        "table1-dev-stream", ["traces:dev"], "traces:dev", PAPER_METHODS,
        transport="stream", bench=False, frontier=False,
    ),
    _analyze_job("recording-eval", ["traces:eval"], "traces:eval"),
    _analyze_job("recording-paper-scene", PAPER_SCENE, "synthetic (hand-over, drill-toss)"),
    _velocity_sources_job(),
)  # fmt: skip


# ---------------------------------------------------------------- Tables 2-3: the budget


def relative_error_budget(traces: Sequence[Any]) -> dict[str, Any]:
    """What the paper's translation metric is made of, for SoA keeping 1 frame in 2.

    Reconstructing a dropped frame ``i`` by LERP of ``i - 1`` and ``i + 1`` at
    a = 1/2 misses by exactly half the second difference: ``|p[i-1] - 2 p[i] +
    p[i+1]| / 2 = |a| dt^2 / 2`` (``a``: the finite-difference acceleration,
    ``dt`` the frame interval). So the mean relative error is the mean of
    ``|a| dt^2 / (2 |p|)``: acceleration, frame interval squared, and distance
    from the world origin. Returns those factors pooled per device class.
    """
    from posecast.recorder.analyze import relative_error_pct
    from posecast.scenarios.traces import device_class

    pools: dict[str, dict[str, list[Any]]] = {}
    for tr in traces:
        p = tr.poses[..., :3]
        n = (p.shape[0] - 1) // 2 * 2
        i = np.arange(1, n, 2)
        lerp = 0.5 * (p[i - 1] + p[i + 1])
        err = np.linalg.norm(lerp - p[i], axis=-1)
        dt = 0.5 * (tr.times[i + 1] - tr.times[i - 1])
        acc = 2.0 * err / (dt * dt)[:, None]
        rel = relative_error_pct(lerp, p[i])
        dist = np.linalg.norm(p[i], axis=-1)
        for j, stream in enumerate(tr.streams):
            d = pools.setdefault(device_class(stream), {k: [] for k in "eadrf"})
            d["e"].append(err[:, j])
            d["a"].append(acc[:, j])
            d["d"].append(dist[:, j])
            d["r"].append(rel[:, j])
            d["f"].append(1.0 / dt)
    out: dict[str, Any] = {}
    for cls, d in pools.items():
        c = {k: np.concatenate(v) for k, v in d.items()}
        out[cls] = {
            "frames": int(c["e"].size),
            "translation_rel_pct": float(np.nanmean(c["r"])),
            "abs_error_mean_mm": 1000.0 * float(np.mean(c["e"])),
            "accel_mean_mps2": float(np.mean(c["a"])),
            "accel_p50_mps2": float(np.median(c["a"])),
            "distance_from_origin_mean_m": float(np.mean(c["d"])),
            "frame_rate_mean_hz": float(np.mean(c["f"])),
        }
    return out


# ---------------------------------------------------------------- provenance and changes


def provenance(split: str, command: str) -> dict[str, Any]:
    """The command, the git revision (``-dirty`` with uncommitted changes) and the split."""
    return {"command": command, "revision": git_revision(), "traces": split}


def git_revision() -> str:
    """``git describe``-like short revision of the checkout, or ``unknown``."""
    try:
        rev = subprocess.run(
            ["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return rev + ("-dirty" if dirty else "")


#: JSON keys that change on every run without any result changing (how long it took,
#: the revision), left out of the comparison. The receiver CPU times are results and
#: count (they move with the host's load on every run).
VOLATILE_KEYS = frozenset({"elapsed_s", "timings_s", "provenance", "command"})
#: The same for Markdown: the run-time sentence of table1.md and revisions.
_VOLATILE_TEXT = (
    (re.compile(rb"Run time [0-9.]+ s \([^)]*\)\."), b"Run time"),
    (re.compile(rb"revision `[^`]*`"), b"revision"),
)


def _stable(x: Any) -> Any:
    if isinstance(x, dict):
        return {k: _stable(v) for k, v in x.items() if k not in VOLATILE_KEYS}
    if isinstance(x, list):
        return [_stable(v) for v in x]
    return x


def fingerprint(path: Path) -> str:
    """A digest of a file's content; JSON without :data:`VOLATILE_KEYS`, Markdown
    without run times and revisions."""
    data = path.read_bytes()
    if path.suffix == ".md":
        for pattern, repl in _VOLATILE_TEXT:
            data = pattern.sub(repl, data)
    if path.suffix == ".json":
        try:
            stable = _stable(json.loads(data))
            data = json.dumps(stable, sort_keys=True).encode()
        except ValueError:
            pass
    return hashlib.sha256(data).hexdigest()


def snapshot(paths: Sequence[Path]) -> dict[Path, str]:
    """``{file: fingerprint}`` of every file under ``paths`` (folders or files)."""
    out: dict[Path, str] = {}
    for p in paths:
        files = sorted(f for f in p.rglob("*") if f.is_file()) if p.is_dir() else [p]
        out.update({f: fingerprint(f) for f in files if f.exists()})
    return out


def changes(before: Mapping[Path, str], after: Mapping[Path, str]) -> list[tuple[str, Path]]:
    """``(status, file)`` for every file added, changed or removed."""
    out: list[tuple[str, Path]] = []
    for f in sorted(set(before) | set(after)):
        if f not in before:
            out.append(("new", f))
        elif f not in after:
            out.append(("removed", f))
        elif before[f] != after[f]:
            out.append(("changed", f))
    return out


def _write_json(path: Path, data: Any) -> None:
    from posecast.scenarios.table1.report import jsonable

    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(jsonable(data), indent=1) + "\n")


# ---------------------------------------------------------------- the run


def run_results(
    only: Sequence[str] | None = None, *, docs_only: bool = False, results: Path = RESULTS
) -> list[tuple[str, Path]]:
    """Recompute the outputs (all, or ``only``), rewrite the pages; return what changed."""
    from posecast.results_docs import rewrite_pages

    jobs = [j for j in JOBS if only is None or j.name in only]
    unknown = sorted(set(only or ()) - {j.name for j in JOBS})
    if unknown:
        raise ValueError(f"unknown output(s) {unknown}; known: {', '.join(j.name for j in JOBS)}")
    before = snapshot([results, *PAGES])
    if not docs_only:
        for job in jobs:
            t0 = time.perf_counter()
            print(f"{job.name}: {job.command}", flush=True)
            out = results / job.name
            out.mkdir(parents=True, exist_ok=True)
            job.run(out, provenance(job.split, job.command))
            print(f"{job.name}: done in {time.perf_counter() - t0:.0f} s", flush=True)
    rewrite_pages(PAGES, results)
    return changes(before, snapshot([results, *PAGES]))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m posecast.results", description=__doc__)
    parser.add_argument("--only", help="Comma-separated outputs to recompute (default: all).")
    parser.add_argument(
        "--docs-only", action="store_true", help="Only rewrite the pages from the outputs."
    )
    parser.add_argument("--list", action="store_true", help="List the outputs and exit.")
    args = parser.parse_args(argv)
    if args.list:
        for j in JOBS:
            print(f"{j.name:24s} {j.split:36s} {j.command}")
        return 0
    only = None if args.only is None else [s.strip() for s in args.only.split(",") if s.strip()]
    try:
        changed = run_results(only, docs_only=args.docs_only)
    except (ValueError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not changed:
        print("no output changed")
    for status, f in changed:
        print(f"{status:8s} {f.relative_to(ROOT)}")
    names = {j.name for j in JOBS}
    for d in sorted(p for p in RESULTS.iterdir() if p.is_dir() and p.name not in names):
        print(f"kept     {d.relative_to(ROOT)} (not produced by make results: live or stale)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
