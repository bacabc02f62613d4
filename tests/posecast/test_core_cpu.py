"""``python -m posecast.bench.core_cpu``: the relay core's CPU per pose, in one process."""

from __future__ import annotations

import math

import pytest

from posecast.bench.core_cpu import PHASES, main, measure, measure_phases
from posecast.scenarios.traces import find_traces, load_trace


@pytest.mark.parametrize("codec", ["raw", "compact"])
def test_measure_delivers_poses_and_gives_a_cost(codec: str) -> None:
    """One room for one second: a finite, positive CPU figure per delivered pose."""
    traces = [load_trace(p) for p in find_traces("traces:sample")]
    got = measure(codec, rooms=1, seconds=1.0, traces=traces)
    assert math.isfinite(got) and got > 0


def test_phases_add_up_to_the_figure() -> None:
    """The receive, tick and take phases are each finite and positive."""
    traces = [load_trace(p) for p in find_traces("traces:sample")]
    got = measure_phases("compact", rooms=1, seconds=1.0, traces=traces)
    assert list(got) == list(PHASES)
    assert all(math.isfinite(v) and v > 0 for v in got.values())


def test_main_prints_every_path(capsys: pytest.CaptureFixture[str]) -> None:
    """The command prints a line per path (raw, compact compiled where built, compact pure)."""
    main(["--rooms", "1", "--seconds", "0.5", "--rounds", "1"])
    out = capsys.readouterr().out
    assert "raw" in out and "compact pure" in out
    assert all(phase in out for phase in PHASES)


def test_interleaved_times_the_relay_between_its_clients(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """``--interleaved`` times the first core (no replay) and says so."""
    traces = [load_trace(p) for p in find_traces("traces:sample")]
    got = measure_phases("raw", rooms=1, seconds=0.5, traces=traces, interleaved=True)
    assert all(math.isfinite(v) and v > 0 for v in got.values())
    main(["--rooms", "1", "--seconds", "0.5", "--rounds", "1", "--interleaved"])
    assert "interleaved with its clients" in capsys.readouterr().out
