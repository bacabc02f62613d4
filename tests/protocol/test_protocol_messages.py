"""Control messages: round trips, constructor validation, error codes and clock-sync arithmetic."""

from __future__ import annotations

import math

import pytest

from posecast.protocol import (
    Bye,
    ControlMessage,
    ErrorCode,
    ErrorMessage,
    Hello,
    Join,
    Joined,
    Limits,
    LocalProtocolError,
    PeerJoined,
    PeerLeft,
    Ping,
    Pong,
    ProtocolError,
    RemoteProtocolError,
    SetRate,
    UserEvent,
    Welcome,
    close_reason,
    decode_message,
    encode_message,
    is_valid_stream_name,
)
from posecast.protocol.testing import raw_frame

MESSAGES: list[ControlMessage] = [
    Hello(),
    Hello(agent="posecast-bot/0.1"),
    Welcome(user=0, server_time=-3.25, min_rate=1.0, max_rate=90.0, max_streams=1),
    Welcome(user=65535, server_time=1e9),
    Join(room="r", streams=("head",), rate=5.0),
    Join(room="lab", streams=("head", "left", "right", "object:drill"), rate=30, label="walk"),
    Joined(room="lab", streams={}, rate=12.5),
    Joined(room="lab", streams={"head": 0, "left": 65535}, rate=12.5),
    PeerJoined(user=3, streams={"head": 7}, label="wave"),
    PeerLeft(user=3),
    Ping(seq=0, time=0.0),
    Ping(seq=2**63 - 1, time=-1.0),
    Pong(seq=5, ping_time=1.0, recv_time=11.05, send_time=11.06),
    SetRate(rate=7.5),
    UserEvent(kind="button", stream=1, payload={"button": "a", "pressed": True}),
    UserEvent(kind="scene_step", user=4, payload={"step": 3, "data": [1, 2.5, None, b"\x00"]}),
    UserEvent(kind="release"),
    ErrorMessage(code="room-full", message="room lab is full"),
    ErrorMessage(code="stream-not-owned", message="stream 9 not owned", fatal=True),
    Bye(),
]


@pytest.mark.parametrize("message", MESSAGES, ids=repr)
def test_round_trip(message: ControlMessage) -> None:
    """Every control message decodes back to an equal message."""
    assert decode_message(encode_message(message)) == message  # type: ignore[arg-type]


def test_float_fields_normalised() -> None:
    """Ints given for float fields are stored as floats, lists as tuples."""
    join = Join(room="lab", streams=["head"], rate=20)  # type: ignore[arg-type]
    assert type(join.rate) is float
    assert join.streams == ("head",)


@pytest.mark.parametrize(
    "build",
    [
        lambda: Hello(version=-1),
        lambda: Hello(agent=5),
        lambda: Welcome(user=65536, server_time=0.0),
        lambda: Welcome(user=True, server_time=0.0),
        lambda: Welcome(user=1, server_time=math.nan),
        lambda: Welcome(user=1, server_time=0.0, min_rate=10.0, max_rate=5.0),
        lambda: Join(room="lab", streams="head", rate=20.0),
        lambda: Join(room="lab", streams=(1,), rate=20.0),
        lambda: Join(room="lab", streams=("head",), rate=math.inf),
        lambda: Join(room="x" * 300, streams=("head",), rate=20.0),
        lambda: Joined(room="lab", streams={"head": 1, "left": 1}, rate=20.0),
        lambda: Joined(room="lab", streams={"head": -1}, rate=20.0),
        lambda: Joined(room="lab", streams=[("head", 1)], rate=20.0),
        lambda: PeerJoined(user=1, streams={"": 1}),
        lambda: PeerLeft(user=None),
        lambda: Ping(seq=-1, time=0.0),
        lambda: Ping(seq=1.0, time=0.0),
        lambda: Pong(seq=1, ping_time=0.0, recv_time="1", send_time=0.0),
        lambda: SetRate(rate=True),
        lambda: UserEvent(kind="teleport"),
        lambda: UserEvent(kind="grab", stream=70000),
        lambda: UserEvent(kind="grab", payload={1: "x"}),
        lambda: UserEvent(kind="grab", payload={"x": {1, 2}}),
        lambda: UserEvent(kind="grab", payload={"x": 2**70}),
        lambda: UserEvent(kind="grab", payload=[1]),
        lambda: ErrorMessage(code="", message="x"),
        lambda: ErrorMessage(code="x", message="y", fatal=1),
        lambda: Bye(reason=None),
    ],
)
def test_constructor_rejects(build: object) -> None:
    """Invalid field values raise LocalProtocolError bad-message at construction."""
    with pytest.raises(LocalProtocolError) as caught:
        build()  # type: ignore[operator]
    assert caught.value.code is ErrorCode.BAD_MESSAGE


