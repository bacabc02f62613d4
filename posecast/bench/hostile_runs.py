"""What ``posecast bench hostile`` adds around the attacks of issue 29.

- the runs: ``churn`` and ``lag-liar`` run once per rate and per lag
  (:func:`plan`), each beside the same clean run;
- the relay's own log: tracebacks in its stderr (:func:`tracebacks`), counted in
  every run (the target is 0);
- ``/healthz``, polled with the ``/metrics`` scrapes (:func:`healthz`);
- the blackholed bot: ``posecast bots --n 1`` through the attacker's proxy, beside
  the honest room, and what it reported (:func:`victim_argv`, :func:`victim_figures`);
- the targets of issue 29 (:func:`targets_29`): 0 tracebacks, no honest bot
  closed, honest hands p95, D and snapshot rate within 25 % of clean (D within
  10 % under the lag-liar), the hijack refused and the victim resumed,
  ``/healthz`` answering through the slowloris, the blackholed bot back.
"""

from __future__ import annotations

import math
import secrets
import sys
import time
import urllib.request
from pathlib import Path
from typing import TYPE_CHECKING, Any

from posecast.bench.common import _SERVER_BOOT
from posecast.bench.hostile_config import WAIT_FOR_BOTS, HostileConfig, RunSpec, victim_seconds

if TYPE_CHECKING:
    from posecast.bench.procs import _Child

__all__ = [
    "Signal",
    "healthz",
    "hook",
    "plan",
    "targets_29",
    "tracebacks",
    "victim_figures",
]

#: Issue 29's bounds: ratios to the clean run.
QOE_RATIO_29 = 1.25
LIAR_DELAY_RATIO = 1.10
RATE_RATIO_29 = 0.75


def plan(cfg: HostileConfig) -> list[RunSpec]:
    """The clean run, then every attack (churn once per rate, lag-liar once per lag)."""
    runs = [RunSpec(None)]
    for kind in cfg.attacks:
        if kind == "churn":
            runs += [RunSpec(kind, r) for r in cfg.churn_rates]
        elif kind == "lag-liar":
            runs += [RunSpec(kind, lag) for lag in cfg.liar_lags]
        else:
            runs.append(RunSpec(kind))
    return runs


def secret_file(folder: Path) -> Path:
    """A fresh relay secret in a file of ``folder`` (for the resume-hijack run)."""
    path = folder / "secret"
    path.write_text(secrets.token_urlsafe(24) + "\n")
    path.chmod(0o600)
    return path


def tracebacks(child: _Child) -> int:
    """Tracebacks the child has written to its stderr so far."""
    try:
        child.stderr_file.seek(0)
        return child.stderr_file.read().count(b"Traceback (most recent call last)")
    except (OSError, ValueError):
        return -1


def healthz(port: int, timeout: float) -> float | None:
    """Seconds ``GET /healthz`` took to answer 200, or None if it did not in time."""
    start = time.monotonic()
    try:
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/healthz", timeout=timeout) as r:
            r.read()
            ok = r.status == 200
    except OSError:
        return None
    return time.monotonic() - start if ok else None


class Signal:
    """A sampling hook: tell the attacker ``name`` (a stdin line) ``after`` s after the
    relay first holds ``need`` connections (the honest bots, and the blackholed one)."""

    def __init__(self, attacker: _Child, name: str, need: int, after: float = 0.0) -> None:
        self.attacker, self.name, self.need, self.after = attacker, name, need, after
        self.full_at: float | None = None
        self.done = False

    def __call__(self, samples: Any) -> None:
        now, last = time.monotonic(), samples.last or {}
        if self.full_at is None and last.get("posecast_connections", 0) >= self.need:
            self.full_at = now
        if not self.done and self.full_at is not None and now >= self.full_at + self.after:
            self.attacker.tell({"signal": self.name})
            self.done = True


def hook(attacker: _Child, kind: str, cfg: HostileConfig) -> Signal | None:
    """The signal the attacker ``kind`` waits for, if any."""
    if kind == "blackhole":
        return Signal(attacker, "cut", cfg.bots + 1, cfg.blackhole_after)
    if kind in WAIT_FOR_BOTS:
        return Signal(attacker, "go", cfg.bots)
    return None


