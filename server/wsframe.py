"""Websocket data frames written and cut without a protocol object (RFC 6455 section 5.2).

Both websocket ends of posecast carry websockets' sans-I/O protocol objects for
the handshake, control frames and closing (the relay's
:class:`~posecast.server.transport.WebSocketConnection`, the load generator's
:class:`~posecast.bench.wsclient.FrameConnection`), and both write their data
frames themselves, here, because the protocol objects cost more than the hot
path affords:

- :func:`frame_binary`: a server's frame (unmasked), built once per snapshot
  and written to every subscriber of it;
- :func:`client_frame`: a client's frame, masked with the all-zero key (the
  mask bit is set, as a server requires; XOR with zeros leaves the payload as it
  is, so there is no per-byte work);
- :func:`frame_head`: where the frame at a position of a byte stream starts its
  payload and how long that is: the load generator cuts its received snapshots
  out of a read with it and hands every other frame to its protocol object.

Pure functions of bytes: no socket, no clock.
"""

from __future__ import annotations

import struct

__all__ = [
    "OP_BINARY",
    "OP_CLOSE",
    "OP_CONT",
    "OP_PING",
    "OP_PONG",
    "OP_TEXT",
    "client_frame",
    "frame_binary",
    "frame_head",
]

OP_CONT, OP_TEXT, OP_BINARY, OP_CLOSE, OP_PING, OP_PONG = 0x0, 0x1, 0x2, 0x8, 0x9, 0xA
#: The first byte of a final binary frame: FIN set, opcode binary.
FINAL_BINARY = 0x80 | OP_BINARY
#: The second byte's mask bit.
MASKED = 0x80

_HEAD16 = struct.Struct("!BBH")
_HEAD64 = struct.Struct("!BBQ")
_ZERO_KEY = b"\0\0\0\0"


def _head(first: int, mask: int, n: int) -> bytes:
    """The header of a frame of ``n`` payload bytes (without a masking key)."""
    if n < 126:
        return bytes((first, mask | n))
    if n < 65536:
        return _HEAD16.pack(first, mask | 126, n)
    return _HEAD64.pack(first, mask | 127, n)


def frame_binary(payload: bytes) -> bytes:
    """A complete unmasked binary frame (FIN set) carrying ``payload``: what a server sends."""
    return _head(FINAL_BINARY, 0, len(payload)) + payload


def client_frame(payload: bytes, opcode: int = OP_BINARY) -> bytes:
    """A complete final client frame of ``payload``, masked with the zero key."""
    return _head(0x80 | opcode, MASKED, len(payload)) + _ZERO_KEY + payload


def frame_head(data: bytes, pos: int) -> tuple[int, int, int, int] | None:
    """(first byte, second byte, payload start, payload size) of the frame that starts
    at ``data[pos]``; None while its header is incomplete. The second byte's
    :data:`MASKED` bit says whether a 4-byte masking key precedes the payload (the
    payload start counts it)."""
    end = len(data)
    if end - pos < 2:
        return None
    b1 = data[pos + 1]
    size, head = b1 & 0x7F, 2
    if size == 126:
        if end - pos < 4:
            return None
        size, head = int.from_bytes(data[pos + 2 : pos + 4], "big"), 4
    elif size == 127:
        if end - pos < 10:
            return None
        size, head = int.from_bytes(data[pos + 2 : pos + 10], "big"), 10
    if b1 & MASKED:
        head += 4
    return data[pos], b1, pos + head, size
