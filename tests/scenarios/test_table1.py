"""Table 1: equal-QoE rate arithmetic, the running-time bench, and a small end-to-end run."""

from __future__ import annotations

import gzip
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from posecast.scenarios.network import Tier, builtin_tiers, wire_bytes
from posecast.scenarios.synthetic import synthetic_motion
from posecast.scenarios.table1 import (
    PAPER,
    Table1Interrupted,
    describe_rates,
    equal_qoe_rate,
    receiver_cpu_time,
    run_table1,
    saving_pct,
    snapped_range,
    tier_rate,
)
from posecast.scenarios.traces import TraceError, load_trace

STAT_KEYS = {"pos_p50_mm", "pos_p95_mm", "rot_p50_deg", "rot_p95_deg", "tip_p50_mm", "tip_p95_mm"}


def test_equal_qoe_rate_is_the_lowest_rate_no_worse_than_the_reference() -> None:
    """The lowest rate whose headline is <= the reference; equality counts as no worse."""
    curve = {5: 90.0, 6: 70.0, 7: 50.0, 8: 40.0, 9: 30.0}
    assert equal_qoe_rate(curve, 50.0) == 7
    assert equal_qoe_rate(curve, 49.9) == 8
    assert equal_qoe_rate(curve, 1000.0) == 5


def test_equal_qoe_rate_is_none_when_no_rate_reaches_the_reference() -> None:
    """None when even the highest rate is worse; NaN headlines never qualify."""
    assert equal_qoe_rate({5: 9.0, 6: 8.0}, 7.0) is None
    assert equal_qoe_rate({5: math.nan, 6: 6.0}, 7.0) == 6
    assert equal_qoe_rate({5: 1.0}, math.nan) is None


def test_equal_qoe_rate_searches_only_the_given_rates() -> None:
    """Rates outside the search range are ignored even if they qualify."""
    curve = {4: 1.0, 5: 9.0, 6: 5.0, 40: 0.1}
    assert equal_qoe_rate(curve, 5.0, rates=range(5, 31)) == 6
    assert equal_qoe_rate(curve, 0.5, rates=range(5, 31)) is None


def test_saving_is_one_minus_the_ratio_in_percent() -> None:
    """Bandwidth saving = 100 (1 - r_method / r_soa); the paper's tiers give 33/50/53/58 %."""
    got = [round(saving_pct(p["ga_rate"], p["soa_rate"]) or 0.0) for p in PAPER["tiers"]]
    assert got == [p["bandwidth_saving_pct"] for p in PAPER["tiers"]]
    assert saving_pct(None, 30) is None
    assert saving_pct(33.0, 30.0) == pytest.approx(-10.0)


def test_tier_rate_is_capped_by_the_bandwidth() -> None:
    """SoA runs at the tier's max rate unless the cap cannot carry the room's snapshots."""
    tiers = builtin_tiers()
    assert [tier_rate(t, wire_bytes(48)) for t in tiers.values()] == [30, 20, 15, 12]
    small = Tier("thin", 30, 80.0, 10, 1, 0)  # 10 000 B/s
    assert tier_rate(small, 1000) == 10


def test_receiver_bench_counts_the_work() -> None:
    """The bench decodes rate x seconds snapshots and renders render_hz x seconds frames."""
    out = receiver_cpu_time("dq-slerp", 10.0, streams=6, seconds=0.5, repeats=1)
    assert out["snapshots"] == 6 and out["frames"] == 45 and out["streams"] == 6
    assert out["decode_s"] > 0 and out["render_s"] > 0
    assert out["total_s"] == pytest.approx(out["decode_s"] + out["render_s"], rel=0.5)


def _strict_json(path: Path) -> Any:
    def refuse(token: str) -> None:
        raise AssertionError(f"non-JSON constant {token} in {path}")

    return json.loads(path.read_text(), parse_constant=refuse)


