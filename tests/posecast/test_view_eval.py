"""posecast.view_eval: a room driven offline through the relay's own per-peer schedule."""

from __future__ import annotations

from posecast.scenarios.traces import DEVICE_NAMES, find_traces, load_trace
from posecast.view_eval import build, run_policy, score


def test_a_wide_budget_sends_fewer_bytes_and_a_fixed_rate_sends_every_peer_at_30() -> None:
    """Five users on a circle of 4 m for 3 s: fixed 30 Hz gives every pair 30 keyframes
    a second and one encode per tick; a budget of 10 degrees lowers the peers' rates
    and the bytes, at more encodes per tick and more error."""
    traces = [load_trace(p).select(DEVICE_NAMES) for p in find_traces("traces:sample")]
    room = build(traces, 5, "circle:4", 3.0)
    fixed = run_policy(room, True, None, 1.0)
    view = run_policy(room, True, 10.0, 1.0)
    f, _ = score(room, fixed, "fixed", "compact", 1.0)
    v, _ = score(room, view, "view", "compact", 1.0)
    assert abs(f.mean_rate_hz - 30.0) < 0.5 and f.encodes_per_tick <= 1.0
    assert v.mean_rate_hz < 25.0 and v.bytes_per_s < f.bytes_per_s
    assert v.encodes_per_tick > 1.0
    assert v.angle_p95_deg > f.angle_p95_deg


def test_the_client_rule_with_per_peer_delays_bridges_slower_peers() -> None:
    """Scored with the client's own playout rule: at a fixed rate, per peer gives the
    room's D and figures exactly; under a budget, the room's D stalls the slower peers
    and per peer D stalls less, at a longer D for the slower (farther) bands."""
    traces = [load_trace(p).select(DEVICE_NAMES) for p in find_traces("traces:sample")]
    room = build(traces, 5, "circle:4", 4.0)
    fixed = run_policy(room, True, None, 1.0)
    f_room, _ = score(room, fixed, "fixed", "compact", 1.0, rule="room")
    f_peer, _ = score(room, fixed, "fixed", "compact", 1.0, rule="peer")
    assert f_peer.delay_ms == f_room.delay_ms and f_peer.angle_p95_deg == f_room.angle_p95_deg
    view = run_policy(room, True, 10.0, 1.0)
    v_room, _ = score(room, view, "view", "compact", 1.0, rule="room")
    v_peer, _ = score(room, view, "view", "compact", 1.0, rule="peer")
    assert v_peer.stall_pct < v_room.stall_pct
    assert v_peer.delay_ms > v_room.delay_ms


def test_a_longer_look_back_never_lowers_a_peers_rate() -> None:
    """The acceleration estimate is a running max: over 1 s it is at least the one over
    0.1 s, so every peer goes at least as often and the bytes do not fall."""
    traces = [load_trace(p).select(DEVICE_NAMES) for p in find_traces("traces:sample")]
    room = build(traces, 5, "circle:4", 3.0)
    short = run_policy(room, False, 10.0, 1.0, lookback=0.1)
    long = run_policy(room, False, 10.0, 1.0, lookback=1.0)
    s, _ = score(room, short, "short", "raw", 1.0)
    g, _ = score(room, long, "long", "raw", 1.0)
    assert g.mean_rate_hz > s.mean_rate_hz and sum(long.wire_bytes) > sum(short.wire_bytes)
