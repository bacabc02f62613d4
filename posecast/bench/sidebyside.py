"""Two checkouts' relay benchmarks side by side, runs alternating, medians and ratios.

    python -m posecast.bench.sidebyside --before OLD --after NEW [--rounds 3]
        [--codecs raw,compact] [--pure-after] [--clients 100] [--procs 2] [--duration 10]
        [--core-rooms 3] [--core-seconds 6] [--no-core] [--no-relay]
        [--hostile timestamp,fuzz,flood,never-reader,rooms] [--hostile-args "..."]
        [--nice -10] [--out DIR]
    python -m posecast.bench.sidebyside --summarize DIR

``OLD`` and ``NEW`` are checkouts, each with its own venv in ``.venv`` (``make
.venv/.installed-test``), e.g. ``git worktree add ../old b50f95a^``. Each round
runs, for each codec, every side one after the other (before, after, and with
``--pure-after`` the after checkout again with its compiled accelerator off),
so the machine's drift falls on both alike:

- **in process**: :mod:`posecast.bench.sidebyside_probe` in each side's venv
  (the method of ``python -m posecast.bench.core_cpu``, which old checkouts may
  not have), fed the same poses (one ``.npz`` written once); it also checks
  that both relays took the same bytes (CRC of every frame);
- **sockets**: ``posecast bench relay --clients N --procs P --duration D
  --codec C --json`` of each side's own CLI.

``uptime`` is recorded before and after every run. With ``--hostile``, ``posecast
bench hostile --attacks ...`` then runs once per side and its targets are set
side by side. Everything goes to ``--out``: ``runs.jsonl`` (one record a run),
each run's JSON and log, and ``summary.md`` (printed at the end; ``--summarize``
prints it again from ``runs.jsonl``).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["RELAY_FIGURES", "Side", "main", "summarize"]

PROBE = Path(__file__).with_name("sidebyside_probe.py")
CORE_FIGURES = ("us_per_pose", "us_receive", "us_tick", "us_take")
RELAY_FIGURES = (
    "server_cpu_us_per_pose",
    "server_cpu_pct",
    "relay_p50_ms",
    "relay_p99_ms",
    "latency_p99_ms",
    "snapshot_rate_ratio",
    "skips",
    "bytes_per_pose",
    "other_cpu_pct",
)
TIMEOUT_S = 1800.0


@dataclass(frozen=True)
class Side:
    """One column: a checkout, and whether its compiled codec is turned off."""

    label: str
    checkout: Path
    pure: bool = False

    def tool(self, name: str) -> str:
        return str(self.checkout / ".venv" / "bin" / name)

    def env(self) -> dict[str, str]:
        env = dict(os.environ)
        env.pop("POSECAST_PURE", None)
        if self.pure:
            env["POSECAST_PURE"] = "1"
        return env


def _uptime() -> str:
    try:
        got = subprocess.run(["uptime"], capture_output=True, text=True, timeout=10, check=True)
        return got.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "load average: " + ", ".join(Path("/proc/loadavg").read_text().split()[:3])


def _load1(uptime: str) -> float | None:
    try:
        return float(uptime.rsplit("load average:", 1)[1].split(",")[0])
    except (IndexError, ValueError):
        return None


def describe(checkout: Path) -> dict[str, str]:
    """The commit a checkout is at, and what its ``posecast --version`` says of its codec."""

    def out(*cmd: str) -> str:
        got = subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)
        return got.stdout.strip() if got.returncode == 0 else ""

    version = out(str(checkout / ".venv" / "bin" / "posecast"), "--version")
    codec = [line for line in version.splitlines() if line.startswith("codec:")]
    return {
        "checkout": str(checkout),
        "commit": out("git", "-C", str(checkout), "rev-parse", "HEAD"),
        "subject": out("git", "-C", str(checkout), "log", "-1", "--format=%s"),
        "codec": codec[0].removeprefix("codec:").strip() if codec else "no accelerator",
    }


def _run(
    cmd: list[str], side: Side, log: Path, nice: int, timeout: float = TIMEOUT_S
) -> tuple[int, float, str, str]:
    """Run ``cmd`` (under ``nice -n`` if ``nice``), its output to ``log``: exit code,
    wall seconds, ``uptime`` before and after."""
    if nice:
        cmd = ["nice", "-n", str(nice), *cmd]
    before, t = _uptime(), time.monotonic()
    with log.open("w") as f:
        f.write("$ " + shlex.join(cmd) + "\n")
        f.flush()
        try:
            code = subprocess.run(
                cmd, stdout=f, stderr=subprocess.STDOUT, env=side.env(), timeout=timeout
            ).returncode
        except subprocess.TimeoutExpired:
            code = -1
            f.write(f"\ntimed out after {timeout:.0f} s\n")
    return code, time.monotonic() - t, before, _uptime()


def _record(
    out: Path, bench: str, side: Side, codec: str, rnd: int, run: tuple[int, float, str, str]
) -> dict[str, Any]:
    code, seconds, before, after = run
    record: dict[str, Any] = {
        "bench": bench,
        "side": side.label,
        "codec": codec,
        "round": rnd,
        "at": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()),
        "seconds": round(seconds, 1),
        "uptime_before": before,
        "uptime_after": after,
        "ok": code == 0,
        "figures": {},
    }
    with (out / "runs.jsonl").open("a") as f:
        f.write(json.dumps(record) + "\n")
    return record


def _rewrite_last(out: Path, record: dict[str, Any]) -> None:
    lines = (out / "runs.jsonl").read_text().splitlines()
    lines[-1] = json.dumps(record)
    (out / "runs.jsonl").write_text("\n".join(lines) + "\n")


def run_core(side: Side, codec: str, rnd: int, args: argparse.Namespace) -> dict[str, Any]:
    """The in-process probe once on ``side``."""
    out: Path = args.out
    name = f"core-{side.label.replace(' ', '_')}-{codec}-{rnd}"
    cmd = [side.tool("python"), "-I", str(PROBE), "--codec", codec, "--traces"]
    cmd += [str(out / "traces.npz"), "--rooms", str(args.core_rooms)]
    cmd += ["--seconds", str(args.core_seconds)] + (["--pure"] if side.pure else [])
    record = _record(out, "core", side, codec, rnd, _run(cmd, side, out / f"{name}.log", args.nice))
    if record["ok"]:
        last = (out / f"{name}.log").read_text().strip().splitlines()[-1]
        record["figures"] = json.loads(last)
        _rewrite_last(out, record)
    return record


def run_relay(side: Side, codec: str, rnd: int, args: argparse.Namespace) -> dict[str, Any]:
    """``posecast bench relay`` once on ``side``."""
    out: Path = args.out
    name = f"relay-{side.label.replace(' ', '_')}-{codec}-{rnd}"
    cmd = [side.tool("posecast"), "bench", "relay", "--clients", str(args.clients)]
    cmd += ["--procs", str(args.procs), "--duration", str(args.duration), "--codec", codec]
    cmd += ["--json", str(out / f"{name}.json")]
    run = _run(cmd, side, out / f"{name}.log", args.nice)
    record = _record(out, "relay", side, codec, rnd, run)
    if record["ok"]:
        report = json.loads((out / f"{name}.json").read_text())
        figures = {k: report.get(k) for k in RELAY_FIGURES}
        figures["codec_implementation"] = report.get("codec_implementation", "not reported")
        figures["saturated_by"] = report.get("saturated_by")
        record["figures"] = figures
        _rewrite_last(out, record)
    return record


def run_hostile(side: Side, args: argparse.Namespace) -> dict[str, Any]:
    """``posecast bench hostile --attacks ...`` once on ``side``."""
    out: Path = args.out
    name = f"hostile-{side.label.replace(' ', '_')}"
    cmd = [side.tool("posecast"), "bench", "hostile", "--attacks", args.hostile]
    cmd += [*shlex.split(args.hostile_args), "--json", str(out / f"{name}.json")]
    # Exit 1 is the bench saying a target was missed: the report is still there.
    run = _run(cmd, side, out / f"{name}.log", args.nice)
    record = _record(out, "hostile", side, "", 0, run)
    path = out / f"{name}.json"
    if path.exists():
        report = json.loads(path.read_text())
        record["ok"] = True
        record["figures"] = {
            "targets": [
                {"attack": r["attack"], **t} for r in report["runs"] for t in r.get("targets", [])
            ],
            "missed": report.get("missed", []),
        }
        _rewrite_last(out, record)
    return record


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:,.3g}" if abs(value) < 100 else f"{value:,.0f}"
    return "-" if value is None else str(value)


def _cell(values: list[float]) -> tuple[float | None, str]:
    if not values:
        return None, "-"
    median = statistics.median(values)
    return median, f"{_fmt(median)} ({', '.join(_fmt(v) for v in values)})"


def _table(records: list[dict[str, Any]], bench: str, figures: tuple[str, ...]) -> list[str]:
    """Medians by codec and figure, a column per side (its rounds in brackets), ratios."""
    runs = [r for r in records if r["bench"] == bench and r["ok"]]
    if not runs:
        return []
    sides = list(dict.fromkeys(r["side"] for r in runs))
    head = ["codec", "figure", *sides, *(f"{s} / {sides[0]}" for s in sides[1:])]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for codec in dict.fromkeys(r["codec"] for r in runs):
        for figure in figures:
            medians, cells = [], []
            for side in sides:
                values = [
                    float(r["figures"][figure])
                    for r in runs
                    if r["side"] == side
                    and r["codec"] == codec
                    and isinstance(r["figures"].get(figure), int | float)
                ]
                median, cell = _cell(values)
                medians.append(median)
                cells.append(cell)
            base = medians[0]
            ratios = [f"{m / base:.2f}x" if m is not None and base else "-" for m in medians[1:]]
            lines.append("| " + " | ".join([codec, figure, *cells, *ratios]) + " |")
    return lines


def _notes(records: list[dict[str, Any]]) -> list[str]:
    """Load by side, the codec that ran, failures; connections sent the same bytes."""
    lines = []
    for side in dict.fromkeys(r["side"] for r in records):
        mine = [r for r in records if r["side"] == side]
        loads = [
            x for r in mine for x in (_load1(r["uptime_before"]), _load1(r["uptime_after"])) if x
        ]
        failed = sum(1 for r in mine if not r["ok"])
        impl = sorted(
            {
                f"{r['codec']}: {r['figures'].get('codec_implementation')}"
                for r in mine
                if r["bench"] == "relay" and r["ok"]
            }
        )
        lines.append(
            f"- {side}: {len(mine)} runs ({failed} failed), load average (1 min) "
            + (f"{min(loads):.2f}-{max(loads):.2f}" if loads else "-")
            + (f"; relay codec {'; '.join(impl)}" if impl else "")
        )
    return lines + _same_bytes(records)


def _same_bytes(records: list[dict[str, Any]]) -> list[str]:
    """How many connections each side's relay sent the same bytes as before's, in process."""
    core = [r for r in records if r["bench"] == "core" and r["ok"]]
    first: dict[tuple[str, str], list[str]] = {}
    for r in core:
        first.setdefault((r["side"], r["codec"]), r["figures"].get("conn_crcs", []))
    sides = list(dict.fromkeys(r["side"] for r in core))
    lines = []
    for side in sides[1:]:
        for codec in dict.fromkeys(r["codec"] for r in core):
            old, new = first.get((sides[0], codec)), first.get((side, codec))
            if old and new:
                same = sum(a == b for a, b in zip(old, new, strict=False))
                lines.append(
                    f"- in process, {codec}: {side}'s relay sent {same} of {len(old)} "
                    f"connections the same bytes as {sides[0]}'s"
                )
    return lines


def _hostile(records: list[dict[str, Any]]) -> list[str]:
    runs = [r for r in records if r["bench"] == "hostile" and r["ok"]]
    if not runs:
        return []
    keys = list(
        dict.fromkeys((t["attack"], t["target"]) for r in runs for t in r["figures"]["targets"])
    )
    lines = ["| attack | target | " + " | ".join(r["side"] for r in runs) + " |"]
    lines.append("|" + "---|" * (2 + len(runs)))
    for attack, target in keys:
        cells = []
        for r in runs:
            got = [
                t for t in r["figures"]["targets"] if (t["attack"], t["target"]) == (attack, target)
            ]
            cells.append(
                f"{got[0]['value']:.2f} {'met' if got[0]['met'] else '**MISSED**'}" if got else "-"
            )
        lines.append(f"| {attack} | {target} | " + " | ".join(cells) + " |")
    return lines


def summarize(out: Path) -> str:
    """The markdown summary of the runs recorded in ``out/runs.jsonl``."""
    records = [json.loads(line) for line in (out / "runs.jsonl").read_text().splitlines() if line]
    meta = json.loads((out / "meta.json").read_text()) if (out / "meta.json").exists() else {}
    parts = [f"# Side by side ({out})", ""]
    for label, info in meta.get("sides", {}).items():
        parts.append(f"- {label}: {info['commit'][:10]} {info['subject']!r}, codec {info['codec']}")
    if "command" in meta:
        parts.append(f"- command: `{meta['command']}`")
    parts += ["", *_notes(records), ""]
    core = _table(records, "core", CORE_FIGURES)
    if core:
        parts += ["## In process (relay core CPU, us per remote pose)", "", *core, ""]
    relay = _table(records, "relay", RELAY_FIGURES)
    if relay:
        parts += ["## posecast bench relay", "", *relay, ""]
    hostile = _hostile(records)
    if hostile:
        parts += ["## posecast bench hostile", "", *hostile, ""]
    return "\n".join(parts)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    parser.add_argument("--before", type=Path, help="the old checkout (with .venv)")
    parser.add_argument("--after", type=Path, help="the new checkout (with .venv)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--codecs", default="raw,compact")
    parser.add_argument("--pure-after", action="store_true", help="also the after, pure Python")
    parser.add_argument("--clients", type=int, default=100)
    parser.add_argument("--procs", type=int, default=2)
    parser.add_argument("--duration", type=float, default=10.0)
    parser.add_argument("--core-rooms", type=int, default=3)
    parser.add_argument("--core-seconds", type=float, default=6.0)
    parser.add_argument("--no-core", action="store_true", help="skip the in-process runs")
    parser.add_argument("--no-relay", action="store_true", help="skip posecast bench relay")
    parser.add_argument("--hostile", default="", help="attacks for posecast bench hostile")
    parser.add_argument("--hostile-args", default="", help="more options for bench hostile")
    parser.add_argument("--nice", type=int, default=0, help="run every bench under nice -n N")
    parser.add_argument("--out", type=Path, help="where the runs go")
    parser.add_argument("--summarize", type=Path, metavar="DIR", help="print DIR's summary")
    return parser


def main(argv: list[str] | None = None) -> None:
    args = _parser().parse_args(argv)
    if args.summarize:
        print(summarize(args.summarize))
        return
    if args.before is None or args.after is None:
        raise SystemExit("sidebyside: give --before and --after (checkouts with a .venv)")
    for checkout in (args.before, args.after):
        if not (checkout / ".venv" / "bin" / "posecast").exists():
            raise SystemExit(f"sidebyside: {checkout} has no .venv/bin/posecast")
    sides = [Side("before", args.before.resolve()), Side("after", args.after.resolve())]
    if args.pure_after:
        sides.append(Side("after, pure", args.after.resolve(), pure=True))
    args.out = args.out or Path(time.strftime("sidebyside-%Y%m%d-%H%M%S", time.gmtime()))
    args.out.mkdir(parents=True, exist_ok=True)
    described = {s.label: describe(s.checkout) for s in sides}
    for s in sides:
        if s.pure:
            described[s.label]["codec"] = "pure Python (POSECAST_PURE=1)"
    meta = {
        "sides": described,
        "command": shlex.join(
            ["python", "-m", "posecast.bench.sidebyside", *(argv or sys.argv[1:])]
        ),
    }
    (args.out / "meta.json").write_text(json.dumps(meta, indent=1))
    if not args.no_core:
        save = [sides[1].tool("python"), "-I", str(PROBE), "--save-traces"]
        subprocess.run([*save, str(args.out / "traces.npz")], check=True, timeout=300)
    codecs = [c.strip() for c in args.codecs.split(",") if c.strip()]
    for rnd in range(1, args.rounds + 1):
        for bench, go in (("core", run_core), ("relay", run_relay)):
            if getattr(args, f"no_{bench}"):
                continue
            for codec in codecs:
                for side in sides:
                    if side.pure and codec != "compact":
                        continue
                    r = go(side, codec, rnd, args)
                    print(
                        f"round {rnd} {bench} {codec} {side.label}: ok={r['ok']} "
                        f"{r['seconds']} s, {r['uptime_before'].split('load')[-1]}",
                        flush=True,
                    )
    if args.hostile:
        for side in sides[:2]:
            r = run_hostile(side, args)
            print(f"hostile {side.label}: ok={r['ok']} {r['seconds']} s", flush=True)
    summary = summarize(args.out)
    (args.out / "summary.md").write_text(summary + "\n")
    print(summary)


if __name__ == "__main__":
    main()
