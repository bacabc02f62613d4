"""View-aware rates against a fixed rate in a 20-user room (``python -m posecast.view_eval``).

A room of ``users`` users stands on the spawn points of ``layout``
(``scenarios.spawn``; ``circle:4``: neighbours 1.25 m apart, 8 m across). User i
plays trace ``i mod T`` of ``traces`` from ``10 (i div T)`` s in, moved onto its
spawn point, for ``seconds`` s; every user publishes every native sample of its
head and hands, and every user subscribes at 30 Hz. The relay is the relay's own
:class:`server.room.Room` driven offline (no sockets, no clocks, seeded by the
traces): the *fixed* policy is every member without a budget (every peer at
30 Hz, today's relay), *view* every member with ``join.budget_deg`` (each peer at
``30 / k`` Hz, :mod:`server.view_rates`). Frames are taken by each subscriber's
writer at once (an ideal network: what changes is the schedule, not the link),
decoded with the client's own decoders, and rendered with SoA.

Budget: SoA@30's angular error at 1 m, i.e. ``atan(p95 tip error / 1 m)`` of the
fixed policy in the same run (all streams pooled), unless ``--budget-deg`` says.

Scoring (DESIGN.md's angular error): for each subscriber, each peer stream and each
native sample tau of that stream after ``warmup`` s, the tip error of the rendered
pose against the true one, as a visual angle from the subscriber's true head at
tau. The playout delay D (``--delays``, one row per rule): ``room``, the client's own
:class:`client.playout.RoomPlayoutDelay` as a client without per-peer delays runs
it (every peer at the room's D, sized from the snapshot rate); ``peer``, the same
with ``per_peer`` (what a client that joined with ``budget_deg`` runs: each peer's
D also bridges its own keyframe interval); ``pair``, an oracle, the 99th
percentile over the whole run of the time from a keyframe's capture to the next
keyframe's arrival, per (subscriber, peer) pair. The client rules are fed every
keyframe at its arrival (its age, its snapshot's send time) and updated at 90 Hz
frames; a sample tau is shown at the frame time t with t - D(t) = tau, with the
keyframes arrived by then (a sample past the newest arrived keyframe holds it and
counts as a stall). Latency is capture-to-display: a pair's D averaged over its
scored samples; ``D ms`` is the mean over pairs, also per distance band.
``+1 frame`` renders every view pair at the fixed policy's D plus one 30 Hz frame
instead (the goal's latency bound), stalls and all. Bytes are on the wire: frame,
websocket header, TCP/IP headers (``scenarios.network``).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from posecast.client.playout import RoomPlayoutDelay
from posecast.interp import TIP_OFFSET_M, quat_rotate, tip_error_mm
from posecast.interp import get as get_interp
from posecast.interp.expected_error import WINDOW_S, Acceleration
from posecast.protocol import PoseUpdate, Snapshot, decode_message
from posecast.protocol._compact import SnapshotDecoder
from posecast.protocol.codec import DEFAULT_VOLUME
from posecast.scenarios.network import TCP_IP_HEADER_BYTES, TCP_MSS, websocket_header_bytes
from posecast.scenarios.spawn import layout_points, place, placement_for
from posecast.scenarios.traces import DEVICE_NAMES, Trace, find_traces, load_trace
from posecast.server.room import Member, Outbox, Room
from posecast.server.view_rates import Motion, ViewRates, ViewState

__all__ = ["Room20", "Scored", "main", "run_policy", "score"]

F64 = NDArray[np.float64]
RATE = 30.0
#: Render frames per second the client playout rules are updated at.
FRAME_RATE = 90.0
#: Distance bands (m) between a subscriber's and a peer's spawn points.
BANDS = ((0.0, 2.0), (2.0, 4.0), (4.0, 6.0), (6.0, 9.0))


@dataclass
class Room20:
    """The placed motions: per user its (times, poses (n, 3, 7)) on the room's clock."""

    times: list[F64]
    poses: list[F64]
    spawn: list[tuple[float, float]]
    seconds: float


