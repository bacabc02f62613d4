"""posecast table1 --live: a real relay with link emulation and real bots beside offline."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from typer.testing import CliRunner

from posecast.cli import app
from posecast.scenarios.live_agreement import Tolerance
from posecast.scenarios.network import load_tiers
from posecast.table1_live import LiveConfig, live_motions, run_live_tier

runner = CliRunner()


async def test_short_live_run_agrees_with_offline(sample_dir: Path) -> None:
    """Two trace bots, 6 s through a mediocre link: live and offline agree within tolerance.

    The mediocre tier without its loss: in a run this short, which few snapshots
    two independent loss draws hit decides the hands' p95 (the eval run covers
    the lossy tiers over longer runs). The offline counterpart sees neither the
    live arrivals nor the live keyframes: only the tier, the room's grid, the
    senders' start times and each bot's D.
    """
    tier = replace(load_tiers()["mediocre"], name="mediocre-lossless", loss_pct=0.0)
    motions = live_motions([str(sample_dir)])
    row = await run_live_tier(tier, motions, LiveConfig(duration=6.0, bots=2))
    failed = [c for c in row["agreement"]["checks"] if not c["ok"]]
    assert row["agreement"]["pass"], failed
    live, offline = row["live"], row["offline"]
    # What was compared: every method and class at both D, the server's own rate choice.
    assert set(live["methods_ample"]) == set(offline["methods_ample"]) == set(LiveConfig().methods)
    assert set(live["methods"]["soa"]) == {"hands", "head"}
    assert live["server_rate_hz"] == pytest.approx(tier.max_rate_hz)
    assert live["methods"]["soa"]["hands"]["tip_p95_mm"] > 0
    assert len(row["bots"]) == 2 and all(b["rate_hz"] > 0 for b in row["bots"])


def test_live_config_refuses_what_cannot_run() -> None:
    """One bot, a non-positive duration or a velocity method are refused with the reason."""
    with pytest.raises(ValueError, match="at least 2 bots"):
        LiveConfig(bots=1)
    with pytest.raises(ValueError, match="duration"):
        LiveConfig(duration=0)
    with pytest.raises(ValueError, match="velocities"):
        LiveConfig(methods=("soa", "motor-hermite"))


def _run_cli(args: list[str]) -> Any:
    return runner.invoke(app, ["table1", *args])


def test_table1_live_command_writes_the_live_key(dev_trace_path: Path, tmp_path: Path) -> None:
    """posecast table1 --live keeps the offline JSON and adds "live" with every tier's verdict."""
    out = tmp_path / "t1"
    res = _run_cli(
        [
            "--traces",
            str(dev_trace_path),
            "--rates",
            "10,20,30",
            "--out",
            str(out),
            "--no-link",
            "--no-bench",
            "--no-plots",
            "--no-frontier",
            "--live",
            "--live-duration",
            "2.5",
            "--live-bots",
            "2",
        ]
    )
    data = json.loads((out / "table1.json").read_text())
    live = data["live"]
    # The exit code follows the verdict: 0 when every tier agrees, 1 otherwise.
    assert res.exit_code == (0 if live["pass"] else 1), res.output
    assert {"curves", "tiers", "paper", "config"} <= set(data)
    assert [t["tier"] for t in live["tiers"]] == ["excellent", "good", "mediocre", "poor"]
    assert live["config"]["tolerance"] == Tolerance().as_dict()
    for t in live["tiers"]:
        assert {"live", "offline", "agreement"} <= set(t)
        assert t["agreement"]["pass"] == all(c["ok"] for c in t["agreement"]["checks"])
        assert set(t["live"]["methods"]) == {"soa", "dq-slerp", "motor-lerp"}
    md = (out / "table1.md").read_text()
    assert "## Live vs offline" in md and "Verdict:" in md
    assert "Live vs offline" in res.output


def test_table1_live_refuses_a_synthetic_suite_before_the_sweep(tmp_path: Path) -> None:
    """A synthetic suite has no live counterpart: exit 2 with the reason, nothing written."""
    out = tmp_path / "t1"
    res = _run_cli(["--traces", "synthetic", "--out", str(out), "--live"])
    assert res.exit_code == 2
    assert "--live" in res.output and "synthetic suite" in res.output
    assert not (out / "table1.json").exists()


@pytest.mark.parametrize("budget", [None, 2.0])
async def test_live_auto_runs_the_tier_again_with_the_relays_rates(
    sample_dir: Path, budget: float | None
) -> None:
    """LiveConfig(auto=True): the tier once more with auto rates (and, with a budget,
    each peer at the rate its view needs). On a link that carries about 15 Hz of 2-bot
    raw snapshots, the relay brings the bots down from 30 Hz and keeps the link's
    bytes/s within its cap; the fixed run and its verdict are as before."""
    tier = replace(load_tiers()["mediocre"], name="narrow", max_rate_hz=10.0,
                   bandwidth_kbps=34.0, loss_pct=0.0)  # fmt: skip
    motions = live_motions([str(sample_dir)])
    cfg = LiveConfig(duration=5.0, bots=2, auto=True, budget_deg=budget)
    row = await run_live_tier(tier, motions, cfg)
    assert {"live", "offline", "agreement", "auto"} <= set(row)
    auto = row["auto"]
    budget_text = "" if budget is None else ", budget 2 deg"
    assert auto["asked"] == "auto (up to 30 Hz)" + budget_text
    assert 5.0 <= auto["server_rate_low_hz"] < 30.0
    assert auto["server_rate_low_hz"] <= auto["server_rate_mean_hz"] <= auto["server_rate_high_hz"]
    assert auto["bytes_per_s"] <= 1.05 * tier.bytes_per_s
    assert auto["methods"]["soa"]["hands"]["tip_p95_mm"] > 0
    assert row["live"]["server_rate_hz"] == pytest.approx(tier.max_rate_hz)


def test_live_auto_needs_live(tmp_path: Path) -> None:
    res = _run_cli(["--traces", "traces:sample", "--out", str(tmp_path / "t1"), "--live-auto"])
    assert res.exit_code == 2 and "give --live too" in res.output


def test_live_budget_needs_live_auto_and_a_valid_angle(tmp_path: Path) -> None:
    """--live-budget-deg: one line, before any work, without --live-auto or out of range."""
    base = ["--traces", "traces:sample", "--out", str(tmp_path / "t1"), "--live"]
    res = _run_cli([*base, "--live-budget-deg", "2"])
    assert res.exit_code == 2 and "give --live-auto too" in res.output
    res = _run_cli([*base, "--live-auto", "--live-budget-deg", "95"])
    assert res.exit_code == 2 and "budget must be in (0, 90) degrees" in res.output
    assert not (tmp_path / "t1" / "table1.json").exists()
    with pytest.raises(ValueError, match="ask for auto rates too"):
        LiveConfig(budget_deg=2.0)
