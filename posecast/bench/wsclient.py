"""The load generator's websocket client: websockets' sans-I/O client on an asyncio transport.

The relay is what ``posecast bench relay`` measures, so the load must cost far
less than the relay per frame. A websockets client gives each connection a
reader task, an assembler and a writer; here a connection is one
``asyncio.Protocol`` carrying websockets' sans-I/O
:class:`~websockets.client.ClientProtocol`, as the relay's
:mod:`~posecast.server.transport` carries its ``ServerProtocol``:

- the protocol writes and checks the opening handshake, answers pings, runs the
  closing handshake and refuses what a server must not send (a masked frame:
  1002, a message over :data:`MAX_FRAME`: 1009);
- received snapshots (final unmasked binary frames) are cut out of each read in
  ``data_received`` (:func:`~posecast.server.wsframe.frame_head`) and handed to a
  callback: no task, no queue, no protocol object per frame (a 478-byte
  snapshot cost 11.5 us through ``ClientProtocol``, 2.8 us cut here: the load
  must stay far cheaper than the relay per frame);
- every update is pre-encoded (:class:`RawUpdateFrames`,
  :class:`CompactUpdateFrames`): per tick only the sequence number and the time
  are written into fixed bytes, framed by
  :func:`~posecast.server.wsframe.client_frame` (the relay's framing module):
  masked with the all-zero key, so no per-byte work.
"""

from __future__ import annotations

import asyncio
import math
import struct
from collections.abc import Callable
from typing import Any, cast

import msgpack
import numpy as np
from websockets.client import ClientProtocol
from websockets.frames import Frame, Opcode
from websockets.http11 import Response
from websockets.protocol import State
from websockets.uri import parse_uri

from posecast.protocol import PoseUpdate
from posecast.protocol._compact import F_RELATIVE
from posecast.protocol.bits import zz
from posecast.protocol.codec_frame import _svarint, _uvarint
from posecast.server.wsframe import FINAL_BINARY, MASKED, client_frame, frame_head

__all__ = [
    "CompactUpdateFrames",
    "FrameConnection",
    "RawUpdateFrames",
    "StepTimeout",
    "client_frame",
    "connect",
    "split_codec_update",
]

_F64 = struct.Struct(">d")
#: Largest frame the load accepts from a server (the relay's snapshots are far smaller).
MAX_FRAME = 1 << 20


def _cycle(poses: np.ndarray) -> np.ndarray:
    """``poses`` as a cycle of frames, shape (K, n, 7) (one frame (n, 7) is K = 1)."""
    cycle = np.asarray(poses, dtype=np.float64)
    if cycle.ndim == 2:
        cycle = cycle[None]
    if cycle.ndim != 3 or cycle.shape[-1] != 7 or len(cycle) == 0:
        raise ValueError(f"Expected poses of shape (K, n, 7) or (n, 7), got {cycle.shape}")
    return cycle


class RawUpdateFrames:
    """Raw update frames of a cycle of poses: only ``seq`` and ``time`` are packed per tick.

    ``poses`` is one frame (n, 7) or a cycle (K, n, 7): update ``seq`` carries
    frame ``(seq - 1) % K``. ``payload(seq, t)`` is byte for byte
    ``protocol.encode_update(seq, ids, [t] * n, poses, base_time=t)`` (a test
    checks it): each frame's msgpack map is cut around its two varying values
    once, and each tick packs only those.
    """

    def __init__(self, stream_ids: list[int], poses: np.ndarray) -> None:
        cycle = _cycle(poses)
        n = len(stream_ids)
        pack = msgpack.packb
        self._pre = b""
        self._mid = pack("time") + b"\xcb"
        self._posts: list[bytes] = []
        for frame in cycle:
            update = PoseUpdate.from_arrays(0, stream_ids, np.zeros(n), frame, base_time=0.0)
            wire = update.to_wire()
            keys = list(wire)
            if keys[:3] != ["type", "seq", "time"] or len(keys) != 4:
                raise ValueError(f"unexpected update layout {keys}")
            self._pre = bytes((0x84,)) + pack("type") + pack(wire["type"]) + pack("seq")
            self._posts.append(pack(keys[3]) + pack(wire[keys[3]]))

    def payload(self, seq: int, now: float) -> bytes:
        post = self._posts[(seq - 1) % len(self._posts)]
        return b"".join((self._pre, msgpack.packb(seq), self._mid, _F64.pack(now), post))

    def frame(self, seq: int, now: float) -> bytes:
        return client_frame(self.payload(seq, now))


