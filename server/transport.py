"""One websocket on the event loop's transport: an ``asyncio.Protocol``, no task, no Event.

:class:`WebSocketConnection` carries websockets' sans-I/O
:class:`~websockets.server.ServerProtocol` (opening handshake, frame parsing,
the message size limit -> 1009, ping/pong, the closing handshake) on the
transport the loop hands it: received bytes go to the protocol, the messages
it parses go to :meth:`~WebSocketConnection.on_messages` in one batch per read,
what it has to send is written at once. Writes of data frames bypass it:
:func:`~posecast.server.wsframe.frame_binary` frames a payload once (a server's
frames are unmasked, so the same bytes serve every subscriber of one snapshot) and
:meth:`~WebSocketConnection.write` hands them to the transport.

Time here is the loop's timers only (``call_later``): the opening handshake
must end within ``open_timeout``; a keepalive ping goes out every
``ping_interval`` (the first ``EARLY_PINGS`` ``FIRST_PING`` s apart from the handshake
on, so that the relay knows each connection's round trip early: ``pongs``) and a pong must
answer within ``ping_timeout`` (else 1011 "keepalive ping timeout", as websockets
does); once a close is expected (a
close frame sent or received, a refused handshake) the TCP connection is
aborted if it has not ended within ``close_timeout``. The relay's rules are
the subclass's (``server/app.py``).
"""

from __future__ import annotations

import asyncio
import logging
import struct
import time
from collections.abc import Callable, Sequence
from typing import Any, cast

from websockets.exceptions import NegotiationError
from websockets.frames import Frame, Opcode
from websockets.http11 import Request, Response
from websockets.protocol import State
from websockets.server import ServerProtocol
from websockets.typing import Subprotocol

from posecast.server.logs import LogLimiter
from posecast.server.wsframe import frame_binary

__all__ = ["SUBPROTOCOL", "WRITE_HIGH_WATER", "WebSocketConnection", "frame_binary"]

log = logging.getLogger("posecast.server")

#: The transport pauses our writes above this many unsent bytes (websockets' own
#: default ``write_limit``); it resumes them below a quarter of it.
WRITE_HIGH_WATER = 32 * 1024

_PING = struct.Struct("!I")

#: A failed read (a relay bug some input reaches) logs its traceback at most this
#: often, whatever the peers send: a fuzzer must not be able to fill the disk.
BUG_LOG_INTERVAL = 60.0
_bug_log = LogLimiter(BUG_LOG_INTERVAL, time.monotonic)

#: The first ``EARLY_PINGS`` keepalive pings go out this long after the handshake and
#: after each other's pong (at most ``ping_interval``): the connection's first round
#: trips, the lowest of a few (one alone may be late on a busy loop).
FIRST_PING = 0.5
EARLY_PINGS = 3

#: The websocket subprotocol of this wire format (selected when offered, not required).
SUBPROTOCOL = "posecast.v1"


def _select_subprotocol(
    protocol: ServerProtocol, offered: Sequence[Subprotocol]
) -> Subprotocol | None:
    """``posecast.v1`` if offered; none if nothing is offered; else refuse (HTTP 400)."""
    if not offered:
        return None
    if SUBPROTOCOL in offered:
        return Subprotocol(SUBPROTOCOL)
    names = ", ".join(offered)
    raise NegotiationError(f"unsupported subprotocol {names}; this relay speaks {SUBPROTOCOL}")


