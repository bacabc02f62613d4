"""The controller's view of its children: subprocesses, /proc CPU figures, /metrics."""

from __future__ import annotations

import contextlib
import json
import math
import os
import queue
import signal
import subprocess
import tempfile
import threading
import time
import urllib.request
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any


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

    def close_stdin(self) -> None:
        """Tell a polite child to finish (it exits at the end of its stdin)."""
        if self.proc.stdin is not None:
            with contextlib.suppress(OSError, ValueError):
                self.proc.stdin.close()

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

    Histogram buckets keep their bound: ``NAME_bucket|LE`` (summed over the other
    labels). None if it does not answer in time: an overloaded server can be
    that slow.
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
        name, _, labels = name_labels.partition("{")
        if name.endswith("_bucket") and 'le="' in labels:
            name += "|" + labels.split('le="', 1)[1].split('"', 1)[0]
        v = float(value)
        if name.endswith("_max_ms"):
            out[name] = max(out.get(name, 0.0), v)
        else:
            out[name] = out.get(name, 0.0) + v
    return out


def _histogram_quantile(
    m0: dict[str, float] | None, m1: dict[str, float] | None, name: str, q: float
) -> float:
    """Quantile ``q`` (0..1) of histogram ``name`` over the window between two scrapes.

    Prometheus' rule: the upper bound of the first bucket whose cumulative count
    reaches ``q`` of the total, interpolated linearly inside it. NaN if the
    server exports no such histogram or it counted nothing in the window.
    """
    if m0 is None or m1 is None:
        return math.nan
    prefix = f"{name}_bucket|"
    bounds = sorted(
        (float(key[len(prefix) :]), m1[key] - m0.get(key, 0.0))
        for key in m1
        if key.startswith(prefix)
    )
    if not bounds or bounds[-1][1] <= 0:
        return math.nan
    total = bounds[-1][1]
    rank = q * total
    lo_bound, lo_count = 0.0, 0.0
    for bound, count in bounds:
        if count >= rank:
            if math.isinf(bound):
                return lo_bound
            inside = count - lo_count
            frac = (rank - lo_count) / inside if inside > 0 else 1.0
            return lo_bound + (bound - lo_bound) * frac
        lo_bound, lo_count = bound, count
    return math.nan


def _value(metrics: dict[str, float] | None, name: str) -> float:
    return math.nan if metrics is None else metrics.get(name, 0.0)


def _gauge(metrics: dict[str, float] | None, name: str) -> float:
    """A gauge's value; NaN if the server did not answer or exports no such series.

    (A room's gauges vanish with the room: 0 would read as "no lag" when every
    client was closed, which is the opposite of the truth.)
    """
    if metrics is None or name not in metrics:
        return math.nan
    return metrics[name]


def _delta(m0: dict[str, float] | None, m1: dict[str, float] | None, name: str) -> float:
    return _value(m1, name) - _value(m0, name)


def _sleep_until(t: float) -> None:
    while (left := t - time.monotonic()) > 0:
        time.sleep(min(left, 0.5))
