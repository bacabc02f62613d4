"""Network quality tiers and a seeded link model for offline experiments.

Tiers are data (``scenarios/data/tiers.toml``): the paper's update rate per
tier (30/20/15/12 Hz) and our assumed bandwidth budget, one-way latency,
jitter and loss (see the file for units and where the figures come from).
:func:`load_tiers` reads the built-ins and merges a user's file over them.

:class:`LinkModel` maps the send times and wire sizes of the snapshots sent to
one subscriber to their arrival times, deterministically for a seed:

1. **Bandwidth cap**: a token bucket filled at the tier's bytes/s, holding at
   most ``burst_bytes``; a frame departs when the bucket holds its size.
   Frames are *latest wins*: a frame still waiting when a newer one is offered
   is skipped (never sent), so the queue never grows beyond one frame and the
   delivered rate adapts to what the cap affords (:func:`affordable_rate` is
   that rate, for a sender that wants to adapt instead of being skipped).
2. **Delay**: departure plus a one-way delay ``latency - sqrt(2) jitter +
   Gamma(k=2, theta=jitter/sqrt(2))``: mean ``latency``, standard deviation
   ``jitter``, right-skewed (a floor plus queueing), never below
   ``latency - sqrt(2) jitter``. Independent per frame, so frames may reorder.
3. **Loss**: each frame is lost with probability ``loss_pct / 100``,
   independently. With ``transport="datagram"`` (the default) a lost frame
   never arrives (arrival NaN). With ``transport="stream"`` (TCP-like, what a
   websocket gives) it is retransmitted after an RTO of
   ``max(200 ms, 2 latency + 4 sqrt(2) jitter)``, doubling per further loss,
   and every frame waits for the ones before it (in-order delivery).

Wire sizes: :func:`wire_bytes` is the snapshot frame (``protocol.frame_size``)
plus the websocket header and the TCP/IPv4 headers of its segments. The
velocity keyframe variant (for interpolators that need keyframe velocities)
adds :data:`VELOCITY_BYTES_PER_POSE` to every pose: 6 x float16 (linear m/s,
angular rad/s). float16 holds up to 65504 with a relative step of 2^-11, so at
20 m/s and 40 rad/s it quantises to 0.008 m/s and 0.016 rad/s (the largest
speeds in the real traces are 22 m/s and 114 rad/s, glitches included). The
protocol does not carry the variant yet; the size is what it would cost.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from posecast.protocol import SNAPSHOT_ENTRY_SIZE, frame_size
from posecast.protocol.errors import PosecastError

__all__ = [
    "GAMMA_SHAPE",
    "TCP_IP_HEADER_BYTES",
    "TCP_MSS",
    "VELOCITY_BYTES_PER_POSE",
    "VELOCITY_WIRE_DTYPE",
    "Delivery",
    "LinkModel",
    "Tier",
    "TierError",
    "affordable_rate",
    "builtin_tiers",
    "load_tiers",
    "websocket_header_bytes",
    "wire_bytes",
]

F64 = NDArray[np.float64]

#: Shape of the Gamma distribution of the variable part of the one-way delay.
GAMMA_SHAPE = 2.0
#: IPv4 (20) + TCP (20) + TCP timestamp option (12) bytes per segment.
TCP_IP_HEADER_BYTES = 52
#: Payload bytes per TCP segment on a 1500-byte MTU with timestamps.
TCP_MSS = 1448
#: Smallest retransmission timeout of the stream transport (Linux's minimum RTO).
MIN_RTO_S = 0.200

Transport = Literal["datagram", "stream"]

#: Element type of the velocity variant's 6 numbers per pose on the wire.
VELOCITY_WIRE_DTYPE = np.float16
#: Extra bytes per pose of the velocity keyframe variant (6 x float16).
VELOCITY_BYTES_PER_POSE = 6 * np.dtype(VELOCITY_WIRE_DTYPE).itemsize


class TierError(PosecastError, ValueError):
    """A tier file or tier definition that cannot be used, with the reason."""


@dataclass(frozen=True)
class Tier:
    """One network quality tier (units in the field names)."""

    name: str
    max_rate_hz: float
    bandwidth_kbps: float
    latency_ms: float
    jitter_ms: float
    loss_pct: float
    note: str = ""

    def __post_init__(self) -> None:
        where = f"tier {self.name!r}"
        if not self.max_rate_hz > 0:
            raise TierError(f"{where}: max_rate_hz must be positive, got {self.max_rate_hz}")
        if not self.bandwidth_kbps > 0:
            raise TierError(f"{where}: bandwidth_kbps must be positive, got {self.bandwidth_kbps}")
        if not (self.latency_ms >= 0 and self.jitter_ms >= 0):
            raise TierError(f"{where}: latency_ms and jitter_ms must be >= 0")
        if self.latency_ms < math.sqrt(GAMMA_SHAPE) * self.jitter_ms - 1e-9:
            raise TierError(
                f"{where}: latency_ms must be at least sqrt(2) x jitter_ms "
                f"({math.sqrt(GAMMA_SHAPE) * self.jitter_ms:.1f} ms) so delays stay positive"
            )
        if not 0 <= self.loss_pct < 100:
            raise TierError(f"{where}: loss_pct must be in [0, 100), got {self.loss_pct}")

    @property
    def bytes_per_s(self) -> float:
        """The bandwidth cap in bytes per second."""
        return self.bandwidth_kbps * 1000.0 / 8.0

    def as_dict(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in fields(self)}


_NUMERIC = ("max_rate_hz", "bandwidth_kbps", "latency_ms", "jitter_ms", "loss_pct")


def _parse_tiers(text: str, where: str, base: Mapping[str, Tier] | None = None) -> dict[str, Tier]:
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise TierError(f"{where}: not valid TOML ({exc})") from None
    tables = data.get("tier")
    if not isinstance(tables, dict) or not tables:
        raise TierError(f"{where}: expected [tier.NAME] tables")
    out = dict(base or {})
    for name, table in tables.items():
        if not isinstance(table, dict):
            raise TierError(f"{where}: [tier.{name}] must be a table")
        unknown = sorted(set(table) - set(_NUMERIC) - {"note"})
        if unknown:
            raise TierError(
                f"{where}: [tier.{name}] has unknown field(s) {unknown}; known: "
                f"{', '.join((*_NUMERIC, 'note'))}"
            )
        values: dict[str, Any] = {}
        for key, value in table.items():
            if key == "note":
                values[key] = str(value)
            elif isinstance(value, bool) or not isinstance(value, int | float):
                raise TierError(f"{where}: [tier.{name}] {key} must be a number, got {value!r}")
            else:
                values[key] = float(value)
        try:
            if name in out:
                out[name] = replace(out[name], **values)
            else:
                missing = [k for k in _NUMERIC if k not in values]
                if missing:
                    raise TierError(f"new tier needs {', '.join(missing)}")
                out[name] = Tier(name=name, **values)
        except TierError as exc:
            raise TierError(f"{where}: [tier.{name}]: {exc}") from None
    return out


def builtin_tiers() -> dict[str, Tier]:
    """The packaged tiers (``scenarios/data/tiers.toml``), in file order."""
    text = resources.files("posecast.scenarios").joinpath("data/tiers.toml").read_text()
    return _parse_tiers(text, "scenarios/data/tiers.toml")


def load_tiers(path: str | Path | None = None) -> dict[str, Tier]:
    """Built-in tiers, with the tiers of ``path`` merged over them.

    A table of ``path`` whose name is a built-in tier overrides the fields it
    gives; other names add tiers (all numeric fields required).
    """
    tiers = builtin_tiers()
    if path is None:
        return tiers
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise TierError(f"{p}: no such tier file") from None
    except IsADirectoryError:
        raise TierError(f"{p}: is a directory; give a tiers file ([tier.NAME] tables)") from None
    except UnicodeDecodeError:
        raise TierError(f"{p}: not a tiers file (TOML text with [tier.NAME] tables)") from None
    except OSError as exc:
        raise TierError(f"{p}: cannot read the tier file ({exc.strerror or exc})") from None
    return _parse_tiers(text, str(p), tiers)


def websocket_header_bytes(payload: int) -> int:
    """Header of an unmasked (server -> client) websocket binary frame."""
    return 2 if payload < 126 else 4 if payload < 1 << 16 else 10


def _bin_header(body: int) -> int:
    return 2 if body < 1 << 8 else 3 if body < 1 << 16 else 5


def wire_bytes(n_poses: int, extra_bytes_per_pose: int = 0) -> int:
    """Bytes on the wire of one snapshot of ``n_poses`` poses (frame + ws + TCP/IP).

    ``extra_bytes_per_pose``: a keyframe variant carrying more per pose (e.g.
    :data:`VELOCITY_BYTES_PER_POSE`), in the same msgpack ``bin`` payload.
    """
    if extra_bytes_per_pose < 0:
        raise ValueError(f"extra_bytes_per_pose must be >= 0, got {extra_bytes_per_pose}")
    payload = frame_size(n_poses, "snapshot")
    if extra_bytes_per_pose:
        body = n_poses * SNAPSHOT_ENTRY_SIZE
        extra = n_poses * extra_bytes_per_pose
        payload += extra + _bin_header(body + extra) - _bin_header(body)
    payload += websocket_header_bytes(payload)
    segments = max(1, -(-payload // TCP_MSS))
    return payload + segments * TCP_IP_HEADER_BYTES


def affordable_rate(tier: Tier, frame_bytes: float) -> float:
    """Highest rate (Hz) the tier allows for frames of ``frame_bytes`` wire bytes.

    The smaller of the tier's maximum rate and ``cap / frame_bytes``: a sender
    at this rate never queues behind the bandwidth cap.
    """
    if frame_bytes <= 0:
        raise ValueError(f"frame_bytes must be positive, got {frame_bytes}")
    return min(tier.max_rate_hz, tier.bytes_per_s / frame_bytes)


@dataclass(frozen=True)
class Delivery:
    """What happened to each frame offered to a link (arrays of shape ``(N,)``).

    ``departure`` is NaN for skipped frames (superseded while waiting for the
    bandwidth cap); ``arrival`` is NaN for skipped and lost frames.
    """

    send: F64
    size: NDArray[np.int64]
    departure: F64
    arrival: F64
    skipped: NDArray[np.bool_]
    lost: NDArray[np.bool_]

    @property
    def delivered(self) -> NDArray[np.bool_]:
        out: NDArray[np.bool_] = ~np.isnan(self.arrival)
        return out

    @property
    def delay(self) -> F64:
        """Arrival minus send time (NaN where not delivered), seconds."""
        out: F64 = self.arrival - self.send
        return out

    def sent_bytes_per_s(self) -> float:
        """Bytes that departed, per second of the run (first send to last departure)."""
        dep = ~np.isnan(self.departure)
        if not dep.any():
            return 0.0
        span = float(np.nanmax(self.departure) - self.send[0])
        return float(self.size[dep].sum()) / span if span > 0 else float("inf")


class LinkModel:
    """A tier's downlink: bandwidth cap, delay with jitter, loss; seeded.

    ``transmit`` is a pure function of its arguments and the seed: calling it
    twice gives the same :class:`Delivery`.
    """

    def __init__(
        self,
        tier: Tier,
        seed: int | np.random.SeedSequence = 0,
        *,
        burst_bytes: float | None = None,
        transport: Transport = "datagram",
    ) -> None:
        if transport not in ("datagram", "stream"):
            raise ValueError(f"transport must be 'datagram' or 'stream', got {transport!r}")
        self.tier = tier
        self.seed = seed
        #: Bucket size; default 50 ms of the cap (a frame larger than it still goes out
        #: once the bucket is full: the bucket grows to the largest frame offered).
        self.burst_bytes = 0.05 * tier.bytes_per_s if burst_bytes is None else float(burst_bytes)
        self.transport = transport

    @property
    def rto(self) -> float:
        """Retransmission timeout of the stream transport (s)."""
        t = self.tier
        return max(
            MIN_RTO_S, (2 * t.latency_ms + 4 * math.sqrt(GAMMA_SHAPE) * t.jitter_ms) / 1000.0
        )

    def shape(self, send: F64, size: NDArray[np.int64]) -> tuple[F64, NDArray[np.bool_]]:
        """Token-bucket departures (NaN = skipped) and the skipped mask."""
        n = send.size
        rate = self.tier.bytes_per_s
        burst = max(self.burst_bytes, float(size.max()) if n else 0.0)
        departure = np.full(n, np.nan)
        skipped = np.zeros(n, dtype=bool)
        tokens, t_tokens, last = burst, -math.inf, -math.inf
        send_l = send.tolist()
        size_l = size.tolist()
        for i in range(n):
            start = max(send_l[i], last)
            have = (
                burst if t_tokens == -math.inf else min(burst, tokens + (start - t_tokens) * rate)
            )
            dep = start + max(0.0, (size_l[i] - have) / rate)
            if i + 1 < n and dep > send_l[i + 1]:
                skipped[i] = True  # a newer frame is offered before this one can leave
                continue
            tokens = min(burst, have + (dep - start) * rate) - size_l[i]
            t_tokens = last = dep
            departure[i] = dep
        return departure, skipped

    def transmit(self, send_times: ArrayLike, sizes: ArrayLike | int) -> Delivery:
        """Arrival times of frames sent at ``send_times`` (non-decreasing) with ``sizes``."""
        send = np.asarray(send_times, dtype=np.float64)
        if send.ndim != 1:
            raise ValueError(f"expected send_times of shape (N,), got {send.shape}")
        if send.size > 1 and np.any(np.diff(send) < 0):
            raise ValueError("expected non-decreasing send_times")
        size = np.broadcast_to(np.asarray(sizes, dtype=np.int64), send.shape).copy()
        if np.any(size <= 0):
            raise ValueError("frame sizes must be positive")
        tier = self.tier
        rng = np.random.default_rng(self.seed)
        n = send.size
        # Draw for every frame, skipped or not, so the draws do not depend on the cap.
        theta = tier.jitter_ms / 1000.0 / math.sqrt(GAMMA_SHAPE)
        floor = tier.latency_ms / 1000.0 - GAMMA_SHAPE * theta
        one_way = floor + rng.gamma(GAMMA_SHAPE, theta, n) if theta > 0 else np.full(n, floor)
        lost = rng.random(n) < tier.loss_pct / 100.0
        departure, skipped = self.shape(send, size)
        arrival = departure + one_way
        if self.transport == "datagram":
            arrival[lost] = np.nan
        else:
            # Retransmissions: one RTO, doubling per further loss of the same frame.
            losses = rng.geometric(1.0 - tier.loss_pct / 100.0, n) - 1
            losses[~lost] = 0
            losses[lost] = np.maximum(losses[lost], 1)
            arrival = arrival + self.rto * (2.0**losses - 1.0)
            ok = ~np.isnan(arrival)
            arrival[ok] = np.maximum.accumulate(arrival[ok])  # in-order delivery
            lost = np.zeros(n, dtype=bool)
        lost &= ~skipped
        return Delivery(send, size, departure, arrival, skipped, lost)
