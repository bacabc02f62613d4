"""A thin asyncio adapter from a websocket to :class:`protocol.ClientSession`.

``ClientConnection`` does the handshake (hello, welcome, join, joined), then
hands every received event to the caller through :meth:`recv` with its
arrival time, and sends messages through the session so the state table is
kept. Arrival times come from the ``clock`` passed in.

A client may know several relays (the nodes of a cluster, or spares):
:func:`relay_urls` reads them from one comma-separated option;
:func:`connect_any` connects to the first of them that answers;
:func:`connect_first` to the first that answers from a given one on, cycling
until a deadline (a bot's failover after its relay died). :class:`SessionEnd`
says how a bot's session ended.
"""

from __future__ import annotations

import asyncio
import ssl
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from urllib.parse import urlsplit

from websockets.asyncio.client import ClientConnection as WsConnection
from websockets.asyncio.client import connect

from posecast.client.reconnect import (
    CLOSE_TIMEOUT,
    GRACEFUL_CLOSE_CODES,
    KEEPALIVE_INTERVAL,
    KEEPALIVE_TIMEOUT,
    SessionEnd,
)
from posecast.protocol import (
    AUTO_RATE,
    ClientSession,
    ErrorMessage,
    Hello,
    Join,
    Joined,
    ObjectCreate,
    PeerJoined,
    PosecastError,
    ProtocolError,
    RateNotice,
    Release,
    RequestOwnership,
    Welcome,
)
from posecast.protocol.events import Event, Message
from posecast.protocol.objects import pose_tuple

__all__ = [
    "GRACEFUL_CLOSE_CODES",
    "ClientConnection",
    "JoinRefused",
    "Received",
    "SessionEnd",
    "Tls",
    "connect_any",
    "connect_first",
    "relay_urls",
]


def relay_urls(text: str) -> tuple[str, ...]:
    """The relay URLs of ``ws://a:8765,ws://b:8765`` (one URL is a list of one).

    ValueError, in one line, for an empty item, a URL that is not ``ws://`` or
    ``wss://`` with a host, or a URL listed twice.
    """
    urls = tuple(item.strip() for item in text.split(","))
    for url in urls:
        if not url:
            raise ValueError(f"empty URL in {text!r}: separate the URLs by single commas")
        try:
            parts = urlsplit(url)
            parts.port  # noqa: B018 - parsing it checks it
        except ValueError as exc:
            raise ValueError(f"{url!r} is not a valid URL: {exc}") from None
        if parts.scheme not in ("ws", "wss") or not parts.hostname:
            raise ValueError(f"{url!r} is not a ws:// or wss:// URL with a host")
    if len(set(urls)) != len(urls):
        raise ValueError(f"a URL is listed twice in {text!r}")
    return urls


@dataclass(frozen=True, slots=True)
class Tls:
    """How a ``wss://`` URL's server certificate is checked.

    By default against the system's trusted roots; ``cafile`` trusts the
    certificates in that PEM file instead (a private CA, a self-signed server);
    ``insecure`` checks nothing (the traffic is encrypted but anyone could be at
    the other end: for tests only). Ignored for ``ws://``.
    """

    cafile: str | None = None
    insecure: bool = False

    def context(self, url: str) -> ssl.SSLContext | None:
        """The client TLS context for ``url`` (None for a plain ``ws://`` URL)."""
        if not url.startswith("wss://"):
            return None
        if self.insecure:
            ctx = ssl.create_default_context()
            ctx.check_hostname = False
            ctx.verify_mode = ssl.CERT_NONE
            return ctx
        return ssl.create_default_context(cafile=self.cafile)


class JoinRefused(PosecastError, RuntimeError):
    """The server refused the handshake or the join; ``code`` says why.

    For ``bad-rate``, ``rate_range`` is the server's ``(min_rate, max_rate)`` in Hz
    (from its welcome) when known, and the message names it.
    """

    def __init__(
        self, code: str, message: str, *, rate_range: tuple[float, float] | None = None
    ) -> None:
        super().__init__(f"{code}: {message}")
        self.code = code
        self.message = message
        self.rate_range = rate_range


def _vec3(v: Sequence[float]) -> tuple[float, float, float]:
    if len(v) != 3:
        raise ValueError(f"expected 3 numbers, got {len(v)}")
    return (float(v[0]), float(v[1]), float(v[2]))


@dataclass(frozen=True, slots=True)
class Received:
    event: Event
    arrival: float
    size: int