def _skip_varint(data: bytes, pos: int) -> int:
    while data[pos] & 0x80:
        pos += 1
    return pos + 1


def split_codec_update(data: bytes) -> tuple[bytes, bytes]:
    """(magic + flags, rest after seq and base time) of a codec update frame."""
    if len(data) < 4 or data[0] != 0xC1 or not data[1] & 1:
        raise ValueError("not a codec update frame")
    pos = _skip_varint(data, 2)  # seq
    pos = _skip_varint(data, pos)  # base time, us
    return data[:2], data[pos:]


class CompactUpdateFrames:
    """Codec update frames of a cycle of poses, as ``Join.codec == "compact"`` sends them.

    ``poses`` is one frame (n, 7) or a cycle (K, n, 7); the i-th frame sent
    (from 0) carries frame ``i % K``. The first K + 1 go through ``encode`` (the
    client session's codec encoder: a key frame, then deltas). From then on a
    frame's delta is from cycle frame ``(i - 1) % K`` to ``i % K`` against the
    same baselines as K frames before, so its bytes after the seq and the base
    time (counts, baseline check, Exp-Golomb orders, deltas, dt 0) are those of
    the frame K before: they are reused as they are, with a new seq and base time
    (relative to the previous frame's, as the session's encoder writes them after
    the first frame: ``protocol._compact``).
    """

    def __init__(
        self,
        stream_ids: list[int],
        poses: np.ndarray,
        encode: Callable[[PoseUpdate], bytes],
    ) -> None:
        self._ids = stream_ids
        self._cycle = _cycle(poses)
        self._encode = encode
        self._sent = 0
        #: (magic + flags, tail) by ``i % K``, from the frames the encoder made.
        self._parts: dict[int, tuple[bytes, bytes]] = {}
        #: (seq, base time us) of the frame sent last.
        self._previous = (0, 0)

    def payload(self, seq: int, now: float) -> bytes:
        k = len(self._cycle)
        i = self._sent
        self._sent += 1
        if i <= k:
            n = len(self._ids)
            frame = self._cycle[i % k]
            update = PoseUpdate.from_arrays(seq, self._ids, [now] * n, frame, base_time=now)
            data = self._encode(update)
            if i >= 1:
                self._parts[i % k] = split_codec_update(data)
            self._previous = (seq, round(now * 1e6))
            return data
        head, tail = self._parts[i % k]
        base_us = round(now * 1e6)
        if head[1] & F_RELATIVE:
            fields = _uvarint(zz(seq - self._previous[0])) + _svarint(base_us - self._previous[1])
        else:
            fields = _uvarint(seq) + _svarint(base_us)
        self._previous = (seq, base_us)
        return b"".join((head, fields, tail))

    def frame(self, seq: int, now: float) -> bytes:
        return client_frame(self.payload(seq, now))


#: on_message(payload, arrival): a whole data message from the server.
OnMessage = Callable[[bytes, float], None]


