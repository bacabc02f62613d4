"""Bots against a real relay on loopback: rates, QoE, and live = offline."""

from __future__ import annotations

import asyncio
import itertools
import math

import numpy as np
import pytest
from support import running_server

from posecast.client.bot import BotConfig, BotReport, RemoteStream, remote_log, run_bot
from posecast.client.swarm import run_bots, swarm_report
from posecast.interp import get
from posecast.scenarios.qoe import STAT_KEYS, playout_brackets
from posecast.server.room import room_phase


async def _session(configs: list[BotConfig]) -> list[BotReport]:
    async with running_server() as server:
        url = f"ws://127.0.0.1:{server.port}"
        async with asyncio.TaskGroup() as bots:
            tasks = [
                bots.create_task(run_bot(BotConfig(**{**c.__dict__, "url": url}))) for c in configs
            ]
    return [t.result() for t in tasks]


@pytest.fixture(scope="module")
def three_bots() -> list[BotReport]:
    """Three bots (two synthetic, one real trace) for 4 s at 15 Hz, render log kept."""
    configs = [
        BotConfig(
            url="",
            room="t",
            rate=15,
            motion="synthetic:orbit",
            seed=1,
            duration=4,
            keep_render_log=True,
            name="a",
        ),
        BotConfig(
            url="",
            room="t",
            rate=15,
            motion="synthetic:orbit",
            seed=2,
            duration=4,
            keep_render_log=True,
            name="b",
        ),
        BotConfig(
            url="",
            room="t",
            rate=15,
            motion="traces:sample",
            duration=4,
            keep_render_log=True,
            name="c",
        ),
    ]
    from posecast.client.bot import motion_for_bot

    configs[2] = BotConfig(
        **{**configs[2].__dict__, "motion": motion_for_bot("traces:sample", 1)[0]}
    )
    return asyncio.run(_session(configs))


def test_each_bot_receives_every_other_stream(three_bots: list[BotReport]) -> None:
    """Every bot renders the 6 streams of the two others, named head/left/right."""
    for rep in three_bots:
        names = sorted(rs.name for rs in rep.streams.values())
        assert names == ["head", "head", "left", "left", "right", "right"]
        assert rep.user not in {rs.user for rs in rep.streams.values()}


def _grid_after(now: float, rate: float, phase: float) -> float:
    """The room's schedule: the first point of the ``(k + phase) / rate`` grid after ``now``."""
    return (math.floor(now * rate - phase + 1e-9) + 1 + phase) / rate


def test_keyframe_rate_matches_subscription(three_bots: list[BotReport]) -> None:
    """Bots publishing at 30 Hz and subscribing at 15 Hz get at most one keyframe per
    stream per point of their room's 15 Hz grid, each newer than the last.

    Checked on the server's own send times, so it holds however little CPU the
    process gets: a starved relay skips grid points (fewer keyframes), but it can
    never send twice within one grid interval. How many it sends when it is on
    time is the room's schedule, tested with an injected clock in test_room.py.
    """
    phase = room_phase("t")
    for rep in three_bots:
        assert rep.asked_hz == rep.granted_hz == 15.0
        # Every snapshot the bot got (the ones carrying remote streams), in send order.
        sent = sorted({s for rs in rep.streams.values() for s in rs.sent})
        assert len(sent) >= 5  # liveness only
        for prev, nxt in itertools.pairwise(sent):
            assert nxt >= _grid_after(prev, 15.0, phase) - 1e-9, (prev, nxt)
        for rs in rep.streams.values():
            # Latest wins: each keyframe of a stream is newer than the one before it.
            assert np.all(np.diff(rs.capture) > 0)
            assert np.all(np.diff(rs.sent) > 0)
            # The received ones are among the sender's 30 Hz keyframes: never more than
            # the grid points spanned by the snapshots that brought them.
            span = rs.sent[-1] - rs.sent[0]
            assert len(rs.capture) <= math.floor(span * 15.0) + 2


def test_qoe_is_reported_for_every_method_and_class(three_bots: list[BotReport]) -> None:
    """The swarm report has p50/p95 stats for hands and head for each interpolator."""
    report = swarm_report(three_bots)
    assert set(report["methods"]) == {"soa", "dq-slerp", "motor-lerp"}
    for classes in report["methods"].values():
        assert set(classes) == {"hands", "head"}
        for st in classes.values():
            assert set(st) == set(STAT_KEYS)
            assert np.isfinite(st["tip_p95_mm"]) and st["tip_p95_mm"] > 0
            assert st["pos_p50_mm"] <= st["pos_p95_mm"]
    # Compact by default: relay delta frames of 6 remote poses (raw would be 36-80 B).
    assert report["wire"]["codec"] == "compact"
    assert 5 < report["wire"]["bytes_per_pose"] < 20
    assert {b["id"] for b in report["bots"]} == {r.user for r in three_bots}


def test_live_render_equals_offline_computation(three_bots: list[BotReport]) -> None:
    """Each rendered pose equals the QoE definition's pose from the arrival log.

    For every frame, the offline path takes the keyframes that had arrived by the
    render's wall time, brackets t_play and interpolates (soa); it must
    reproduce what the live render loop showed, stall flags included. Arrival
    and render times are compared on the bot's own clock, so a refinement of
    the clock offset between the two cannot blur the comparison.
    """
    soa = get("soa")
    checked = 0
    shown_total = 0
    for rep in three_bots:
        # Each stream's frames (t_play, rendered at, pose shown, stalled), in order:
        # bracketed and interpolated in one call per stream, compared frame by frame.
        frames: dict[tuple[int, int], list[tuple[float, float, object, bool]]] = {}
        for t_play, _d, rendered_at, shown in rep.render_log[5:]:
            shown_total += len(shown)
            for key, (pose, stalled) in shown.items():
                frames.setdefault(key, []).append((t_play, rendered_at, pose, stalled))
        for key, rows in frames.items():
            rs = rep.streams[key]
            local = RemoteStream(rs.user, rs.stream, rs.name, rs.label)
            local.capture, local.arrival, local.poses = rs.capture, rs.arrival_local, rs.poses
            log = remote_log(local)
            t_play = np.array([r[0] for r in rows])
            delay = np.array([r[1] for r in rows]) - t_play
            play = playout_brackets(log.capture, log.arrival, t_play, delay)
            # The loop only shows streams with a keyframe in their buffer.
            assert not play.missing.any()
            want = soa(log.poses[play.lo, 0], log.poses[play.hi, 0], play.s)
            np.testing.assert_array_equal(play.stall, [r[3] for r in rows])
            np.testing.assert_allclose(np.array([r[2] for r in rows]), want, atol=1e-6)
            checked += len(rows)
    # Every shown pose was checked; how many there are depends on the machine's load.
    assert checked == shown_total > 0


def test_swarm_runs_n_bots_with_trace_motion() -> None:
    """run_bots starts N bots on distinct dev traces; all finish with a report."""

    async def go() -> list[BotReport]:
        async with running_server() as server:
            base = BotConfig(
                url=f"ws://127.0.0.1:{server.port}",
                room="s",
                rate=10,
                motion="traces:sample",
                duration=2.0,
            )
            return await run_bots(base, 3)

    reports = asyncio.run(go())
    assert len(reports) == 3
    assert len({r.user for r in reports}) == 3
    labels = {rs.label.split("|")[0] for r in reports for rs in r.streams.values() if rs.label}
    assert len(labels) == 3