class ClientConnection:
    """One client's websocket, handshake done, events in and messages out."""

    def __init__(self, ws: WsConnection, clock: Callable[[], float] = time.monotonic) -> None:
        self.ws = ws
        self.clock = clock
        self.session = ClientSession()
        self.welcome: Welcome | None = None
        self.joined: Joined | None = None
        #: Called with each rate the relay chose for an auto-rate join (``RateNotice``).
        self.on_rate: Callable[[float], None] | None = None
        #: Peers announced before the handshake finished.
        self.early_peers: list[PeerJoined] = []
        self.bytes_in = 0
        self.frames_in = 0
        self.bytes_out = 0
        self.frames_out = 0
        self._pending: deque[Received] = deque()

    @classmethod
    async def connect(
        cls,
        url: str,
        *,
        agent: str = "posecast-bot",
        clock: Callable[[], float] = time.monotonic,
        open_timeout: float = 10.0,
        tls: Tls | None = None,
        resumable: bool = False,
        resume: str | None = None,
    ) -> ClientConnection:
        """Connect and say hello; returns once the server's welcome arrived.

        A ``wss://`` URL is checked as ``tls`` says (default: the system's roots).
        ``resumable``: ask for a resume token (``welcome.resume``); ``resume``: the
        token of a dropped connection (``welcome.resumed`` says if it was honoured).
        """
        ws = await connect(
            url,
            open_timeout=open_timeout,
            # Shorter than the library's 20 s + 20 s: a dead path is noticed inside the
            # resume window (client.reconnect), as the relay notices it.
            ping_interval=KEEPALIVE_INTERVAL,
            ping_timeout=KEEPALIVE_TIMEOUT,
            close_timeout=CLOSE_TIMEOUT,
            max_size=2**20,
            compression=None,
            ssl=(tls or Tls()).context(url),
        )
        conn = cls(ws, clock)
        try:
            await conn.send(Hello(agent=agent, resumable=resumable, resume=resume))
            welcome = await conn._expect(Welcome)
            assert isinstance(welcome, Welcome)
            conn.welcome = welcome
        except BaseException:
            await ws.close()
            raise
        return conn

    async def join(
        self,
        *,
        room: str,
        streams: tuple[str, ...],
        rate: float,
        token: str | None = None,
        label: str | None = None,
        sends_velocities: bool = False,
        wants_velocities: bool = False,
        codec: str = "raw",
        auto_rate: bool = False,
        spectator: bool = False,
        budget_deg: float | None = None,
    ) -> Joined:
        """Join ``room``; :class:`JoinRefused` if the server refuses.

        ``sends_velocities``: this client's updates will be of the velocity
        variant; ``wants_velocities``: send it velocity snapshots; ``codec``:
        ``compact`` codes the updates sent through :meth:`send` with the
        compact codec (``protocol.codec``), ``raw`` as float records. ``auto_rate``:
        the relay chooses the rate, up to ``rate`` (``join.rate = "auto"``), and tells
        each change (``rate``), which :attr:`on_rate` hears. ``spectator``: watch
        only (publish nothing, nobody is told). ``budget_deg``: an error budget in
        degrees of visual angle (``join.budget_deg``): the relay may send each peer
        at a lower rate, the lowest that keeps its expected error, seen from this
        client's ``head``, within it.
        """
        welcome = self.welcome
        if welcome is not None and not welcome.min_rate <= rate <= welcome.max_rate:
            # The session would refuse to send it (a LocalProtocolError): say it as the
            # server would, with the range from its welcome.
            raise self._bad_rate(f"rate {rate:g} Hz is refused")
        await self.send(
            Join(
                room=room,
                streams=streams,
                rate=AUTO_RATE if auto_rate else rate,
                token=token,
                label=label,
                sends_velocities=sends_velocities,
                wants_velocities=wants_velocities,
                codec=codec,
                max_rate=rate if auto_rate else None,
                spectator=spectator,
                budget_deg=budget_deg,
            )
        )
        joined = await self._expect(Joined)
        assert isinstance(joined, Joined)
        self.joined = joined
        return joined

    @classmethod
    async def open(
        cls,
        url: str,
        *,
        room: str,
        streams: tuple[str, ...],
        rate: float,
        token: str | None = None,
        label: str | None = None,
        agent: str = "posecast-bot",
        clock: Callable[[], float] = time.monotonic,
        open_timeout: float = 10.0,
        sends_velocities: bool = False,
        wants_velocities: bool = False,
        codec: str = "raw",
        tls: Tls | None = None,
        auto_rate: bool = False,
        budget_deg: float | None = None,
    ) -> ClientConnection:
        """Connect, say hello and join ``room``; :class:`JoinRefused` if refused."""
        conn = await cls.connect(url, agent=agent, clock=clock, open_timeout=open_timeout, tls=tls)
        try:
            await conn.join(
                room=room,
                streams=streams,
                rate=rate,
                token=token,
                label=label,
                sends_velocities=sends_velocities,
                wants_velocities=wants_velocities,
                codec=codec,
                auto_rate=auto_rate,
                budget_deg=budget_deg,
            )
        except BaseException:
            await conn.ws.close()
            raise
        return conn

    async def _expect(self, kind: type[Welcome] | type[Joined]) -> Welcome | Joined | ErrorMessage:
        while True:
            rec = await self.recv()
            ev = rec.event
            if isinstance(ev, kind):
                return ev
            if isinstance(ev, ErrorMessage):
                if ev.code == "bad-rate":
                    raise self._bad_rate(ev.message)
                raise JoinRefused(ev.code, ev.message)
            if isinstance(ev, ProtocolError):
                raise JoinRefused(str(ev.code), ev.message)
            if isinstance(ev, PeerJoined):
                self.early_peers.append(ev)

    def _bad_rate(self, detail: str) -> JoinRefused:
        """A ``bad-rate`` refusal that names the range from the server's welcome."""
        welcome = self.welcome
        if welcome is None:
            return JoinRefused("bad-rate", detail)
        lo, hi = welcome.min_rate, welcome.max_rate
        return JoinRefused(
            "bad-rate", f"{detail}; the server allows {lo:g}-{hi:g} Hz", rate_range=(lo, hi)
        )

    @property
    def user(self) -> int:
        assert self.welcome is not None
        return self.welcome.user

    async def send(self, message: Message) -> None:
        data = self.session.send(message)
        await self.ws.send(data)
        self.frames_out += 1
        self.bytes_out += len(data)

    async def create_object(
        self,
        name: str,
        pose: Sequence[float],
        *,
        hold: bool = False,
        keep: bool = True,
        steal: bool = False,
        time: float | None = None,
    ) -> None:
        """Create room object ``name`` (``object:NAME``) at ``pose``, captured at ``time``
        (server clock; None: on arrival); ``hold``: own it at once.

        The server answers every member with ``object`` (and ``owner`` if held), or
        this client alone with a non-fatal ``ownership-refused`` error.
        """
        p = pose_tuple("object_create.pose", [float(x) for x in pose])
        await self.send(
            ObjectCreate(name=name, pose=p, keep=keep, steal=steal, hold=hold, time=time)
        )

    async def request_ownership(self, stream: int, *, steal: bool = False) -> None:
        """Ask to own object ``stream`` (a grab, or a catch while it flies)."""
        await self.send(RequestOwnership(stream=stream, steal=steal))

    async def release_object(
        self,
        stream: int,
        velocity: Sequence[float] | None = None,
        angular: Sequence[float] | None = None,
    ) -> None:
        """Let go of object ``stream``: at rest, or thrown with ``velocity`` (m/s) and
        ``angular`` (rad/s, world frame), which the server then flies."""
        v = None if velocity is None else _vec3(velocity)
        w = None if angular is None else _vec3(angular)
        await self.send(Release(stream=stream, velocity=v, angular=w))

    async def send_bytes(self, data: bytes) -> None:
        """Send pre-encoded frame bytes (bypassing the session's checks)."""
        await self.ws.send(data)
        self.frames_out += 1
        self.bytes_out += len(data)

    async def recv(self) -> Received:
        """The next event with its arrival time (raises ConnectionClosed at the end)."""
        while not self._pending:
            data = await self.ws.recv()
            arrival = self.clock()
            raw = data.encode() if isinstance(data, str) else data
            self.frames_in += 1
            self.bytes_in += len(raw)
            for ev in self.session.receive_data(raw):
                if isinstance(ev, RateNotice) and self.on_rate is not None:
                    self.on_rate(ev.rate)
                self._pending.append(Received(ev, arrival, len(raw)))
        return self._pending.popleft()

    async def close(self, reason: str = "bye") -> None:
        await self.ws.close(1000, reason)


