"""Attacks of issue 29 on the way in: slow handshakes, a stolen resume, a dead path.

Run by the attacker process of :mod:`posecast.bench.hostile_attacks`:

- ``slowloris``: ``slowloris_connections`` TCP connections, each sending a websocket
  upgrade request one byte a second and opening a new one when the relay drops it,
  ``slowloris_rate`` (re)opened a second at most;
- ``resume-hijack``: a victim member (a resumable session of user ``victim`` in the
  honest room, simulated here) whose connection drops, and a thief who holds the
  victim's resume token and her own access token (user ``mallory``). Each round the
  thief tries the whole token with her own access token, the token's id with a
  forged secret, and the whole token with no access token; then the victim's own
  client resumes. Tallied: each try refused or not (and how), and whether the victim
  resumed with its user id and stream ids. Needs a relay with a secret
  (``secret_file``; without one the whole token alone is the credential and only
  the forged secret is tried);
- ``blackhole``: a TCP proxy in front of the relay (its port is in the
  ``attacking`` line). The connection through it (an honest bot's) goes dead when
  the controller signals ``cut`` (or ``blackhole_after`` seconds after the first
  one opened, if that is >= 0): both ways, bytes are read and dropped and nothing
  is closed, as on a path that silently stopped. Later connections are forwarded.
  Tallied: when the bot closed the dead connection and when it came back through
  the proxy (seconds after the path died).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections import Counter
from pathlib import Path
from typing import Any

import msgpack
from websockets.exceptions import ConnectionClosed, WebSocketException

from posecast.bench.hostile_attacks import (
    AttackConfig,
    Tally,
    _address,
    _connect,
    _frame,
    ready,
    signal,
)
from posecast.server.auth import make_token

__all__ = ["RUNNERS"]

#: A websocket upgrade request, sent one byte a second.
_UPGRADE = (
    b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
    b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
)


def _host_port(url: str) -> tuple[str, int]:
    host, port = url.split("://", 1)[-1].rstrip("/").rsplit(":", 1)
    return host, int(port)


async def _wait(stop: asyncio.Event, seconds: float) -> None:
    with contextlib.suppress(TimeoutError):
        await asyncio.wait_for(stop.wait(), max(0.0, seconds))


class _Pacer:
    """At most ``rate`` starts a second, shared by many tasks."""

    def __init__(self, rate: float) -> None:
        self.rate, self.next = rate, time.monotonic()

    async def slot(self, stop: asyncio.Event) -> None:
        """Wait for this task's turn (or ``stop``)."""
        now = time.monotonic()
        turn = max(self.next, now)
        self.next = turn + 1.0 / self.rate
        await _wait(stop, turn - now)


# -- slowloris ----------------------------------------------------------------------


async def _dropped_within(reader: asyncio.StreamReader, seconds: float) -> bool:
    """Whether the relay ended the connection (or answered it) within ``seconds``."""
    try:
        await asyncio.wait_for(reader.read(4096), seconds)
    except TimeoutError:
        return False
    except (ConnectionError, OSError):
        return True
    return True  # EOF, or an answer (a refusal): either way it is over


async def _slow_one(
    cfg: AttackConfig, stop: asyncio.Event, tally: Tally, i: int, pacer: _Pacer
) -> None:
    """One slow upgrade after another from connection slot ``i``, until the end."""
    host, port = _host_port(cfg.url)
    while not stop.is_set():
        await pacer.slot(stop)
        if stop.is_set():
            return
        try:
            reader, writer = await asyncio.wait_for(
                asyncio.open_connection(host, port, local_addr=(_address(cfg, i), 0)), 5.0
            )
        except (OSError, TimeoutError) as exc:
            tally.extra.setdefault("connect_failures", Counter())[type(exc).__name__] += 1
            await _wait(stop, 1.0)
            continue
        tally.sent["connection"] += 1
        opened = time.monotonic()
        try:
            for k in range(len(_UPGRADE)):
                writer.write(_UPGRADE[k : k + 1])
                tally.sent["byte"] += 1
                if await _dropped_within(reader, 1.0):
                    tally.closes["dropped by the relay"] += 1
                    held = tally.extra.setdefault("held_s_max", 0.0)
                    tally.extra["held_s_max"] = max(held, time.monotonic() - opened)
                    break
                if stop.is_set():
                    tally.closes["held to the end"] += 1
                    break
        except (ConnectionError, OSError):
            tally.closes["reset"] += 1
        finally:
            writer.transport.abort()