class FrameConnection(asyncio.Protocol):
    """One websocket connection: handshake, then whole data messages to ``on_message``.

    websockets' sans-I/O :class:`~websockets.client.ClientProtocol` writes and
    checks the opening handshake and takes every frame but the hot one (pings,
    closes, fragments, anything it must refuse); final unmasked binary frames are
    cut out of each read here (:func:`~posecast.server.wsframe.frame_head`) and go
    to ``on_message`` without it. Writes of data frames bypass it too: the caller
    writes :func:`~posecast.server.wsframe.client_frame` bytes with :meth:`write`.
    """

    def __init__(self, url: str, clock: Callable[[], float], max_size: int = MAX_FRAME) -> None:
        self.protocol = ClientProtocol(parse_uri(url), max_size=max_size)
        self._clock = clock
        self._max = max_size
        #: Bytes read but not yet handed on: a partial frame (or the handshake response).
        self._buf = bytearray()
        #: The handshake is done and the protocol open: reads are cut here.
        self._cutting = False
        #: The parts of a fragmented message so far (None: not inside one).
        self._parts: list[bytes] | None = None
        self.transport: asyncio.Transport | None = None
        self.on_message: OnMessage = lambda data, arrival: None
        self.opened: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self.closed: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        #: ``clock`` readings once the TCP connection and the handshake were done.
        self.connected_at = self.opened_at = math.nan

    # -- asyncio.Protocol ---------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # uvloop's transports do not subclass asyncio.Transport; they have its methods.
        self.transport = cast(asyncio.Transport, transport)
        self.protocol.send_request(self.protocol.connect())
        self._send_pending()

    def connection_lost(self, exc: Exception | None) -> None:
        self._cutting = False
        self.protocol.receive_eof()
        why = f"{type(exc).__name__}: {exc}" if exc else "connection lost"
        if not self.opened.done():
            self.opened.set_exception(ConnectionError(why))
        if not self.closed.done():
            self.closed.set_result(why)

    def eof_received(self) -> bool | None:
        self.protocol.receive_eof()
        self._send_pending()
        return None  # the transport closes itself

    def data_received(self, data: bytes) -> None:
        arrival = self._clock()
        buf = self._buf
        if not self._cutting:
            if self.protocol.state is State.CONNECTING:
                data = self._response(buf, data, arrival)
                if not self._cutting:
                    return
            else:  # closing: the protocol reads (and discards) the rest
                self._to_protocol(data, arrival)
                return
        if buf:
            buf += data
            data = bytes(buf)
            buf.clear()
        # Most reads hold whole frames: cut them in place, keep only a tail.
        pos = self._cut(data, arrival)
        if pos < len(data):
            buf += data[pos:]

    def _cut(self, data: bytes, arrival: float) -> int:
        """Dispatch the whole frames in ``data``; where a partial one starts."""
        pos, end = 0, len(data)
        while end - pos >= 2:
            head = frame_head(data, pos)
            if head is None:
                break
            first, second, start, size = head
            if second & MASKED or size > self._max:
                self._to_protocol(data[pos:], arrival)  # it refuses the frame: 1002, 1009
                return end
            stop = start + size
            if stop > end:
                break
            if first == FINAL_BINARY and self._parts is None:  # the hot path
                self.on_message(data[start:stop], arrival)
            else:
                self._to_protocol(data[pos:stop], arrival)
                if not self._cutting:  # a close: the protocol reads (and discards) the rest
                    if stop < end:
                        self._to_protocol(data[stop:], arrival)
                    return end
            pos = stop
        return pos

    # -- what the load calls ------------------------------------------------------

    async def upgraded(self, within: float) -> None:
        """Wait for the server's handshake response, ``within`` s (else
        :class:`StepTimeout` ``upgrade``; the connection is dropped if it fails);
        ``opened_at`` is the clock reading then."""
        try:
            await asyncio.wait_for(self.opened, within)
        except BaseException as exc:
            self.abort()
            if isinstance(exc, TimeoutError):
                raise StepTimeout("upgrade", within) from exc
            raise
        self.opened_at = self._clock()

    def write(self, frame: bytes) -> None:
        """Write a data frame (:func:`client_frame`) while the connection is open."""
        if self._cutting and self.transport is not None and not self.transport.is_closing():
            self.transport.write(frame)

    def buffered(self) -> int:
        """Bytes written but not yet taken by the kernel."""
        t = self.transport
        return 0 if t is None or t.is_closing() else t.get_write_buffer_size()

    def close(self, code: int = 1000, reason: str = "") -> None:
        """Send a close frame; the transport closes when the server answers (or on abort)."""
        if self.protocol.state is State.OPEN:
            self.protocol.send_close(code, reason[:120])
            self._send_pending()

    def abort(self) -> None:
        if self.transport is not None:
            self.transport.abort()

    def fail(self, code: int, reason: str) -> None:
        """Close with ``code`` at once, without waiting for the server's answer."""
        if self.protocol.state is State.OPEN:
            self.protocol.fail(code, reason)
            self._send_pending()
            self._end(f"{code} {reason}")

    # -- internals ----------------------------------------------------------------

    def _response(self, buf: bytearray, data: bytes, arrival: float) -> bytes:
        """Hand the protocol the server's handshake response once its head is whole
        (a 101 has no body: what follows it is frames, cut here); the bytes left."""
        buf += data
        end = buf.find(b"\r\n\r\n")
        if end < 0 and len(buf) <= 16384:
            return b""
        head = bytes(buf) if end < 0 else bytes(buf[: end + 4])
        rest = b"" if end < 0 else bytes(buf[end + 4 :])
        buf.clear()
        self._to_protocol(head, arrival)
        if self.protocol.state is State.CONNECTING and rest:  # a refusal's body
            self._to_protocol(rest, arrival)
            return b""
        return rest

    def _to_protocol(self, data: bytes, arrival: float) -> None:
        """Feed ``data`` to the protocol; act on what it parsed and write what it answers."""
        protocol = self.protocol
        protocol.receive_data(data)
        for event in protocol.events_received():
            if isinstance(event, Frame):
                self._frame(event, arrival)
            elif isinstance(event, Response):
                self._handshake()
        self._send_pending()

    def _handshake(self) -> None:
        exc = self.protocol.handshake_exc
        if exc is None and self.protocol.state is State.OPEN:
            self._cutting = True
            if not self.opened.done():
                self.opened.set_result(None)
        elif not self.opened.done():
            self.opened.set_exception(ConnectionError(f"handshake refused: {exc}"))

    def _frame(self, frame: Frame, arrival: float) -> None:
        opcode = frame.opcode
        if opcode is Opcode.BINARY or opcode is Opcode.TEXT:
            if frame.fin:
                self.on_message(bytes(frame.data), arrival)
            else:  # a fragmented message (the relay never sends one); the protocol bounds it
                self._parts = [bytes(frame.data)]
        elif opcode is Opcode.CONT and self._parts is not None:
            self._parts.append(bytes(frame.data))
            if frame.fin:
                whole, self._parts = b"".join(self._parts), None
                self.on_message(whole, arrival)

    def _send_pending(self) -> None:
        """Write what the protocol has to send; once it is closing, say why in
        ``closed`` and end the connection when the server has answered (a client
        waits for that) or the protocol failed the connection."""
        protocol, transport = self.protocol, self.transport
        if transport is None:
            return
        for data in protocol.data_to_send():
            if data:
                transport.write(data)
            else:  # the end of the stream (a refused handshake, the server's EOF)
                transport.close()
        state = protocol.state
        if state is State.OPEN or state is State.CONNECTING:
            return
        self._cutting = False
        if protocol.close_rcvd is None and protocol.parser_exc is None:
            return  # our close frame is out (or none is due): the server ends it
        close = protocol.close_rcvd or protocol.close_sent
        self._end("" if close is None else f"{close.code} {close.reason}".strip())

    def _end(self, why: str) -> None:
        if why and not self.closed.done():
            self.closed.set_result(why)
        if self.transport is not None:
            self.transport.close()


