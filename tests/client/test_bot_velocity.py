"""Velocity keyframes live: buffers, rendering, and bots rendering motor-hermite."""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import numpy as np
import pytest
from support import running_server
from typer.testing import CliRunner

from posecast.cli import app
from posecast.client.bot import (
    BotConfig,
    BotReport,
    RemoteStream,
    evaluate_remote,
    motion_for_bot,
    remote_log,
    run_bot,
)
from posecast.client.buffers import StreamBuffer
from posecast.client.render import VELOCITY_FALLBACK, render_buffers, rendered_method
from posecast.client.swarm import swarm_report
from posecast.interp import interpolate_brackets
from posecast.protocol import VELOCITY_BYTES, VELOCITY_MAX, frame_size
from posecast.scenarios.motion import MotionSpec
from posecast.scenarios.network import (
    TCP_IP_HEADER_BYTES,
    TCP_MSS,
    VELOCITY_BYTES_PER_POSE,
    websocket_header_bytes,
    wire_bytes,
)
from posecast.scenarios.qoe import (
    KeyframeLog,
    evaluate_group,
    playout_brackets,
    summarize,
)
from posecast.scenarios.traces import DEVICE_NAMES


@pytest.mark.parametrize("n", [1, 3, 18, 48, 200, 1500])
def test_wire_velocity_bytes_match_the_offline_accounting(n: int) -> None:
    """The link model's and Table 1's velocity frames are exactly the protocol's frames."""
    assert VELOCITY_BYTES == VELOCITY_BYTES_PER_POSE == 12
    payload = frame_size(n, "snapshot", velocities=True)
    segments = -(-(payload + websocket_header_bytes(payload)) // TCP_MSS)
    want = payload + websocket_header_bytes(payload) + segments * TCP_IP_HEADER_BYTES
    assert wire_bytes(n, VELOCITY_BYTES_PER_POSE) == want


def test_velocity_methods_need_velocities() -> None:
    cfg = BotConfig(url="ws://127.0.0.1:9", methods=("motor-hermite",), velocities=False)
    with pytest.raises(ValueError, match="motor-hermite need keyframe velocities"):
        asyncio.run(run_bot(cfg))


async def _session(configs: list[BotConfig]) -> list[BotReport]:
    async with running_server() as server:
        url = f"ws://127.0.0.1:{server.port}"
        async with asyncio.TaskGroup() as tg:
            tasks = [
                tg.create_task(run_bot(BotConfig(**{**c.__dict__, "url": url}))) for c in configs
            ]
    return [t.result() for t in tasks]


RATE = 15.0


@pytest.fixture(scope="module")
def mixed_room() -> list[BotReport]:
    """Two bots rendering soa + motor-hermite (velocity keyframes) and one plain bot.

    Raw codec: these tests compare the velocity records bit for bit (compact
    quantises them; tests/server/test_compact_relay.py covers that path)."""
    base = BotConfig(url="", room="v", rate=RATE, duration=5.0, keep_render_log=True, codec="raw")
    configs = [
        BotConfig(
            **{
                **base.__dict__,
                "name": f"v{i}",
                "methods": ("soa", "motor-hermite"),
                "motion": motion_for_bot("traces:sample", i)[0],
            }
        )
        for i in range(2)
    ]
    configs.append(
        BotConfig(
            **{
                **base.__dict__,
                "name": "plain",
                "methods": ("soa",),
                "motion": motion_for_bot("traces:sample", 2)[0],
            }
        )
    )
    return asyncio.run(_session(configs))


def test_bots_negotiate_velocities_by_method(mixed_room: list[BotReport]) -> None:
    v0, v1, plain = mixed_room
    assert v0.velocities and v1.velocities and not plain.velocities
    for rep in (v0, v1):
        by_user: dict[int, list[RemoteStream]] = {}
        for rs in rep.streams.values():
            by_user.setdefault(rs.user, []).append(rs)
            assert len(rs.velocities) == len(rs.capture) >= 5  # liveness only
        other = v1 if rep is v0 else v0
        assert all(rs.sends_velocities for rs in by_user[other.user])
        # The plain bot's streams arrive with zero velocities, and are flagged as such.
        assert all(not rs.sends_velocities for rs in by_user[plain.user])
        assert all(not np.any(v) for rs in by_user[plain.user] for v in rs.velocities)
    for rs in plain.streams.values():
        assert rs.velocities == [] and len(rs.capture) >= 5


def test_received_velocities_are_the_senders_causal_velocities(
    mixed_room: list[BotReport],
) -> None:
    """Each received velocity is the sender's causal estimate at that sample, as float16."""
    v0, v1, _ = mixed_room
    checked = 0
    for rep, sender in ((v0, v1), (v1, v0)):
        for rs in rep.streams.values():
            if rs.user != sender.user:
                continue
            assert rs.label is not None
            spec = MotionSpec.parse(rs.label)
            trace = spec.load().select(DEVICE_NAMES)
            vel = trace.causal_velocities()[:, DEVICE_NAMES.index(rs.name)]
            want16 = np.clip(vel, -VELOCITY_MAX, VELOCITY_MAX).astype(np.float16)
            rel = np.asarray(rs.capture) - spec.t0
            idx = np.abs(trace.times[None, :] - rel[:, None]).argmin(axis=1)
            assert np.abs(trace.times[idx] - rel).max() < 1e-5
            got = np.asarray(rs.velocities)
            np.testing.assert_array_equal(got, want16[idx].astype(np.float64))
            assert np.abs(got).max() > 0.1  # real motion, not zeros
            checked += len(idx)
    assert checked >= 2 * 3 * 5  # every keyframe is checked; how many: the machine's load


def test_live_hermite_render_equals_offline_computation(mixed_room: list[BotReport]) -> None:
    """Every live motor-hermite frame is the QoE definition's pose from the arrival log;
    on the plain bot's streams (no velocities) that is the fallback, motor-lerp."""
    checked = {"motor-hermite": 0, VELOCITY_FALLBACK: 0}
    for rep in mixed_room[:2]:
        assert rep.render_log
        logs: dict[tuple[int, int], KeyframeLog] = {}
        for k, rs in rep.streams.items():
            local = RemoteStream(
                rs.user, rs.stream, rs.name, rs.label, sends_velocities=rs.sends_velocities
            )
            local.capture, local.arrival, local.poses = rs.capture, rs.arrival_local, rs.poses
            local.velocities = rs.velocities
            logs[k] = remote_log(local)
            # zeros from a sender that reports none are fillers, not velocities
            assert (logs[k].velocities is not None) == rs.sends_velocities
        # The render log keeps the first method: soa. Re-render motor-hermite from the
        # same arrivals and check it against the live renderer's own code path below.
        for t_play, _d, rendered_at, shown in rep.render_log[5::7]:
            for key in shown:
                log = logs[key]
                play = playout_brackets(
                    log.capture, log.arrival, np.array([t_play]), np.array([rendered_at - t_play])
                )
                if play.missing[0]:
                    continue
                method = rendered_method("motor-hermite", log.velocities is not None)
                offline = interpolate_brackets(
                    log.poses,
                    play.lo,
                    play.hi,
                    play.s,
                    method,
                    times=log.capture,
                    velocities=log.velocities,
                )[0, 0]
                buf = StreamBuffer(has_velocities=log.velocities is not None)
                arrived = log.arrival <= rendered_at
                for n, (c, p) in enumerate(
                    zip(log.capture[arrived], log.poses[arrived, 0], strict=True)
                ):
                    v = None if log.velocities is None else log.velocities[arrived, 0][n]
                    buf.push(float(c), p.astype(np.float32), velocity=v)
                live = render_buffers([buf], t_play, ["motor-hermite"]).poses["motor-hermite"]
                np.testing.assert_allclose(live[0], offline, atol=1e-6)
                checked[method] += 1
    # Every 7th frame is checked; how many frames there are depends on the machine's load.
    assert checked["motor-hermite"] >= 10 and checked[VELOCITY_FALLBACK] >= 10


def test_velocity_methods_are_scored_like_the_fallback_on_streams_without_velocities(
    mixed_room: list[BotReport],
) -> None:
    """The live QoE of motor-hermite on the plain bot's streams is motor-lerp's, exactly."""
    v0, _v1, plain = mixed_room
    assert v0.render_log
    play_t = [r[0] for r in v0.render_log]
    play_d = [r[1] for r in v0.render_log]
    streams = {k: rs for k, rs in v0.streams.items() if rs.user == plain.user}
    assert streams and not any(rs.sends_velocities for rs in streams.values())
    res = evaluate_remote(streams, play_t, play_d, ["motor-hermite", VELOCITY_FALLBACK])
    assert res["motor-hermite"].keys() == res[VELOCITY_FALLBACK].keys() == {"hands", "head"}
    for cls, samples in res["motor-hermite"].items():
        assert samples.stats() == res[VELOCITY_FALLBACK][cls].stats()


def test_live_hermite_qoe_is_finite_and_in_the_offline_ballpark(
    mixed_room: list[BotReport],
) -> None:
    """motor-hermite is scored live like the others; its typical error matches offline.

    The offline side interpolates the very keyframes each bot received, on an ideal
    network (each arrives at its capture time, D covers the longest gap): a starved
    machine delivers fewer keyframes, and both sides then interpolate the same
    longer gaps. What only the live side has (its adaptive D, late arrivals held
    through) costs both methods alike, so the two live/offline factors stay close.
    """
    report = swarm_report(mixed_room[:2])
    methods = report["methods"]
    assert set(methods) == {"soa", "motor-hermite"}
    for cls in ("hands", "head"):
        for key in ("tip_p50_mm", "tip_p95_mm", "rot_p95_deg"):
            assert np.isfinite(methods["motor-hermite"][cls][key])
    groups = []
    for rep in mixed_room[:2]:
        by_label: dict[str, list[RemoteStream]] = {}
        for rs in rep.streams.values():
            if rs.user != mixed_room[2].user:
                assert rs.label is not None
                by_label.setdefault(rs.label, []).append(rs)
        for label, streams in by_label.items():
            spec = MotionSpec.parse(label)
            truth = spec.truth().select(DEVICE_NAMES)
            caps = np.unique(np.concatenate([rs.capture for rs in streams]))
            idx = np.abs(truth.times[None, :] - caps[:, None]).argmin(axis=1)
            assert np.abs(truth.times[idx] - caps).max() < 1e-5
            # What the sender sent with each: its causal velocity, as float16.
            vel = truth.causal_velocities()
            vel = np.clip(vel, -VELOCITY_MAX, VELOCITY_MAX).astype(np.float16).astype(float)
            keys = truth.times[idx]
            log = KeyframeLog(keys, keys, truth.poses[idx], vel[idx])
            delay = float(np.diff(keys).max()) + 1.0 / truth.native_rate
            window = truth.window(float(caps[0]), float(caps[-1]))
            groups.append(evaluate_group(window, log, delay, ["soa", "motor-hermite"]))
    offline = summarize(groups)
    # On the same keyframes, velocities help where keyframes bracket the sample.
    assert offline["motor-hermite"]["hands"]["tip_p50_mm"] < offline["soa"]["hands"]["tip_p50_mm"]
    ratio = {
        m: methods[m]["hands"]["tip_p50_mm"] / offline[m]["hands"]["tip_p50_mm"]
        for m in ("soa", "motor-hermite")
    }
    # Live costs more than ideal (holds, D), never less than about ideal...
    assert 0.5 < ratio["motor-hermite"] < 6.0
    # ... and hermite not much more than soa (measured: about twice): velocities
    # received wrong (units, frame, stream) would blow up hermite's factor alone.
    assert ratio["motor-hermite"] < 3.0 * ratio["soa"]


def test_velocity_bytes_are_counted_per_remote_pose(mixed_room: list[BotReport]) -> None:
    """Velocity bots pay at least 12 B more per remote pose than the plain bot, in the report."""
    v = swarm_report(mixed_room[:2])["wire"]
    p = swarm_report(mixed_room[2:])["wire"]
    assert v["velocity_keyframes"] and not p["velocity_keyframes"]
    assert v["bytes_per_pose"] - p["bytes_per_pose"] >= 10.0
    assert p["bytes_per_pose"] > 36


def test_demo_command_renders_motor_hermite_live(tmp_path: Path) -> None:
    out = tmp_path / "demo.json"
    result = CliRunner().invoke(
        app,
        [
            "demo",
            "--bots",
            "2",
            "--duration",
            "3",
            "--interp",
            "soa,motor-hermite",
            "--no-record",
            "--json",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    report = json.loads(out.read_text())
    assert set(report["methods"]) == {"soa", "motor-hermite"}
    assert report["wire"]["velocity_keyframes"] is True
    assert np.isfinite(report["methods"]["motor-hermite"]["hands"]["tip_p50_mm"])


def test_bot_velocity_table_equals_the_whole_trace_estimate(dev_trace_path: Path) -> None:
    """The bot's chunked causal velocities are exactly Trace.causal_velocities()."""
    from posecast.client.publish import CausalVelocities
    from posecast.scenarios.traces import load_trace

    trace = load_trace(dev_trace_path).select(DEVICE_NAMES).window(0.0, 12.0)
    full = trace.causal_velocities()
    table = CausalVelocities(trace)
    n = len(trace.times)
    assert n > 2 * CausalVelocities.CHUNK
    for i in [n - 1, 0, 1, 2, 3, 255, 256, 257, 511, 512, 700, *range(0, n, 37)]:
        np.testing.assert_array_equal(table[i], full[i])