async def _slowloris(cfg: AttackConfig, stop: asyncio.Event, tally: Tally) -> None:
    """``slowloris_connections`` slow upgrade requests at once, reopened when dropped."""
    ready()
    pacer = _Pacer(cfg.slowloris_rate)
    async with asyncio.TaskGroup() as tg:
        for i in range(cfg.slowloris_connections):
            tg.create_task(_slow_one(cfg, stop, tally, i, pacer))


# -- resume-hijack ------------------------------------------------------------------


async def _session(
    cfg: AttackConfig, resume: str | None, access: str | None
) -> tuple[str, dict[str, Any]]:
    """One connection: hello (resumable, ``resume``), join the honest room with ``access``.

    ``("joined", {...})`` with the welcome's ``user``/``resume``/``resumed`` and the
    joined ``streams`` and the still open ``ws``; or ``("refused", {"code", "close"})``.
    """
    try:
        ws = await _connect(cfg)
    except (OSError, WebSocketException, TimeoutError) as exc:
        return "refused", {"code": "handshake", "close": type(exc).__name__}
    hello = {"version": 1, "agent": "bench-hostile", "resumable": True}
    got: dict[str, Any] = {}
    try:
        await ws.send(_frame("hello", **hello, **({"resume": resume} if resume else {})))
        while True:
            msg = msgpack.unpackb(await ws.recv())
            if msg.get("type") == "welcome":
                got |= {k: msg.get(k) for k in ("user", "resume", "resumed")}
                join = {"room": cfg.room, "streams": ["head"], "rate": 10.0}
                await ws.send(_frame("join", **join, **({"token": access} if access else {})))
            elif msg.get("type") == "joined":
                return "joined", got | {"streams": msg.get("streams"), "ws": ws}
            elif msg.get("type") == "error" and msg.get("fatal", True):
                got["code"] = str(msg.get("code"))
    except ConnectionClosed:
        rcvd = ws.protocol.close_rcvd
        got["close"] = str(rcvd.code) if rcvd is not None else "none"
        return "refused", got


async def _victim_back(
    cfg: AttackConfig, token: str, access: str | None, victim: dict[str, Any], tally: Tally
) -> dict[str, Any] | None:
    """The victim's own client resumes (a few tries: the relay may still be parking it
    again after a thief's refused try). Its new session, or None."""
    for _ in range(3):
        await asyncio.sleep(0.3)
        outcome, got = await _session(cfg, token, access)
        if outcome == "joined":
            back = got["resumed"] and got["user"] == victim["user"]
            same = back and got["streams"] == victim["streams"]
            tally.extra["victim"]["resumed" if back else "rejoined"] += 1
            tally.extra["victim"]["same_streams"] += bool(same)
            return got
    tally.extra["victim"]["failed"] += 1
    return None


def _thieves(token: str, mallory: str | None) -> list[tuple[str, str, str | None]]:
    """The thief's tries on ``token``: (name, resume token, access token)."""
    forged = token[:12] + ("A" if token[-1] != "A" else "B") * (len(token) - 12)
    tries = [("forged-secret", forged, mallory)]
    if mallory is not None:  # with a secret: the whole stolen token is not enough
        tries += [("own-access-token", token, mallory), ("no-access-token", token, None)]
    return tries


def _secret(path: str | None) -> str | None:
    """The relay's secret (the first line of its file), or None."""
    return Path(path).read_text().splitlines()[0].strip() if path else None


async def _resume_hijack(cfg: AttackConfig, stop: asyncio.Event, tally: Tally) -> None:
    """Rounds of: the victim drops, the thief tries its token, the victim resumes."""
    secret = _secret(cfg.secret_file)

    def access(user: str) -> str | None:
        return None if secret is None else make_token(secret, cfg.room, user, 3600, time.time())

    tally.extra["victim"] = Counter()
    tally.extra["hijack"] = {"tries": Counter(), "refused": Counter(), "accepted": Counter()}
    outcome, first = await _session(cfg, None, access("victim"))
    if outcome != "joined":
        raise RuntimeError(f"the victim could not join: {first}")
    victim: dict[str, Any] | None = first
    ready()
    hijack = tally.extra["hijack"]
    rounds = 0
    while not stop.is_set() and rounds < cfg.hijack_attempts and victim is not None:
        rounds += 1
        victim["ws"].transport.abort()  # its connection drops: the relay parks it
        await asyncio.sleep(0.3)
        for name, token, key in _thieves(victim["resume"], access("mallory")):
            outcome, got = await _session(cfg, token, key)
            tally.sent[name] += 1
            hijack["tries"][name] += 1
            if outcome == "joined":
                hijack["accepted"][name] += 1
                got["ws"].transport.abort()
            else:
                tally.errors[got.get("code", "none")] += 1
                tally.closes[got.get("close", "none")] += 1
                hijack["refused"][name] += 1
        back = await _victim_back(cfg, victim["resume"], access("victim"), victim, tally)
        victim = None if back is None else victim | {"ws": back["ws"], "resume": back["resume"]}
        await _wait(stop, 0.5)
    if victim is not None:
        await victim["ws"].close()
    tally.extra["rounds"] = rounds


