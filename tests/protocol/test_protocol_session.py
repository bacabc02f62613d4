"""Sessions: the handshake, the state table, and every hostile input -> the right error event."""

from __future__ import annotations

import math

import msgpack
import numpy as np
import pytest

from posecast.protocol import (
    PROTOCOL_VERSION,
    Bye,
    ClientSession,
    ErrorCode,
    ErrorMessage,
    Event,
    Hello,
    Join,
    Joined,
    Limits,
    LocalProtocolError,
    PeerJoined,
    PeerLeft,
    Ping,
    Pong,
    PoseUpdate,
    ProtocolError,
    ServerSession,
    SetRate,
    Snapshot,
    State,
    UserEvent,
    Welcome,
    encode_snapshot,
    encode_update,
)
from posecast.protocol.testing import SessionPair, raw_frame

IDENTITY = [0.0, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0]


def poses(n: int) -> np.ndarray:
    """n identical valid poses."""
    return np.tile(IDENTITY, (n, 1))


def only_error(events: list[Event]) -> ProtocolError:
    """The single ProtocolError in events."""
    assert len(events) == 1, events
    (event,) = events
    assert isinstance(event, ProtocolError), event
    return event


def assert_error(events: list[Event], code: ErrorCode, message: str | None = None) -> ProtocolError:
    """events is one ProtocolError with this code (and message, if given)."""
    error = only_error(events)
    assert error.code is code, error
    if message is not None:
        assert error.message == message
    # Lowercase wording; only quoted peer values may carry capitals.
    assert error.message.split("'")[0] == error.message.split("'")[0].lower()
    return error


# Handshake and state --------------------------------------------------------


def test_full_handshake(pair: SessionPair) -> None:
    """hello, welcome, join, joined move both sides to JOINED with ids and streams agreed."""
    assert pair.client_send(Hello(agent="bot")) == [Hello(agent="bot")]
    assert pair.client.state is pair.server.state is State.HELLO
    welcome = pair.server.make_welcome(user=4, server_time=12.5)
    assert pair.server_send(welcome) == [welcome]
    assert pair.client.user == pair.server.user == 4
    assert pair.client.state is pair.server.state is State.READY
    join = Join(room="lab", streams=("head", "left", "object:drill"), rate=15.0, label="walk")
    assert pair.client_send(join) == [join]
    assert pair.client.state is pair.server.state is State.JOINING
    joined = Joined(room="lab", streams={"head": 10, "left": 11, "object:drill": 12}, rate=15.0)
    assert pair.server_send(joined) == [joined]
    assert pair.client.state is pair.server.state is State.JOINED
    for session in (pair.client, pair.server):
        assert session.streams == {"head": 10, "left": 11, "object:drill": 12}
        assert session.owned_streams == {10, 11, 12}
        assert (session.room, session.rate) == ("lab", 15.0)


def test_welcome_announces_server_limits() -> None:
    """make_welcome carries the server's rate range and stream limit to the client."""
    server = ServerSession(Limits(min_rate=2.0, max_rate=60.0, max_streams=4))
    welcome = server.make_welcome(user=1, server_time=0.0)
    assert (welcome.min_rate, welcome.max_rate, welcome.max_streams) == (2.0, 60.0, 4)
    assert welcome.version == PROTOCOL_VERSION


def test_pose_traffic_both_ways(joined: SessionPair) -> None:
    """Once joined, client updates reach the server and server snapshots reach the client."""
    update = PoseUpdate.from_arrays(1, [0, 2], [10.0, 10.0], poses(2))
    (received,) = joined.client_send(update)
    assert received == update
    frame = encode_snapshot(5, 10.1, [2, 2], [0, 1], [10.0, 10.05], poses(2))
    (snapshot,) = joined.client.receive_data(frame)
    assert isinstance(snapshot, Snapshot)
    assert snapshot.tick == 5
    np.testing.assert_allclose(snapshot.capture_times, [10.0, 10.05])