class WebSocketConnection(asyncio.Protocol):
    """A server websocket on a transport; subclasses implement the ``on_*`` hooks."""

    def __init__(
        self,
        *,
        max_size: int | None,
        ping_interval: float | None,
        ping_timeout: float | None,
        close_timeout: float,
        open_timeout: float,
        logger: Any,
    ) -> None:
        self.protocol = ServerProtocol(
            max_size=max_size,
            logger=logger,
            subprotocols=[Subprotocol(SUBPROTOCOL)],
            select_subprotocol=_select_subprotocol,
        )
        self.transport: asyncio.Transport = None  # type: ignore[assignment]
        self.ping_interval = ping_interval
        self.ping_timeout = ping_timeout
        self.close_timeout = close_timeout
        self.open_timeout = open_timeout
        #: Set while the transport asks us to stop writing (its buffer is full).
        self.paused = False
        #: The handshake succeeded and on_open ran (on_end runs once, if so).
        self.is_open = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._open_timer: asyncio.TimerHandle | None = None
        self._ping_timer: asyncio.TimerHandle | None = None
        self._pong_timer: asyncio.TimerHandle | None = None
        self._abort_timer: asyncio.TimerHandle | None = None
        self._ping_seq = 0
        self._ping_data = b""
        self._ping_at = 0.0
        #: Told each keepalive round trip (s, the loop's clock) when set.
        self.pongs: Callable[[float], None] | None = None
        #: The parts of a fragmented message so far (None: not inside one).
        self._parts: list[bytes] | None = None
        self._text = False
        self._lost = False
        #: The opening handshake did not end within ``open_timeout`` (dropped for it).
        self.handshake_expired = False

    # -- hooks ---------------------------------------------------------------------------

    def on_request(self, request: Request) -> Response | None:
        """Answer ``request`` without a handshake (plain HTTP), or None to accept it."""
        return None

    def on_open(self) -> None:
        """The opening handshake succeeded."""

    def on_messages(self, messages: list[bytes | str]) -> None:
        """Complete messages that arrived in one read, in order."""

    def on_writable(self) -> None:
        """The transport takes writes again (after a pause)."""

    def on_end(self) -> None:
        """The connection has ended (only after :meth:`on_open`)."""

    # -- what the relay calls ----------------------------------------------------------------

    @property
    def ws(self) -> WebSocketConnection:
        """This connection (where the websockets adapter had its connection object)."""
        return self

    @property
    def state(self) -> State:
        return self.protocol.state

    def write(self, framed: bytes) -> None:
        """Hand a framed message (:func:`frame_binary`) to the transport."""
        self.transport.write(framed)

    def start_close(self, code: int, reason: str) -> None:
        """Send a close frame; the connection ends when the peer answers, or is
        dropped ``close_timeout`` later."""
        if self.protocol.state is State.OPEN:
            self.protocol.send_close(code, reason)
            self._send_pending()

    def abort(self) -> None:
        """Drop the TCP connection now."""
        if self.transport is not None:
            self.transport.abort()

    # -- asyncio.Protocol ----------------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # (uvloop's transports quack like asyncio.Transport without deriving from it)
        self.transport = cast(asyncio.Transport, transport)
        self.transport.set_write_buffer_limits(high=WRITE_HIGH_WATER)
        self._loop = asyncio.get_running_loop()
        self._open_timer = self._loop.call_later(self.open_timeout, self._open_expired)

    def data_received(self, data: bytes) -> None:
        messages = self.read(data)
        if messages:
            try:
                self.on_messages(messages)
            except Exception:
                self.read_failed()

    def read(self, data: bytes) -> list[bytes | str]:
        """Feed ``data`` to the protocol: the messages it completes, for :meth:`on_messages`
        (none once the connection is closing or lost; also those read with the peer's
        close frame: they came before it). A subclass may call it and hand the messages
        on itself (``server/connection.py``), :meth:`read_failed` if that raises."""
        protocol = self.protocol
        protocol.receive_data(data)
        events = protocol.events_received()
        messages: list[bytes | str] = []
        for event in events:
            if isinstance(event, Frame):
                self._frame(event, messages)
            elif isinstance(event, Request):
                self._handshake(event)
        self._send_pending()
        if messages and self.is_open and not self._lost:
            return messages
        return []

    def read_failed(self) -> None:
        """Handling a read's messages raised (call it in the ``except`` clause): a bug,
        not the peer's doing: this connection ends (1011), the others go on."""
        held = _bug_log.admit()
        if held is not None:
            log.exception("handling a read failed; closing the connection%s",
                          _bug_log.note(held))  # fmt: skip
        if self.protocol.state is State.OPEN:
            self.protocol.fail(1011, "internal-error")
            self._send_pending()

    def eof_received(self) -> bool | None:
        self.protocol.receive_eof()
        self._send_pending()
        return None  # the transport closes itself

    def pause_writing(self) -> None:
        self.paused = True

    def resume_writing(self) -> None:
        self.paused = False
        if self.is_open and not self._lost:
            self.on_writable()

    def connection_lost(self, exc: Exception | None) -> None:
        self._lost = True
        self.protocol.receive_eof()  # the protocol's state becomes CLOSED
        for timer in (self._open_timer, self._ping_timer, self._pong_timer, self._abort_timer):
            if timer is not None:
                timer.cancel()
        if self.is_open:
            self.on_end()

    # -- the protocol's work ---------------------------------------------------------------

    def _frame(self, frame: Frame, messages: list[bytes | str]) -> None:
        opcode = frame.opcode
        if opcode is Opcode.BINARY or opcode is Opcode.TEXT:
            if frame.fin:
                self._message(bytes(frame.data), opcode is Opcode.TEXT, messages)
            else:
                self._parts, self._text = [bytes(frame.data)], opcode is Opcode.TEXT
        elif opcode is Opcode.CONT:
            if self._parts is not None:  # (the protocol refuses a stray continuation)
                self._parts.append(bytes(frame.data))
                if frame.fin:
                    data, self._parts = b"".join(self._parts), None
                    self._message(data, self._text, messages)
        elif (
            opcode is Opcode.PONG and frame.data == self._ping_data and self._pong_timer is not None
        ):
            self._pong_timer.cancel()
            self._pong_timer = None
            self._schedule_ping(FIRST_PING if self._ping_seq < EARLY_PINGS else None)
            if self.pongs is not None and self._loop is not None:
                self.pongs(self._loop.time() - self._ping_at)

    def _message(self, data: bytes, text: bool, messages: list[bytes | str]) -> None:
        if not text:
            messages.append(data)
            return
        try:
            messages.append(data.decode())
        except UnicodeDecodeError as exc:
            # As websockets' own connection does: 1007, the rest of the read discarded.
            self.protocol.fail(1007, f"{exc.reason} at position {exc.start}")

    def _handshake(self, request: Request) -> None:
        protocol = self.protocol
        response = self.on_request(request)
        if response is None:
            response = protocol.accept(request)
        protocol.send_response(response)
        if protocol.state is State.OPEN:
            if self._open_timer is not None:
                self._open_timer.cancel()
                self._open_timer = None
            self.is_open = True
            self._schedule_ping(FIRST_PING)
            self.on_open()

    def _send_pending(self) -> None:
        """Write what the protocol has to send (an empty chunk: half-close); arm the
        abort timer once the protocol expects the TCP connection to end."""
        protocol, transport = self.protocol, self.transport
        for data in protocol.data_to_send():
            if self._lost:
                break
            if data:
                transport.write(data)
            elif transport.can_write_eof():
                transport.write_eof()
            else:
                transport.close()  # TLS: no half-close
        if self._abort_timer is None and not self._lost and protocol.close_expected():
            assert self._loop is not None
            self._abort_timer = self._loop.call_later(self.close_timeout, self._close_expired)

    def _open_expired(self) -> None:
        self._open_timer = None
        if not self.is_open:
            self.handshake_expired = True
            self.abort()

    def _close_expired(self) -> None:
        self._abort_timer = None
        if not self._lost:
            log.info(
                "no closing handshake within %g s, dropping the connection", self.close_timeout
            )
            self.abort()

    def _schedule_ping(self, within: float | None = None) -> None:
        interval = self.ping_interval
        if interval and self._loop is not None and not self._lost:
            delay = interval if within is None else min(within, interval)
            self._ping_timer = self._loop.call_later(delay, self._ping)

    def _ping(self) -> None:
        self._ping_timer = None
        if self.protocol.state is not State.OPEN or self._lost:
            return
        self._ping_seq += 1
        self._ping_data = _PING.pack(self._ping_seq & 0xFFFFFFFF)
        self.protocol.send_ping(self._ping_data)
        self._send_pending()
        assert self._loop is not None
        self._ping_at = self._loop.time()
        if self.ping_timeout:
            assert self._loop is not None
            self._pong_timer = self._loop.call_later(self.ping_timeout, self._pong_missing)
        else:
            self._schedule_ping()

    def _pong_missing(self) -> None:
        self._pong_timer = None
        if not self._lost and not self.transport.is_reading():
            # The relay stopped reading (a join waits for its room to open): a pong
            # may sit unread in the socket. Judge it ``ping_timeout`` after reading
            # resumes at the earliest, not on bytes the relay chose not to read.
            assert self._loop is not None and self.ping_timeout
            self._pong_timer = self._loop.call_later(self.ping_timeout, self._pong_missing)
            return
        if self.protocol.state is State.OPEN and not self._lost:
            self.protocol.logger.debug("- timed out waiting for keepalive pong")
            self.protocol.fail(1011, "keepalive ping timeout")
            self._send_pending()
