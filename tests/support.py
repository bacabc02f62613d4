"""Test support shared by every test package: a real relay on loopback."""

from __future__ import annotations

import asyncio
import inspect
import json
import os
import selectors
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Awaitable, Callable
from contextlib import AbstractAsyncContextManager
from pathlib import Path

from posecast.server.app import RelayServer, ServerConfig, serving

__all__ = [
    "CHROMIUM_ARGS",
    "CliForker",
    "Pacer",
    "find_chromium",
    "import_root",
    "poll_until",
    "relayed",
    "running_server",
    "wait_until",
]

#: Software WebGL (SwiftShader): what a machine without a GPU (CI, this one) renders with.
CHROMIUM_ARGS = ["--use-gl=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]


def find_chromium() -> str | None:
    """``POSECAST_CHROMIUM``, else ``chromium`` or ``chromium-browser`` on PATH."""
    env = os.environ.get("POSECAST_CHROMIUM")
    if env:
        return env if os.path.exists(env) else None
    for name in ("chromium", "chromium-browser"):
        found = shutil.which(name)
        if found:
            return found
    return None


#: The repository's folders, each installed as ``posecast.<folder>``.
FOLDERS = frozenset({"server", "client", "protocol", "interp", "recorder", "scenarios"})


def import_root(name: str) -> str:
    """The package a module name belongs to: ``posecast.protocol.wire`` is ``protocol``
    (a folder installed under ``posecast.``), ``posecast.cli`` is ``posecast``,
    ``numpy.linalg`` is ``numpy``."""
    head, _, rest = name.partition(".")
    sub = rest.split(".")[0]
    return sub if head == "posecast" and sub in FOLDERS else head


def running_server(config: ServerConfig | None = None) -> AbstractAsyncContextManager[RelayServer]:
    """Run a RelayServer on 127.0.0.1:0 while the block runs; stop it on exit."""
    return serving(RelayServer(config or ServerConfig(host="127.0.0.1", port=0)))


# The suite's real sleeps live here (tests/test_guards.py counts them): polling an
# observable condition, and pacing a source that publishes at a rate. A test that
# needs "later" waits for what it is waiting for, through these.


async def poll_until(
    condition: Callable[[], bool | Awaitable[bool]], limit: float = 60.0, every: float = 0.02
) -> None:
    """Poll ``condition`` (plain or async) every ``every`` s until it holds; ``limit`` is
    a hang guard (TimeoutError), not a timing check."""
    async with asyncio.timeout(limit):
        while True:
            got = condition()
            if inspect.isawaitable(got):
                got = await got
            if got:
                return
            await asyncio.sleep(every)


def wait_until(condition: Callable[[], bool], limit: float = 60.0, every: float = 0.02) -> None:
    """:func:`poll_until` for code without an event loop (threads, child processes):
    ``limit`` is a hang guard (TimeoutError), not a timing check."""
    deadline = time.monotonic() + limit
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError(f"condition not met within {limit} s (a hang guard)")
        time.sleep(every)


class Pacer:
    """Steps on a grid of ``period`` s of ``clock``, for a source publishing at 1/period Hz:
    ``await pacer.next()`` returns when the next step is due. A late step goes at once;
    the grid does not move."""

    def __init__(self, period: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.period = period
        self.clock = clock
        self.start = clock()
        self.step = 0

    async def next(self) -> int:
        """Wait for the next step of the grid; its number (1, 2, ...)."""
        self.step += 1
        await asyncio.sleep(max(0.0, self.start + self.step * self.period - self.clock()))
        return self.step


def relayed(server: RelayServer, room: str) -> int:
    """Poses the relay has sent out in ``room`` so far (0 before the room exists)."""
    r = server.rooms.get(room)
    return 0 if r is None else r.statistics().poses_out


# -- the CLI in child processes, without an interpreter start each -------------------

#: The forker's own process: imports the CLI and what its commands import (the relay, the
#: bots, the recorder, the codec: most of a case's CPU when each child imported them),
#: then forks a child per request that runs ``posecast ARGS`` as the console script does
#: (``posecast.cli.main()``) and exits the way the interpreter would (SystemExit's code;
#: a traceback and 1 on an exception). A request whose environment differs from the
#: forker's in a variable read at import (``POSECAST_PURE``) runs in a fresh interpreter.
_FORKER = r"""
import atexit, importlib, json, os, sys, traceback
import posecast.cli

for name in ("posecast.server.app", "posecast.client.bot", "posecast.client.swarm",
             "posecast.recorder", "posecast.recorder.export", "posecast.scenarios.qoe",
             "posecast.scenarios.traces", "posecast.scenarios.motion"):
    importlib.import_module(name)
AT_IMPORT = {k: os.environ.get(k) for k in ("POSECAST_PURE",)}
BOOT = "import sys; sys.argv[0] = {!r}; from posecast.cli import main; main()"

def child(req):
    code = 1
    try:
        os.chdir(req["cwd"])
        os.environ.clear()
        os.environ.update(req["env"])
        for fd, path, flags in ((0, os.devnull, os.O_RDONLY),
                                (1, req["stdout"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC),
                                (2, req["stderr"], os.O_WRONLY | os.O_CREAT | os.O_TRUNC)):
            os.dup2(os.open(path, flags), fd)
        if any(os.environ.get(k) != v for k, v in AT_IMPORT.items()):
            boot = BOOT.format(req["argv0"])
            os.execve(sys.executable, [sys.executable, "-c", boot, *req["args"]], os.environ)
        sys.argv = [req["argv0"], *req["args"]]
        try:
            posecast.cli.main()
            code = 0
        except SystemExit as exc:
            if exc.code is None or isinstance(exc.code, int):
                code = exc.code or 0
            else:
                print(exc.code, file=sys.stderr)
        except BaseException:
            traceback.print_exc()
        atexit._run_exitfuncs()
        sys.stdout.flush()
        sys.stderr.flush()
    finally:
        os._exit(code)

for line in sys.stdin:
    req = json.loads(line)
    pid = os.fork()
    if pid == 0:
        child(req)
    print(json.dumps({"pid": pid}), flush=True)
    _, status = os.waitpid(pid, 0)
    print(json.dumps({"code": os.waitstatus_to_exitcode(status)}), flush=True)
"""


class CliForker:
    """Runs ``posecast ARGS`` in a fresh child process each, forked from one process that
    imported the CLI once: each run is a real process (its own exit code, stdout and
    stderr, nothing shared with the next run) without paying an interpreter start and
    the CLI's imports per run. ``env`` is the forker's environment (the children get
    the one each :meth:`run` gives). Close it with :meth:`close` (or ``with``)."""

    def __init__(self, env: dict[str, str]) -> None:
        self.argv0 = str(Path(sys.executable).with_name("posecast"))
        self.proc = subprocess.Popen(
            [sys.executable, "-c", _FORKER],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=env,
        )
        self._buf = b""

    def __enter__(self) -> CliForker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _line(self, limit: float) -> dict[str, int]:
        """The forker's next reply; ``limit`` is a hang guard (TimeoutError)."""
        assert self.proc.stdout is not None
        fd = self.proc.stdout.fileno()
        deadline = time.monotonic() + limit
        with selectors.DefaultSelector() as sel:
            sel.register(fd, selectors.EVENT_READ)
            while b"\n" not in self._buf:
                left = deadline - time.monotonic()
                if left <= 0 or not sel.select(timeout=left):
                    raise TimeoutError(f"no answer within {limit} s (a hang guard)")
                chunk = os.read(fd, 4096)
                if not chunk:
                    raise RuntimeError(f"the CLI forker ended (exit code {self.proc.wait()})")
                self._buf += chunk
        line, self._buf = self._buf.split(b"\n", 1)
        reply: dict[str, int] = json.loads(line)
        return reply

    def run(
        self, args: list[str], env: dict[str, str], cwd: Path | None = None, limit: float = 120.0
    ) -> tuple[int, str, str]:
        """(exit code, stdout, stderr) of ``posecast ARGS``; ``limit`` is a hang guard: the
        child is killed and TimeoutError raised."""
        assert self.proc.stdin is not None
        with tempfile.TemporaryDirectory(prefix="posecast-cli-") as folder:
            out, err = Path(folder, "stdout"), Path(folder, "stderr")
            request = {
                "args": args,
                "env": env,
                "cwd": str(cwd or Path.cwd()),
                "argv0": self.argv0,
                "stdout": str(out),
                "stderr": str(err),
            }
            self.proc.stdin.write(json.dumps(request).encode() + b"\n")
            self.proc.stdin.flush()
            pid = self._line(30.0)["pid"]
            try:
                code = self._line(limit)["code"]
            except TimeoutError:
                os.kill(pid, signal.SIGKILL)
                self._line(30.0)
                raise
            return code, out.read_text(), err.read_text()

    def close(self) -> None:
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        try:
            self.proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
        if self.proc.stdout is not None:
            self.proc.stdout.close()
