"""Spawn points: layouts, the rigid map to a point, labels, the volume, and QoE unchanged."""

from __future__ import annotations

import asyncio
import json
import math
from pathlib import Path

import numpy as np
import pytest
from support import running_server

from posecast.client.bot import BotConfig, remote_log
from posecast.client.swarm import run_bots
from posecast.interp.metrics import rotation_error_deg
from posecast.scenarios.compare import compare_trace
from posecast.scenarios.motion import MotionSpec
from posecast.scenarios.spawn import (
    CIRCLE_SPACING,
    Placement,
    SpawnPoint,
    layout_points,
    place,
    placement_for,
)
from posecast.scenarios.traces import Trace, TraceError, find_traces, load_trace


@pytest.fixture(scope="module")
def trace() -> Trace:
    """The first bundled trace, cut to 20 s (a real Beat Saber motion)."""
    tr = load_trace(find_traces("traces:sample")[0])
    keep = tr.times <= tr.times[0] + 20.0
    return Trace(tr.name, tr.times[keep], tr.poses[keep], tr.streams)


def _forward_deg(q: np.ndarray) -> float:
    """face_deg of one rotation's -z, projected on the floor."""
    w, x, y, z = q
    fx, fz = -2.0 * (x * z + w * y), -(1.0 - 2.0 * (x * x + y * y))
    return math.degrees(math.atan2(-fx, -fz))


def test_qoe_is_the_same_at_a_spawn_point(trace: Trace) -> None:
    """The same trace scored at its own place and moved to a spawn point (turned 137 deg,
    6 m away) gives the same errors, every method, class and statistic: to float
    tolerance for the methods that send poses alone (a placement is a rigid map of the
    world), and to the float16 rounding of the velocities on the wire (which depends
    on the frame they are written in) for the velocity method."""
    methods = ["soa", "dq-slerp", "motor-lerp", "motor-hermite"]
    moved = place(trace, placement_for(trace, SpawnPoint(-4.5, 4.0, 137.0)))
    assert np.linalg.norm(moved.poses[0, 0, [0, 2]] - trace.poses[0, 0, [0, 2]]) > 5.0
    base = compare_trace(trace, [10.0, 20.0], methods)
    there = compare_trace(moved, [10.0, 20.0], methods)
    checked = 0
    for rate, per_method in base.items():
        for m, per_class in per_method.items():
            rel = 2e-3 if m == "motor-hermite" else 1e-6
            for cls, stats in per_class.items():
                for key, value in stats.items():
                    assert there[rate][m][cls][key] == pytest.approx(
                        value, rel=rel, abs=1e-6, nan_ok=True
                    ), (rate, m, cls, key)
                    checked += 1
    assert checked > 50


def test_placement_puts_the_head_on_the_point_facing_its_way(trace: Trace) -> None:
    """The head's first floor position lands on the point; its mean heading over the
    first seconds turns to the point's direction; heights and rotations stay rigid."""
    point = SpawnPoint(2.0, -3.0, 90.0)
    moved = place(trace, placement_for(trace, point))
    head = moved.poses[:, 0, :]
    assert np.allclose(head[0, [0, 2]], [2.0, -3.0], atol=2e-4)
    assert np.allclose(moved.poses[..., 1], trace.poses[..., 1])
    first = moved.times <= moved.times[0] + 3.0
    fwd = np.array([_forward_deg(q) for q in head[first, 3:]])
    mean = math.degrees(
        math.atan2(np.mean(np.sin(np.radians(fwd))), np.mean(np.cos(np.radians(fwd))))
    )
    assert abs((mean - 90.0 + 180) % 360 - 180) < 10.0  # mean of angles vs of vectors
    # Distances between streams and relative rotations are kept.
    d0 = np.linalg.norm(trace.poses[:, 1, :3] - trace.poses[:, 2, :3], axis=-1)
    d1 = np.linalg.norm(moved.poses[:, 1, :3] - moved.poses[:, 2, :3], axis=-1)
    assert np.allclose(d0, d1, atol=1e-9)
    assert np.allclose(norm := np.linalg.norm(moved.poses[..., 3:], axis=-1), 1.0), norm


def test_placements_compose_and_round_trip_through_labels(trace: Trace) -> None:
    """``a.then(b)`` is a then b; a motion label carries its placement exactly, so a
    receiver's ground truth is the sender's samples."""
    a, b = Placement(33.3, 1.25, -2.0), Placement(-120.0, 0.5, 3.0)
    p = trace.poses[:50]
    assert np.allclose(a.then(b).apply(p)[..., :3], b.apply(a.apply(p))[..., :3], atol=2e-4)
    assert np.all(
        rotation_error_deg(a.then(b).apply(p)[..., 3:], b.apply(a.apply(p))[..., 3:]) < 1e-2
    )
    spec = MotionSpec.for_trace(find_traces("traces:sample")[0], 1000.5)
    placed = spec.placed(SpawnPoint(3.0, 1.0, 45.0))
    back = MotionSpec.parse(placed.label())
    assert back == placed and "|at=" in placed.label()
    assert np.array_equal(back.load().poses, placed.load().poses)
    # Placing a placed motion again composes the maps: the head lands on the new point.
    again = placed.placed(SpawnPoint(-2.0, 0.5, 0.0))
    assert np.allclose(again.load().poses[0, 0, [0, 2]], [-2.0, 0.5], atol=3e-4)