def build(traces: Sequence[Trace], users: int, layout: str, seconds: float) -> Room20:
    points = layout_points(layout, users)
    assert points is not None, "a view judgement needs a layout with distances"
    times, poses = [], []
    for i in range(users):
        tr = traces[i % len(traces)]
        start = tr.times[0] + 10.0 * (i // len(traces))
        keep = (tr.times >= start) & (tr.times <= start + seconds)
        placed = place(tr, placement_for(tr, points[i]))
        times.append(tr.times[keep] - start)
        poses.append(placed.poses[keep])
    return Room20(times, poses, [(p.x, p.z) for p in points], seconds)


def _wire(payload: int) -> int:
    payload += websocket_header_bytes(payload)
    return payload + max(1, -(-payload // TCP_MSS)) * TCP_IP_HEADER_BYTES


@dataclass
class Received:
    """What one policy delivered: per subscriber, per (peer user, stream index) the
    keyframes (capture, arrival, pose), and the wire bytes per subscriber."""

    keyframes: dict[int, dict[tuple[int, int], tuple[F64, F64, F64]]]
    wire_bytes: list[int]
    encodes: int
    room_ticks: int
    tick_cpu_s: float
    ingest_cpu_s: float


@dataclass
class LookbackMotion(Motion):
    """The relay's motion follower with another look-back of its acceleration
    estimate (``--lookback``; the relay's is ``WINDOW_S``)."""

    window_s: float = WINDOW_S

    def observe(self, sid: int, t: float, pose: bytes) -> None:
        if sid not in self.accel:
            self.accel[sid] = Acceleration(window_s=self.window_s)
        super().observe(sid, t, pose)


def run_policy(
    room20: Room20,
    compact: bool,
    budget_deg: float | None,
    margin: float,
    min_rate: float = 5.0,
    lookback: float | None = None,
) -> Received:
    """Drive the relay's Room through the whole session under one policy (``lookback``:
    seconds of the acceleration estimate's look-back, None: the relay's)."""
    room = Room("view-eval", views=ViewRates(min_rate, margin), phase=0.0)
    if lookback is not None and budget_deg is not None:
        room.motion = LookbackMotion(window_s=lookback)
    n = len(room20.times)
    members = []
    for u in range(n):
        m = Member(u, f"u{u}", room.allocate_streams(DEVICE_NAMES), RATE, Outbox(), compact=compact)
        m.view = None if budget_deg is None else ViewState(budget_deg)
        room.add(m, 0.0)
        members.append(m)
    events = sorted((float(t), u, j) for u in range(n) for j, t in enumerate(room20.times[u]))
    frames: list[list[tuple[float, bytes]]] = [[] for _ in range(n)]
    tick_cpu = ingest_cpu = 0.0
    room_ticks = 0
    for seq, (t, u, j) in enumerate(events, 1):
        due = room.next_due()
        while due is not None and due <= t:
            c0 = time.process_time()
            room.tick(due)
            tick_cpu += time.process_time() - c0
            room_ticks += 1
            for v, m in enumerate(members):
                data = m.outbox.take()
                if data is not None:
                    frames[v].append((due, data))
            due = room.next_due()
        sids = list(members[u].streams.values())
        c0 = time.process_time()
        room.ingest(u, PoseUpdate.from_arrays(seq, sids, [t] * 3, room20.poses[u][j]))
        ingest_cpu += time.process_time() - c0
    keyframes = {}
    for v in range(n):
        keyframes[v] = _decode(frames[v], compact, members)
    return Received(
        keyframes,
        [sum(_wire(len(d)) for _, d in f) for f in frames],
        room.statistics().snapshots_encoded,
        room_ticks,
        tick_cpu,
        ingest_cpu,
    )


def _decode(
    frames: list[tuple[float, bytes]], compact: bool, members: list[Member]
) -> dict[tuple[int, int], tuple[F64, F64, F64]]:
    index = {sid: (m.user, j) for m in members for j, sid in enumerate(m.streams.values())}
    dec = SnapshotDecoder(DEFAULT_VOLUME) if compact else None
    got: dict[tuple[int, int], list[tuple[float, float, Any]]] = {}
    for arrival, data in frames:
        snap = dec.decode(data) if dec is not None else decode_message(data)
        assert isinstance(snap, Snapshot)
        for s, c, p in zip(snap.streams, snap.capture_times, snap.poses, strict=True):
            got.setdefault(index[int(s)], []).append((float(c), arrival, p))
    out = {}
    for key, rows in got.items():
        out[key] = (
            np.array([r[0] for r in rows]),
            np.array([r[1] for r in rows]),
            np.array([r[2] for r in rows], np.float64),
        )
    return out


@dataclass
class Scored:
    """One policy's figures (all subscribers, all peer streams pooled)."""

    policy: str
    codec: str
    bytes_per_s: float
    angle_p50_deg: float
    angle_p95_deg: float
    tip_p95_mm: float
    delay_ms: float
    stall_pct: float
    mean_rate_hz: float
    band_p95_deg: list[float]
    band_delay_ms: list[float]
    band_rate_hz: list[float]
    encodes_per_tick: float
    tick_cpu_ms_per_s: float
    #: How D was chosen: ``pair``, ``room``, ``peer`` or ``fixed`` (``delay_of``).
    rule: str = "pair"


def _render(
    kf: tuple[F64, F64, F64], taus: F64, delay: float | F64
) -> tuple[F64, NDArray[np.bool_]]:
    """Rendered poses at ``taus`` with keyframes arrived by tau + delay; stall mask."""
    c, a, p = kf
    arrived = np.searchsorted(a, taus + delay, side="right")  # a prefix of the keyframes
    i = np.searchsorted(c, taus, side="right") - 1
    ok = (i >= 0) & (i + 1 < arrived)
    lo = np.clip(i, 0, len(c) - 1)
    hi = np.clip(i + 1, 0, len(c) - 1)
    span = np.where(ok, c[hi] - c[lo], 1.0)
    s = np.where(ok, (taus - c[lo]) / np.where(span > 0, span, 1.0), 0.0)
    out = get_interp("soa")(p[lo], p[hi], s)
    held = p[np.clip(arrived - 1, 0, len(c) - 1)]
    out = np.where(ok[:, None], out, held)
    return out, ~ok


def _pair_delay(kf: tuple[F64, F64, F64]) -> float:
    c, a, _ = kf
    if len(c) < 3:
        return 1.0 / RATE
    return float(np.percentile(a[1:] - c[:-1], 99))


def client_delays(
    kfs: dict[tuple[int, int], tuple[F64, F64, F64]], seconds: float, per_peer: bool
) -> tuple[F64, dict[int, F64]]:
    """One subscriber's client playout rule run over what it received: every keyframe
    observed at its arrival (age; the snapshot's send time is its arrival here, an
    ideal network), D updated every render frame. Returns the frame times and each
    peer's D at them."""
    delay = RoomPlayoutDelay(interval=1.0 / RATE, rate=RATE, per_peer=per_peer)
    rows = sorted(
        (float(ai), u, float(ai - ci))
        for (u, _), (c, a, _) in kfs.items()
        for ci, ai in zip(c, a, strict=True)
    )
    grid = np.arange(0.0, seconds + 1.0, 1.0 / FRAME_RATE)
    users = sorted({u for u, _ in kfs})
    out = {u: np.empty(len(grid)) for u in users}
    i = 0
    for g, t in enumerate(grid.tolist()):
        while i < len(rows) and rows[i][0] <= t:
            arrival, u, age = rows[i]
            delay.observe(u, age, arrival)
            i += 1
        delay.update(t)
        for u in users:
            out[u][g] = delay.delay(u)
    return grid, out


def _shown_delay(grid: F64, d: F64, taus: F64) -> F64:
    """D at the frame that shows ``taus`` (t - D(t) = tau, two fixed-point steps)."""
    shown = np.interp(taus, grid, d)
    for _ in range(2):
        shown = np.interp(taus + shown, grid, d)
    return shown


def score(
    room20: Room20,
    rec: Received,
    policy: str,
    codec: str,
    warmup: float,
    delay_of: float | None = None,
    rule: str = "pair",
) -> tuple[Scored, F64]:
    """Angular errors of every subscriber's view of every peer stream (and the tips' mm),
    each pair rendered at ``delay_of`` (s), else by ``rule`` (``pair``, ``room``,
    ``peer``: see the module docstring)."""
    n = len(room20.times)
    offset = np.array([0.0, 0.0, -TIP_OFFSET_M])
    true_tips = [p[..., :3] + quat_rotate(p[..., 3:], offset) for p in room20.poses]
    angles, tips, stalls, delays, rates = [], [], [], [], []
    bands: list[list[F64]] = [[] for _ in BANDS]
    band_d: list[list[float]] = [[] for _ in BANDS]
    band_r: list[list[float]] = [[] for _ in BANDS]
    for v in range(n):
        head_t, head_p = room20.times[v], room20.poses[v][:, 0, :3]
        sx, sz = room20.spawn[v]
        grid, per_user = (
            client_delays(rec.keyframes[v], room20.seconds, rule == "peer")
            if delay_of is None and rule != "pair"
            else (None, {})
        )
        for (u, j), kf in rec.keyframes[v].items():
            if u == v:
                continue
            taus = room20.times[u]
            sel = (taus >= warmup) & (taus <= room20.seconds - 0.5)
            taus, truth, true_tip = taus[sel], room20.poses[u][sel, j], true_tips[u][sel, j]
            delay: float | F64 = _pair_delay(kf) if delay_of is None else delay_of
            if grid is not None:
                delay = _shown_delay(grid, per_user[u], taus)
            shown, stalled = _render(kf, taus, delay)
            tip = tip_error_mm(shown, truth)
            eye = np.stack([np.interp(taus, head_t, head_p[:, k]) for k in range(3)], 1)
            dist = np.linalg.norm(true_tip - eye, axis=1)
            ang = np.degrees(np.arctan2(tip / 1000.0, np.maximum(dist, 0.05)))
            angles.append(ang)
            tips.append(tip)
            stalls.append(stalled)
            delay = float(np.mean(delay))
            delays.append(delay)
            span = kf[0][-1] - kf[0][0]
            rate = (len(kf[0]) - 1) / span if span > 0 else 0.0
            rates.append(rate)
            ux, uz = room20.spawn[u]
            d = math.hypot(ux - sx, uz - sz)
            b = next(k for k, (lo, hi) in enumerate(BANDS) if lo <= d < hi)
            bands[b].append(ang)
            band_d[b].append(delay)
            band_r[b].append(rate)
    all_ang = np.concatenate(angles)
    secs = room20.seconds
    return Scored(
        policy=policy,
        codec=codec,
        bytes_per_s=float(np.mean(rec.wire_bytes)) / secs,
        angle_p50_deg=float(np.percentile(all_ang, 50)),
        angle_p95_deg=float(np.percentile(all_ang, 95)),
        tip_p95_mm=float(np.percentile(np.concatenate(tips), 95)),
        delay_ms=1000.0 * float(np.mean(delays)),
        stall_pct=100.0 * float(np.mean(np.concatenate(stalls))),
        mean_rate_hz=float(np.mean(rates)),
        band_p95_deg=[
            float(np.percentile(np.concatenate(b), 95)) if b else math.nan for b in bands
        ],
        band_delay_ms=[1000.0 * float(np.mean(b)) if b else math.nan for b in band_d],
        band_rate_hz=[float(np.mean(b)) if b else math.nan for b in band_r],
        encodes_per_tick=rec.encodes / max(1, rec.room_ticks),
        tick_cpu_ms_per_s=1000.0 * rec.tick_cpu_s / secs,
        rule=rule if delay_of is None else "fixed",
    ), np.concatenate(tips)


def _table(rows: Sequence[Scored]) -> list[str]:
    bands = " | ".join(f"p95 deg {lo:g}-{hi:g} m" for lo, hi in BANDS)
    band_d = " | ".join(f"D ms {lo:g}-{hi:g} m" for lo, hi in BANDS)
    out = [
        f"| codec | policy | D rule | bytes/s per subscriber | angle p50 / p95 deg | {bands} "
        f"| D ms | {band_d} | stall % | mean peer rate Hz | encodes per tick | tick CPU ms/s |",
        "|---|---|---|---|---|" + "---|" * (2 * len(BANDS)) + "---|---|---|---|---|",
    ]
    for r in rows:
        b = " | ".join(f"{x:.3f}" for x in r.band_p95_deg)
        d = " | ".join(f"{x:.0f}" for x in r.band_delay_ms)
        out.append(
            f"| {r.codec} | {r.policy} | {r.rule} | {r.bytes_per_s:,.0f} | {r.angle_p50_deg:.3f}"
            f" / {r.angle_p95_deg:.3f} | {b} | {r.delay_ms:.0f} | {d} | {r.stall_pct:.2f} "
            f"| {r.mean_rate_hz:.1f} | {r.encodes_per_tick:.1f} | {r.tick_cpu_ms_per_s:.0f} |"
        )
    return out


def main(argv: Sequence[str] | None = None) -> None:
    ap = argparse.ArgumentParser(prog="python -m posecast.view_eval")
    ap.add_argument("--traces", default="traces:eval")
    ap.add_argument("--users", type=int, default=20)
    ap.add_argument("--layout", default="circle:4")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--warmup", type=float, default=2.0)
    ap.add_argument("--codecs", default="raw,compact")
    ap.add_argument("--margins", default="1", help="safety factors to run (comma-separated)")
    ap.add_argument("--floors", default="5,15", help="lowest per-peer rates to run (Hz)")
    ap.add_argument(
        "--delays",
        default="room,peer",
        help="playout delay rules to score each policy with: room, peer, pair (comma-separated)",
    )
    ap.add_argument("--budget-deg", type=float, default=None)
    ap.add_argument(
        "--lookback",
        type=float,
        default=None,
        help=f"look-back (s) of the relay's acceleration estimate (default {WINDOW_S})",
    )
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    rules = args.delays.split(",")
    bad = [r for r in rules if r not in ("room", "peer", "pair")]
    if bad:
        ap.error(f"--delays: unknown rule {bad[0]!r} (room, peer, pair)")
    traces = [load_trace(p).select(DEVICE_NAMES) for p in find_traces(args.traces)]
    room20 = build(traces, args.users, args.layout, args.seconds)
    rows: list[Scored] = []
    budget = args.budget_deg
    for codec in args.codecs.split(","):
        compact = codec == "compact"
        fixed = run_policy(room20, compact, None, 1.0)
        # The budget comes from the oracle D (few stalls), as in the first judgement.
        oracle, tips = score(room20, fixed, "fixed 30 Hz", codec, args.warmup)
        fixed_rows = {r: score(room20, fixed, "fixed 30 Hz", codec, args.warmup, rule=r)[0]
                      for r in rules if r != "pair"}  # fmt: skip
        fixed_rows["pair"] = oracle
        rows += [fixed_rows[r] for r in rules]
        if budget is None:
            budget = math.degrees(math.atan(float(np.percentile(tips, 95)) / 1000.0))
            print(f"budget: SoA@30's angular error at 1 m = {budget:.3f} deg ({codec})")
        for floor in (float(f) for f in args.floors.split(",")):
            for margin in (float(m) for m in args.margins.split(",")):
                view = run_policy(room20, compact, budget, margin, floor, args.lookback)
                name = f"view x{margin:g} >={floor:g} Hz"
                if args.lookback is not None:
                    name += f" look-back {args.lookback:g} s"
                for r in rules:
                    rows.append(score(room20, view, name, codec, args.warmup, rule=r)[0])
                if floor < RATE / 2:  # the latency bound: render at the fixed D + 1 frame
                    plus = fixed_rows[rules[0]].delay_ms / 1000.0 + 1.0 / RATE
                    rows.append(
                        score(room20, view, f"{name}, +1 frame", codec, args.warmup, plus)[0]
                    )
        print("\n".join(_table(rows)), flush=True)
    print(f"{len(traces)} traces ({args.traces}), {args.users} users on {args.layout}, "
          f"{args.seconds:g} s, budget {budget:.3f} deg")  # fmt: skip
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"budget_deg": budget, "rows": [asdict(r) for r in rows]}, f, indent=1)


if __name__ == "__main__":
    main()
