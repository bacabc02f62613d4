"""The load generator as several processes (``--procs``), seen by the controller as one.

Clients are split into contiguous ranges, one per process; each process ramps
its share at its share of the ramp rate, so the whole joins at the rate asked.
Counts add up; percentiles come from the processes' samples (``.npz`` files in
a temporary folder) concatenated, never from averaging percentiles.
"""

from __future__ import annotations

import json
import math
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from posecast.bench.common import _LOAD_BOOT, _pct
from posecast.bench.procs import _Child, _proc_cpu

#: Keys of the processes' results that add up.
_SUMMED = (
    "snapshots",
    "snapshots_per_client_s_sum",
    "clients_without_snapshots",
    "clients_without_snapshots_in_window",
    "poses_delivered",
    "poses_delivered_incl_own",
    "payload_bytes",
    "wire_bytes",
    "updates_sent",
    "updates_sent_total",
    "sends_late",
    "send_skips",
    "other_frames",
    "bad_frames",
    "decoded_frames",
    "codec_snapshots",
    "codec_own_echo",
    "empty_ticks",
    "clients_closed",
    "load_clients",
    "clients_measured",
)


class LoadFleet:
    """``procs`` load subprocesses sharing ``clients`` clients."""

    def __init__(self, cfg: dict[str, Any], procs: int, seed: int) -> None:
        clients = int(cfg["clients"])
        procs = max(1, min(procs, clients))
        self._tmp = tempfile.TemporaryDirectory(prefix="posecast-load-")
        self.children: list[_Child] = []
        self.samples: list[Path] = []
        #: The processes' own ``result`` messages, once :meth:`results` has them.
        self.parts: list[dict[str, Any]] = []
        for k in range(procs):
            first, last = k * clients // procs, (k + 1) * clients // procs
            path = Path(self._tmp.name) / f"load-{k}.npz"
            self.samples.append(path)
            part = {
                **cfg,
                "first": first,
                "last": last,
                "ramp_rate": float(cfg["ramp_rate"]) / procs,
                "samples": str(path),
            }
            name = "load" if procs == 1 else f"load {k + 1}/{procs}"
            self.children.append(
                _Child(
                    name,
                    [sys.executable, "-c", _LOAD_BOOT, json.dumps(part)],
                    stdin=True,
                    hash_seed=seed,
                )
            )

    @property
    def pids(self) -> list[int]:
        return [child.pid for child in self.children]

    def ramped(self, timeout: float) -> dict[str, Any]:
        """Wait for every process to have joined its clients; their figures, added up."""
        parts = [child.wait_json("ramped", timeout=timeout) for child in self.children]
        merged = merge_ramped(parts)
        if merged["joined"] == 0:
            raise self.children[0].fail(f"no client could join: {merged['errors']}")
        return merged

    def tell(self, message: dict[str, Any]) -> None:
        for child in self.children:
            child.tell(message)

    def cpu(self) -> list[float]:
        """CPU seconds (user + system) of each process so far."""
        return [sum(_proc_cpu(pid)) for pid in self.pids]

    def results(self, timeout: float) -> dict[str, Any]:
        """Every process's result, merged: sums, extremes, percentiles of the samples."""
        parts = [child.wait_json("result", timeout=timeout) for child in self.children]
        self.parts = parts
        return {**merge_parts(parts), **sample_percentiles(self.samples)}

    def stop(self, grace: float) -> None:
        for child in self.children:  # all at once: each closes its clients in parallel
            child.close_stdin()
        for child in self.children:
            child.stop(grace=grace)
        self._tmp.cleanup()

    def fail(self, what: str) -> RuntimeError:
        return self.children[0].fail(what)