def victim_argv(cfg: HostileConfig, proxy_port: int, json_path: Path) -> list[str]:
    """One honest bot (``posecast bots --n 1``) whose path runs through the proxy."""
    return [
        *(sys.executable, "-c", _SERVER_BOOT, "bots", "--url", f"ws://127.0.0.1:{proxy_port}"),
        *("--n", "1", "--room", cfg.room, "--rate", f"{cfg.rate:g}"),
        *("--send-rate", f"{cfg.send_rate:g}", "--duration", f"{victim_seconds(cfg):g}"),
        *("--motion", cfg.motion, "--interp", cfg.method, "--codec", "compact"),
        *("--json", str(json_path)),
    ]


def victim_figures(victim: _Child, json_path: Path, seconds: float) -> dict[str, Any]:
    """Wait for the blackholed bot to end; how it ended and what it reported."""
    deadline = time.monotonic() + seconds + 60.0
    while victim.proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    code = victim.stop(grace=10.0)
    if not json_path.exists():
        return {"exit_code": code, "report": False}
    import json

    report = json.loads(json_path.read_text())
    (bot,) = report["bots"]
    return {
        "exit_code": code,
        "report": True,
        "seconds": seconds,
        "ended": bot["ended"],
        "complete": bool(report["ending"]["complete"]),
        "resumed": bot["resumed"],
        "rejoined": bot["rejoined"],
        "stale_s": bot["stale_s"],
        "stall_share": bot["stale_s"] / seconds,
        "render_stall_fraction": bot["render_stall_fraction"],
        "rate_hz": bot["rate_hz"],
        "snapshot_gap_s": bot["snapshot_gap_s"],
    }


def closed_bots(report: dict[str, Any]) -> int:
    """Honest bots the relay closed or lost (not ``complete``, not ``stalled``); all of
    them if they wrote no report (e.g. their join was refused)."""
    if "failed" in report:
        return int(report["n"])
    ends = [str(b.get("ended", "")) for b in report.get("bots", [])]
    return sum(not e.startswith(("complete", "stalled", "interrupted")) for e in ends)


def targets_29(run: dict[str, Any], check: Any) -> None:
    """Issue 29's targets for ``run`` (an attack of issue 29), through ``check(what,
    value, met)``."""
    kind, vs, h = run["attack"], run["vs_clean"], run["honest"]
    check(
        "0 tracebacks in the relay's log",
        run["server"]["tracebacks"],
        not run["server"]["tracebacks"],
    )
    check("no honest bot closed", h["closed"], h["closed"] == 0)
    check(
        "hands p95 within 25 % of clean", vs["hands_tip_p95"], vs["hands_tip_p95"] <= QOE_RATIO_29
    )
    bound = LIAR_DELAY_RATIO if kind == "lag-liar" else QOE_RATIO_29
    check(f"D within {round(100 * (bound - 1))} % of clean", vs["delay"], vs["delay"] <= bound)
    check("snapshot rate within 25 % of clean", vs["rate"], vs["rate"] >= RATE_RATIO_29)
    got = run.get("attacker", {})
    if kind == "resume-hijack":
        hijack = got.get("hijack", {})
        tries = float(sum(hijack.get("tries", {}).values()))
        accepted = float(sum(hijack.get("accepted", {}).values()))
        check("hijack refused (every try)", accepted, tries > 0 and accepted == 0)
        victim = got.get("victim", {})
        back, rounds = float(victim.get("resumed", 0)), float(got.get("rounds", 0))
        check("victim resumed (every round)", back, rounds > 0 and back == rounds)
    if kind == "slowloris":
        s = run["server"]
        missed = float(s["healthz_unanswered"])
        check("/healthz answered through the run", missed, s["healthz_polls"] > 0 and missed == 0)
    if kind == "blackhole":
        v = run.get("victim", {})
        back = float(got.get("bot_back_after_s", math.nan))
        came = v.get("resumed", 0) + v.get("rejoined", 0) > 0
        check("blackholed bot noticed and came back (s after)", back, came and math.isfinite(back))
        # The bot says "stalled" over half its own run without fresh poses (its run
        # starts a little after this run's clock: a small allowance).
        share = float(v.get("stall_share", math.nan))
        honest = not v.get("complete") or share <= 0.55
        check("its stall reported (share; not complete over half)", share, share > 0 and honest)
