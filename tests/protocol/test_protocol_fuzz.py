"""Fuzzing: whatever bytes a peer sends, sessions return events and never raise.

Invariant (as in h11's fuzz harness): ``receive_data`` returns a list of events,
every error is a ``ProtocolError`` with a known code and a message that fits a
websocket close frame, and a fatal error leaves the session CLOSED.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import msgpack
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from posecast.protocol import (
    MAX_CLOSE_REASON_BYTES,
    UPDATE_ENTRY_SIZE,
    ClientSession,
    ControlMessage,
    ErrorCode,
    Hello,
    PoseUpdate,
    ProtocolError,
    ServerSession,
    Snapshot,
    State,
    decode_message,
    encode_snapshot,
    encode_update,
)
from posecast.protocol.testing import SessionPair, raw_frame

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def fresh_server() -> ServerSession:
    """A server session that has received nothing."""
    return ServerSession()


def hello_client() -> ClientSession:
    """A client session that has sent hello."""
    client = ClientSession()
    client.send(Hello())
    return client


def joined_server() -> ServerSession:
    """A joined server session (user 1 owns streams 0, 1, 2)."""
    pair = SessionPair()
    pair.handshake()
    return pair.server


def joined_client() -> ClientSession:
    """A joined client session."""
    pair = SessionPair()
    pair.handshake()
    return pair.client


def velocity_server() -> ServerSession:
    """A joined server session whose client declared velocity updates."""
    pair = SessionPair()
    pair.handshake(sends_velocities=True, wants_velocities=True)
    return pair.server


def velocity_client() -> ClientSession:
    """A joined client session that asked for velocity snapshots."""
    pair = SessionPair()
    pair.handshake(sends_velocities=True, wants_velocities=True)
    return pair.client


Factory = Callable[[], ServerSession | ClientSession]

SESSIONS: list[Factory] = [
    fresh_server,
    hello_client,
    joined_server,
    joined_client,
    velocity_server,
    velocity_client,
]


def check_invariant(session: ServerSession | ClientSession, frames: list[bytes]) -> None:
    """Feed frames; every result is an event, errors are well formed, fatal ones close."""
    for frame in frames:
        was_closed = session.closed
        events = session.receive_data(frame)
        assert isinstance(events, list)
        if was_closed:
            assert events == []
        for event in events:
            if isinstance(event, ProtocolError):
                assert isinstance(event.code, ErrorCode)
                assert len(event.message.encode()) <= MAX_CLOSE_REASON_BYTES, event.message
                assert event.fatal == session.closed or not event.fatal
                if event.fatal:
                    assert session.state is State.CLOSED
            else:
                assert isinstance(event, ControlMessage | PoseUpdate | Snapshot)


msgpack_scalars = (
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**63), max_value=2**64 - 1)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=20)
    | st.binary(max_size=80)
)
msgpack_values = st.recursive(
    msgpack_scalars,
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=12,
)
# Per type, the field names of its schema; values are random, and the map
# holds any subset of the fields, so frames get past the key checks into the
# value checks and session rules.
FIELDS: dict[str, list[str]] = {
    cls.TYPE: [f.name for f in dataclasses.fields(cls)]  # type: ignore[arg-type]
    for cls in ControlMessage.__subclasses__()
}
FIELDS["update"] = ["seq", "time", "poses", "vpose"]
FIELDS["snapshot"] = ["tick", "time", "poses", "vpose"]


def maps_of(type_: str) -> st.SearchStrategy[bytes]:
    """Frames of this type with a random subset of its fields holding random values."""
    fields = st.fixed_dictionaries({}, optional=dict.fromkeys(FIELDS[type_], msgpack_values))
    return fields.map(lambda values: raw_frame(type_, **values))


message_maps = st.sampled_from(sorted(FIELDS)).flatmap(maps_of)


@FUZZ
@given(st.lists(st.binary(max_size=200), min_size=1, max_size=4), st.sampled_from(SESSIONS))
def test_random_bytes_never_raise(frames: list[bytes], make: Factory) -> None:
    """Random bytes to a client or server session in any state only yield events."""
    check_invariant(make(), frames)


@FUZZ
@given(st.lists(message_maps, min_size=1, max_size=4), st.sampled_from(SESSIONS))
def test_random_messages_never_raise(frames: list[bytes], make: Factory) -> None:
    """Well-formed maps with real types and field names but random values only yield events."""
    check_invariant(make(), frames)


@FUZZ
@given(msgpack_values)
def test_random_msgpack_values_never_raise(value: object) -> None:
    """Any msgpack value as a whole frame is refused as an event, not an exception."""
    check_invariant(fresh_server(), [msgpack.packb(value)])


@FUZZ
@given(
    st.integers(min_value=0, max_value=6).flatmap(
        lambda n: st.binary(min_size=n * UPDATE_ENTRY_SIZE, max_size=n * UPDATE_ENTRY_SIZE)
    )
)
def test_random_pose_records_never_raise(body: bytes) -> None:
    """Random record bytes in a well-formed update give a PoseUpdate or a ProtocolError."""
    server = joined_server()
    (event,) = server.receive_data(raw_frame("update", seq=1, time=0.0, poses=body))
    assert isinstance(event, PoseUpdate | ProtocolError)
    if isinstance(event, PoseUpdate):
        assert set(event.streams.tolist()) <= {0, 1, 2}
        assert np.isfinite(event.poses).all()
        norms = np.linalg.norm(event.poses[:, 3:].astype(np.float64), axis=1)
        assert (np.abs(norms - 1) <= 1e-3).all()


@FUZZ
@given(st.data())
def test_mutated_frames_never_raise(data: st.DataObject) -> None:
    """Valid frames with random bytes flipped, cut or appended only yield events."""
    frames = [
        encode_update(3, [0, 1], [1.0, 1.0], np.tile([0, 1, 0, 1, 0, 0, 0.0], (2, 1))),
        encode_snapshot(3, 1.0, [2], [0], [1.0], [[0, 1, 0, 1, 0, 0, 0.0]]),
        encode_update(4, [0], [1.0], [[0, 1, 0, 1, 0, 0, 0.0]], velocities=[[1, 2, 3, 4, 5, 6]]),
        encode_snapshot(4, 1.0, [2], [0], [1.0], [[0, 1, 0, 1, 0, 0, 0.0]], velocities=[[0.5] * 6]),
        raw_frame("join", room="lab", streams=["head", "object:drill"], rate=20.0),
        raw_frame("event", kind="grab", stream=1, user=None, time=1.0, payload={"a": [1]}),
    ]
    frame = bytearray(data.draw(st.sampled_from(frames)))
    for _ in range(data.draw(st.integers(1, 4))):
        frame[data.draw(st.integers(0, len(frame) - 1))] = data.draw(st.integers(0, 255))
    frame = frame[: data.draw(st.integers(0, len(frame)))] + data.draw(st.binary(max_size=3))
    for make in SESSIONS:
        check_invariant(make(), [bytes(frame)])


finite32 = st.floats(-1e4, 1e4, width=32)


@FUZZ
@given(
    arrays(np.float64, st.tuples(st.integers(0, 16), st.just(7)), elements=finite32),
    st.floats(-1e7, 1e7),
    st.floats(-5, 0),
)
def test_snapshot_round_trip_property(poses: np.ndarray, send_time: float, age: float) -> None:
    """Any snapshot decodes to its float32 poses and capture times within float32 resolution."""
    n = len(poses)
    users = np.arange(n) % 3
    times = send_time + age * np.linspace(0, 1, n)
    decoded = decode_message(encode_snapshot(7, send_time, users, np.arange(n), times, poses))
    assert isinstance(decoded, Snapshot)
    np.testing.assert_array_equal(decoded.poses, poses.astype(np.float32))
    np.testing.assert_array_equal(decoded.users, users)
    # dt is float32: relative error 2**-24 of the age, plus float64 rounding.
    assert np.all(
        np.abs(decoded.capture_times - times) <= 1e-6 * (1 + abs(age)) + 1e-9 * abs(send_time)
    )
    assert all(math.isfinite(t) for t in decoded.capture_times.tolist())