def test_peers_tracked_by_client(joined: SessionPair) -> None:
    """peer_joined and peer_left keep ClientSession.peers current."""
    joined.server_send(PeerJoined(user=2, streams={"head": 3}, label="wave"))
    joined.server_send(PeerJoined(user=3, streams={"head": 4}))
    assert joined.client.peers == {2: {"head": 3}, 3: {"head": 4}}
    joined.server_send(PeerLeft(user=2, reason="bye"))
    assert joined.client.peers == {3: {"head": 4}}


def test_events_stamped_with_sender(joined: SessionPair) -> None:
    """The server session stamps the sender's user id on a client's event."""
    (event,) = joined.client_send(UserEvent(kind="grab", stream=1, payload={"object": "x"}))
    assert isinstance(event, UserEvent)
    assert event.user == 1
    assert event.payload == {"object": "x"}
    relayed = UserEvent(kind="release", stream=7, user=9)
    assert joined.server_send(relayed) == [relayed]


def test_ping_pong_after_welcome(pair: SessionPair) -> None:
    """Pings and pongs flow either way from welcome on and do not change state."""
    pair.client_send(Hello())
    pair.server_send(pair.server.make_welcome(1, 0.0))
    assert pair.client_send(Ping(seq=1, time=1.0)) == [Ping(seq=1, time=1.0)]
    pong = Pong(seq=1, ping_time=1.0, recv_time=5.0, send_time=5.0)
    assert pair.server_send(pong) == [pong]
    assert pair.server_send(Ping(seq=9, time=5.0)) == [Ping(seq=9, time=5.0)]
    assert pair.client.state is State.READY


def test_set_rate(joined: SessionPair) -> None:
    """A valid set_rate is delivered and becomes the session's rate."""
    assert joined.client_send(SetRate(rate=7.0)) == [SetRate(rate=7.0)]
    assert joined.server.rate == 7.0


def test_join_refused_then_retried(pair: SessionPair) -> None:
    """A non-fatal error in reply to join sends both sides back to READY; a new join works."""
    pair.client_send(Hello())
    pair.server_send(pair.server.make_welcome(1, 0.0))
    pair.client_send(Join(room="full", streams=("head",), rate=20.0))
    refusal = ErrorMessage.from_code(ErrorCode.ROOM_FULL, "room full is full", in_reply_to="join")
    assert pair.server_send(refusal) == [refusal]
    assert pair.client.state is pair.server.state is State.READY
    pair.client_send(Join(room="lab", streams=("head",), rate=20.0))
    pair.server_send(Joined(room="lab", streams={"head": 0}, rate=20.0))
    assert pair.client.state is pair.server.state is State.JOINED


def test_bye_ends_both_sides(joined: SessionPair) -> None:
    """bye closes both sessions; a closed session ignores further input."""
    assert joined.client_send(Bye(reason="done")) == [Bye(reason="done")]
    assert joined.client.closed and joined.server.closed
    assert joined.server.receive_data(encode_update(2, [0], [0.0], poses(1))) == []
    assert joined.server.receive_data(b"\xc1garbage") == []
    with pytest.raises(LocalProtocolError):
        joined.client.send(PoseUpdate.from_arrays(2, [0], [0.0], poses(1)))
    # A closed session may still explain itself.
    joined.server.send(ErrorMessage(code="internal-error", message="shutting down", fatal=True))
    joined.server.send(Bye())


def test_bye_allowed_before_hello() -> None:
    """A client may leave before saying hello."""
    assert ServerSession().receive_data(raw_frame("bye", reason="")) == [Bye()]


def test_fatal_error_message_received_closes(joined: SessionPair) -> None:
    """A fatal error message from the peer closes the receiving session."""
    message = ErrorMessage.from_code(ErrorCode.UNAUTHORIZED, "bad token")
    assert joined.server_send(message) == [message]
    assert joined.client.closed and joined.server.closed


def test_non_fatal_error_message_keeps_state(joined: SessionPair) -> None:
    """A non-fatal error message (e.g. a dropped pose) changes no state."""
    joined.server_send(ErrorMessage.from_code(ErrorCode.BAD_POSE, "non-finite pose"))
    joined.client_send(ErrorMessage(code="bad-pose", message="snapshot dropped"))
    assert joined.client.state is joined.server.state is State.JOINED


