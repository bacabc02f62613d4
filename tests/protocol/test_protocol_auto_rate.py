"""join rate "auto" and the rate notice: schema, session checks, state table."""

from __future__ import annotations

import pytest

from posecast.protocol import (
    ErrorCode,
    Hello,
    Join,
    Joined,
    LocalProtocolError,
    ProtocolError,
    RateNotice,
    decode_message,
    encode_message,
)
from posecast.protocol.testing import SessionPair, raw_frame


def _ready() -> SessionPair:
    pair = SessionPair()
    pair.client_send(Hello())
    pair.server_send(pair.server.make_welcome(1, 0.0))
    return pair


def test_auto_join_round_trips_and_a_fixed_join_is_unchanged() -> None:
    """An auto join decodes to itself; a fixed join's map has no new key."""
    auto = Join(room="r", streams=("head",), rate="auto", max_rate=20.0)
    assert decode_message(encode_message(auto)) == auto and auto.auto_rate
    fixed = Join(room="r", streams=("head",), rate=20.0)
    assert not fixed.auto_rate and "max_rate" not in fixed.to_wire()


def test_max_rate_without_auto_is_a_bad_message() -> None:
    """max_rate belongs to auto rates; another string than "auto" is no rate."""
    with pytest.raises(LocalProtocolError, match="max_rate"):
        Join(room="r", streams=("head",), rate=20.0, max_rate=25.0)
    with pytest.raises(LocalProtocolError, match="rate"):
        Join(room="r", streams=("head",), rate="fast")


def test_the_server_session_takes_auto_and_checks_its_max_rate() -> None:
    """An auto join is accepted; an auto max_rate outside the range is bad-rate."""
    pair = _ready()
    events = pair.server.receive_data(raw_frame("join", room="r", streams=["head"], rate="auto"))
    assert isinstance(events[0], Join) and events[0].auto_rate
    pair = _ready()
    frame = raw_frame("join", room="r", streams=["head"], rate="auto", max_rate=99.0)
    (error,) = pair.server.receive_data(frame)
    assert isinstance(error, ProtocolError) and error.code is ErrorCode.BAD_RATE


def test_a_rate_notice_moves_the_client_sessions_rate() -> None:
    """Once joined, the server may send rate; both sessions take the new rate."""
    pair = _ready()
    pair.client_send(Join(room="r", streams=("head",), rate="auto", max_rate=30.0))
    pair.server_send(Joined(room="r", streams={"head": 0}, rate=30.0))
    (notice,) = pair.server_send(RateNotice(rate=12.0))
    assert notice == RateNotice(rate=12.0)
    assert pair.client.rate == pair.server.rate == 12.0


def test_a_rate_notice_before_joined_is_unexpected() -> None:
    """rate is a JOINED message: before it, the client refuses it (fatal)."""
    pair = _ready()
    events = pair.client.receive_data(encode_message(RateNotice(rate=12.0)))
    assert isinstance(events[0], ProtocolError) and events[0].fatal