def merge_ramped(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """Load processes' ``ramped`` messages as one: joins by outcome, their times (s)."""
    codes: dict[str, int] = {}
    hung_at: dict[str, int] = {}
    for p in parts:
        for code, n in p.get("codes", {}).items():
            codes[code] = codes.get(code, 0) + int(n)
        for step, n in p.get("hung_at", {}).items():
            hung_at[step] = hung_at.get(step, 0) + int(n)
    times = ("join_s", "refused_s", "server_full_s", "connect_s", "upgrade_s")
    return {
        "joined": sum(int(p["joined"]) for p in parts),
        "failed": sum(int(p["failed"]) for p in parts),
        "errors": [e for p in parts for e in p["errors"]][:5],
        "codes": codes,
        "hung": sum(int(p.get("hung", 0)) for p in parts),
        "hung_at": hung_at,
        **{key: [t for p in parts for t in p.get(key, [])] for key in times},
        "ramp_s": max(float(p["ramp_s"]) for p in parts),
    }


def join_figures(ramped: dict[str, Any]) -> dict[str, Any]:
    """The report's join accounting from a (merged) ``ramped`` message: admitted,
    refused by the server's error code, hung (no answer within the open timeout) and
    at which step, and how long joins and refusals took from each client's first
    byte (ms): every refusal, ``server-full`` ones apart, and the TCP connect and the
    websocket handshake of every client that got that far."""
    codes = dict(ramped.get("codes", {}))
    hung = int(codes.pop("hung", 0))

    def ms(key: str) -> np.ndarray:
        return np.asarray(ramped.get(key, []), dtype=np.float64) * 1e3

    refused, joins, full = ms("refused_s"), ms("join_s"), ms("server_full_s")
    connect, upgrade = ms("connect_s"), ms("upgrade_s")
    return {
        "clients_joined": int(ramped["joined"]),
        "clients_failed": int(ramped["failed"]),
        "clients_refused": sum(n for code, n in codes.items() if code != "unreachable"),
        "clients_hung": hung,
        "clients_hung_at": dict(ramped.get("hung_at", {})),
        "join_errors": codes,
        "join_error_examples": ramped["errors"],
        "join_p50_ms": _pct(joins, 50),
        "join_p99_ms": _pct(joins, 99),
        "refusal_p50_ms": _pct(refused, 50),
        "refusal_p99_ms": _pct(refused, 99),
        "refusal_max_ms": float(refused.max()) if len(refused) else math.nan,
        "server_full_p50_ms": _pct(full, 50),
        "server_full_p99_ms": _pct(full, 99),
        "server_full_max_ms": float(full.max()) if len(full) else math.nan,
        "server_full_within_1s": int((full <= 1e3).sum()),
        "connect_p50_ms": _pct(connect, 50),
        "connect_p99_ms": _pct(connect, 99),
        "upgrade_p50_ms": _pct(upgrade, 50),
        "upgrade_p99_ms": _pct(upgrade, 99),
    }


def merge_parts(parts: list[dict[str, Any]]) -> dict[str, Any]:
    """Load processes' ``result`` messages as one: sums and extremes (no percentiles)."""
    merged: dict[str, Any] = {key: sum(p.get(key, 0) for p in parts) for key in _SUMMED}
    merged["window_s"] = max(float(p["window_s"]) for p in parts)
    # Per joined client: a client the relay refused is not one that got no snapshots.
    measured = merged["clients_measured"] or merged["load_clients"]
    merged["snapshots_per_client_s"] = merged.pop("snapshots_per_client_s_sum") / max(1, measured)
    some = [p for p in parts if p.get("clients_measured", 1)] or parts
    merged["snapshots_per_client_s_min"] = min(p["snapshots_per_client_s_min"] for p in some)
    merged["snapshots_per_client_s_max"] = max(p["snapshots_per_client_s_max"] for p in some)
    # Snapshots and the ticks that had nothing for the client (load.RoomTicks).
    merged["ticks_per_client_s"] = sum(p.get("ticks_per_client_s_sum", 0.0) for p in parts) / max(
        1, measured
    )
    merged["ticks_per_client_s_min"] = min(p.get("ticks_per_client_s_min", 0.0) for p in some)
    merged["close_reasons"] = sorted({r for p in parts for r in p["close_reasons"]})[:5]
    errors: dict[str, int] = {}
    for p in parts:
        for code, n in p["server_errors"].items():
            errors[code] = errors.get(code, 0) + int(n)
    merged["server_errors"] = errors
    merged["server_error_examples"] = {
        code: text for p in parts for code, text in p["server_error_examples"].items()
    }
    merged["load_procs"] = len(parts)
    return merged


def load_samples(paths: list[Path]) -> dict[str, np.ndarray]:
    """The load processes' window samples (``.npz`` files), concatenated per key."""
    arrays: dict[str, list[np.ndarray]] = {}
    for path in paths:
        if not path.exists():
            continue
        with np.load(path) as data:
            for key in data.files:
                arrays.setdefault(key, []).append(data[key])
    return {k: np.concatenate(v) for k, v in arrays.items()}


def sample_percentiles(paths: list[Path]) -> dict[str, float]:
    """Latency percentiles (ms) over the samples of every file in ``paths``."""
    cat = load_samples(paths)
    empty = np.zeros(0)
    lat, hold = cat.get("latency", empty), cat.get("hold", empty)
    relay, lag = cat.get("relay", empty), cat.get("tick_lag", empty)
    send = cat.get("send_lag", empty)
    return {
        "latency_p50_ms": _pct(lat, 50),
        "latency_p99_ms": _pct(lat, 99),
        "latency_max_ms": float(lat.max()) if len(lat) else math.nan,
        "latency_samples": len(lat),
        "hold_p50_ms": _pct(hold, 50),
        "hold_p99_ms": _pct(hold, 99),
        "relay_p50_ms": _pct(relay, 50),
        "relay_p99_ms": _pct(relay, 99),
        "relay_max_ms": float(relay.max()) if len(relay) else math.nan,
        "tick_lag_p50_ms": _pct(lag, 50),
        "tick_lag_p99_ms": _pct(lag, 99),
        "send_lag_p99_ms": _pct(send, 99),
        "send_lag_max_ms": float(send.max()) if len(send) else math.nan,
    }
