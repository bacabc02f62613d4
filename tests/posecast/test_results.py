"""``make results``: generated page blocks, change detection, provenance and the
Tables 2-3 error budget (small real inputs; the full run is not part of the tests)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import pytest

from posecast import results, results_docs
from posecast.recorder.analyze import analyze
from posecast.scenarios.table1 import run_table1
from posecast.scenarios.traces import load_trace

PAGE = """# Title

Prose stays.

<!-- results:demo -->
old table
<!-- /results:demo -->

More prose.
"""


def test_rewrite_page_replaces_only_the_generated_blocks(monkeypatch: pytest.MonkeyPatch) -> None:
    """The text between a block's markers is regenerated; everything else is kept."""
    monkeypatch.setitem(results_docs.BLOCKS, "demo", lambda _: "| new | table |\n")
    out = results_docs.rewrite_page(PAGE, Path("."))
    assert "old table" not in out and "| new | table |\n<!-- /results:demo -->" in out
    assert out.replace("| new | table |", "old table") == PAGE
    assert results_docs.rewrite_page(out, Path(".")) == out  # idempotent


def test_an_unknown_block_is_an_error() -> None:
    """A marker whose name has no generator fails with the known names."""
    with pytest.raises(ValueError, match="unknown results block 'demo'"):
        results_docs.rewrite_page(PAGE, Path("."))


def test_fingerprint_ignores_timings_but_not_results(tmp_path: Path) -> None:
    """A JSON output that differs only in its timings counts as unchanged."""
    f = tmp_path / "a.json"
    f.write_text(json.dumps({"x": 1.0, "config": {"elapsed_s": 3.0, "timings_s": {"a": 1}}}))
    before = results.snapshot([tmp_path])
    f.write_text(json.dumps({"x": 1.0, "config": {"elapsed_s": 9.0, "timings_s": {"a": 2}}}))
    assert results.changes(before, results.snapshot([tmp_path])) == []
    f.write_text(json.dumps({"x": 2.0, "config": {"elapsed_s": 9.0}}))
    (tmp_path / "b.md").write_text("new")
    got = results.changes(before, results.snapshot([tmp_path]))
    assert got == [("changed", f), ("new", tmp_path / "b.md")]


def test_provenance_names_the_command_revision_and_split() -> None:
    """The revision is the checkout's short hash (with -dirty for local changes)."""
    prov = results.provenance("traces:eval", "posecast table1 --traces traces:eval")
    assert prov["traces"] == "traces:eval" and prov["command"].startswith("posecast table1")
    assert prov["revision"] == "unknown" or len(prov["revision"].split("-")[0]) >= 7


def test_every_job_has_a_command_and_a_split() -> None:
    """--list names every output, its split and its command."""
    names = [j.name for j in results.JOBS]
    assert len(names) == len(set(names))
    assert {"table1-eval", "table1-dev", "table1-paper-scene", "recording-eval"} <= set(names)
    for j in results.JOBS:
        assert j.split and j.command.startswith(("posecast ", "python -m posecast.results"))
    assert results.main(["--list"]) == 0


def test_unknown_outputs_are_refused_before_any_work(capsys: pytest.CaptureFixture[str]) -> None:
    """--only with a name that is no output exits 2 with the known names."""
    assert results.main(["--only", "nope"]) == 2
    assert "unknown output(s) ['nope']" in capsys.readouterr().err


def test_error_budget_is_the_papers_metric_for_soa(dev_trace_path: Path) -> None:
    """The budget's mean relative error equals recorder.analyze's SoA figure (keep 1 in 2),
    and LERP's miss is half the second difference: |a| dt^2 / 2."""
    trace = load_trace(dev_trace_path).window(10.0, 20.0)
    budget = results.relative_error_budget([trace])
    table = analyze([trace], (2,), ["soa"])["tables"]["2"]["methods"]["soa"]["classes"]
    for cls in ("hands", "head"):
        assert budget[cls]["translation_rel_pct"] == pytest.approx(
            table[cls]["translation_rel_pct"], rel=1e-9
        )
        b = budget[cls]
        dt = 1.0 / b["frame_rate_mean_hz"]
        # mean |a| dt^2 / 2 is the mean error when dt hardly varies (traces jitter < 1.5 ms)
        assert b["abs_error_mean_mm"] == pytest.approx(
            1000 * b["accel_mean_mps2"] * dt * dt / 2, rel=0.1
        )


@pytest.fixture(scope="module")
def small_results(tmp_path_factory: pytest.TempPathFactory, sample_dir: Path) -> Path:
    """table1-eval and table1-dev folders from a 12 s real window (ideal network only)."""
    root = tmp_path_factory.mktemp("results")
    trace = load_trace(sample_dir / "S02_riftS_expertplus.csv.gz").window(20.0, 32.0)
    prov = results.provenance("traces:sample", "posecast table1 ...")
    run_table1(
        [trace],
        rates=range(8, 31),
        methods=["dq-slerp", "motor-lerp", "soa-hermite", "motor-hermite"],
        out_dir=root / "table1-eval",
        provenance=prov,
        link=False,
        bench=False,
        plots=False,
        frontier=False,
        codecs=["raw"],
    )
    shutil.copytree(root / "table1-eval", root / "table1-dev")
    return root


@pytest.mark.parametrize(
    "block", ["paper-table1", "closing-eval", "closing-dev", "split-eval", "velocity-error-eval"]
)
def test_table1_blocks_render_from_real_outputs(small_results: Path, block: str) -> None:
    """Each Table 1 block holds a Markdown table and ends with its command, revision and split."""
    text = results_docs.BLOCKS[block](small_results)
    assert any(ln.startswith("|---|") for ln in text.splitlines())
    source = text.splitlines()[-1]
    assert source.startswith("*Source: `posecast table1") and "traces `traces:sample`" in source
    assert "revision `" in source


def test_closing_block_shows_both_rates_of_every_method(small_results: Path) -> None:
    """The closing table's cells are the JSON's equal-accuracy / equal-smoothness rates."""
    rep: dict[str, Any] = json.loads((small_results / "table1-eval" / "table1.json").read_text())
    text = results_docs.BLOCKS["closing-eval"](small_results)
    row = next(ln for ln in text.splitlines() if ln.startswith("| `soa-hermite` |"))
    t = rep["tiers"][0]
    a, s = t["equal_qoe_rate"]["soa-hermite"], t["equal_smoothness_rate"]["soa-hermite"]
    assert row.split(" | ")[1].startswith(f"{a} / {s} Hz")


def test_markdown_fingerprint_ignores_run_time_and_revision(tmp_path: Path) -> None:
    """A table1.md whose run time or source revision moved is unchanged; a number is not."""
    f = tmp_path / "table1.md"
    f.write_text("Run time 6 s (ideal sweep 3 s).\n| 1.0 |\n*revision `abc1234`*\n")
    before = results.snapshot([tmp_path])
    f.write_text("Run time 9 s (ideal sweep 4 s).\n| 1.0 |\n*revision `def5678-dirty`*\n")
    assert results.changes(before, results.snapshot([tmp_path])) == []
    f.write_text("Run time 9 s (ideal sweep 4 s).\n| 1.1 |\n*revision `def5678-dirty`*\n")
    assert results.changes(before, results.snapshot([tmp_path])) == [("changed", f)]