def test_statistics(joined: SessionPair) -> None:
    """statistics() counts frames, bytes and error events."""
    joined.server.receive_data(b"\xc1")
    stats = joined.server.statistics()
    assert stats.frames_received == 3
    assert stats.frames_sent == 2
    assert stats.errors == 1
    assert stats.bytes_received > 0 and stats.bytes_sent > 0
    assert stats.state is State.CLOSED


def test_assign_streams_without_joined() -> None:
    """assign_streams sets ownership directly, for replays and tests."""
    server = ServerSession()
    server.assign_streams({"head": 5})
    assert server.owned_streams == {5}


# Hostile input to the server: fatal -------------------------------------------


@pytest.mark.parametrize(
    ("frame", "code", "message"),
    [
        (b"", ErrorCode.BAD_FRAME, "not a msgpack frame"),
        (b"\xc1", ErrorCode.BAD_FRAME, "not a msgpack frame"),
        (b"GET / HTTP/1.1\r\n\r\n", ErrorCode.BAD_FRAME, None),
        (raw_frame("hello", version=1, agent="")[:-3], ErrorCode.BAD_FRAME, None),
        (raw_frame("hello") + b"\x00", ErrorCode.BAD_FRAME, "trailing bytes after frame"),
        (msgpack.packb([1, 2, 3]), ErrorCode.BAD_FRAME, "frame is not a map"),
        (msgpack.packb({"kind": "hello"}), ErrorCode.BAD_FRAME, "frame has no string type"),
        (msgpack.packb({"type": 1}), ErrorCode.BAD_FRAME, "frame has no string type"),
        (msgpack.packb({1: 2}), ErrorCode.BAD_FRAME, "not a msgpack frame"),
        (msgpack.packb({"type": "hello", "v": float("nan")})[:-1], ErrorCode.BAD_FRAME, None),
        (raw_frame("teleport"), ErrorCode.UNKNOWN_TYPE, "unknown type 'teleport'"),
        (
            raw_frame("hello", version=2),
            ErrorCode.VERSION_MISMATCH,
            "hello for version 2, this is 1",
        ),
        (raw_frame("hello", version=1, agent=7), ErrorCode.BAD_MESSAGE, None),
        (
            raw_frame("join", room="lab", streams=["head"], rate=20.0),
            ErrorCode.UNEXPECTED_MESSAGE,
            "join before hello",
        ),
        (raw_frame("ping", seq=1, time=0.0), ErrorCode.UNEXPECTED_MESSAGE, "ping before hello"),
        (
            raw_frame("welcome", user=1, server_time=0.0),
            ErrorCode.UNEXPECTED_MESSAGE,
            "welcome from a client",
        ),
    ],
)
def test_fresh_server_fatal(frame: bytes, code: ErrorCode, message: str | None) -> None:
    """Garbage, cut frames, unknown types, other versions and early messages close the session."""
    server = ServerSession()
    error = assert_error(server.receive_data(frame), code, message)
    assert error.fatal
    assert error.close_code == 1002
    assert server.closed


def test_text_frame_is_bad_frame() -> None:
    """A websocket text frame (str) is refused as a fatal bad-frame, not a TypeError."""
    server = ServerSession()
    error = assert_error(server.receive_data('{"type": "hello"}'), ErrorCode.BAD_FRAME)
    assert error.message == "text frame, posecast frames are binary"
    assert server.closed


def test_bytearray_and_memoryview_accepted() -> None:
    """Frames may arrive as bytearray or memoryview as well as bytes."""
    frame = raw_frame("hello", version=1, agent="")
    assert ServerSession().receive_data(bytearray(frame)) == [Hello()]
    assert ServerSession().receive_data(memoryview(frame)) == [Hello()]


def test_frame_too_large() -> None:
    """A frame over max_frame_size is refused before parsing, with close code 1009."""
    server = ServerSession(Limits(max_frame_size=100))
    frame = raw_frame("hello", version=1, agent="x" * 100)
    error = assert_error(server.receive_data(frame), ErrorCode.FRAME_TOO_LARGE)
    assert error.close_code == 1009
    assert server.closed