class StepTimeout(TimeoutError):
    """No answer to one step of a join within its time: ``step`` names it (``connect``:
    the TCP connection, ``upgrade``: the websocket handshake, or a later step)."""

    def __init__(self, step: str, within: float) -> None:
        super().__init__(f"no answer to {step} within {within:g} s")
        self.step = step


async def connect(url: str, clock: Callable[[], float], within: float) -> FrameConnection:
    """A TCP connection to ``ws://host:port/path`` within ``within`` s (else
    :class:`StepTimeout` ``connect``), its upgrade request written; its
    ``connected_at`` is the ``clock`` reading once connected."""
    if not url.startswith("ws://"):
        raise ValueError(f"the load speaks ws:// only, not {url!r}")
    loop = asyncio.get_running_loop()
    conn = FrameConnection(url, clock)
    uri = conn.protocol.uri
    try:
        await asyncio.wait_for(loop.create_connection(lambda: conn, uri.host, uri.port), within)
    except TimeoutError as exc:
        raise StepTimeout("connect", within) from exc
    conn.connected_at = clock()
    return conn


async def open_connection(
    url: str, clock: Callable[[], float], within: float
) -> tuple[FrameConnection, Any]:
    """Connect to ``ws://host:port/path`` and finish the opening handshake, each ``within`` s
    (:class:`StepTimeout` names the step that took longer)."""
    conn = await connect(url, clock, within)
    await conn.upgraded(within)
    return conn, conn.transport
