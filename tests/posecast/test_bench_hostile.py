"""``posecast bench hostile``: a short real run (server, attacker and bots as subprocesses).

Figures are what the machine gave; the tests check the report's shape and what
the relay answered each attacker (close and error codes), never a time or a rate.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from posecast.bench.hostile import HostileConfig
from posecast.bench.hostile_attacks import ATTACKS

HONEST_KEYS = {"hands_tip_p95_mm", "delay_ms", "delay_ms_max", "rate_hz", "rate_hz_min"}
SERVER_KEYS = {
    "rss_mb_peak",
    "tick_lag_max_ms",
    "tick_overdue_p99_ms",
    "scrapes",
    "scrapes_unanswered",
    "protocol_errors",
    "misbehaviour_closes",
    "connections_refused",
    "join_timeouts",
    "updates_refused",
    "rooms_peak",
}


def _posecast(*args: str, timeout: float) -> subprocess.CompletedProcess[str]:
    boot = "from posecast.cli import main; main()"
    return subprocess.run(
        [sys.executable, "-c", boot, *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """One short run of every attack: 2 bots, 3 s a run, small counts."""
    out = tmp_path_factory.mktemp("hostile") / "hostile.json"
    res = _posecast(
        "bench", "hostile", "--bots", "2", "--duration", "3", "--fuzz-frames", "3000",
        "--fuzz-connections", "4", "--flood-connections", "100", "--flood-rate", "200",
        "--rooms", "12", "--json", str(out),
        timeout=240,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    assert "honest bots" in res.stdout and "what the attacker sent and got" in res.stdout
    data: dict[str, object] = json.loads(out.read_text())
    return data


def _run(report: dict[str, object], attack: str) -> dict[str, dict[str, object]]:
    runs = report["runs"]
    assert isinstance(runs, list)
    found = [r for r in runs if r["attack"] == attack]
    assert len(found) == 1, [r["attack"] for r in runs]
    run: dict[str, dict[str, object]] = found[0]
    return run


def test_a_row_per_attack_with_its_figures(report: dict[str, object]) -> None:
    """A clean run then one per attack, each with honest, server and ratio figures."""
    runs = report["runs"]
    assert isinstance(runs, list)
    assert [r["attack"] for r in runs] == ["clean", *ATTACKS]
    for run in runs:
        assert set(run["honest"]) >= HONEST_KEYS, run["attack"]
        assert set(run["server"]) >= SERVER_KEYS, run["attack"]
        assert set(run["vs_clean"]) == {"hands_tip_p95", "delay", "rate"}
        # The honest bots measured something in every run, and the server answered.
        assert math.isfinite(run["honest"]["hands_tip_p95_mm"]), run
        assert math.isfinite(run["honest"]["delay_ms"]), run
        assert run["server"]["rss_mb_peak"] > 0
        assert run["server"]["scrapes"] > run["server"]["scrapes_unanswered"]
        assert run["server"]["exit_code"] == 0
        assert ("attacker" in run) == (run["attack"] != "clean")
    clean = runs[0]
    assert clean["vs_clean"] == {"hands_tip_p95": 1.0, "delay": 1.0, "rate": 1.0}
    # Each target is reported with its value; a missed one is listed by name.
    targets = {t["target"] for r in runs for t in r["targets"]}
    assert "tick lag p99 under 50 ms" in targets
    assert "honest rates kept (>= 90 % of clean)" in targets
    missed = [f"{r['attack']}: {t['target']}" for r in runs for t in r["targets"] if not t["met"]]
    assert report["missed"] == missed


def test_timestamp_attack_is_refused(report: dict[str, object]) -> None:
    """Poses stamped 2 s in the past: each refused with bad-pose, none closes the member."""
    run = _run(report, "timestamp")
    got = run["attacker"]
    sent = got["sent"]["stale-update"]
    assert isinstance(sent, int) and sent > 0
    assert 0 < got["errors"]["bad-pose"] <= sent
    assert set(got["errors"]) == {"bad-pose"}
    assert run["server"]["updates_refused"] >= got["errors"]["bad-pose"]
    assert "1008" not in got["closes"]


def test_fuzz_gets_closed(report: dict[str, object]) -> None:
    """Invalid frames: over budget or not owned 1008, bad bytes 1002, oversized 1009."""
    run = _run(report, "fuzz")
    got = run["attacker"]
    closes = got["closes"]
    assert isinstance(closes, dict)
    assert set(closes) <= {"1002", "1008", "1009", "none", "closed by the attacker"}
    assert closes.get("1008", 0) > 0 and closes.get("1002", 0) > 0
    assert {"bad-pose", "bad-frame", "stream-not-owned"} <= set(got["errors"])
    assert run["server"]["misbehaviour_closes"] > 0


def test_connection_flood_refused(report: dict[str, object]) -> None:
    """100 silent connections from one address: over 64 closed 1013, the rest held or 1008."""
    run = _run(report, "flood")
    closes = run["attacker"]["closes"]
    assert isinstance(closes, dict)
    assert set(closes) <= {"1013", "1008", "held to the end"}
    assert closes.get("1013", 0) > 0
    assert run["server"]["connections_refused"] >= closes["1013"]


def test_never_reader_and_room_spam(report: dict[str, object]) -> None:
    """The never-reading member joined; the room spammer opened rooms (12 is under every limit)."""
    reader = _run(report, "never-reader")["attacker"]
    assert reader["sent"] == {"join": 1}
    rooms = _run(report, "rooms")
    assert rooms["attacker"]["sent"]["connection"] == 12
    assert rooms["server"]["rooms_peak"] > 1


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--attacks", "timestamp,teleport"], "unknown attack 'teleport'"),
        (["--bots", "1"], "bots must be at least 2"),
        (["--fuzz-frames", "0"], "attack counts and rates must be positive"),
    ],
)
def test_bad_settings_one_line(args: list[str], message: str, tmp_path: Path) -> None:
    """A bad setting is one line on stderr and exit code 2, before anything starts."""
    res = _posecast("bench", "hostile", *args, timeout=60)
    assert res.returncode == 2
    assert message in res.stderr and "Traceback" not in res.stderr


def test_config_checks_attacks() -> None:
    """HostileConfig refuses an unknown attack by name."""
    with pytest.raises(ValueError, match="unknown attack 'x'"):
        HostileConfig(attacks=("x",)).check()