def test_default_frame_limit_is_64_kib(joined: SessionPair) -> None:
    """The default limit admits 64 KiB and refuses one byte more."""
    assert only_error(joined.server.receive_data(b"\xc1" * 65537)).code is ErrorCode.FRAME_TOO_LARGE
    assert (
        only_error(SessionPair().server.receive_data(b"\xc1" * 65536)).code is ErrorCode.BAD_FRAME
    )


@pytest.mark.parametrize(
    ("frame", "message"),
    [
        (raw_frame("hello"), "hello while joined"),
        (raw_frame("join", room="lab", streams=["head"], rate=20.0), "join while joined"),
        (raw_frame("snapshot", tick=0, time=0.0, poses=b""), "snapshot from a client"),
        (raw_frame("joined", room="lab", streams={}, rate=20.0), "joined from a client"),
        (raw_frame("peer_left", user=1, reason=""), "peer_left from a client"),
    ],
)
def test_joined_server_unexpected(joined: SessionPair, frame: bytes, message: str) -> None:
    """Messages out of order or from the wrong side are fatal unexpected-message errors."""
    error = assert_error(joined.server.receive_data(frame), ErrorCode.UNEXPECTED_MESSAGE, message)
    assert error.fatal
    assert joined.server.closed


def test_update_before_joined(pair: SessionPair) -> None:
    """Poses before joined are unexpected, even with a valid frame."""
    pair.client_send(Hello())
    pair.server_send(pair.server.make_welcome(1, 0.0))
    frame = encode_update(0, [0], [0.0], poses(1))
    assert_error(
        pair.server.receive_data(frame), ErrorCode.UNEXPECTED_MESSAGE, "update before join"
    )


@pytest.mark.parametrize(
    "frame",
    [
        raw_frame("join", room=5, streams=["head"], rate=20.0),
        raw_frame("join", room="lab", streams="head", rate=20.0),
        raw_frame("join", room="lab", streams=["head"]),
        raw_frame("join", room="lab", streams=["head"], rate="fast"),
        raw_frame("join", room="lab", streams=["head"], rate=20.0, admin=True),
    ],
)
def test_join_wrong_types(frame: bytes) -> None:
    """A join with missing, unknown or ill-typed fields is a fatal bad-message."""
    pair = SessionPair()
    pair.client_send(Hello())
    pair.server_send(pair.server.make_welcome(1, 0.0))
    error = assert_error(pair.server.receive_data(frame), ErrorCode.BAD_MESSAGE)
    assert error.in_reply_to == "join"
    assert pair.server.closed


@pytest.mark.parametrize("stream", [3, 9, 65535])
def test_update_for_stream_not_owned(joined: SessionPair, stream: int) -> None:
    """An update naming a stream not assigned to this user closes with 1008."""
    frame = encode_update(1, [0, stream], [0.0, 0.0], poses(2))
    error = assert_error(
        joined.server.receive_data(frame), ErrorCode.STREAM_NOT_OWNED, f"stream {stream} not owned"
    )
    assert error.close_code == 1008
    assert error.in_reply_to == "update"
    assert joined.server.closed


def test_stream_of_another_user() -> None:
    """In a room of two, each session refuses the other user's stream ids."""
    alice, bob = SessionPair(), SessionPair()
    alice.handshake(user=1, ids={"head": 0, "left": 1, "right": 2})
    bob.handshake(user=2, ids={"head": 3, "left": 4, "right": 5})
    assert alice.server.receive_data(encode_update(0, [0], [0.0], poses(1)))[0] is not None
    error = only_error(alice.server.receive_data(encode_update(1, [4], [0.0], poses(1))))
    assert error.code is ErrorCode.STREAM_NOT_OWNED


def test_event_for_stream_not_owned(joined: SessionPair) -> None:
    """An event about someone else's stream is stream-not-owned."""
    frame = raw_frame("event", kind="grab", stream=40)
    assert_error(joined.server.receive_data(frame), ErrorCode.STREAM_NOT_OWNED)


def test_event_spoofing_user(joined: SessionPair) -> None:
    """A client may not send an event in another user's name."""
    frame = raw_frame("event", kind="grab", user=2)
    assert_error(
        joined.server.receive_data(frame), ErrorCode.BAD_MESSAGE, "event.user is not the sender"
    )


