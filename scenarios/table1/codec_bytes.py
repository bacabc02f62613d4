"""Wire bytes of a room snapshot with each codec, measured offline on the traces.

Table 1 prices a method at rate ``r`` as ``r`` times the wire bytes of one snapshot
of its room (:data:`~scenarios.table1.common.DEFAULT_ROOM_POSES` poses). For the
``raw`` codec that is the float32 record of :mod:`protocol.poses` (fixed size:
:func:`scenarios.network.wire_bytes`). For the ``compact`` codec the size depends on
the motion and the rate, so :func:`compact_snapshot_bytes` measures it the way an
observer subscriber would receive it: a room of ``room_poses // streams`` users, user
``u`` replaying trace ``u % T`` from ``(u // T) * 7 + 0.9 u`` s in (so no two users
move alike); at each tick ``k / r`` every stream's newest native sample; a key
snapshot at the first tick and at least every :data:`KEY_INTERVAL_S`, otherwise each
stream delta-coded against the codes this subscriber last received for it; a stream
with nothing new since is left out; the observer publishes nothing, so it gets no
stream of its own back. Frames are the relay's own snapshot layout, through the
public codec API: :func:`protocol.codec.quantise` of the poses (and velocities, for
velocity methods), then :func:`protocol.codec_relay.encode_group` and
``GroupSnapshot.frame`` (the bytes a subscriber of the relay receives), so a change
of the codec's bit layout shows here without any change to this module. Framing as
:func:`scenarios.network.wire_bytes` counts it: the codec frame is the websocket
payload (not msgpack), plus the websocket header and TCP/IP headers per segment.

The codec's own error (at most 0.25 mm, 0.034 deg, 0.5 ms; ``docs/concepts/codec.md``) is
not fed back into the QoE here: the equal-QoE rates are those of the float poses.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from posecast.protocol.codec import DEFAULT_VOLUME, Volume, quantise
from posecast.protocol.codec_relay import encode_group
from posecast.scenarios.network import TCP_IP_HEADER_BYTES, TCP_MSS, websocket_header_bytes
from posecast.scenarios.traces import Trace

__all__ = [
    "CODECS",
    "KEY_INTERVAL_S",
    "CompactSize",
    "SizeCache",
    "codec_markdown",
    "codec_report",
    "compact_snapshot_bytes",
    "payload_wire_bytes",
    "room_volume",
]

#: The codecs Table 1 prices.
CODECS = ("raw", "compact")
#: A key snapshot at least this often (s), as the relay sends them.
KEY_INTERVAL_S = 2.0
#: Longest room replay measured per rate (s): enough ticks for a stable mean.
MAX_DURATION_S = 60.0


@dataclass(frozen=True)
class CompactSize:
    """Mean sizes of the compact snapshots an observer received at one rate."""

    rate: int
    velocities: bool
    snapshots: int
    poses_per_snapshot: float
    #: mean wire bytes of a snapshot (payload + websocket + TCP/IP), keys included
    wire_bytes: float
    #: mean codec frame bytes (the websocket payload)
    payload_bytes: float
    key_payload_bytes: float
    delta_payload_bytes: float

    @property
    def bytes_per_pose(self) -> float:
        """Mean wire bytes per delivered pose."""
        return self.wire_bytes / self.poses_per_snapshot


def payload_wire_bytes(payload: int) -> int:
    """Wire bytes of one websocket binary message of ``payload`` bytes over TCP/IP."""
    total = payload + websocket_header_bytes(payload)
    return total + max(1, -(-total // TCP_MSS)) * TCP_IP_HEADER_BYTES


@dataclass(frozen=True)
class _Room:
    """Who plays what: per user its trace, start offset and streams."""

    traces: list[Trace]
    offsets: list[float]
    users: list[int]
    streams: list[int]
    duration: float


def _room(traces: Sequence[Trace], room_poses: int) -> _Room:
    per_user = min(len(tr.streams) for tr in traces)
    n_users = max(1, room_poses // per_user)
    trs, offs = [], []
    for u in range(n_users):
        tr = traces[u % len(traces)]
        trs.append(tr)
        # Start offsets wrap within the first half of a short trace, so that every
        # user still has half of it to play.
        span = 0.5 * (float(tr.times[-1]) - float(tr.times[0]))
        offs.append(float(tr.times[0]) + ((u // len(traces)) * 7.0 + 0.9 * u) % span)
    duration = min(float(tr.times[-1]) - o for tr, o in zip(trs, offs, strict=True))
    if duration <= 1.0:
        raise ValueError(f"traces too short for a room of {n_users} users")
    users = [u + 1 for u in range(n_users) for _ in range(per_user)]
    streams = [s for _ in range(n_users) for s in range(per_user)]
    return _Room(trs, offs, users, streams, min(duration, MAX_DURATION_S))


def _sample(
    room: _Room, t: float, vel_of: dict[int, np.ndarray] | None
) -> tuple[list[int], np.ndarray, np.ndarray, np.ndarray | None]:
    """Each user's newest native sample at room time ``t``: indices, poses, capture
    times (room time) and velocities (if ``vel_of``), in (user, stream) order."""
    per_user = len(room.streams) // len(room.traces)
    idx = [
        int(np.searchsorted(tr.times, o + t, side="right")) - 1
        for tr, o in zip(room.traces, room.offsets, strict=True)
    ]
    rows = list(zip(room.traces, room.offsets, idx, strict=True))
    poses = np.concatenate([tr.poses[i, :per_user] for tr, _, i in rows])
    capture = np.repeat([tr.times[i] - o for tr, o, i in rows], per_user)
    vel = None
    if vel_of is not None:
        vel = np.concatenate([vel_of[id(tr)][i, :per_user] for tr, _, i in rows])
    return idx, poses, capture, vel


def _encode(
    tick: int,
    t: float,
    ids: list[tuple[int, int]],
    capture: np.ndarray,
    codes: np.ndarray,
    volume: Volume,
    baselines: dict[tuple[int, int], list[int]],
) -> bytes:
    """One relay snapshot for the observer; its baselines become these codes."""
    rows = codes.tolist()
    entries = [
        (u, s, float(c), row, baselines.get((u, s)))
        for (u, s), c, row in zip(ids, capture, rows, strict=True)
    ]
    group = encode_group(tick, t, entries, volume, codes.shape[1] == 13, trusted=True)
    data, _ = group.frame(exclude=None)
    for (u, s), row in zip(ids, rows, strict=True):
        baselines[(u, s)] = row
    return data


def compact_snapshot_bytes(
    traces: Sequence[Trace],
    rate: int,
    *,
    velocities: Sequence[np.ndarray] | None = None,
    room_poses: int = 48,
    volume: Volume = DEFAULT_VOLUME,
    on_frame: Callable[[bytes, np.ndarray], None] | None = None,
) -> CompactSize:
    """Mean compact snapshot of a ``room_poses`` room received at ``rate`` (see module doc).

    ``velocities``: per trace ``(N, S, 6)`` keyframe velocities for a velocity
    method (the velocity variant), or None for the plain variant. ``on_frame(data,
    poses)`` sees every frame the observer received and the float poses it codes.
    """
    room = _room(traces, room_poses)
    vel_of = {id(tr): v for tr, v in zip(traces, velocities or [], strict=False)}
    users = np.asarray(room.users, np.int64)
    streams = np.asarray(room.streams, np.int64)
    baselines: dict[tuple[int, int], list[int]] = {}
    last_sent: dict[tuple[int, int], int] = {}
    sizes: list[int] = []
    key_sizes: list[int] = []
    delta_sizes: list[int] = []
    counts: list[int] = []
    last_key = -math.inf
    for k in range(int(room.duration * rate)):
        t = k / rate
        idx, poses, capture, vel = _sample(room, t, vel_of if velocities is not None else None)
        key = t - last_key >= KEY_INTERVAL_S - 1e-9
        fresh = np.array(
            [
                key or last_sent.get((int(u), int(s))) != idx[int(u) - 1]
                for u, s in zip(users, streams, strict=True)
            ]
        )
        if not fresh.any():
            continue
        if key:
            baselines.clear()
            last_key = t
        codes = quantise(poses[fresh], volume, None if vel is None else vel[fresh])
        ids = list(zip(users[fresh].tolist(), streams[fresh].tolist(), strict=True))
        data = _encode(k, t, ids, capture[fresh], codes, volume, baselines)
        for u, s in ids:
            last_sent[(u, s)] = idx[u - 1]
        if on_frame is not None:
            on_frame(data, poses[fresh])
        sizes.append(len(data))
        (key_sizes if key else delta_sizes).append(len(data))
        counts.append(int(fresh.sum()))
    wire = [payload_wire_bytes(n) for n in sizes]
    return CompactSize(
        rate=rate,
        velocities=velocities is not None,
        snapshots=len(sizes),
        poses_per_snapshot=float(np.mean(counts)),
        wire_bytes=float(np.mean(wire)),
        payload_bytes=float(np.mean(sizes)),
        key_payload_bytes=float(np.mean(key_sizes)) if key_sizes else math.nan,
        delta_payload_bytes=float(np.mean(delta_sizes)) if delta_sizes else math.nan,
    )


# ---------------------------------------------------------------- the Table 1 stage


def room_volume(traces: Sequence[Trace]) -> Volume:
    """The codec's default volume, grown to whole metres around any trace that leaves it.

    A server states its volume at welcome; one that hosts these motions would state
    one that holds them (the synthetic fixtures wander above 4 m).
    """
    pos = np.concatenate([tr.poses[..., :3].reshape(-1, 3) for tr in traces])
    lo = np.minimum(np.asarray(DEFAULT_VOLUME.lo), np.floor(pos.min(axis=0)))
    hi = np.maximum(np.asarray(DEFAULT_VOLUME.hi), np.ceil(pos.max(axis=0)))
    if np.array_equal(lo, DEFAULT_VOLUME.lo) and np.array_equal(hi, DEFAULT_VOLUME.hi):
        return DEFAULT_VOLUME
    return Volume((lo[0], lo[1], lo[2]), (hi[0], hi[1], hi[2]))


class SizeCache:
    """Compact snapshot sizes per (variant, rate), measured once when first asked for."""

    def __init__(
        self,
        traces: Sequence[Trace],
        velocities: Sequence[np.ndarray] | None,
        room_poses: int,
    ) -> None:
        self.traces = traces
        self.velocities = velocities
        self.room_poses = room_poses
        self.volume = room_volume(traces)
        self.sizes: dict[tuple[bool, int], CompactSize] = {}

    def get(self, velocity: bool, rate: int) -> CompactSize:
        key = (velocity, int(rate))
        if key not in self.sizes:
            if velocity and self.velocities is None:
                raise ValueError("velocity sizes asked for without velocities")
            self.sizes[key] = compact_snapshot_bytes(
                self.traces,
                int(rate),
                velocities=self.velocities if velocity else None,
                room_poses=self.room_poses,
                volume=self.volume,
            )
        return self.sizes[key]


def codec_report(
    cache: SizeCache,
    tier_rows: Sequence[dict[str, Any]],
    frontier: dict[str, Any] | None,
    raw_bytes: dict[str, int],
    needs_velocity: dict[str, bool],
) -> dict[str, Any]:
    """The report's ``codecs`` key: bytes/s at equal QoE per tier, method and codec.

    ``raw_bytes``: each method's raw snapshot wire bytes; ``needs_velocity``: which
    methods send the velocity variant. Reference: raw SoA at the tier rate.
    """

    def bps(codec: str, m: str, rate: int | None) -> float | None:
        if rate is None:
            return None
        if codec == "raw":
            return float(rate * raw_bytes[m])
        return rate * cache.get(needs_velocity[m], rate).wire_bytes

    tiers = []
    for row in tier_rows:
        ref = float(row["soa_rate"] * raw_bytes["soa"])
        eq = row["equal_qoe_rate"]
        per = {c: {m: bps(c, m, eq[m]) for m in eq} for c in CODECS}
        tiers.append(
            {
                "name": row["name"],
                "soa_rate": row["soa_rate"],
                "reference_bytes_per_s": ref,
                "equal_qoe_rate": dict(eq),
                "bytes_per_s": per,
                "saving_vs_raw_soa_pct": {
                    c: {m: _saving(v, ref) for m, v in per[c].items()} for c in CODECS
                },
            }
        )
    out: dict[str, Any] = {
        "room_poses": cache.room_poses,
        "volume": {"lo": list(cache.volume.lo), "hi": list(cache.volume.hi)},
        "key_interval_s": KEY_INTERVAL_S,
        "raw_wire_bytes": dict(raw_bytes),
        "measure": "observer subscriber of the room, own streams excluded; key snapshot "
        f"at least every {KEY_INTERVAL_S:g} s, deltas against what it received otherwise; "
        "wire bytes = codec frame + websocket header + TCP/IP headers",
        "tiers": tiers,
    }
    if frontier is not None:
        out["headline"] = _headline(frontier["points"], bps)
    out["sizes"] = {
        ("velocity" if v else "plain"): {
            str(r): s.__dict__ | {"bytes_per_pose": s.bytes_per_pose}
            for (vv, r), s in sorted(cache.sizes.items())
            if vv == v
        }
        for v in (False, True)
    }
    return out


def _saving(value: float | None, reference: float) -> float | None:
    return None if value is None else 100.0 * (1.0 - value / reference)


def _headline(
    points: Sequence[dict[str, Any]], bps: Callable[[str, str, int | None], float | None]
) -> dict[str, Any]:
    """The fewest bytes/s at which any method with any codec matches raw SoA at 30 Hz
    (ideal network, one-interval playout, hold) at no more latency."""
    ideal = [p for p in points if p["network"] == "ideal"]
    ref = next(
        (
            p
            for p in ideal
            if p["method"] == "soa" and p["rate"] == 30 and p["fraction"] == 1.0
            and p["variant"] == "hold"
        ),
        None,
    )  # fmt: skip
    if ref is None:
        return {"reference": None}
    ref_bps = float(ref["bytes_per_s"])
    ok = [
        p
        for p in ideal
        if p["headline_mm"] <= ref["headline_mm"] and p["latency_ms"] <= ref["latency_ms"]
    ]
    best: dict[str, Any] = {}
    for codec in CODECS:
        cands = [(bps(codec, p["method"], p["rate"]) or math.inf, p) for p in ok]
        per_method: dict[str, Any] = {}
        for b, p in sorted(cands, key=lambda x: x[0]):
            per_method.setdefault(p["method"], _point(p, b, ref_bps))
        best[codec] = {
            "best": min(per_method.values(), key=lambda x: x["bytes_per_s"], default=None),
            "per_method": per_method,
        }
    return {
        "reference": _point(ref, ref_bps, ref_bps),
        "rule": "ideal network; headline <= raw SoA at 30 Hz and latency <= its latency",
        "codecs": best,
    }


def _point(p: dict[str, Any], b: float, ref_bps: float) -> dict[str, Any]:
    keys = ("method", "rate", "fraction", "variant", "latency_ms", "headline_mm")
    return {k: p[k] for k in keys} | {"bytes_per_s": b, "saving_pct": _saving(b, ref_bps)}


# ---------------------------------------------------------------- markdown


def _b(x: float | None) -> str:
    return "none" if x is None else f"{x:,.0f}".replace(",", " ")


def _p(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.0f} %"


def codec_markdown(report: Mapping[str, Any]) -> list[str]:
    """Bytes/s at equal QoE per codec, the compact sizes, and the headline."""
    cx = report.get("codecs")
    if not cx:
        return []
    meths = list(report["config"]["methods"])
    lines = [
        "## Bytes/s at equal QoE, raw and compact codec (ideal network)",
        "",
        "Each method at its equal-QoE rate (hands p95 tip error no worse than SoA's at the "
        "tier rate), priced with the raw float32 snapshots and with the compact codec "
        f"({cx['measure']}); saving against **raw** SoA at the tier rate. The codec's own "
        "error (<= 0.25 mm, 0.034 deg) is not fed back into the QoE.",
        "",
        "| tier | method | rate | raw B/s (saving) | compact B/s (saving) |",
        "|---|---|---|---|---|",
    ]
    for t in cx["tiers"]:
        for m in meths:
            r = t["equal_qoe_rate"].get(m)
            raw, comp = t["bytes_per_s"]["raw"][m], t["bytes_per_s"]["compact"][m]
            sr, sc = t["saving_vs_raw_soa_pct"]["raw"][m], t["saving_vs_raw_soa_pct"]["compact"][m]
            lines.append(
                f"| {t['name']} | `{m}` | {'null' if r is None else r} "
                f"| {_b(raw)} ({_p(sr)}) | {_b(comp)} ({_p(sc)}) |"
            )
    lines += ["", *_sizes_markdown(cx), *_headline_markdown(cx)]
    return lines


def _sizes_markdown(cx: Mapping[str, Any]) -> list[str]:
    lines = [
        f"Compact snapshot of the {cx['room_poses']}-pose room as an observer receives it "
        "(mean wire bytes per snapshot, per pose; raw: "
        + " / ".join(f"{_b(v)} B" for v in sorted(set(cx["raw_wire_bytes"].values())))
        + " per snapshot, plain / velocity variant"
        + (f"; volume {tuple(v['lo'])}..{tuple(v['hi'])} m):" if (v := cx.get("volume")) else "):"),
        "",
        "| rate | plain: B/snapshot | B/pose | key / delta payload | velocity variant: "
        "B/snapshot | B/pose |",
        "|---|---|---|---|---|---|",
    ]
    plain, vel = cx["sizes"].get("plain", {}), cx["sizes"].get("velocity", {})
    for r in sorted({*plain, *vel}, key=int):
        a, b = plain.get(r), vel.get(r)
        cells = (
            [_b(a["wire_bytes"]), f"{a['bytes_per_pose']:.2f}",
             f"{_b(a['key_payload_bytes'])} / {_b(a['delta_payload_bytes'])}"]
            if a else ["", "", ""]
        )  # fmt: skip
        cells += [_b(b["wire_bytes"]), f"{b['bytes_per_pose']:.2f}"] if b else ["", ""]
        lines.append(f"| {r} Hz | " + " | ".join(cells) + " |")
    return [*lines, ""]


def _headline_markdown(cx: Mapping[str, Any]) -> list[str]:
    hl = cx.get("headline")
    if not hl or hl.get("reference") is None:
        return []
    ref = hl["reference"]
    lines = [
        "Headline: the fewest bytes/s at which any method with any codec matches **raw** "
        f"SoA at 30 Hz ({ref['headline_mm']:.1f} mm at {ref['latency_ms']:.1f} ms, "
        f"{_b(ref['bytes_per_s'])} B/s) at no more capture-to-display latency (ideal "
        "network, every rate, playout delay and stall policy of the error-vs-latency view):",
        "",
        "| codec | method | rate, f, stall policy | p95 tip | latency | B/s | saving |",
        "|---|---|---|---|---|---|---|",
    ]
    for codec, entry in hl["codecs"].items():
        for m, p in sorted(entry["per_method"].items(), key=lambda x: x[1]["bytes_per_s"]):
            lines.append(
                f"| {codec} | `{m}` | {p['rate']} Hz, f {p['fraction']:g}, {p['variant']} "
                f"| {p['headline_mm']:.1f} mm | {p['latency_ms']:.1f} ms "
                f"| {_b(p['bytes_per_s'])} | {_p(p['saving_pct'])} |"
            )
    return [*lines, ""]