def test_small_real_run_writes_the_documented_report(dev_trace_path: Path, tmp_path: Path) -> None:
    """A dev-trace window at a few rates writes table1.md/json and plots of the documented shape."""
    trace = load_trace(dev_trace_path).window(20.0, 32.0)
    seen: list[str] = []
    report = run_table1(
        [trace],
        rates=[10, 20],
        out_dir=tmp_path,
        progress=lambda stage, done, total: seen.append(stage),
        bench_seconds=0.2,
        bench_repeats=1,
    )
    for name in ("table1.md", "table1.json", "qoe_vs_rate.png", "error_cdf.png"):
        assert (tmp_path / name).stat().st_size > 0, name
    data = _strict_json(tmp_path / "table1.json")
    assert set(data) >= {"curves", "tiers", "paper"}
    assert set(data["curves"]) == {"soa", "dq-slerp", "motor-lerp"}
    for method in data["curves"].values():
        # searched rates, the tiers' SoA rates and the paper's rates, as strings of integers
        assert set(method) == {"5", "7", "10", "12", "15", "20", "30"}
        for classes in method.values():
            assert set(classes["hands"]) >= STAT_KEYS and set(classes["head"]) >= STAT_KEYS
    assert [t["name"] for t in data["tiers"]] == ["excellent", "good", "mediocre", "poor"]
    for row in data["tiers"]:
        assert set(row) >= {
            "name",
            "soa_rate",
            "equal_qoe_rate",
            "bandwidth_saving_pct",
            "running_time_saving_pct",
        }
        for key in ("equal_qoe_rate", "bandwidth_saving_pct", "running_time_saving_pct"):
            assert set(row[key]) == {"soa", "dq-slerp", "motor-lerp"}
        r = row["equal_qoe_rate"]["dq-slerp"]
        assert r is None or r in (10, 20)
    assert data["paper"]["running_time_saving_pct"] == 16.5
    assert data == report
    assert "ideal" in seen and any(s.startswith("link:") for s in seen)
    md = (tmp_path / "table1.md").read_text()
    assert "| excellent | 30 |" in md and "Through each tier's link model" in md


def test_screw_motion_needs_the_lowest_rate_with_dq_slerp() -> None:
    """On a constant screw dq-slerp is exact, so its equal-QoE rate is 5 Hz in every tier."""
    report = run_table1(
        [synthetic_motion("screw", 0, duration_s=10.0)],
        rates=range(5, 31),
        methods=["dq-slerp"],
        link=False,
        bench=False,
    )
    for row in report["tiers"]:
        assert row["equal_qoe_rate"]["dq-slerp"] == 5
        assert row["bandwidth_saving_pct"]["dq-slerp"] == pytest.approx(
            100 * (1 - 5 / row["soa_rate"])
        )
        assert row["equal_qoe_rate"]["soa"] == row["soa_rate"]


def test_objects_are_reported_as_their_own_class() -> None:
    """Synthetic scenes with objects get an 'objects' curve and per-class equal-QoE rates."""
    report = run_table1(
        [synthetic_motion("drill", 0, duration_s=8.0)],
        rates=[12, 15],
        link=False,
        bench=False,
    )
    assert "objects" in report["curves"]["soa"]["15"]
    assert set(report["tiers"][0]["equal_qoe_rate_by_class"]) == {"hands", "head", "objects"}


def test_run_table1_writes_a_report_for_a_csv_path(dev_trace_path: Path, tmp_path: Path) -> None:
    """run_table1 on a CSV path writes table1.md; a missing file is refused with TraceError."""
    short = tmp_path / "short.csv"
    with gzip.open(dev_trace_path, "rt") as f:
        head = f.read().splitlines(keepends=True)[:900]
    short.write_text("".join(head))
    run_table1(
        [str(short)],
        rates=[12, 20],
        out_dir=tmp_path,
        link=False,
        bench=False,
        plots=False,
    )
    assert "Table 1" in (tmp_path / "table1.md").read_text()
    with pytest.raises(TraceError):
        run_table1([str(tmp_path / "missing.csv")], out_dir=tmp_path)


def test_bad_rates_and_methods_are_refused_before_any_work() -> None:
    """Non-integer rates and unknown interpolators raise ValueError naming the problem."""
    trace = synthetic_motion("screw", 0, duration_s=2.0)
    with pytest.raises(ValueError, match="positive integers"):
        run_table1([trace], rates=[7.5], link=False, bench=False)
    with pytest.raises(ValueError, match="unknown interpolator"):
        run_table1([trace], rates=iter([10]), methods=["cubic"], link=False, bench=False)


def test_every_interpolator_kind_runs_with_its_own_delay_and_bytes(dev_trace_path: Path) -> None:
    """Window and velocity methods get their look-ahead in D and their bytes in the savings."""
    trace = load_trace(dev_trace_path).window(20.0, 35.0)
    report = run_table1(
        [trace],
        rates=[10, 15, 20],
        methods=["motor-cubic", "motor-hermite"],
        link=False,
        bench=False,
        frontier=False,
    )
    cfg = report["config"]
    assert cfg["lookahead"] == {"soa": 0, "motor-cubic": 1, "motor-hermite": 0}
    assert cfg["wire_bytes_by_method"]["motor-hermite"] == wire_bytes(48, 12) == 2460
    assert cfg["wire_bytes_by_method"]["motor-cubic"] == wire_bytes(48) == 1884
    for row in report["tiers"]:
        lat = row["latency_at_equal_rate_ms"]
        for m in ("motor-cubic", "motor-hermite"):
            r = row["equal_qoe_rate"][m]
            if r is None:
                assert row["bytes_saving_pct"][m] is None
                continue
            # One interval plus the look-ahead, plus one native frame of capture lag.
            la = cfg["lookahead"][m]
            assert lat[m] == pytest.approx(1000 * ((1 + la) / r + 1 / trace.native_rate), rel=1e-6)
            want = 100 * (1 - r * cfg["wire_bytes_by_method"][m] / (row["soa_rate"] * 1884))
            assert row["bytes_saving_pct"][m] == pytest.approx(want)
        assert row["running_time_saving_pct"]["motor-hermite"] is None