# Hostile input to the server: non-fatal -----------------------------------------


def bad_update(row: list[float], n: int = 3) -> bytes:
    """An update of streams 0..n-1 whose last pose is row."""
    values = poses(n)
    values[-1] = row
    return encode_update(7, np.arange(n), np.zeros(n), values)


@pytest.mark.parametrize(
    ("frame", "message"),
    [
        (bad_update([math.nan, 0, 0, 1, 0, 0, 0]), "non-finite pose"),
        (bad_update([0, math.inf, 0, 1, 0, 0, 0]), "non-finite pose"),
        (bad_update([0, 0, 0, 1, 0, 0, -math.inf]), "non-finite pose"),
        (bad_update([0, 0, 0, 1.0011, 0, 0, 0]), "quaternion not unit"),
        (bad_update([0, 0, 0, 0.5, 0.5, 0.5, 0.49]), "quaternion not unit"),
        (bad_update([0, 0, 0, 0, 0, 0, 0], n=1), "quaternion not unit"),
    ],
)
def test_bad_pose_dropped(joined: SessionPair, frame: bytes, message: str) -> None:
    """NaN, inf and non-unit quaternions drop the update with bad-pose; the session goes on."""
    error = assert_error(joined.server.receive_data(frame), ErrorCode.BAD_POSE, message)
    assert not error.fatal and error.close_code is None
    assert error.to_message().in_reply_to == "update"
    assert joined.server.state is State.JOINED
    (update,) = joined.server.receive_data(encode_update(8, [0], [0.0], poses(1)))
    assert isinstance(update, PoseUpdate)


def test_nan_time_offset_dropped(joined: SessionPair) -> None:
    """A NaN capture time offset is a bad pose too."""
    frame = encode_update(0, [0], [math.nan], poses(1), base_time=0.0)
    assert_error(joined.server.receive_data(frame), ErrorCode.BAD_POSE, "non-finite pose")


def test_duplicate_stream_dropped(joined: SessionPair) -> None:
    """The same stream twice in one update is dropped, non-fatally."""
    frame = encode_update(0, [1, 1], [0.0, 0.0], poses(2))
    error = assert_error(joined.server.receive_data(frame), ErrorCode.DUPLICATE_STREAM)
    assert not error.fatal and not joined.server.closed


def test_more_entries_than_owned_streams(joined: SessionPair) -> None:
    """An update with more poses than the user has streams is too-many-streams, non-fatal."""
    frame = encode_update(0, [0, 1, 2, 0], np.zeros(4), poses(4))
    error = assert_error(
        joined.server.receive_data(frame),
        ErrorCode.TOO_MANY_STREAMS,
        "update has 4 poses for 3 streams",
    )
    assert not error.fatal


def ready_pair(limits: Limits | None = None) -> SessionPair:
    """A pair after hello and welcome."""
    pair = SessionPair(server=ServerSession(limits) if limits else None)
    pair.client_send(Hello())
    pair.server_send(pair.server.make_welcome(1, 0.0))
    return pair


