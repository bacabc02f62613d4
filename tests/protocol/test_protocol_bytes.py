"""Pinned wire bytes of every message type, and every decoder fed whole, cut and padded frames."""

from __future__ import annotations

import struct

import pytest

from posecast.protocol import (
    Bye,
    ErrorCode,
    ErrorMessage,
    Hello,
    Join,
    Joined,
    Message,
    ObjectCreate,
    ObjectInfo,
    ObjectRemoved,
    Owner,
    PeerJoined,
    PeerLeft,
    PeerResumed,
    PeerStalled,
    Ping,
    Pong,
    PoseUpdate,
    RateNotice,
    Release,
    RemoteProtocolError,
    Renew,
    RequestOwnership,
    SetRate,
    Snapshot,
    UserEvent,
    Welcome,
    decode_message,
    encode_message,
    encode_snapshot,
)


def f64(value: float) -> bytes:
    """msgpack float64: 0xcb then big-endian IEEE 754."""
    return b"\xcb" + struct.pack(">d", value)


IDENTITY_AT_1_5 = struct.pack("<7f", 0.0, 1.5, 0.0, 1.0, 0.0, 0.0, 0.0)

# (message, exact frame). Maps list "type" first, then the fields in order.
PINNED: list[tuple[Message, bytes]] = [
    (
        Hello(agent="bot"),
        b"\x83\xa4type\xa5hello\xa7version\x01\xa5agent\xa3bot",
    ),
    (
        Welcome(user=7, server_time=1.5),
        b"\x87"
        b"\xa4type\xa7welcome"
        b"\xa4user\x07"
        b"\xabserver_time" + f64(1.5) + b"\xa7version\x01"
        b"\xa8min_rate" + f64(5.0) + b"\xa8max_rate" + f64(30.0) + b"\xabmax_streams\x10",
    ),
    (
        Join(room="lab", streams=("head", "object:drill"), rate=20.0, token="t", label="walk"),
        b"\x86"
        b"\xa4type\xa4join"
        b"\xa4room\xa3lab"
        b"\xa7streams\x92\xa4head\xacobject:drill"
        b"\xa4rate" + f64(20.0) + b"\xa5token\xa1t"
        b"\xa5label\xa4walk",
    ),
    (
        Joined(room="lab", streams={"head": 3, "object:drill": 4}, rate=20.0),
        b"\x84"
        b"\xa4type\xa6joined"
        b"\xa4room\xa3lab"
        b"\xa7streams\x82\xa4head\x03\xacobject:drill\x04"
        b"\xa4rate" + f64(20.0),
    ),
    (
        PeerJoined(user=9, streams={"head": 5}),
        b"\x84\xa4type\xabpeer_joined\xa4user\x09\xa7streams\x81\xa4head\x05\xa5label\xc0",
    ),
    (
        PeerLeft(user=9, reason="bye"),
        b"\x83\xa4type\xa9peer_left\xa4user\x09\xa6reason\xa3bye",
    ),
    (
        Ping(seq=1, time=0.5),
        b"\x83\xa4type\xa4ping\xa3seq\x01\xa4time" + f64(0.5),
    ),
    (
        Pong(seq=1, ping_time=0.5, recv_time=2.0, send_time=2.25),
        b"\x85"
        b"\xa4type\xa4pong"
        b"\xa3seq\x01"
        b"\xa9ping_time" + f64(0.5) + b"\xa9recv_time" + f64(2.0) + b"\xa9send_time" + f64(2.25),
    ),
    (
        SetRate(rate=10.0),
        b"\x82\xa4type\xa8set_rate\xa4rate" + f64(10.0),
    ),
    (
        Renew(token="t"),
        b"\x82\xa4type\xa5renew\xa5token\xa1t",
    ),
    (
        RateNotice(rate=12.0),
        b"\x82\xa4type\xa4rate\xa4rate" + f64(12.0),
    ),
    (
        Join(room="r", streams=("head",), rate="auto", max_rate=20.0),
        b"\x87\xa4type\xa4join\xa4room\xa1r\xa7streams\x91\xa4head\xa4rate\xa4auto"
        b"\xa5token\xc0\xa5label\xc0\xa8max_rate" + f64(20.0),
    ),
    (
        PeerStalled(user=3),
        b"\x82\xa4type\xacpeer_stalled\xa4user\x03",
    ),
    (
        PeerResumed(user=3),
        b"\x82\xa4type\xacpeer_resumed\xa4user\x03",
    ),
    (
        UserEvent(kind="grab", stream=4, time=1.0, payload={"object": "object:drill"}),
        b"\x86"
        b"\xa4type\xa5event"
        b"\xa4kind\xa4grab"
        b"\xa6stream\x04"
        b"\xa4user\xc0"
        b"\xa4time" + f64(1.0) + b"\xa7payload\x81\xa6object\xacobject:drill",
    ),
    (
        ErrorMessage(code="bad-rate", message="rate 50 hz outside [5, 30]", in_reply_to="join"),
        b"\x85"
        b"\xa4type\xa5error"
        b"\xa4code\xa8bad-rate"
        b"\xa7message\xbarate 50 hz outside [5, 30]"
        b"\xa5fatal\xc2"
        b"\xabin_reply_to\xa4join",
    ),
    (
        Bye(reason="done"),
        b"\x82\xa4type\xa3bye\xa6reason\xa4done",
    ),
    (
        PoseUpdate.from_arrays(2, [3], [1.0], [[0, 1.5, 0, 1, 0, 0, 0]], base_time=1.0),
        b"\x84"
        b"\xa4type\xa6update"
        b"\xa3seq\x02"
        b"\xa4time" + f64(1.0) + b"\xa5poses\xc4\x22"  # bin8, 34 bytes
        b"\x03\x00" + struct.pack("<f", 0.0) + IDENTITY_AT_1_5,
    ),
    (
        Snapshot.from_arrays(3, 2.0, [7], [3], [1.5], [[0, 1.5, 0, 1, 0, 0, 0]]),
        b"\x84"
        b"\xa4type\xa8snapshot"
        b"\xa4tick\x03"
        b"\xa4time" + f64(2.0) + b"\xa5poses\xc4\x24"  # bin8, 36 bytes
        b"\x07\x00\x03\x00" + struct.pack("<f", -0.5) + IDENTITY_AT_1_5,
    ),
]
POSE_1_5 = b"\x97" + f64(0.0) + f64(1.5) + f64(0.0) + f64(1.0) + f64(0.0) * 3
PINNED += [
    (
        ObjectCreate(name="object:drill", pose=(0, 1.5, 0, 1, 0, 0, 0), hold=True),
        b"\x85\xa4type\xadobject_create\xa4name\xacobject:drill\xa4pose"
        + POSE_1_5
        + b"\xa4keep\xc3\xa4hold\xc3",
    ),
    (
        RequestOwnership(stream=3, lock=True),
        b"\x83\xa4type\xb1request_ownership\xa6stream\x03\xa4lock\xc3",
    ),
    (
        Release(stream=3, velocity=(1.0, 2.0, 0.0)),
        b"\x83\xa4type\xa7release\xa6stream\x03\xa8velocity\x93" + f64(1.0) + f64(2.0) + f64(0.0),
    ),
    (
        ObjectInfo(
            name="object:drill", stream=3, pose=(0, 1.5, 0, 1, 0, 0, 0), time=2.0, creator=7
        ),
        b"\x88\xa4type\xa6object\xa4name\xacobject:drill\xa6stream\x03\xa4pose"
        + POSE_1_5
        + b"\xa4time"
        + f64(2.0)
        + b"\xa7creator\x07\xa5owner\xc0\xa4keep\xc3",
    ),
    (
        Owner(stream=3, owner=7, previous=None, reason="request", time=2.0),
        b"\x86\xa4type\xa5owner\xa6stream\x03\xa5owner\x07\xa8previous\xc0"
        b"\xa6reason\xa7request\xa4time" + f64(2.0),
    ),
    (
        ObjectRemoved(stream=3, reason="creator-left"),
        b"\x83\xa4type\xaeobject_removed\xa6stream\x03\xa6reason\xaccreator-left",
    ),
]
IDS = [message.TYPE for message, _ in PINNED]