def test_velocity_keyframes_are_float16_and_accurate_enough(dev_trace_path: Path) -> None:
    """The velocity variant rounds to float16: under 0.05 % of the value, far below what matters."""
    from posecast.scenarios.table1 import VELOCITY_SOURCE, keyframe_velocities

    trace = load_trace(dev_trace_path)
    for source in ("causal", "central"):
        exact = trace.velocities_from(source)
        sent = keyframe_velocities(trace, source)
        assert np.array_equal(sent, sent.astype(np.float16).astype(np.float64))
        rel = np.abs(sent - exact) / np.maximum(np.abs(exact), 1e-3)
        assert float(rel.max()) <= 2.0**-11
    # The default is what a live sender can report at capture time.
    assert VELOCITY_SOURCE == "causal"
    np.testing.assert_array_equal(keyframe_velocities(trace), keyframe_velocities(trace, "causal"))


def test_link_sweep_sends_velocity_methods_through_the_link(dev_trace_path: Path) -> None:
    """Through a tier's link every method has its own D, bytes/s and network figures."""
    trace = load_trace(dev_trace_path).window(20.0, 30.0)
    tier = {"poor": builtin_tiers()["poor"]}
    report = run_table1(
        [trace],
        rates=[10, 12],
        methods=["motor-cubic", "motor-hermite"],
        tiers=tier,
        bench=False,
        frontier=False,
        plots=False,
    )
    (row,) = report["link"]
    at = row["at_soa_rate"]
    assert at["motor-cubic"]["playout_delay_ms"] == pytest.approx(
        at["soa"]["playout_delay_ms"] + 1000 / 12, rel=1e-6
    )
    assert at["motor-hermite"]["bytes_per_s"] == 12 * 2460
    assert at["soa"]["bytes_per_s"] == 12 * 1884


# -- reduced rate lists: say what was swept, and what a sparse list means -------------------


def test_describe_rates_names_a_1_hz_range_only_when_it_is_one() -> None:
    """A contiguous list is a range in 1 Hz steps; anything else is listed."""
    assert describe_rates(range(5, 31)) == "5-30 Hz in 1 Hz steps"
    assert describe_rates([30, 10, 20]) == "10, 20, 30 Hz"
    assert describe_rates([5, 6, 7, 8, 10, 20, 21]) == "5-8, 10, 20, 21 Hz"
    assert describe_rates([12]) == "12 Hz"


def test_snapped_range_is_the_gap_below_a_listed_rate() -> None:
    """Found on 10, 20, 30: 20 means somewhere in 11..20; the lowest listed rate is not snapped."""
    assert snapped_range(20, [10, 20, 30]) == (11, 20)
    assert snapped_range(30, [10, 20, 30]) == (21, 30)
    assert snapped_range(10, [10, 20, 30]) is None
    assert snapped_range(12, range(5, 31)) is None
    assert snapped_range(None, [10, 20]) is None


QUICK = ("--no-link", "--no-bench", "--no-plots", "--no-frontier")


def _sparse_run(tmp_path: Path, rates: list[int]) -> tuple[dict[str, Any], str]:
    report = run_table1(
        [synthetic_motion("drill", 0, duration_s=8.0)],
        rates=rates,
        out_dir=tmp_path,
        link=False,
        bench=False,
        plots=False,
        frontier=False,
    )
    return report, (tmp_path / "table1.md").read_text()


def test_report_of_a_sparse_rate_list_says_which_rates_and_marks_snapped_cells(
    tmp_path: Path,
) -> None:
    """--rates 5,10,20,30: no "1 Hz steps" claim; snapped equal-QoE rates are marked ≤."""
    report, md = _sparse_run(tmp_path, [5, 10, 20, 30])
    assert "1 Hz steps" not in md
    assert "Rates 5, 10, 20, 30 Hz" in md
    assert "the true rate may lie between listed rates" in md
    assert "not searched: 7, 12, 15 Hz" in md  # tier and paper rates measured beside
    cfg = report["config"]
    assert cfg["rates"] == [5, 10, 20, 30] and cfg["rates_contiguous"] is False
    marked = 0
    for row in report["tiers"]:
        for m, r in row["equal_qoe_rate"].items():
            snapped = row["equal_qoe_rate_snapped"][m]
            if r is None or r == 5:
                assert snapped is None
            else:
                # found at a listed rate above a gap: the 1 Hz-step rate is in (below, r]
                assert snapped == [{10: 6, 20: 11, 30: 21}[r], r]
                marked += 1
            if m != "soa" and snapped is not None:
                assert f"| ≤{r} |" in md.split(f"| {row['name']} | {row['soa_rate']} |")[1]
    assert marked > 0  # the drill needs more than 5 Hz, so some cell is snapped


