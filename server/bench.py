"""``posecast bench relay``: how much load one relay process carries, in figures.

Three processes on loopback:

- the **server**: ``posecast serve --port 0`` started as a subprocess; its CPU
  time is read from ``/proc/<pid>/stat`` and its counters from ``GET /metrics``;
- the **load**: one subprocess running every client in one asyncio loop. Each
  client is a raw websocket that does the hello/join handshake, then publishes
  its three streams (head, left, right) at ``rate`` Hz with capture time
  ``time.monotonic()`` and subscribes at ``rate``. No session checks, no
  jitter buffer, no interpolation: an update is the protocol's own wire map
  re-packed with a new seq and time, a snapshot is unpacked and its records
  viewed as ``protocol.SNAPSHOT_DTYPE`` in batches;
- this process, which starts both, fixes the measurement window once every
  client has joined and a warm-up has passed, samples CPU and metrics at both
  ends of the window, and prints the report.

CLOCK_MONOTONIC is system-wide, so the server's clock (``time.monotonic``) and
the load's are the same clock: capture-to-receipt latency is receipt time minus
capture time, with no clock sync. Figures per pose count **remote** poses, i.e.
not the echo of a subscriber's own streams that snapshots also carry.

Every wait is bounded and every child is killed on the way out.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import os
import queue
import random
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Callable, Coroutine, Mapping
from pathlib import Path
from typing import IO, Any, Final

import msgpack
import numpy as np
from rich.console import Console
from rich.table import Table

from protocol import SNAPSHOT_DTYPE, SNAPSHOT_ENTRY_SIZE, PoseUpdate
from server.room import room_phase

__all__ = ["STREAMS", "main", "print_relay_report", "run_relay_bench", "update_template"]

#: The streams every bench client publishes.
STREAMS = ("head", "left", "right")

_SERVER_BOOT = "from server.cli import main; main()"
_LOAD_BOOT = "from server.bench import _load_entry; _load_entry()"
_LISTENING = re.compile(r"posecast listening on ws://([^:\s]+):(\d+)")

#: Snapshot scalars and bodies are turned into numpy arrays this many at a time.
_FLUSH_EVERY = 4096


# ----------------------------------------------------------------------------------
# Shared helpers
# ----------------------------------------------------------------------------------


def update_template(stream_ids: list[int], position: tuple[float, float, float]) -> dict[str, Any]:
    """The protocol's wire map of an update with ``stream_ids`` and dt = 0.

    Re-packing it with ``msgpack.packb`` after setting ``seq`` and ``time`` gives
    exactly ``protocol.encode_update(seq, ids, [time] * n, poses, base_time=time)``
    at a twentieth of the cost.
    """
    n = len(stream_ids)
    poses = np.tile([*position, 1.0, 0.0, 0.0, 0.0], (n, 1))
    return PoseUpdate.from_arrays(0, stream_ids, np.zeros(n), poses, base_time=0.0).to_wire()


def _ws_header(n: int) -> int:
    """Bytes of an unmasked (server -> client) websocket frame header for ``n`` bytes."""
    return 2 if n <= 125 else 4 if n <= 0xFFFF else 10


def _pct(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if len(values) else math.nan


def _run_loop(coro: Coroutine[Any, Any, Any]) -> Any:
    try:
        import uvloop
    except ImportError:
        return asyncio.run(coro)
    return uvloop.run(coro)


# ----------------------------------------------------------------------------------
# The load process
# ----------------------------------------------------------------------------------


class _LoadStats:
    """What the load measures; only arrivals inside the window count."""

    def __init__(self, clients: int, rate: float) -> None:
        self.rate = rate
        self.t0 = math.inf
        self.t1 = math.inf
        self.snapshots_total = np.zeros(clients, dtype=np.int64)
        self.snapshots = np.zeros(clients, dtype=np.int64)
        self.updates = 0
        self.updates_total = 0
        self.sends_late = 0
        self.payload_bytes = 0
        self.wire_bytes = 0
        self.other_frames = 0
        self.bad_frames = 0
        self.poses_all = 0
        self.poses_remote = 0
        # Per-snapshot scalars waiting to be flushed into arrays.
        self._bodies: list[bytes] = []
        self._owner: list[int] = []
        self._send: list[float] = []
        self._due: list[float] = []
        self._arrival: list[float] = []
        self._lat: list[np.ndarray] = []
        self._hold: list[np.ndarray] = []
        self._relay: list[np.ndarray] = []
        self._tick_lag: list[np.ndarray] = []
        self._gap: list[float] = []

    def in_window(self, t: float) -> bool:
        return self.t0 <= t < self.t1

    def snapshot(
        self, index: int, user: int, arrival: float, send: float, due: float, body: bytes, size: int
    ) -> None:
        self.snapshots_total[index] += 1
        if not self.t0 <= arrival < self.t1:
            return
        self.snapshots[index] += 1
        self.payload_bytes += size
        self.wire_bytes += size + _ws_header(size)
        self._bodies.append(body)
        self._owner.append(user)
        self._send.append(send)
        self._due.append(due)
        self._arrival.append(arrival)
        if len(self._bodies) >= _FLUSH_EVERY:
            self.flush()

    def sent(self, scheduled: float, now: float) -> None:
        self.updates_total += 1
        if self.t0 <= now < self.t1:
            self.updates += 1
            self._gap.append(now - scheduled)

    def flush(self) -> None:
        if not self._bodies:
            return
        counts = np.fromiter((len(b) // SNAPSHOT_ENTRY_SIZE for b in self._bodies), np.int64)
        entries = np.frombuffer(b"".join(self._bodies), dtype=SNAPSHOT_DTYPE)
        send = np.asarray(self._send, dtype=np.float64)
        arrival = np.asarray(self._arrival, dtype=np.float64)
        owner = np.repeat(np.asarray(self._owner, dtype=np.int64), counts)
        due = np.asarray(self._due, dtype=np.float64)
        remote = entries["user"].astype(np.int64) != owner
        dt = entries["dt"].astype(np.float64)[remote]
        capture = np.repeat(send, counts)[remote] + dt
        self._lat.append(((np.repeat(arrival, counts)[remote] - capture) * 1e3).astype(np.float32))
        self._hold.append(((np.repeat(due, counts)[remote] - capture) * 1e3).astype(np.float32))
        self._relay.append(((arrival - due) * 1e3).astype(np.float32))
        self._tick_lag.append(((send - due) * 1e3).astype(np.float32))
        self.poses_all += len(entries)
        self.poses_remote += int(remote.sum())
        self._bodies.clear()
        self._owner.clear()
        self._send.clear()
        self._due.clear()
        self._arrival.clear()

    def summary(self) -> dict[str, Any]:
        self.flush()

        def cat(parts: list[np.ndarray]) -> np.ndarray:
            return np.concatenate(parts) if parts else np.zeros(0, np.float32)

        lat, hold, relay, lag = (
            cat(self._lat),
            cat(self._hold),
            cat(self._relay),
            cat(self._tick_lag),
        )
        gap = np.asarray(self._gap, dtype=np.float64) * 1e3
        window = self.t1 - self.t0
        per_client = self.snapshots / window if window > 0 else self.snapshots * 0.0
        return {
            "window_s": window,
            "snapshots": int(self.snapshots.sum()),
            "snapshots_per_client_s": float(per_client.mean()) if len(per_client) else 0.0,
            "snapshots_per_client_s_min": float(per_client.min()) if len(per_client) else 0.0,
            "snapshots_per_client_s_max": float(per_client.max()) if len(per_client) else 0.0,
            "clients_without_snapshots": int((self.snapshots_total == 0).sum()),
            "clients_without_snapshots_in_window": int((self.snapshots == 0).sum()),
            "poses_delivered": self.poses_remote,
            "poses_delivered_incl_own": self.poses_all,
            "payload_bytes": self.payload_bytes,
            "wire_bytes": self.wire_bytes,
            "updates_sent": self.updates,
            "updates_sent_total": self.updates_total,
            "sends_late": self.sends_late,
            "send_lag_p99_ms": _pct(gap, 99),
            "latency_p50_ms": _pct(lat, 50),
            "latency_p99_ms": _pct(lat, 99),
            "latency_max_ms": float(lat.max()) if len(lat) else math.nan,
            "hold_p50_ms": _pct(hold, 50),
            "hold_p99_ms": _pct(hold, 99),
            "relay_p50_ms": _pct(relay, 50),
            "relay_p99_ms": _pct(relay, 99),
            "relay_max_ms": float(relay.max()) if len(relay) else math.nan,
            "tick_lag_p50_ms": _pct(lag, 50),
            "tick_lag_p99_ms": _pct(lag, 99),
            "other_frames": self.other_frames,
            "bad_frames": self.bad_frames,
        }


class _BenchClient:
    """One load client: handshake, then publish and receive until cancelled."""

    def __init__(self, index: int, room: str, rate: float, stats: _LoadStats) -> None:
        self.index = index
        self.room = room
        self.rate = rate
        self.stats = stats
        self.settled = asyncio.Event()
        self.error: str | None = None
        self.ws: Any = None

    async def run(self, url: str, rng: random.Random) -> None:
        from client.connection import ClientConnection

        try:
            conn = await ClientConnection.open(
                url,
                room=self.room,
                streams=STREAMS,
                rate=self.rate,
                agent="posecast-bench",
                open_timeout=15.0,
            )
        except Exception as exc:
            self.error = f"{type(exc).__name__}: {exc}"
            self.settled.set()
            return
        self.ws = conn.ws
        assert conn.joined is not None
        ids = [conn.joined.streams[name] for name in STREAMS]
        wire = update_template(ids, (0.01 * self.index, 1.6, 0.0))
        self.settled.set()
        async with asyncio.TaskGroup() as tg:
            tg.create_task(self._publish(wire, rng.random()))
            tg.create_task(self._receive(conn.user))

    async def _publish(self, wire: dict[str, Any], phase: float) -> None:
        from websockets.exceptions import ConnectionClosed

        ws, stats, pack = self.ws, self.stats, msgpack.packb
        period = 1.0 / self.rate
        due = time.monotonic() + phase * period
        seq = 0
        with contextlib.suppress(ConnectionClosed):
            while True:
                delay = due - time.monotonic()
                if delay > 0:
                    await asyncio.sleep(delay)
                now = time.monotonic()
                seq += 1
                wire["seq"] = seq
                wire["time"] = now
                await ws.send(pack(wire))
                stats.sent(due, now)
                due += period
                if due < now:
                    # Behind by more than a period: skip, never burst.
                    missed = math.ceil((now - due) / period)
                    if stats.in_window(now):
                        stats.sends_late += missed
                    due += missed * period

    async def _receive(self, user: int) -> None:
        from websockets.exceptions import ConnectionClosed

        stats, unpack, index, rate = self.stats, msgpack.unpackb, self.index, self.rate
        floor = math.floor
        ph = room_phase(self.room)
        # The server ticks a subscriber on the grid (k + phase) / rate of its clock
        # (phase: the room's, see server.room.room_phase), and after
        # a tick at ``now`` its next one is due at the first grid point after
        # ``now`` (missed points are skipped). A snapshot's send time is the
        # ``now`` of its tick, so the due time of each snapshot follows from the
        # previous one's send time, even when ticks run more than a period late.
        prev: float | None = None
        with contextlib.suppress(ConnectionClosed):
            async for data in self.ws:
                arrival = time.monotonic()
                if not isinstance(data, bytes):
                    stats.bad_frames += 1
                    continue
                try:
                    wire = unpack(data)
                    if wire["type"] != "snapshot":
                        stats.other_frames += 1
                        continue
                    body, send = wire["poses"], float(wire["time"])
                    if type(body) is not bytes or len(body) % SNAPSHOT_ENTRY_SIZE:
                        raise ValueError("not whole snapshot records")
                except Exception:
                    stats.bad_frames += 1
                    continue
                latest = (floor(send * rate - ph + 1e-9) + ph) / rate
                due = latest if prev is None else (floor(prev * rate - ph + 1e-9) + 1 + ph) / rate
                if due > send:
                    due = latest
                prev = send
                stats.snapshot(index, user, arrival, send, due, body, len(data))


async def _load_main(cfg: dict[str, Any], emit: Callable[[dict[str, Any]], None]) -> None:
    loop = asyncio.get_running_loop()
    lines: asyncio.Queue[str | None] = asyncio.Queue()

    def read_stdin() -> None:
        for line in sys.stdin:
            loop.call_soon_threadsafe(lines.put_nowait, line)
        loop.call_soon_threadsafe(lines.put_nowait, None)

    threading.Thread(target=read_stdin, daemon=True).start()

    n, size, rate = int(cfg["clients"]), int(cfg["room_size"]), float(cfg["rate"])
    stats = _LoadStats(n, rate)
    rng = random.Random(int(cfg.get("seed", 0)))
    clients = [_BenchClient(i, f"bench-{i // size}", rate, stats) for i in range(n)]
    tasks: list[asyncio.Task[None]] = []
    try:
        start = time.monotonic()
        for i, client in enumerate(clients):
            delay = start + i / float(cfg["ramp_rate"]) - time.monotonic()
            if delay > 0:
                await asyncio.sleep(delay)
            tasks.append(asyncio.create_task(client.run(cfg["url"], rng)))
        pending = [asyncio.create_task(c.settled.wait()) for c in clients]
        _, still = await asyncio.wait(pending, timeout=30.0)
        for waiter in still:
            waiter.cancel()
        errors = [c.error for c in clients if c.error]
        emit(
            {
                "event": "ramped",
                "joined": sum(1 for c in clients if c.ws is not None),
                "failed": len(errors) + len(still),
                "errors": errors[:5],
                "ramp_s": time.monotonic() - start,
            }
        )
        line = await asyncio.wait_for(lines.get(), timeout=float(cfg["window_timeout"]))
        if line is None:
            return
        order = json.loads(line)
        if "window" not in order:
            return
        stats.t0, stats.t1 = (float(x) for x in order["window"])
        await asyncio.sleep(max(0.0, stats.t1 - time.monotonic()) + 0.05)
        summary = stats.summary()
        summary["crashed_clients"] = sum(
            1 for t in tasks if t.done() and not t.cancelled() and t.exception() is not None
        )
        summary["event"] = "result"
        emit(summary)
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        open_ws = [c.ws for c in clients if c.ws is not None]
        if open_ws:
            await asyncio.wait(
                [asyncio.create_task(ws.close(1000, "bench over")) for ws in open_ws], timeout=10.0
            )


def _load_entry() -> None:
    """Entry of the load subprocess: config as JSON in argv[1], JSON lines on stdout."""
    cfg = json.loads(sys.argv[1])
    out = os.fdopen(os.dup(1), "w", buffering=1)
    sys.stdout = sys.stderr  # nothing else may write to the channel

    def emit(message: dict[str, Any]) -> None:
        out.write(json.dumps(message) + "\n")
        out.flush()

    def watchdog() -> None:
        time.sleep(float(cfg["hard_timeout"]))
        print("bench load: hard timeout, exiting", file=sys.stderr, flush=True)
        os._exit(3)

    threading.Thread(target=watchdog, daemon=True).start()
    _raise_nofile(int(cfg["clients"]) + 256)
    _run_loop(_load_main(cfg, emit))


# ----------------------------------------------------------------------------------
# The controller (this process)
# ----------------------------------------------------------------------------------


def _raise_nofile(needed: int) -> None:
    try:
        import resource

        soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
        if soft != resource.RLIM_INFINITY and soft < needed:
            target = needed if hard == resource.RLIM_INFINITY else min(needed, hard)
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
    except (ImportError, ValueError, OSError):
        pass


class _Child:
    """A subprocess whose stdout lines arrive on a queue and whose stderr goes to a file."""

    def __init__(
        self, name: str, argv: list[str], stdin: bool = False, hash_seed: int | None = None
    ) -> None:
        self.name = name
        env = None
        if hash_seed is not None and "PYTHONHASHSEED" not in os.environ:
            # The same string hashes (dict and set layouts) in every run: the
            # relay's CPU per pose then varies less from one process to the next.
            env = {**os.environ, "PYTHONHASHSEED": str(hash_seed)}
        # Closed in stop(): it must outlive this call, as the child writes to it.
        self.stderr_file: IO[bytes] = tempfile.TemporaryFile()  # noqa: SIM115
        self.proc = subprocess.Popen(
            argv,
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=self.stderr_file,
            text=True,
            bufsize=1,
            cwd=str(Path(__file__).resolve().parent.parent),
            env=env,
        )
        self.lines: queue.Queue[str | None] = queue.Queue()
        self._pump_thread = threading.Thread(target=self._pump, daemon=True)
        self._pump_thread.start()

    def _pump(self) -> None:
        assert self.proc.stdout is not None
        for line in self.proc.stdout:
            self.lines.put(line)
        self.lines.put(None)

    @property
    def pid(self) -> int:
        return self.proc.pid

    def stderr_tail(self, limit: int = 2000) -> str:
        try:
            self.stderr_file.seek(0)
            return self.stderr_file.read().decode(errors="replace")[-limit:]
        except (OSError, ValueError):
            return ""

    def fail(self, what: str) -> RuntimeError:
        code = self.proc.poll()
        state = "still running" if code is None else f"exit code {code}"
        return RuntimeError(f"{self.name}: {what} ({state})\n{self.stderr_tail()}")

    def wait_line(self, match: Callable[[str], bool], timeout: float) -> str:
        deadline = time.monotonic() + timeout
        while True:
            left = deadline - time.monotonic()
            if left <= 0:
                raise self.fail(f"no answer within {timeout:g} s")
            try:
                line = self.lines.get(timeout=left)
            except queue.Empty:
                continue
            if line is None:
                raise self.fail("exited early")
            if match(line):
                return line

    def wait_json(self, event: str, timeout: float) -> dict[str, Any]:
        def match(line: str) -> bool:
            return line.startswith("{") and f'"event": "{event}"' in line

        message: dict[str, Any] = json.loads(self.wait_line(match, timeout))
        return message

    def tell(self, message: dict[str, Any]) -> None:
        if self.proc.stdin is not None and self.proc.poll() is None:
            with contextlib.suppress(OSError, ValueError):
                self.proc.stdin.write(json.dumps(message) + "\n")
                self.proc.stdin.flush()

    def stop(self, grace: float) -> int | None:
        """Close stdin (a polite child exits), SIGTERM, SIGKILL; ``grace`` s each step."""
        if self.proc.stdin is not None:
            with contextlib.suppress(OSError, ValueError):
                self.proc.stdin.close()
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(timeout=grace)
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=grace)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self.proc.wait(timeout=5.0)
        # The pump ends at EOF once the child is gone; then its pipe can close.
        self._pump_thread.join(timeout=5.0)
        if self.proc.stdout is not None and not self._pump_thread.is_alive():
            self.proc.stdout.close()
        with contextlib.suppress(OSError):
            self.stderr_file.close()
        return self.proc.poll()


def _proc_cpu(pid: int) -> tuple[float, float]:
    """(user, system) CPU seconds of process ``pid`` (from /proc/<pid>/stat)."""
    text = Path(f"/proc/{pid}/stat").read_text()
    fields = text[text.rindex(")") + 2 :].split()
    # After "pid (comm) ": state is field 3, utime and stime are fields 14 and 15.
    tick = os.sysconf("SC_CLK_TCK")
    return int(fields[11]) / tick, int(fields[12]) / tick


def _run_time(pid: int) -> float:
    """CPU seconds process ``pid``'s threads have run, to the nanosecond (schedstat).

    Falls back to :func:`_proc_cpu` (clock ticks) where schedstat is missing.
    """
    total = 0
    try:
        for stat in Path(f"/proc/{pid}/task").glob("*/schedstat"):
            with contextlib.suppress(OSError, ValueError, IndexError):
                total += int(stat.read_text().split()[0])
    except OSError:
        total = 0
    return total / 1e9 if total else sum(_proc_cpu(pid))


def _children_run_time(pid: int) -> float:
    """:func:`_run_time` of the live child processes of ``pid`` (its recorders)."""
    return sum(_run_time(kid) for kid in _children(pid))


def _children(pid: int) -> list[int]:
    kids: list[int] = []
    for children in Path(f"/proc/{pid}/task").glob("*/children"):
        with contextlib.suppress(OSError, ValueError):
            kids += [int(k) for k in children.read_text().split()]
    return kids


def _machine_cpu() -> tuple[float, float, float]:
    """(busy, stolen, total) jiffies of all cores from /proc/stat.

    ``busy`` is what this machine ran; ``stolen`` is time the hypervisor gave
    its cores to other guests (a virtual machine on a busy host).
    """
    values = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    total = float(sum(values[:8]))  # guest time is already inside user
    idle = float(values[3] + values[4])
    steal = float(values[7])
    return total - idle - steal, steal, total


def _scrape(port: int, timeout: float = 20.0) -> dict[str, float] | None:
    """The server's /metrics, summed per name (``*_max_ms`` gauges: the max).

    None if it does not answer in time: an overloaded server can be that slow.
    """
    url = f"http://127.0.0.1:{port}/metrics"
    try:
        with urllib.request.urlopen(url, timeout=timeout) as resp:
            text = resp.read().decode()
    except OSError:
        return None
    out: dict[str, float] = {}
    for line in text.splitlines():
        if not line or line.startswith("#"):
            continue
        name_labels, _, value = line.rpartition(" ")
        name = name_labels.split("{", 1)[0]
        v = float(value)
        if name.endswith("_max_ms"):
            out[name] = max(out.get(name, 0.0), v)
        else:
            out[name] = out.get(name, 0.0) + v
    return out


def _value(metrics: dict[str, float] | None, name: str) -> float:
    return math.nan if metrics is None else metrics.get(name, 0.0)


def _delta(m0: dict[str, float] | None, m1: dict[str, float] | None, name: str) -> float:
    return _value(m1, name) - _value(m0, name)


def _sleep_until(t: float) -> None:
    while (left := t - time.monotonic()) > 0:
        time.sleep(min(left, 0.5))


def run_relay_bench(
    clients: int,
    room_size: int,
    rate: float,
    duration: float,
    *,
    record: bool = False,
    record_writer: str = "process",
    repeat: int = 1,
    console: Console | None = None,
    warmup: float = 5.0,
    ramp_rate: float = 50.0,
    seed: int = 0,
    interleave: float = 0.0,
) -> dict[str, Any]:
    """Run the relay benchmark; print and return its report (figures, never pass/fail).

    ``clients`` load clients join rooms of ``room_size``, each publishes 3 streams
    at ``rate`` Hz and subscribes at ``rate``; connections ramp up at
    ``ramp_rate`` per second, measuring starts ``warmup`` s after the last join
    and lasts ``duration`` s. With ``record`` the same load runs recorder off,
    then on (with each of ``record_writer``: ``process``, ``thread`` or
    ``both``), ``repeat`` times alternating (the paper's Table 4), and the report
    adds ``{"recorder": {...}}`` with the cost ratio and bytes per pose on disk
    (medians over the rounds, each round's loss listed).

    With ``interleave`` > 0 each round is instead one recording run whose window
    is cut into phases of ``interleave`` s, recording paused and resumed in
    turn; ``{"recorder_interleaved": {...}}`` compares paired phases of the
    same server process (:func:`_interleaved_summary`).
    """
    console = console or Console()
    args = (clients, room_size, rate, duration)
    opts: dict[str, Any] = {"warmup": warmup, "ramp_rate": ramp_rate, "seed": seed}
    if not record:
        return _run_once(*args, record_dir=None, console=console, **opts)
    writers = ["process", "thread"] if record_writer == "both" else [record_writer]
    if any(w not in ("process", "thread") for w in writers):
        raise ValueError(f"record_writer must be process, thread or both, not {record_writer!r}")
    if repeat < 1:
        raise ValueError("repeat must be at least 1")
    if interleave < 0 or (interleave > 0 and interleave < 2 * _PHASE_SETTLE):
        raise ValueError(f"interleave must be 0 or at least {2 * _PHASE_SETTLE:g} s")
    if interleave > 0:
        return _run_interleaved(args, writers, repeat, interleave, console, opts)
    # Off and on alternate in a balanced order (off first in even rounds, last
    # in odd ones): a drift of a shared machine, or anything that favours the
    # first or second run of a round, hits both alike. Each on-run is compared
    # with the off-run of its own round.
    pairs: dict[str, list[dict[str, Any]]] = {w: [] for w in writers}
    runs: dict[str, dict[str, Any]] = {}
    offs: list[dict[str, Any]] = []
    for k in range(repeat):
        if repeat > 1:
            console.print(f"[bold]recorder cost: round {k + 1} of {repeat}[/bold]")
        order: list[str | None] = [None, *writers]
        if k % 2:
            order.reverse()
        off: dict[str, Any] | None = None
        for writer in order:
            if writer is None:
                off = _run_once(*args, record_dir=None, console=console, **opts)
                offs.append(off)
                continue
            with tempfile.TemporaryDirectory(prefix="posecast-bench-") as tmp:
                on = _run_once(
                    *args, record_dir=Path(tmp), record_writer=writer, console=console, **opts
                )
                # Read what the summary needs while the files exist.
                disk = _disk_figures(sorted(Path(tmp).glob("*.mcap")))
                pairs[writer].append({"on": on, "disk": disk})
                runs[writer] = on
        assert off is not None
        for writer in writers:
            last = pairs[writer][-1]
            pairs[writer][-1] = _recorder_summary(off, last["on"], last["disk"])
    summaries = {w: _median_summary(pairs[w]) for w in writers}
    first = writers[0]
    on = runs[first]
    on["recorder"] = summaries[first]
    on["recorder_by_writer"] = summaries
    on["recorder_off"] = offs[-1]
    for writer in writers[1:]:
        on[f"recorder_on_{writer}"] = runs[writer]
    _print_recorder_table(summaries, console)
    return on


def _run_interleaved(
    args: tuple[int, int, float, float],
    writers: list[str],
    repeat: int,
    interleave: float,
    console: Console,
    opts: dict[str, Any],
) -> dict[str, Any]:
    """``repeat`` recording runs per writer, each window in paused/recording phases."""
    phases: dict[str, list[dict[str, Any]]] = {w: [] for w in writers}
    last: dict[str, Any] = {}
    for k in range(repeat):
        for writer in writers:
            if repeat > 1:
                console.print(f"[bold]recorder cost, interleaved: round {k + 1} of {repeat}[/bold]")
            with tempfile.TemporaryDirectory(prefix="posecast-bench-") as tmp:
                last = _run_once(
                    *args,
                    record_dir=Path(tmp),
                    record_writer=writer,
                    console=console,
                    interleave=interleave,
                    **opts,
                )
            phases[writer] += last.get("phases", [])
    summaries = {w: _interleaved_summary(p) for w, p in phases.items()}
    last["recorder_interleaved"] = summaries
    _print_interleaved(summaries, interleave, console)
    return last


def _print_interleaved(
    summaries: Mapping[str, Mapping[str, Any]], interleave: float, console: Console
) -> None:
    table = Table(
        title=(
            "recorder cost (Table 4), interleaved: one recording server, pose recording "
            f"paused and resumed every {interleave:g} s"
        ),
        title_justify="left",
    )
    table.add_column("figure")
    for writer in summaries:
        table.add_column(f"{writer} writer", justify="right")

    def row(name: str, key: str, digits: int) -> None:
        table.add_row(name, *(_f(s.get(key, math.nan), digits) for s in summaries.values()))

    row("phases (pairs)", "phases", 0)
    row("relay CPU per pose, paused (us)", "relay_cpu_us_per_pose_paused", 3)
    row("relay CPU per pose, recording (us)", "relay_cpu_us_per_pose_recording", 3)
    row("writer process CPU per pose, recording (us)", "writer_cpu_us_per_pose_recording", 3)
    row("relay throughput loss, pooled (%)", "throughput_loss_pct_pooled", 2)
    row("relay throughput loss, median of pairs (%)", "throughput_loss_pct", 2)
    row("relay throughput loss, mean of pairs (%)", "throughput_loss_pct_mean", 2)
    row("  standard error of that mean", "throughput_loss_pct_se", 2)
    row(f"quiet pairs (host steal <= {_QUIET_STEAL_PCT:g} % of a core)", "quiet_pairs", 0)
    row("  relay throughput loss, mean of quiet pairs (%)", "throughput_loss_pct_quiet_mean", 2)
    row("  standard error of that mean", "throughput_loss_pct_quiet_se", 2)
    row("  median of quiet pairs (%)", "throughput_loss_pct_quiet_median", 2)
    row("stolen by the host, median / max (% of a core)", "steal_pct_median", 0)
    console.print(table)
    for writer, summary in summaries.items():
        console.print(
            f"{writer} writer: CPU-bound relay throughput loss while recording "
            f"{_f(summary['throughput_loss_pct_mean'], 2)} % +- "
            f"{_f(summary['throughput_loss_pct_se'], 2)} (mean of {summary['pairs']} pairs, "
            f"standard error; median {_f(summary['throughput_loss_pct'], 2)} %; target <= 2 %, "
            "the paper lost 4.9 %); quiet pairs: "
            f"{_f(summary['throughput_loss_pct_quiet_mean'], 2)} % +- "
            f"{_f(summary['throughput_loss_pct_quiet_se'], 2)} ({summary['quiet_pairs']} pairs)"
        )


def _median_summary(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    """The median of each figure over the rounds, with every round's loss kept."""
    out = dict(rounds[-1])
    if len(rounds) > 1:
        for key, value in rounds[-1].items():
            if isinstance(value, float):
                out[key] = float(np.median([r[key] for r in rounds]))
    out["rounds"] = len(rounds)
    losses = [r["throughput_loss_pct"] for r in rounds]
    out["throughput_loss_pct_rounds"] = losses
    out["steal_pct_rounds"] = [
        [r.get("steal_pct_off", math.nan), r.get("steal_pct_on", math.nan)] for r in rounds
    ]
    out["throughput_loss_pct_mean"] = float(np.mean(losses))
    # Standard error of that mean (the rounds are independent pairs).
    out["throughput_loss_pct_se"] = (
        float(np.std(losses, ddof=1) / math.sqrt(len(losses))) if len(losses) > 1 else math.nan
    )
    out["total_cpu_overhead_pct_rounds"] = [r["total_cpu_overhead_pct"] for r in rounds]
    return out


def _disk_figures(files: list[Path]) -> dict[str, Any]:
    """Files, bytes and poses of a run's recordings (read before they are deleted)."""
    from recorder import info as recording_info

    return {
        "files": len(files),
        "disk_bytes": sum(f.stat().st_size for f in files),
        "poses_on_disk": sum(int(recording_info(f)["sizes"]["poses"]) for f in files),
    }


def _recorder_summary(
    off: Mapping[str, Any], on: Mapping[str, Any], disk_figures: Mapping[str, Any]
) -> dict[str, Any]:
    """Table 4 figures of one recorder-on run against the recorder-off run."""
    disk, poses_on_disk = disk_figures["disk_bytes"], disk_figures["poses_on_disk"]
    cost_off, cost_on = off["server_cpu_us_per_pose"], on["server_cpu_us_per_pose"]
    writer_cost = on["recorder_cpu_us_per_pose"]
    total_on = cost_on + writer_cost
    return {
        "writer": on["record_writer"],
        "server_cpu_us_per_pose_off": cost_off,
        "server_cpu_us_per_pose_on": cost_on,
        "recorder_process_cpu_us_per_pose": writer_cost,
        "total_cpu_us_per_pose_on": total_on,
        # The relay's event loop is one core: when it is CPU-bound its throughput
        # scales with 1 / (its own CPU per pose). A writer process runs on another core.
        "throughput_ratio": cost_off / cost_on if cost_on else math.nan,
        "throughput_loss_pct": 100.0 * (1.0 - cost_off / cost_on) if cost_on else math.nan,
        # Everything the recording costs the machine, wherever it runs.
        "total_cpu_overhead_pct": 100.0 * (total_on / cost_off - 1.0) if cost_off else math.nan,
        "delivered_poses_per_s_off": off["poses_per_s"],
        "delivered_poses_per_s_on": on["poses_per_s"],
        "latency_p99_ms_off": off["latency_p99_ms"],
        "latency_p99_ms_on": on["latency_p99_ms"],
        "steal_pct_off": off.get("steal_pct", math.nan),
        "steal_pct_on": on.get("steal_pct", math.nan),
        "files": disk_figures["files"],
        "disk_bytes": disk,
        "poses_on_disk": poses_on_disk,
        "disk_bytes_per_pose": disk / poses_on_disk if poses_on_disk else math.nan,
    }


def _print_recorder_table(
    summaries: Mapping[str, Mapping[str, Any]],
    console: Console,
) -> None:
    first = next(iter(summaries.values()))
    rounds = int(first["rounds"])
    table = Table(
        title="recorder cost (Table 4): same load, recorder off and on"
        + (f"; medians over {rounds} rounds" if rounds > 1 else ""),
        title_justify="left",
    )
    table.add_column("figure")
    table.add_column("off", justify="right")
    for writer in summaries:
        table.add_column(f"on ({writer} writer)", justify="right")

    def row(name: str, on_key: str, digits: int, off_key: str | None = None) -> None:
        cells = [_f(first[off_key], digits) if off_key else "-"]
        cells += [_f(s.get(on_key, math.nan), digits) for s in summaries.values()]
        table.add_row(name, *cells)

    row(
        "relay process CPU per pose (us)",
        "server_cpu_us_per_pose_on",
        2,
        "server_cpu_us_per_pose_off",
    )
    row("writer process CPU per pose (us)", "recorder_process_cpu_us_per_pose", 2)
    row("delivered poses/s", "delivered_poses_per_s_on", 0, "delivered_poses_per_s_off")
    row("capture->receipt p99 (ms)", "latency_p99_ms_on", 1, "latency_p99_ms_off")
    row("relay throughput loss (%)", "throughput_loss_pct", 1)
    row("total CPU overhead (%)", "total_cpu_overhead_pct", 1)
    row("bytes per pose on disk", "disk_bytes_per_pose", 1)
    console.print(table)
    for writer, summary in summaries.items():
        if summary["rounds"] > 1:
            each = ", ".join(_f(x, 1) for x in summary["throughput_loss_pct_rounds"])
            console.print(
                f"{writer} writer, relay throughput loss per round (%): {each}; "
                f"mean {_f(summary['throughput_loss_pct_mean'], 1)} "
                f"+- {_f(summary['throughput_loss_pct_se'], 1)} (standard error)"
            )
            steal = ", ".join(f"{_f(a, 0)}/{_f(b, 0)}" for a, b in summary["steal_pct_rounds"])
            console.print(f"  stolen by the host per round, off/on (% of a core): {steal}")
        console.print(
            f"{writer} writer: CPU-bound relay throughput with the recorder "
            f"x{_f(summary['throughput_ratio'], 3)} ({_f(summary['throughput_loss_pct'], 1)} % "
            "loss; target <= 2 %, the paper lost 4.4 of 89.6 FPS = 4.9 %); all recording CPU "
            f"together {_f(summary['total_cpu_overhead_pct'], 1)} % of the relay's; "
            f"{_f(summary['disk_bytes_per_pose'], 1)} bytes per pose on disk"
        )


#: Recording state of the phases of an interleaved window, repeating: paused,
#: recording, recording, paused (each pair has one of each, in both orders).
_PHASE_PATTERN: Final = (False, True, True, False)
#: A pair of phases counts as quiet when the host stole at most this much of a
#: core (in %) in each: on a shared virtual machine, steal comes and goes with
#: other guests' load, and a phase with much of it measures them, not us.
_QUIET_STEAL_PCT: Final = 10.0
#: Seconds after a pause or resume before a phase is measured: the writer
#: process finishes what the relay handed it before (batches of <= 0.25 s).
_PHASE_SETTLE: Final = 0.5


def _interleaved_phases(pid: int, port: int, end: float, length: float) -> list[dict[str, Any]]:
    """Pause and resume the recording of server ``pid`` in phases until ``end``.

    The server records when this starts. Each phase sets its state (SIGUSR1
    pauses, SIGUSR2 resumes), waits :data:`_PHASE_SETTLE` s and measures the
    rest: the relay's and its writer process's CPU (their threads' run time
    from ``/proc/*/task/*/schedstat``, in ns), the poses the relay sent
    (its ``posecast_room_poses_out_total``) and the CPU the host stole.
    Same process, same clients, phases seconds apart: what differs between a
    paused and a recording phase is the recording.
    """
    phases: list[dict[str, Any]] = []
    recording = True
    k = 0
    while time.monotonic() + length <= end + 0.5 * _PHASE_SETTLE:
        want = _PHASE_PATTERN[k % len(_PHASE_PATTERN)]
        start = time.monotonic()
        if want != recording:
            os.kill(pid, signal.SIGUSR2 if want else signal.SIGUSR1)
            recording = want
        _sleep_until(start + _PHASE_SETTLE)
        m0, s0, r0, c0, w0 = (
            _scrape(port),
            _run_time(pid),
            _children_run_time(pid),
            _machine_cpu(),
            time.monotonic(),
        )
        _sleep_until(start + length)
        m1, s1, r1, c1, w1 = (
            _scrape(port),
            _run_time(pid),
            _children_run_time(pid),
            _machine_cpu(),
            time.monotonic(),
        )
        poses = _delta(m0, m1, "posecast_room_poses_out_total")
        total = c1[2] - c0[2]
        phases.append(
            {
                "recording": recording,
                "wall_s": w1 - w0,
                "relay_cpu_s": s1 - s0,
                "writer_cpu_s": r1 - r0,
                "poses": poses,
                "relay_cpu_us_per_pose": 1e6 * (s1 - s0) / poses if poses > 0 else math.nan,
                "steal_pct": 100.0 * (c1[1] - c0[1]) / total * (os.cpu_count() or 1)
                if total > 0
                else math.nan,
            }
        )
        k += 1
    if not recording:
        os.kill(pid, signal.SIGUSR2)
    return phases


def _interleaved_summary(phases: list[dict[str, Any]]) -> dict[str, Any]:
    """Table 4 from paired phases: each pair is one paused and one recording phase."""
    losses: list[float] = []
    quiet: list[float] = []
    steals: list[float] = []
    for a, b in zip(phases[0::2], phases[1::2], strict=False):
        paused, recording = (a, b) if b["recording"] else (b, a)
        cost_off = paused["relay_cpu_us_per_pose"]
        cost_on = recording["relay_cpu_us_per_pose"]
        if math.isfinite(cost_off) and math.isfinite(cost_on) and cost_on > 0:
            loss = 100.0 * (1.0 - cost_off / cost_on)
            steal = max(paused["steal_pct"], recording["steal_pct"])
            losses.append(loss)
            steals.append(steal)
            if steal <= _QUIET_STEAL_PCT:
                quiet.append(loss)

    def per_pose(recording: bool, key: str) -> float:
        chosen = [p for p in phases if p["recording"] == recording]
        poses = sum(p["poses"] for p in chosen)
        return 1e6 * sum(p[key] for p in chosen) / poses if poses > 0 else math.nan

    off, on = per_pose(False, "relay_cpu_s"), per_pose(True, "relay_cpu_s")
    n = len(losses)
    return {
        "phases": len(phases),
        "pairs": n,
        "relay_cpu_us_per_pose_paused": off,
        "relay_cpu_us_per_pose_recording": on,
        "writer_cpu_us_per_pose_recording": per_pose(True, "writer_cpu_s"),
        "writer_cpu_us_per_pose_paused": per_pose(False, "writer_cpu_s"),
        # pooled over all phases of each state
        "throughput_loss_pct_pooled": 100.0 * (1.0 - off / on) if on > 0 else math.nan,
        "throughput_loss_pct": float(np.median(losses)) if n else math.nan,
        "throughput_loss_pct_mean": float(np.mean(losses)) if n else math.nan,
        "throughput_loss_pct_se": float(np.std(losses, ddof=1) / math.sqrt(n))
        if n > 1
        else math.nan,
        "throughput_loss_pct_pairs": losses,
        # the host's steal (% of a core), the larger of the pair's two phases
        "steal_pct_pairs": steals,
        # Pairs in which the host stole at most _QUIET_STEAL_PCT of a core in both
        # phases: the figure for a machine of one's own.
        "quiet_steal_pct": _QUIET_STEAL_PCT,
        "quiet_pairs": len(quiet),
        "throughput_loss_pct_quiet_mean": float(np.mean(quiet)) if quiet else math.nan,
        "throughput_loss_pct_quiet_se": float(np.std(quiet, ddof=1) / math.sqrt(len(quiet)))
        if len(quiet) > 1
        else math.nan,
        "throughput_loss_pct_quiet_median": float(np.median(quiet)) if quiet else math.nan,
        "phase_records": phases,
        "steal_pct_max": max((p["steal_pct"] for p in phases), default=math.nan),
        "steal_pct_median": float(np.median([p["steal_pct"] for p in phases]))
        if phases
        else math.nan,
    }


def _run_once(
    clients: int,
    room_size: int,
    rate: float,
    duration: float,
    *,
    record_dir: Path | None,
    console: Console,
    record_writer: str = "process",
    warmup: float,
    ramp_rate: float,
    seed: int,
    interleave: float = 0.0,
) -> dict[str, Any]:
    """One measured run; ``record_dir`` turns the server's recorder on.

    With ``interleave`` (and ``record_dir``) the window is cut into phases of
    that many seconds in which the server records or has recording paused
    (``report["phases"]``, see :func:`_interleaved_phases`).
    """
    if clients < 1 or room_size < 1:
        raise ValueError("clients and room_size must be at least 1")
    if not 0 < rate <= 100:
        raise ValueError("rate must be in (0, 100] Hz")
    if duration <= 0 or warmup < 0 or ramp_rate <= 0:
        raise ValueError("duration and ramp_rate must be positive, warmup non-negative")
    _raise_nofile(clients + 256)
    ramp_s = clients / ramp_rate
    window_timeout = warmup + 60.0
    hard_timeout = ramp_s + 30.0 + window_timeout + duration + 60.0
    server: _Child | None = None
    load: _Child | None = None
    report: dict[str, Any] = {
        "clients": clients,
        "room_size": room_size,
        "rooms": math.ceil(clients / room_size),
        "rate_hz": rate,
        "duration_s": duration,
        "warmup_s": warmup,
        "ramp_per_s": ramp_rate,
        "record": record_dir is not None,
        "record_writer": record_writer if record_dir is not None else None,
        "nproc": os.cpu_count() or 0,
    }
    try:
        with console.status("relay bench: starting the server ...") as status:
            server = _Child(
                "server",
                [
                    sys.executable,
                    "-c",
                    _SERVER_BOOT,
                    "serve",
                    "--host",
                    "127.0.0.1",
                    "--port",
                    "0",
                    "--rate",
                    f"{rate:g}",
                    "--min-rate",
                    f"{min(5.0, rate):g}",
                    "--max-rate",
                    f"{max(30.0, rate):g}",
                    "--log-level",
                    "warning",
                    *(
                        ["--record", str(record_dir), "--record-writer", record_writer]
                        if record_dir is not None
                        else []
                    ),
                ],
                hash_seed=seed,
            )
            found = _LISTENING.search(
                server.wait_line(lambda line: _LISTENING.search(line) is not None, timeout=30.0)
            )
            assert found is not None
            port = int(found.group(2))
            cfg = {
                "url": f"ws://127.0.0.1:{port}",
                "clients": clients,
                "room_size": room_size,
                "rate": rate,
                "ramp_rate": ramp_rate,
                "seed": seed,
                "window_timeout": window_timeout,
                "hard_timeout": hard_timeout,
            }
            status.update(f"relay bench: ramping up {clients} clients at {ramp_rate:g}/s ...")
            load = _Child(
                "load",
                [sys.executable, "-c", _LOAD_BOOT, json.dumps(cfg)],
                stdin=True,
                hash_seed=seed,
            )
            ramped = load.wait_json("ramped", timeout=ramp_s + 60.0)
            report["clients_joined"] = int(ramped["joined"])
            report["clients_failed"] = int(ramped["failed"])
            report["join_errors"] = ramped["errors"]
            report["ramp_s"] = float(ramped["ramp_s"])
            if ramped["joined"] == 0:
                raise load.fail(f"no client could join: {ramped['errors']}")
            t0 = time.monotonic() + warmup
            t1 = t0 + duration
            load.tell({"window": [t0, t1]})
            status.update(f"relay bench: warm-up {warmup:g} s ...")
            _sleep_until(t0)
            status.update(f"relay bench: measuring for {duration:g} s ...")
            r0 = _children_run_time(server.pid)
            s0, l0, c0, w0 = (
                _proc_cpu(server.pid),
                _proc_cpu(load.pid),
                _machine_cpu(),
                time.monotonic(),
            )
            m0 = _scrape(port)
            if interleave > 0 and record_dir is not None:
                status.update(f"relay bench: measuring for {duration:g} s, recording on/off ...")
                report["phases"] = _interleaved_phases(server.pid, port, t1, interleave)
            _sleep_until(t1)
            r1 = _children_run_time(server.pid)
            s1, l1, c1, w1 = (
                _proc_cpu(server.pid),
                _proc_cpu(load.pid),
                _machine_cpu(),
                time.monotonic(),
            )
            m1 = _scrape(port)
            status.update("relay bench: collecting ...")
            result = load.wait_json("result", timeout=60.0)
    finally:
        if load is not None:
            load.stop(grace=15.0)
        if server is not None:
            code = server.stop(grace=15.0)
            report["server_exit_code"] = code

    wall = w1 - w0
    server_user, server_sys = s1[0] - s0[0], s1[1] - s0[1]
    server_cpu = server_user + server_sys
    load_cpu = sum(l1) - sum(l0)
    delivered = int(result["poses_delivered"])
    snapshots = int(result["snapshots"])
    busy, steal, total = (c1[i] - c0[i] for i in range(3))
    ncpu = os.cpu_count() or 1
    # Remote poses/s the clients ask for: each gets its room mates' 3 streams at ``rate``.
    full, last = divmod(clients, room_size)
    offered = rate * len(STREAMS) * (full * room_size * (room_size - 1) + last * (last - 1))
    del result["event"]
    report.update(result)
    report.update(
        {
            "server_cpu_s": server_cpu,
            "server_cpu_pct": 100.0 * server_cpu / wall,
            "server_cpu_us_per_pose": 1e6 * server_cpu / delivered if delivered else math.nan,
            "recorder_cpu_s": r1 - r0,
            "recorder_cpu_us_per_pose": 1e6 * (r1 - r0) / delivered if delivered else math.nan,
            "server_cpu_us_per_snapshot": 1e6 * server_cpu / snapshots if snapshots else math.nan,
            "server_sys_pct": 100.0 * server_sys / wall,
            "load_cpu_pct": 100.0 * load_cpu / wall,
            "machine_cpu_pct": 100.0 * busy / total if total > 0 else math.nan,
            # CPU used by neither the server nor the load (other jobs on this machine).
            "other_cpu_pct": 100.0 * (busy / total * ncpu)
            - 100.0 * (server_cpu + load_cpu + r1 - r0) / wall
            if total > 0
            else math.nan,
            # Of one core: time the hypervisor ran other guests on our cores. A
            # busy host slows every figure here; compare runs with little of it.
            "steal_pct": 100.0 * steal / total * ncpu if total > 0 else math.nan,
            "poses_per_s": delivered / wall,
            "offered_poses_per_s": offered,
            # What the server would need at full rate, at the CPU cost per pose measured.
            "server_core_demand_pct": 100.0 * server_cpu / delivered * offered
            if delivered
            else math.nan,
            "snapshot_rate_ratio": float(result["snapshots_per_client_s"]) / rate,
            "bytes_per_pose": result["wire_bytes"] / delivered if delivered else math.nan,
            "payload_bytes_per_pose": result["payload_bytes"] / delivered
            if delivered
            else math.nan,
            "metrics_ok": m0 is not None and m1 is not None,
            "skips": _delta(m0, m1, "posecast_snapshot_skips_total"),
            "flood_drops": _delta(m0, m1, "posecast_flood_drops_total"),
            "server_poses_out": _delta(m0, m1, "posecast_room_poses_out_total"),
            "tick_lag_max_ms_start": _value(m0, "posecast_room_tick_lag_max_ms"),
            "tick_lag_max_ms_end": _value(m1, "posecast_room_tick_lag_max_ms"),
            "connections_end": _value(m1, "posecast_connections"),
        }
    )
    report["skips_per_s"] = report["skips"] / wall
    print_relay_report(report, console)
    return report


def _f(x: Any, digits: int = 1) -> str:
    if isinstance(x, float) and x != x:
        return "-"
    return f"{x:,.{digits}f}" if isinstance(x, float) else f"{x:,}"


def print_relay_report(report: dict[str, Any], console: Console) -> None:
    """The report as a two-column rich table."""
    r = report
    table = Table(
        title=(
            f"relay bench: {r['clients']} clients, rooms of {r['room_size']}, "
            f"{r['rate_hz']:g} Hz, {r['window_s']:.1f} s measured on {r['nproc']} cores"
        ),
        title_justify="left",
    )
    table.add_column("figure")
    table.add_column("value", justify="right")
    table.add_column("note")
    rows = [
        ("clients joined / failed", f"{r['clients_joined']} / {r['clients_failed']}", ""),
        (
            "server CPU",
            f"{_f(r['server_cpu_pct'])} %",
            f"of one core; {_f(r['server_sys_pct'])} % in the kernel",
        ),
        ("server CPU per pose", f"{_f(r['server_cpu_us_per_pose'], 2)} us", "per remote pose"),
        ("server CPU per snapshot", f"{_f(r['server_cpu_us_per_snapshot'], 1)} us", ""),
        ("load CPU", f"{_f(r['load_cpu_pct'])} %", "load generator; ~100 % = it limits"),
        (
            "machine CPU / other jobs",
            f"{_f(r['machine_cpu_pct'])} % / {_f(r['other_cpu_pct'])} %",
            "all cores / of one core, neither server nor load",
        ),
        (
            "stolen by the host",
            f"{_f(r['steal_pct'])} %",
            "of one core, given to other virtual machines; high: the figures are noisy",
        ),
        (
            "capture->receipt p50 / p99",
            f"{_f(r['latency_p50_ms'], 2)} / {_f(r['latency_p99_ms'], 2)} ms",
            "remote poses; includes the wait for the next tick",
        ),
        (
            "  wait for tick p50 / p99",
            f"{_f(r['hold_p50_ms'], 2)} / {_f(r['hold_p99_ms'], 2)} ms",
            "capture -> due tick, 0..1/rate when unsynchronised",
        ),
        (
            "  relay (due tick->receipt) p50 / p99",
            f"{_f(r['relay_p50_ms'], 2)} / {_f(r['relay_p99_ms'], 2)} ms",
            "the load-dependent part",
        ),
        (
            "tick lag p50 / p99",
            f"{_f(r['tick_lag_p50_ms'], 2)} / {_f(r['tick_lag_p99_ms'], 2)} ms",
            "snapshot send time - grid point",
        ),
        (
            "server tick lag max (start -> end)",
            f"{_f(r['tick_lag_max_ms_start'])} -> {_f(r['tick_lag_max_ms_end'])} ms",
            "/metrics, max over rooms",
        ),
        (
            "snapshots / client / s",
            f"{_f(r['snapshots_per_client_s'], 2)} (min {_f(r['snapshots_per_client_s_min'], 2)})",
            f"asked {r['rate_hz']:g}; ratio {_f(r['snapshot_rate_ratio'], 3)}",
        ),
        ("skips", f"{_f(r['skips'], 0)} ({_f(r['skips_per_s'], 1)}/s)", "/metrics"),
        (
            "poses delivered / s",
            _f(r["poses_per_s"], 0),
            f"remote poses; {_f(r['offered_poses_per_s'], 0)} asked for",
        ),
        (
            "server core demand at full rate",
            f"{_f(r['server_core_demand_pct'])} %",
            "CPU per pose x poses asked for; > 100 %: one process cannot keep up",
        ),
        (
            "bytes per pose",
            f"{_f(r['bytes_per_pose'], 1)}",
            f"on the wire incl. ws header and own echo; {_f(r['payload_bytes_per_pose'], 1)} "
            "payload",
        ),
        (
            "updates sent late",
            _f(r["sends_late"]),
            f"send lag p99 {_f(r['send_lag_p99_ms'], 2)} ms",
        ),
    ]
    for row in rows:
        table.add_row(*row)
    console.print(table)


def main(argv: list[str] | None = None) -> None:
    """``python -m server.bench --clients 500 --room-size 10 --rate 20 --duration 30``."""
    parser = argparse.ArgumentParser(
        prog="python -m server.bench", description="Relay benchmark (figures, never pass/fail)."
    )
    parser.add_argument("--clients", type=int, default=500)
    parser.add_argument("--room-size", type=int, default=10)
    parser.add_argument("--rate", type=float, default=20.0)
    parser.add_argument("--duration", type=float, default=30.0)
    parser.add_argument("--warmup", type=float, default=5.0)
    parser.add_argument("--ramp-rate", type=float, default=50.0, help="connections per second")
    parser.add_argument(
        "--record",
        action="store_true",
        help="recorder off and on, one round (Table 4); more: posecast bench relay --help",
    )
    parser.add_argument("--json", type=Path, default=None, help="also write the report as JSON")
    args = parser.parse_args(argv)
    console = Console(width=None if sys.stdout.isatty() else 140)
    try:
        report = run_relay_bench(
            args.clients,
            args.room_size,
            args.rate,
            args.duration,
            record=args.record,
            console=console,
            warmup=args.warmup,
            ramp_rate=args.ramp_rate,
        )
    except (ValueError, RuntimeError) as exc:
        console.print(f"[bold red]error:[/] {exc}")
        sys.exit(2)
    except KeyboardInterrupt:
        sys.exit(130)
    if args.json is not None:
        args.json.write_text(json.dumps(report, indent=2))
        console.print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