def test_layouts() -> None:
    """circle: neighbours CIRCLE_SPACING apart (or radius R), facing the centre; grid:
    a square of S m cells around the origin; none: None; a JSON file: its points."""
    pts = layout_points("circle", 12)
    assert pts is not None and len(pts) == 12
    xy = np.array([[p.x, p.z] for p in pts])
    gaps = np.linalg.norm(xy - np.roll(xy, 1, axis=0), axis=1)
    assert np.allclose(gaps, gaps[0], atol=1e-3) and abs(gaps[0] - CIRCLE_SPACING) < 0.05
    for p in pts:  # facing (-sin f, -cos f) points at the origin
        f = math.radians(p.face_deg)
        assert np.allclose(
            [-math.sin(f), -math.cos(f)], -np.array([p.x, p.z]) / math.hypot(p.x, p.z)
        )
    small = layout_points("circle:3", 4)
    assert small is not None and all(abs(math.hypot(p.x, p.z) - 3.0) < 1e-3 for p in small)
    grid = layout_points("grid:2.5", 5)
    assert grid is not None
    assert sorted({p.x for p in grid}) == [-2.5, 0.0, 2.5] and sorted({p.z for p in grid}) == [
        -1.25,
        1.25,
    ]
    assert layout_points("none", 3) is None


def test_layout_files_and_refusals(tmp_path: Path) -> None:
    """A JSON layout gives its points in order; each mistake is one TraceError line."""
    f = tmp_path / "room.json"
    f.write_text(json.dumps({"spawns": [{"x": 1, "z": 2, "face_deg": 90}, {"x": -1, "z": 0}]}))
    assert layout_points(str(f), 2) == [SpawnPoint(1.0, 2.0, 90.0), SpawnPoint(-1.0, 0.0, 0.0)]
    bad = tmp_path / "bad.json"
    bad.write_text("{")
    cases = [
        ("square", 2, "unknown spawn layout"),
        ("circle:-1", 2, "positive number"),
        ("grid:x", 2, "positive number"),
        (str(f), 3, "has 2 spawn points for 3 users"),
        (str(bad), 1, "is not JSON"),
        (str(tmp_path / "missing.json"), 1, "cannot read spawn layout"),
    ]
    for layout, n, message in cases:
        with pytest.raises(TraceError, match=message) as info:
            layout_points(layout, n)
        assert "\n" not in str(info.value)


def test_a_spawn_point_outside_the_volume_is_refused() -> None:
    """A motion that its spawn point moves out of the room's volume is refused in one line."""
    spec = MotionSpec.for_trace(find_traces("traces:sample")[0])
    with pytest.raises(TraceError, match="leaves the room's volume"):
        spec.placed(SpawnPoint(7.9, 0.0, 0.0))


def test_live_bots_stand_on_their_spawn_points() -> None:
    """Bots on a circle of 2 m publish poses at their spawn points, and each scores the
    other against the placed ground truth its label names (else the errors would be
    metres, not millimetres)."""

    async def go() -> list:
        async with running_server() as server:
            base = BotConfig(
                url=f"ws://127.0.0.1:{server.port}",
                room="spawn",
                rate=15,
                motion="traces:sample",
                duration=2.5,
                methods=("soa",),
            )
            return await run_bots(base, 2, spawn="circle:2")

    reports = asyncio.run(go())
    points = layout_points("circle:2", 2)
    assert points is not None
    for rep in reports:
        heads = [rs for key, rs in rep.streams.items() if rs.name == "head"]
        assert len(heads) == 1 and "|at=" in (heads[0].label or "")
        log = remote_log(heads[0])
        floor = log.poses[:, 0, [0, 2]] if log.poses.ndim == 3 else log.poses[:, [0, 2]]
        near = min(np.linalg.norm(floor[0] - [p.x, p.z]) for p in points)
        assert near < 0.5, floor[0]
        tip = rep.qoe["soa"]["hands"].stats()["tip_p50_mm"]
        assert 0 < tip < 200, tip


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["bots", "--url", "ws://127.0.0.1:9", "--spawn", "square"], "--spawn: unknown spawn"),
        (["demo", "--spawn", "grid:0"], "--spawn: spawn layout 'grid:0'"),
        (
            ["bots", "--url", "ws://127.0.0.1:9", "--n", "3", "--spawn", "nofile.json"],
            "cannot read",
        ),
    ],
)
def test_the_cli_refuses_a_bad_layout_in_one_line(args: list[str], message: str) -> None:
    """``bots`` and ``demo`` check ``--spawn`` before connecting: one line, exit code 2."""
    from typer.testing import CliRunner

    from posecast.cli import app

    res = CliRunner().invoke(app, args)
    assert res.exit_code == 2 and message in res.output, res.output


def test_a_replay_plan_moves_each_user_with_its_ground_truth(tmp_path: Path) -> None:
    """``replay --spawn``: each recorded user's poses go to its spawn point, and its
    label's ground truth moves with them (what a live receiver scores against)."""
    from posecast.recorder.plan import plan_replay, spawn_plan
    from posecast.recorder.replay import synthesize_recording

    rec = synthesize_recording(tmp_path, users=3, rate=30.0, duration=3.0)
    plan = plan_replay(rec)
    moved = spawn_plan(plan, "circle:2.5")
    points = layout_points("circle:2.5", 3)
    assert points is not None and spawn_plan(plan, "none") is plan
    for up, point in zip(moved.users, points, strict=True):
        head = next(k for k, name in up.streams.items() if name == "head")
        caps, poses = [], []
        for ids, c, p in up.updates:
            for i in np.flatnonzero(ids == head):
                caps.append(c[i])
                poses.append(p[i])
        first = int(np.argmin(caps))
        assert np.allclose(poses[first][[0, 2]], [point.x, point.z], atol=1e-3)
        truth = MotionSpec.parse(up.label or "").truth(until=max(caps) + 1.0)
        j = truth.streams.index("head")
        idx = np.abs(truth.times[None, :] - np.array(caps)[:, None]).argmin(axis=1)
        assert np.allclose(truth.poses[idx, j, :3], np.array(poses)[:, :3], atol=1e-4)