def test_report_of_a_contiguous_range_keeps_the_1_hz_wording(tmp_path: Path) -> None:
    """A 1 Hz range is described as one, and nothing is marked as snapped."""
    report, md = _sparse_run(tmp_path, list(range(10, 16)))
    assert "Rates 10-15 Hz in 1 Hz steps" in md
    assert "between listed rates" not in md and "≤" not in md
    assert report["config"]["rates_contiguous"] is True
    for row in report["tiers"]:
        assert set(row["equal_qoe_rate_snapped"].values()) == {None}


def test_run_table1_with_sparse_rates_prints_nothing_and_notes_the_gaps(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """run_table1 with sparse rates: nothing printed; the rates and the snapping note reported."""
    report = run_table1(
        ["synthetic:drill"],
        rates=[5, 10, 20, 30],
        out_dir=tmp_path,
        link=False,
        bench=False,
        plots=False,
        frontier=False,
    )
    out, err = capsys.readouterr()
    assert out == "" and err == ""
    assert describe_rates(report["config"]["rates"]) == "5, 10, 20, 30 Hz"
    assert "the true rate may lie between listed rates" in (tmp_path / "table1.md").read_text()


def test_posecast_table1_prints_readable_lines_not_json(tmp_path: Path) -> None:
    """`posecast table1 --rates 10,20,30`: the summary table and plain notes, no JSON dump."""
    from typer.testing import CliRunner

    from posecast.cli import app

    args = ["--traces", "synthetic:drill", "--rates", "5,10,20,30", "--out", str(tmp_path)]
    res = CliRunner().invoke(app, ["table1", *args, *QUICK])
    assert res.exit_code == 0, res.output
    for line in res.output.splitlines():
        assert not line.lstrip().startswith(("{", "[")) and '": ' not in line, line
    assert "rates swept: 5, 10, 20, 30 Hz" in res.output
    assert "≤" in res.output and "between listed rates" in res.output
    assert "16.5 % less running time" in res.output
    assert "and plots" not in res.output  # --no-plots: none written
    assert "1 Hz steps" not in (tmp_path / "table1.md").read_text()


@pytest.mark.parametrize("stop_at", ["ideal 2", "link"])
def test_an_interrupted_run_keeps_what_it_measured(stop_at: str, tmp_path: Path) -> None:
    """Ctrl-C (a KeyboardInterrupt from the progress callback) mid ideal sweep keeps
    the finished rates' curves; after the ideal sweep, Table 1's rows too; no files."""
    rates = [10, 15, 20, 30]

    def progress(stage: str, done: int, total: int) -> None:
        if stop_at == f"{stage} {done}" or (stop_at == "link" and stage.startswith("link")):
            raise KeyboardInterrupt

    motion = [synthetic_motion("reach-grasp", 0, duration_s=6.0)]
    with pytest.raises(KeyboardInterrupt) as caught:
        run_table1(motion, rates, ["dq-slerp"], out_dir=tmp_path, progress=progress,
                   bench=False, plots=False, frontier=False)  # fmt: skip
    exc = caught.value
    assert isinstance(exc, Table1Interrupted)
    # The rates swept: those asked for and each tier's SoA rate.
    assert set(rates) <= set(exc.rates) and list(tmp_path.iterdir()) == []
    full = run_table1(motion, rates, ["dq-slerp"], link=False, bench=False, plots=False,
                      frontier=False)  # fmt: skip
    if stop_at == "ideal 2":  # one trace: each rate is one tick, the 2nd not pooled yet
        assert sorted(exc.curves) == exc.rates[:1] and exc.tiers is None
    else:
        assert sorted(exc.curves) == exc.rates and exc.tiers is not None
        assert [r["equal_qoe_rate"] for r in exc.tiers] == [
            r["equal_qoe_rate"] for r in full["tiers"]
        ]
    for rate in exc.curves:
        got = exc.curves[rate]["dq-slerp"]["hands"]["tip_p95_mm"]
        assert got == pytest.approx(full["curves"]["dq-slerp"][str(rate)]["hands"]["tip_p95_mm"])
