"""``python -m posecast.bench.sidebyside``: two checkouts' relay benches side by side."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from posecast.bench import sidebyside, sidebyside_probe
from posecast.protocol import _accel

BIN = Path(sys.executable).parent


def _checkout(root: Path) -> Path:
    """A folder laid out as a checkout whose ``.venv`` is the running one (no copy)."""
    bin_ = root / ".venv" / "bin"
    bin_.mkdir(parents=True)
    for name, target in (("python", sys.executable), ("posecast", str(BIN / "posecast"))):
        tool = bin_ / name
        tool.write_text(f'#!/bin/sh\nexec "{target}" "$@"\n')
        tool.chmod(0o755)
    return root


def test_probe_measures_and_the_compiled_codec_takes_the_pure_one_s_bytes() -> None:
    """The probe gives a finite cost per pose by phase; compact compiled and pure relays
    take byte-identical frames for the same poses (the CRC the side by side compares)."""
    traces = sidebyside_probe.load_traces(None)
    got = {}
    for pure in (True, False):
        sidebyside_probe._implementation(pure)
        try:
            got[pure] = sidebyside_probe.measure("compact", rooms=1, seconds=0.5, traces=traces)
        finally:
            _accel.use(False)
    for figures in got.values():
        assert figures["poses"] > 0
        assert all(math.isfinite(figures[f"us_{p}"]) for p in sidebyside_probe.PHASES)
    assert got[True]["crc"] == got[False]["crc"]


def test_probe_runs_as_a_file_in_an_isolated_interpreter(tmp_path: Path) -> None:
    """Run as the driver runs it (``python -I FILE``): one JSON line, the traces from an .npz."""
    npz = tmp_path / "t.npz"
    probe = str(sidebyside.PROBE)
    subprocess.run([sys.executable, "-I", probe, "--save-traces", str(npz)], check=True)
    cmd = [sys.executable, "-I", probe, "--codec", "raw", "--rooms", "1", "--seconds", "0.5"]
    out = subprocess.run(
        [*cmd, "--traces", str(npz)],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    got = json.loads(out)
    assert got["layout"] == "posecast" and got["codec"] == "raw" and got["poses"] > 0
    direct = sidebyside_probe.measure("raw", 1, 0.5, sidebyside_probe.load_traces(str(npz)))
    assert direct["crc"] == got["crc"]


def _rec(bench: str, side: str, codec: str, figures: dict[str, object]) -> str:
    up = "04:00:00 up 1 day,  0 users,  load average: 1.50, 1.00, 0.50"
    return json.dumps(
        {"bench": bench, "side": side, "codec": codec, "round": 1, "ok": True, "seconds": 1.0}
        | {"uptime_before": up, "uptime_after": up, "figures": figures}
    )


def test_summary_gives_medians_of_the_rounds_and_the_ratio_to_before(tmp_path: Path) -> None:
    """Three before rounds (median 3) and one after (6): 2.00x; hostile targets side by side."""
    lines = [_rec("relay", "before", "raw", {"server_cpu_us_per_pose": v}) for v in (2, 4, 3)]
    lines.append(_rec("relay", "after", "raw", {"server_cpu_us_per_pose": 6.0}))
    target = {"attack": "flood", "target": "rates kept", "value": 0.5, "met": False}
    lines.append(_rec("hostile", "before", "", {"targets": [target], "missed": ["x"]}))
    lines.append(_rec("hostile", "after", "", {"targets": [target | {"met": True}]}))
    (tmp_path / "runs.jsonl").write_text("\n".join(lines) + "\n")
    summary = sidebyside.summarize(tmp_path)
    row = next(line for line in summary.splitlines() if "server_cpu_us_per_pose" in line)
    assert row.split(" | ")[2:] == ["3 (2, 4, 3)", "6 (6)", "2.00x |"]
    assert "| flood | rates kept | 0.50 **MISSED** | 0.50 met |" in summary
    assert "load average (1 min) 1.50-1.50" in summary


def test_driver_alternates_the_sides_and_writes_the_summary(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two rounds of the in-process probe, the same checkout on both sides: before and
    after alternate, their frames' CRCs agree, the summary is written."""
    old, new = _checkout(tmp_path / "old"), _checkout(tmp_path / "new")
    out = tmp_path / "out"
    sides = ["--before", str(old), "--after", str(new), "--rounds", "2", "--codecs", "raw"]
    sidebyside.main(
        [*sides, "--no-relay", "--core-rooms", "1", "--core-seconds", "0.3", "--out", str(out)]
    )
    runs = [json.loads(line) for line in (out / "runs.jsonl").read_text().splitlines()]
    assert [(r["round"], r["codec"], r["side"]) for r in runs] == [
        (n, "raw", side) for n in (1, 2) for side in ("before", "after")
    ]
    assert all(r["ok"] and "load average" in r["uptime_before"] for r in runs)
    assert len({r["figures"]["crc"] for r in runs}) == 1
    assert len(runs[0]["figures"]["conn_crcs"]) == 10
    summary = capsys.readouterr().out
    assert "| raw | us_per_pose |" in summary and "| raw | us_tick |" in summary
    assert "raw: after's relay sent 10 of 10 connections the same bytes as before's" in summary
    assert (out / "summary.md").read_text().strip() in summary


def test_a_relay_run_reads_the_bench_s_report(tmp_path: Path) -> None:
    """``posecast bench relay`` of a checkout, small: its figures land in the record."""
    args = sidebyside._parser().parse_args(
        [*("--clients", "4", "--procs", "1", "--duration", "1", "--out", str(tmp_path))]
    )
    side = sidebyside.Side("after", _checkout(tmp_path / "new"))
    record = sidebyside.run_relay(side, "raw", 1, args)
    assert record["ok"], (tmp_path / "relay-after-raw-1.log").read_text()
    figures = record["figures"]
    assert set(sidebyside.RELAY_FIGURES) <= set(figures)
    assert figures["server_cpu_us_per_pose"] > 0 and figures["skips"] == 0
    assert json.loads((tmp_path / "runs.jsonl").read_text())["figures"] == figures
