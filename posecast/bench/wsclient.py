"""The load generator's websocket client: its own framing over an asyncio transport.

The relay is what ``posecast bench relay`` measures, so the load must cost far
less than the relay per frame. A websockets client gives each connection a
reader task, an assembler and a writer; here a connection is one
``asyncio.Protocol`` and nothing else:

- the opening handshake is written and checked by hand (RFC 6455 section 4);
- received frames are cut out of the byte stream in ``data_received`` and
  handed to a callback: no task, no queue per connection;
- every update is pre-encoded (:class:`RawUpdateFrames`,
  :class:`CompactUpdateFrames`): per tick only the sequence number and the time
  are written into fixed bytes, and the client frame is masked with the all-zero
  key (the mask bit is set, as the server requires; XOR with zeros leaves the
  payload as it is, so no per-byte work).

Pings are answered, a close frame is answered and ends the connection; a
masked or oversized frame from the server closes it too.
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import math
import os
import struct
from collections.abc import Callable
from typing import Any, cast

import msgpack
import numpy as np

from posecast.protocol import PoseUpdate
from posecast.protocol._compact import F_RELATIVE
from posecast.protocol.codec_frame import _svarint, _uvarint

__all__ = [
    "CompactUpdateFrames",
    "FrameConnection",
    "RawUpdateFrames",
    "StepTimeout",
    "client_frame",
    "connect",
    "split_codec_update",
]

_GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
_F64 = struct.Struct(">d")
#: Largest frame the load accepts from a server (the relay's snapshots are far smaller).
MAX_FRAME = 1 << 20
OP_TEXT, OP_BINARY, OP_CLOSE, OP_PING, OP_PONG = 0x1, 0x2, 0x8, 0x9, 0xA


def client_frame(payload: bytes, opcode: int = OP_BINARY) -> bytes:
    """One final client -> server frame of ``payload``, masked with the zero key."""
    n = len(payload)
    if n < 126:
        head = bytes((0x80 | opcode, 0x80 | n))
    elif n < 1 << 16:
        head = bytes((0x80 | opcode, 0xFE)) + n.to_bytes(2, "big")
    else:
        head = bytes((0x80 | opcode, 0xFF)) + n.to_bytes(8, "big")
    return head + b"\0\0\0\0" + payload


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
            d = seq - self._previous[0]
            fields = _uvarint(d * 2 if d >= 0 else -d * 2 - 1) + _svarint(
                base_us - self._previous[1]
            )
        else:
            fields = _uvarint(seq) + _svarint(base_us)
        self._previous = (seq, base_us)
        return b"".join((head, fields, tail))

    def frame(self, seq: int, now: float) -> bytes:
        return client_frame(self.payload(seq, now))


#: on_message(payload, arrival): a whole data message from the server.
OnMessage = Callable[[bytes, float], None]


class FrameConnection(asyncio.Protocol):
    """One websocket connection: handshake, then whole data frames to ``on_message``."""

    def __init__(self, host: str, path: str, clock: Callable[[], float]) -> None:
        self._host, self._path, self._clock = host, path, clock
        self._key = base64.b64encode(os.urandom(16))
        self._buf = bytearray()
        self._fragments: list[bytes] = []
        self._upgraded = False
        self._close_sent = False
        self.transport: asyncio.Transport | None = None
        self.on_message: OnMessage = lambda data, arrival: None
        self.opened: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self.closed: asyncio.Future[str] = asyncio.get_running_loop().create_future()
        #: ``clock`` readings once the TCP connection and the handshake were done.
        self.connected_at = self.opened_at = math.nan

    # -- asyncio.Protocol ---------------------------------------------------------

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        # uvloop's transports do not subclass asyncio.Transport; they have its methods.
        transport = cast(asyncio.Transport, transport)
        self.transport = transport
        transport.write(
            b"GET %s HTTP/1.1\r\nHost: %s\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            b"Sec-WebSocket-Key: %s\r\nSec-WebSocket-Version: 13\r\n\r\n"
            % (self._path.encode(), self._host.encode(), self._key)
        )

    def connection_lost(self, exc: Exception | None) -> None:
        why = f"{type(exc).__name__}: {exc}" if exc else "connection lost"
        if not self.opened.done():
            self.opened.set_exception(ConnectionError(why))
        if not self.closed.done():
            self.closed.set_result(why)

    def data_received(self, data: bytes) -> None:
        arrival = self._clock()
        buf = self._buf
        if buf or not self._upgraded:
            buf += data
            if not self._upgraded and not self._upgrade(buf):
                return
            data = bytes(buf)
            buf.clear()
        # Most reads hold whole frames: parse them in place, keep only a tail.
        pos = self._frames(data, arrival)
        if 0 <= pos < len(data):
            buf += data[pos:]

    def _frames(self, data: bytes, arrival: float) -> int:
        """Dispatch the whole frames in ``data``; where a partial one starts (-1: failed)."""
        pos, end = 0, len(data)
        while end - pos >= 2:
            b0, b1 = data[pos], data[pos + 1]
            size, head = b1 & 0x7F, 2
            if size == 126:
                if end - pos < 4:
                    break
                size, head = int.from_bytes(data[pos + 2 : pos + 4], "big"), 4
            elif size == 127:
                if end - pos < 10:
                    break
                size, head = int.from_bytes(data[pos + 2 : pos + 10], "big"), 10
            if b1 & 0x80 or size > MAX_FRAME:
                self.fail(1002 if b1 & 0x80 else 1009, "masked or oversized server frame")
                return -1
            stop = pos + head + size
            if stop > end:
                break
            payload = data[pos + head : stop]
            pos = stop
            if b0 == 0x82:  # final binary frame: the hot path
                self.on_message(payload, arrival)
            else:
                self._control(b0, payload, arrival)
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
        if self.transport is not None and not self.transport.is_closing():
            self.transport.write(frame)

    def buffered(self) -> int:
        """Bytes written but not yet taken by the kernel."""
        t = self.transport
        return 0 if t is None or t.is_closing() else t.get_write_buffer_size()

    def close(self, code: int = 1000, reason: str = "") -> None:
        """Send a close frame; the transport closes when the server answers (or on abort)."""
        if not self._close_sent:
            self._close_sent = True
            self.write(client_frame(code.to_bytes(2, "big") + reason.encode()[:120], OP_CLOSE))

    def abort(self) -> None:
        if self.transport is not None:
            self.transport.abort()

    def fail(self, code: int, reason: str) -> None:
        self.close(code, reason)
        if not self.closed.done():
            self.closed.set_result(f"{code} {reason}")
        if self.transport is not None:
            self.transport.close()

    # -- internals ----------------------------------------------------------------

    def _upgrade(self, buf: bytearray) -> bool:
        """Check the server's handshake response once it is whole; True once open."""
        end = buf.find(b"\r\n\r\n")
        if end < 0:
            if len(buf) > 16384:
                self.fail(1002, "handshake response too long")
            return False
        head = bytes(buf[:end]).decode("latin-1").split("\r\n")
        del buf[: end + 4]
        accept = base64.b64encode(hashlib.sha1(self._key + _GUID).digest()).decode()
        fields = {k.strip().lower(): v.strip() for k, _, v in (h.partition(":") for h in head[1:])}
        if not head[0].startswith("HTTP/1.1 101") or fields.get("sec-websocket-accept") != accept:
            if not self.opened.done():
                self.opened.set_exception(ConnectionError(f"handshake refused: {head[0]}"))
            if self.transport is not None:
                self.transport.close()
            return False
        self._upgraded = True
        self.opened.set_result(None)
        return True

    def _control(self, b0: int, payload: bytes, arrival: float) -> None:
        opcode, final = b0 & 0x0F, b0 & 0x80
        if opcode == OP_PING:
            self.write(client_frame(payload, OP_PONG))
        elif opcode == OP_CLOSE:
            code = int.from_bytes(payload[:2], "big") if len(payload) >= 2 else 1005
            reason = payload[2:].decode(errors="replace")
            if not self._close_sent:  # answer a close the server started
                self._close_sent = True
                self.write(client_frame(payload[:2], OP_CLOSE))
            if not self.closed.done():
                self.closed.set_result(f"{code} {reason}".strip())
            if self.transport is not None:
                self.transport.close()
        elif opcode in (OP_BINARY, OP_TEXT, 0x0):
            # A fragmented message (the relay never sends one): assemble it, bounded.
            self._fragments.append(payload)
            if sum(map(len, self._fragments)) > MAX_FRAME:
                self.fail(1009, "message too big")
            elif final:
                whole = b"".join(self._fragments)
                self._fragments.clear()
                self.on_message(whole, arrival)


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
    hostport, _, path = url[5:].partition("/")
    host, _, port = hostport.rpartition(":")
    loop = asyncio.get_running_loop()
    conn = FrameConnection(hostport, "/" + path, clock)
    try:
        await asyncio.wait_for(loop.create_connection(lambda: conn, host, int(port)), within)
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