@pytest.mark.parametrize(
    ("join", "code", "message"),
    [
        (
            raw_frame("join", room="lab", streams=["head"], rate=50.0),
            ErrorCode.BAD_RATE,
            "rate 50 hz outside [5, 30]",
        ),
        (raw_frame("join", room="lab", streams=["head"], rate=4.9), ErrorCode.BAD_RATE, None),
        (raw_frame("join", room="lab", streams=["head"], rate=0), ErrorCode.BAD_RATE, None),
        (
            raw_frame("join", room="lab", streams=[f"object:o{i}" for i in range(17)], rate=20.0),
            ErrorCode.TOO_MANY_STREAMS,
            "17 streams, at most 16",
        ),
        (
            raw_frame("join", room="lab", streams=["head", "head"], rate=20.0),
            ErrorCode.BAD_STREAM_NAME,
            "duplicate stream name",
        ),
        (
            raw_frame("join", room="lab", streams=["Head"], rate=20.0),
            ErrorCode.BAD_STREAM_NAME,
            "bad stream name 'Head'",
        ),
        (
            raw_frame("join", room="lab", streams=["object:" + "x" * 40], rate=20.0),
            ErrorCode.BAD_STREAM_NAME,
            None,
        ),
        (
            raw_frame("join", room="lab", streams=[], rate=20.0),
            ErrorCode.BAD_STREAM_NAME,
            "no streams",
        ),
    ],
)
def test_join_refused_non_fatal(join: bytes, code: ErrorCode, message: str | None) -> None:
    """Bad rates, too many or bad stream names refuse the join; the session stays READY."""
    pair = ready_pair()
    error = assert_error(pair.server.receive_data(join), code)
    if message is not None:
        assert error.message == message
    assert not error.fatal
    assert error.in_reply_to == "join"
    assert pair.server.state is State.READY
    # The server tells the client; both stay READY and a good join still works.
    assert pair.server_send(error.to_message()) == [error.to_message()]
    pair.client_send(Join(room="lab", streams=("head",), rate=20.0))
    assert pair.server.state is State.JOINING


def test_rate_limits_are_configurable() -> None:
    """A server with max_rate 90 accepts a 60 Hz join."""
    pair = ready_pair(Limits(max_rate=90.0))
    assert pair.client_send(Join(room="lab", streams=("head",), rate=60.0))[0] == Join(
        room="lab", streams=("head",), rate=60.0
    )


def test_set_rate_out_of_range(joined: SessionPair) -> None:
    """set_rate outside the range is bad-rate, non-fatal, and the old rate stays."""
    error = assert_error(
        joined.server.receive_data(raw_frame("set_rate", rate=31.0)), ErrorCode.BAD_RATE
    )
    assert not error.fatal
    assert joined.server.rate == 20.0
    assert joined.server.state is State.JOINED


def test_event_payload_too_large(joined: SessionPair) -> None:
    """An event payload over max_event_payload is dropped, non-fatally."""
    frame = raw_frame("event", kind="button", payload={"blob": b"x" * 5000})
    error = assert_error(joined.server.receive_data(frame), ErrorCode.PAYLOAD_TOO_LARGE)
    assert not error.fatal
    assert joined.server.state is State.JOINED


def test_nan_in_control_field(joined: SessionPair) -> None:
    """NaN in a control message's number is a bad-message."""
    frame = raw_frame("ping", seq=1, time=math.nan)
    assert_error(
        joined.server.receive_data(frame),
        ErrorCode.BAD_MESSAGE,
        "ping.time must be a finite number",
    )


# Hostile input to the client ----------------------------------------------------


def test_client_rejects_other_version() -> None:
    """A welcome of another protocol version closes the client session."""
    client = ClientSession()
    client.send(Hello())
    frame = raw_frame("welcome", version=3, user=1, server_time=0.0)
    assert assert_error(client.receive_data(frame), ErrorCode.VERSION_MISMATCH).fatal
    assert client.closed


def test_client_rejects_snapshot_with_bad_pose(joined: SessionPair) -> None:
    """A snapshot with a NaN pose is dropped with bad-pose; the client stays joined."""
    values = poses(3)
    values[1, 0] = math.nan
    frame = encode_snapshot(1, 1.0, [2, 2, 2], [0, 1, 2], [1.0] * 3, values)
    error = assert_error(joined.client.receive_data(frame), ErrorCode.BAD_POSE)
    assert not error.fatal
    assert joined.client.state is State.JOINED


def test_client_rejects_mismatched_joined(pair: SessionPair) -> None:
    """A joined for other stream names than the join asked for is a bad-message."""
    pair.client_send(Hello())
    pair.server_send(pair.server.make_welcome(1, 0.0))
    pair.client_send(Join(room="lab", streams=("head",), rate=20.0))
    frame = raw_frame("joined", room="lab", streams={"left": 0}, rate=20.0)
    assert_error(
        pair.client.receive_data(frame), ErrorCode.BAD_MESSAGE, "joined does not match the join"
    )


