"""Compact upstream updates: a session's end of the codec's update frames.

A client that joined with ``codec="compact"`` sends each ``PoseUpdate`` as one
codec update frame (``protocol.codec``: first byte 0xC1, never msgpack),
quantised in the room volume of the server's welcome and delta-coded against
the codes it last sent for each stream (a stream's first pose goes as a key
entry). The server decodes it against its own copy of those baselines and hands
the relay the same ``PoseUpdate`` a raw client sends: the dequantised poses as
float32, capture times to the codec's millisecond.

Both ends store a frame's codes as baselines (``PoseFrame.remember``) once it
is surely sent, or decoded: the websocket is reliable and ordered, so the two
copies stay equal; a frame coded against other baselines (a CRC mismatch) or
naming a stream without one raises ``BaselineMismatch`` (fatal, ``bad-message``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from protocol.codec import (
    PoseFrame,
    Volume,
    decode_update,
    encode_update_codes,
    quantise,
)
from protocol.codec_relay import decode_relay_snapshot
from protocol.errors import ProtocolViolation, RemoteProtocolError
from protocol.poses import PoseUpdate, Snapshot

__all__ = ["CODEC_FRAME_BYTE", "SnapshotDecoder", "UpstreamDecoder", "UpstreamEncoder"]

#: First byte of every codec frame (the one byte msgpack never uses).
CODEC_FRAME_BYTE = 0xC1

Baselines = dict[int, NDArray[np.int64]]


class UpstreamEncoder:
    """The client's half: ``PoseUpdate`` -> codec update frame, baselines per stream."""

    def __init__(self, volume: Volume) -> None:
        self.volume = volume
        self.baselines: Baselines = {}
        self._pending: PoseFrame | None = None

    def encode(self, update: PoseUpdate) -> bytes:
        """The frame of ``update``; raises ``LocalProtocolError`` (``bad-pose`` outside the
        volume). Call :meth:`commit` once the frame is surely sent."""
        velocities = update.velocities
        codes = quantise(update.poses, self.volume, velocities)
        encoded = encode_update_codes(
            update.seq,
            update.base_time,
            update.streams,
            update.capture_times,
            codes,
            self.volume,
            self.baselines,
        )
        self._pending = encoded.frame
        return encoded.data

    def commit(self) -> None:
        """The last encoded frame was sent: its codes are the streams' new baselines."""
        if self._pending is not None:
            self._pending.remember(self.baselines)
            self._pending = None


class UpstreamDecoder:
    """The server's half: codec update frame -> ``PoseUpdate``, baselines per stream."""

    def __init__(self, volume: Volume) -> None:
        self.volume = volume
        self.baselines: Baselines = {}
        #: Stream id -> codes of the last decoded frame: a relay forwards these codes
        #: to compact subscribers rather than quantising the decoded floats again.
        self.last_codes: dict[int, list[int]] = {}

    def decode(self, data: bytes | bytearray | memoryview) -> PoseUpdate:
        """The update in ``data``; raises ``RemoteProtocolError`` (in reply to "update")."""
        try:
            frame = decode_update(bytes(data), self.volume, self.baselines)
        except ProtocolViolation as exc:
            raise RemoteProtocolError(exc.code, exc.message, in_reply_to="update") from None
        # The sender stored these codes when it sent them, whatever the session
        # rules say of the update next: keep the two copies equal.
        frame.remember(self.baselines)
        self.last_codes = dict(zip(frame.streams.tolist(), frame.codes.tolist(), strict=True))
        return PoseUpdate.from_arrays(
            frame.number,
            frame.streams,
            frame.capture_times,
            frame.poses,
            base_time=frame.base_time,
            velocities=frame.velocities,
        )


class SnapshotDecoder:
    """The client's half of compact snapshots: relay frame -> ``Snapshot``.

    Baselines are the codes last received for each (user, stream); a frame coded
    against others raises ``BaselineMismatch`` (fatal ``bad-baseline``).
    """

    def __init__(self, volume: Volume) -> None:
        self.volume = volume
        self.baselines: dict[tuple[int, int], list[int]] = {}

    def decode(self, data: bytes | bytearray | memoryview) -> Snapshot:
        """The snapshot in ``data``; raises ``RemoteProtocolError``."""
        try:
            frame = decode_relay_snapshot(bytes(data), self.volume, self.baselines)
        except ProtocolViolation as exc:
            raise RemoteProtocolError(exc.code, exc.message, in_reply_to="snapshot") from None
        frame.remember(self.baselines)
        poses, velocities = frame.arrays()
        return Snapshot.from_arrays(
            frame.tick,
            frame.base_time,
            frame.users,
            frame.streams,
            frame.capture_times,
            poses,
            velocities=velocities,
        )

    def forget(self, user: int) -> None:
        """Drop the baselines of a user who left (its stream ids may be reused)."""
        for key in [k for k in self.baselines if k[0] == user]:
            del self.baselines[key]