def test_every_type_is_pinned() -> None:
    """The pinned table covers every message type."""
    from posecast.protocol import MESSAGE_TYPES

    assert set(IDS) == MESSAGE_TYPES


@pytest.mark.parametrize(("message", "frame"), PINNED, ids=IDS)
def test_encode_pinned_bytes(message: Message, frame: bytes) -> None:
    """Each message encodes to exactly its pinned bytes."""
    assert encode_message(message) == frame


@pytest.mark.parametrize(("message", "frame"), PINNED, ids=IDS)
def test_decode_pinned_bytes(message: Message, frame: bytes) -> None:
    """Each pinned frame decodes, whole, to the message it pins."""
    assert decode_message(frame) == message


@pytest.mark.parametrize(("message", "frame"), PINNED, ids=IDS)
def test_decode_with_trailing_bytes(message: Message, frame: bytes) -> None:
    """A frame followed by any extra byte is a bad-frame, never a silent success."""
    for extra in (b"\x00", b"\xc0", frame):
        with pytest.raises(RemoteProtocolError) as caught:
            decode_message(frame + extra)
        assert caught.value.code is ErrorCode.BAD_FRAME


@pytest.mark.parametrize(("message", "frame"), PINNED, ids=IDS)
def test_decode_every_truncation(message: Message, frame: bytes) -> None:
    """Every strict prefix of a frame, down to empty, is a bad-frame."""
    for end in range(len(frame)):
        with pytest.raises(RemoteProtocolError) as caught:
            decode_message(frame[:end])
        assert caught.value.code is ErrorCode.BAD_FRAME


def test_encode_snapshot_matches_snapshot_message() -> None:
    """encode_snapshot produces the same bytes as encoding a Snapshot message."""
    message, frame = next(pin for pin in PINNED if pin[0].TYPE == "snapshot")
    assert encode_snapshot(3, 2.0, [7], [3], [1.5], [[0, 1.5, 0, 1, 0, 0, 0]]) == frame
    assert isinstance(message, Snapshot)


def test_int_accepted_for_float_fields() -> None:
    """A peer that packs 20 instead of 20.0 (JavaScript) is understood."""
    frame = b"\x82\xa4type\xa8set_rate\xa4rate\x14"
    decoded = decode_message(frame)
    assert decoded == SetRate(rate=20.0)
    assert type(decoded.rate) is float  # type: ignore[union-attr]


def test_omitted_optional_fields_take_defaults() -> None:
    """Keys of fields with defaults may be left out; required ones may not."""
    assert decode_message(b"\x81\xa4type\xa3bye") == Bye()
    with pytest.raises(RemoteProtocolError) as caught:
        decode_message(b"\x81\xa4type\xa4ping")
    assert caught.value.code is ErrorCode.BAD_MESSAGE
