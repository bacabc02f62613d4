"""The spectator flag of join: sent only when true, and a bool."""

from __future__ import annotations

import pytest

from posecast.protocol import (
    ErrorCode,
    Join,
    LocalProtocolError,
    RemoteProtocolError,
    decode_message,
    encode_message,
)
from posecast.protocol.testing import raw_frame


def test_spectator_travels_only_when_true() -> None:
    """A plain join is byte for byte as before; spectator=True adds one key at the end."""
    plain = encode_message(Join(room="lab", streams=("head",), rate=20.0))
    watcher = Join(room="lab", streams=("head",), rate=20.0, spectator=True)
    assert b"spectator" not in plain and plain[0] == 0x86  # a map of 6 keys
    assert encode_message(watcher) == b"\x87" + plain[1:] + b"\xa9spectator\xc3"
    assert decode_message(encode_message(watcher)) == watcher
    # An explicit false is the default: accepted, and equal to leaving it out.
    explicit = raw_frame("join", room="lab", streams=["head"], rate=20.0, spectator=False)
    assert encode_message(decode_message(explicit)) == plain


@pytest.mark.parametrize("value", [1, 0, "yes", None])
def test_spectator_must_be_a_bool(value: object) -> None:
    """Anything but a bool is a fatal bad-message naming the field, on either side."""
    frame = raw_frame("join", room="lab", streams=["head"], rate=20.0, spectator=value)
    with pytest.raises(RemoteProtocolError, match=r"join\.spectator") as caught:
        decode_message(frame)
    assert caught.value.code is ErrorCode.BAD_MESSAGE
    with pytest.raises(LocalProtocolError, match=r"join\.spectator"):
        Join(room="lab", streams=("head",), rate=20.0, spectator=value)  # type: ignore[arg-type]