def test_payload_depth_limited_without_recursion() -> None:
    """A payload nested far deeper than allowed is refused without RecursionError."""
    deep: object = "leaf"
    for _ in range(5000):
        deep = [deep]
    with pytest.raises(LocalProtocolError, match="nested deeper"):
        UserEvent(kind="grab", payload={"x": deep})
    UserEvent(kind="grab", payload={"a": [[[[[[1]]]]]]})


def test_decoder_reports_constructor_errors_as_remote() -> None:
    """A schema error in a received frame surfaces as RemoteProtocolError bad-message."""
    with pytest.raises(RemoteProtocolError) as caught:
        decode_message(raw_frame("ping", seq="one", time=0.0))
    assert caught.value.code is ErrorCode.BAD_MESSAGE
    assert caught.value.message == "ping.seq must be an int in [0, 9223372036854775807]"


def test_unknown_field_is_bad_message() -> None:
    """A field the schema does not list is refused by name."""
    with pytest.raises(RemoteProtocolError, match="unknown field 'colour'"):
        decode_message(raw_frame("bye", reason="", colour="red"))


def test_hello_version_checked_before_schema() -> None:
    """A hello from another version is a version-mismatch even if its fields differ."""
    with pytest.raises(RemoteProtocolError) as caught:
        decode_message(raw_frame("hello", version=2, features=["x"]))
    assert caught.value.code is ErrorCode.VERSION_MISMATCH
    with pytest.raises(RemoteProtocolError) as caught:
        decode_message(raw_frame("welcome", version="1", user=1, server_time=0.0))
    assert caught.value.code is ErrorCode.VERSION_MISMATCH


def test_error_codes_table() -> None:
    """Fatal codes carry their close code, non-fatal ones none."""
    assert ErrorCode.BAD_FRAME.close_code == 1002
    assert ErrorCode.FRAME_TOO_LARGE.close_code == 1009
    assert ErrorCode.STREAM_NOT_OWNED.close_code == 1008
    assert ErrorCode.INTERNAL_ERROR.close_code == 1011
    for code in ErrorCode:
        assert code.fatal == (code.close_code is not None)
        assert code.value == code.value.lower()
    non_fatal = {code for code in ErrorCode if not code.fatal}
    assert ErrorCode.BAD_POSE in non_fatal
    assert ErrorCode.BAD_RATE in non_fatal
    assert ErrorCode.VERSION_MISMATCH not in non_fatal


def test_protocol_error_to_message() -> None:
    """A ProtocolError event converts to the error message that tells the peer."""
    error = ProtocolError(ErrorCode.STREAM_NOT_OWNED, "stream 9 not owned", "update")
    message = error.to_message()
    assert message == ErrorMessage(
        code="stream-not-owned", message="stream 9 not owned", fatal=True, in_reply_to="update"
    )
    assert (error.fatal, error.close_code) == (True, 1008)


def test_close_reason_fits_close_frame() -> None:
    """Close reasons are cut to 123 UTF-8 bytes without splitting a character."""
    assert close_reason("short") == "short"
    cut = close_reason("é" * 100)
    assert len(cut.encode()) <= 123
    assert cut == "é" * 61


def test_pong_clock_offset() -> None:
    """Pong.offset and round_trip recover a known clock offset and network delay."""
    # Server clock = client clock + 100 s, 30 ms each way, 2 ms inside the server.
    ping_time = 10.0
    recv_time = ping_time + 0.030 + 100.0
    send_time = recv_time + 0.002
    arrival = send_time - 100.0 + 0.030
    pong = Pong(seq=1, ping_time=ping_time, recv_time=recv_time, send_time=send_time)
    assert pong.offset(arrival) == pytest.approx(100.0)
    assert pong.round_trip(arrival) == pytest.approx(0.060)


@pytest.mark.parametrize(
    ("name", "valid"),
    [
        ("head", True),
        ("left", True),
        ("left_foot", True),
        ("object:drill", True),
        ("object:Drill-2.v1", True),
        ("", False),
        ("Head", False),
        ("object:", False),
        ("object:a b", False),
        ("hand:left", False),
        ("object:" + "x" * 26, False),
        (3, False),
    ],
)
def test_stream_names(name: object, valid: bool) -> None:
    """Device names are lowercase identifiers, objects are object:NAME, 32 chars at most."""
    assert is_valid_stream_name(name) is valid


def test_limits_validated() -> None:
    """Limits refuse nonsense such as min_rate above max_rate or zero frame size."""
    with pytest.raises(LocalProtocolError):
        Limits(min_rate=40.0)
    with pytest.raises(LocalProtocolError):
        Limits(max_frame_size=0)
    assert Limits(max_rate=90.0).max_rate == 90.0