# -- blackhole ----------------------------------------------------------------------


class _Path:
    """The proxy's state: connections through it and the dead one's times."""

    def __init__(self, tally: Tally) -> None:
        self.tally = tally
        self.count = 0
        self.died_at: float | None = None
        self.writers: list[asyncio.StreamWriter] = []
        #: The open connections' "dead" events, oldest first.
        self.live: list[asyncio.Event] = []

    def cut(self) -> None:
        """The newest open connection's path dies (once)."""
        if self.died_at is None and self.live:
            self.died_at = time.monotonic()
            self.live[-1].set()

    def note(self, key: str) -> None:
        """Record ``key`` as seconds after the path died (the first time only)."""
        if self.died_at is not None and key not in self.tally.extra:
            self.tally.extra[key] = round(time.monotonic() - self.died_at, 3)


async def _pump(
    src: asyncio.StreamReader,
    dst: asyncio.StreamWriter,
    dead: asyncio.Event,
    way: str,
    path: _Path,
) -> None:
    """Copy ``src`` to ``dst`` until EOF; once ``dead`` is set, read and drop instead,
    and do not pass the end on (a dead path carries nothing, not even a close)."""
    tally = path.tally
    try:
        while data := await src.read(65536):
            if dead.is_set():
                tally.sent[f"dropped {way} bytes"] += len(data)
                continue
            dst.write(data)
            await dst.drain()
            tally.sent[f"{way} bytes"] += len(data)
    except (ConnectionError, OSError):
        pass
    if not dead.is_set():
        dst.transport.abort()
    elif way == "up":  # the bot gave up on the dead connection
        path.note("bot_closed_dead_after_s")


async def _forward(
    cfg: AttackConfig, path: _Path, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
) -> None:
    """One connection through the proxy (the first one dies ``blackhole_after`` s in)."""
    k, path.count = path.count, path.count + 1
    path.tally.sent["connection"] += 1
    if k > 0:
        path.note("bot_back_after_s")
    host, port = _host_port(cfg.url)
    try:
        up_reader, up_writer = await asyncio.open_connection(host, port)
    except OSError:
        writer.transport.abort()
        return
    path.writers += [writer, up_writer]
    dead = asyncio.Event()
    path.live.append(dead)
    timer = None
    if k == 0 and cfg.blackhole_after >= 0:
        timer = asyncio.get_running_loop().call_later(cfg.blackhole_after, path.cut)
    try:
        async with asyncio.TaskGroup() as tg:
            tg.create_task(_pump(reader, up_writer, dead, "up", path))
            tg.create_task(_pump(up_reader, writer, dead, "down", path))
    finally:
        path.live.remove(dead)
        if timer is not None:
            timer.cancel()
        writer.transport.abort()
        up_writer.transport.abort()


async def _blackhole(cfg: AttackConfig, stop: asyncio.Event, tally: Tally) -> None:
    """A proxy in front of the relay whose first connection's path dies."""
    path = _Path(tally)
    server = await asyncio.start_server(lambda r, w: _forward(cfg, path, r, w), "127.0.0.1", 0)
    ready(port=server.sockets[0].getsockname()[1])
    cut = asyncio.create_task(signal("cut").wait())
    stopped = asyncio.create_task(stop.wait())
    try:
        await asyncio.wait([cut, stopped], return_when=asyncio.FIRST_COMPLETED)
        if cut.done():
            tally.extra["open_at_cut"] = len(path.live)
            path.cut()
            await stopped
    finally:
        cut.cancel()
        stopped.cancel()
        server.close()
        for w in path.writers:
            w.transport.abort()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(server.wait_closed(), 5.0)
    tally.extra["path_died"] = path.died_at is not None


RUNNERS = {
    "slowloris": _slowloris,
    "resume-hijack": _resume_hijack,
    "blackhole": _blackhole,
}