@pytest.mark.parametrize(
    ("frame", "message"),
    [
        (raw_frame("update", seq=0, time=0.0, poses=b""), "update from a server"),
        (raw_frame("hello"), "hello from a server"),
        (raw_frame("set_rate", rate=10.0), "set_rate from a server"),
    ],
)
def test_client_refuses_client_only_types(joined: SessionPair, frame: bytes, message: str) -> None:
    """A server sending client-only messages is an unexpected-message."""
    assert_error(joined.client.receive_data(frame), ErrorCode.UNEXPECTED_MESSAGE, message)


def test_client_refuses_snapshot_before_joined() -> None:
    """A snapshot before welcome is unexpected."""
    client = ClientSession()
    client.send(Hello())
    frame = encode_snapshot(0, 0.0, [1], [0], [0.0], poses(1))
    assert_error(
        client.receive_data(frame), ErrorCode.UNEXPECTED_MESSAGE, "snapshot before welcome"
    )


# Local mistakes raise ---------------------------------------------------------


def test_local_send_out_of_order() -> None:
    """Sending a message the state forbids raises LocalProtocolError, state unchanged."""
    client = ClientSession()
    with pytest.raises(LocalProtocolError, match="cannot send join before hello"):
        client.send(Join(room="lab", streams=("head",), rate=20.0))
    server = ServerSession()
    with pytest.raises(LocalProtocolError, match="cannot send hello from a server"):
        server.send(Hello())
    assert client.state is server.state is State.START


def test_local_join_checked_against_welcome(pair: SessionPair) -> None:
    """The client refuses to send a join the welcome's limits would refuse."""
    pair.client_send(Hello())
    pair.server_send(Welcome(user=1, server_time=0.0, max_rate=10.0, max_streams=2))
    with pytest.raises(LocalProtocolError) as caught:
        pair.client.send(Join(room="lab", streams=("head",), rate=20.0))
    assert caught.value.code is ErrorCode.BAD_RATE
    with pytest.raises(LocalProtocolError) as caught:
        pair.client.send(Join(room="lab", streams=("head", "left", "right"), rate=10.0))
    assert caught.value.code is ErrorCode.TOO_MANY_STREAMS
    assert pair.client.state is State.READY


def test_local_bad_update(joined: SessionPair) -> None:
    """The client refuses to send NaN poses or streams it does not own."""
    bad = poses(1)
    bad[0, 0] = math.nan
    with pytest.raises(LocalProtocolError) as caught:
        joined.client.send(PoseUpdate.from_arrays(0, [0], [0.0], bad))
    assert caught.value.code is ErrorCode.BAD_POSE
    with pytest.raises(LocalProtocolError) as caught:
        joined.client.send(PoseUpdate.from_arrays(0, [5], [0.0], poses(1)))
    assert caught.value.code is ErrorCode.STREAM_NOT_OWNED


def test_local_joined_must_match_join(pair: SessionPair) -> None:
    """The server session refuses to send a joined that does not answer the join."""
    pair.client_send(Hello())
    pair.server_send(pair.server.make_welcome(1, 0.0))
    pair.client_send(Join(room="lab", streams=("head",), rate=20.0))
    with pytest.raises(LocalProtocolError, match="joined does not match the join"):
        pair.server.send(Joined(room="lab", streams={"head": 0, "left": 1}, rate=20.0))
    with pytest.raises(LocalProtocolError) as caught:
        pair.server.send(Joined(room="lab", streams={"head": 0}, rate=99.0))
    assert caught.value.code is ErrorCode.BAD_RATE
    assert pair.server.owned_streams == frozenset()


def test_local_frame_too_large() -> None:
    """Sending a frame over the limit raises and changes nothing."""
    client = ClientSession(Limits(max_frame_size=64))
    with pytest.raises(LocalProtocolError) as caught:
        client.send(Hello(agent="x" * 100))
    assert caught.value.code is ErrorCode.FRAME_TOO_LARGE
    assert client.state is State.START


def test_local_wrong_version() -> None:
    """A session refuses to send hello or welcome of another version."""
    with pytest.raises(LocalProtocolError) as caught:
        ClientSession().send(Hello(version=2))
    assert caught.value.code is ErrorCode.VERSION_MISMATCH