async def connect_any(
    urls: Sequence[str],
    *,
    clock: Callable[[], float] = time.monotonic,
    agent: str = "posecast-bot",
    tls: Tls | None = None,
    resumable: bool = False,
) -> tuple[int, ClientConnection]:
    """Connect to the first of ``urls`` that answers, trying each once in order: its
    index and the connection; if none answers, the first one's error."""
    error: Exception | None = None
    for i, url in enumerate(urls):
        try:
            conn = await ClientConnection.connect(
                url, agent=agent, clock=clock, tls=tls, resumable=resumable
            )
        except Exception as exc:
            error = error or exc
            continue
        return i, conn
    raise error or ValueError("no relay URL to connect to")


async def connect_first(
    urls: Sequence[str],
    first: int,
    deadline: float,
    *,
    clock: Callable[[], float] = time.monotonic,
    agent: str = "posecast-bot",
    tls: Tls | None = None,
    resumable: bool = False,
    resume: str | None = None,
    attempt_timeout: float = 2.0,
    pause: float = 0.2,
) -> tuple[int, ClientConnection] | None:
    """Connect to ``urls[first]``, else the next ones in order, cycling, until ``deadline``.

    Returns the index of the URL that answered (its welcome arrived) and the
    connection, or None when the deadline (on ``clock``) passed first. Each attempt
    takes at most ``attempt_timeout`` seconds (a dead host may never answer); after
    every URL failed once it waits ``pause`` before the next round. The other
    arguments are :meth:`ClientConnection.connect`'s.
    """
    n, tries = len(urls), 0
    while clock() < deadline:
        i = (first + tries) % n
        tries += 1
        try:
            conn = await ClientConnection.connect(
                urls[i],
                agent=agent,
                clock=clock,
                open_timeout=max(0.1, min(attempt_timeout, deadline - clock())),
                tls=tls,
                resumable=resumable,
                resume=resume,
            )
        except Exception:  # refused, reset, timed out, a handshake cut short: the next
            if tries % n == 0:
                await asyncio.sleep(max(0.0, min(pause, deadline - clock())))
            continue
        return i, conn
    return None
