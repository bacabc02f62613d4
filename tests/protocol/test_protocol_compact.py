"""Compact upstream updates in sessions: negotiation, raw bytes unchanged, round trip, refusals."""

from __future__ import annotations

import copy

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posecast.protocol import (
    DEFAULT_VOLUME,
    ErrorCode,
    Hello,
    Join,
    Joined,
    LocalProtocolError,
    PoseUpdate,
    ProtocolError,
    RemoteProtocolError,
    ServerSession,
    State,
    Volume,
    Welcome,
    decode_message,
    encode_message,
    encode_update,
)
from posecast.protocol._compact import F_RELATIVE, absolute, relative
from posecast.protocol.testing import SessionPair, raw_frame

# The raw session of tests/protocol (hello agent "a", welcome user 7 at 12.5 s,
# join lab head/left/right at 20 Hz, joined 0/1/2, one update of two poses),
# recorded before the codec was negotiated: an old client's bytes, pinned.
RAW_SESSION = [
    "83a474797065a568656c6c6fa776657273696f6e01a56167656e74a161",
    "87a474797065a777656c636f6d65a47573657207ab7365727665725f74696d65cb4029000000000000"
    "a776657273696f6e01a86d696e5f72617465cb4014000000000000a86d61785f72617465cb403e000000"
    "000000ab6d61785f73747265616d7310",
    "86a474797065a46a6f696ea4726f6f6da36c6162a773747265616d7393a468656164a46c656674a572"
    "69676874a472617465cb4034000000000000a5746f6b656ec0a56c6162656cc0",
    "84a474797065a66a6f696e6564a4726f6f6da36c6162a773747265616d7383a46865616400a46c6566"
    "7401a5726967687402a472617465cb4034000000000000",
    "84a474797065a6757064617465a373657101a474696d65cb3ff0000000000000a5706f736573c444"
    "00000000000000000000cdcccc3f000000000000803f000000000000000000000000010000000000cdcc"
    "4c3e9a99993fcdcccc3d000000000000803f0000000000000000",
]
TWO_POSES = [[0, 1.6, 0, 1, 0, 0, 0], [0.2, 1.2, 0.1, 0, 1, 0, 0]]
# The codec's errors (docs/concepts/codec.md): half a position step, 0.0343 deg, 0.5 ms.
POS_ERR = max(DEFAULT_VOLUME.step) / 2 + 1e-6
ROT_ERR_RAD = np.deg2rad(0.0343) + 1e-6
TIME_ERR = 0.5e-3 + 1e-6


def _handshake(pair: SessionPair, codec: str = "compact", **kw: object) -> None:
    pair.handshake(user=7, ids={"head": 0, "left": 1, "right": 2}, codec=codec, **kw)  # type: ignore[arg-type]


def _motion(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """``n`` frames (30 Hz) of 3 streams: smooth paths in the room, slow rotations."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 30.0
    phase = np.sin(t[:, None] + np.arange(3)) * 0.5
    pos = np.stack([phase, 1.2 + 0.1 * phase, 0.3 * phase], -1)
    axis = rng.normal(size=(3, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = t[:, None] * np.array([0.7, 2.0, -1.5])
    quat = np.concatenate(
        [np.cos(angle / 2)[..., None], np.sin(angle / 2)[..., None] * axis[None]], -1
    )
    return np.concatenate([pos, quat], -1), 100.0 + t


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation angle between unit quaternions (chord form: exact near zero)."""
    a = a / np.linalg.norm(a.astype(np.float64), axis=-1, keepdims=True)
    b = b / np.linalg.norm(b.astype(np.float64), axis=-1, keepdims=True)
    chord = np.minimum(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1))
    return 4 * np.arcsin(np.clip(chord / 2, 0.0, 1.0))


def test_old_client_session_is_byte_for_byte_unchanged() -> None:
    """A client that sends no codec (and a server at the default volume): the same bytes."""
    pair = SessionPair()
    out = [pair.client.send(Hello(agent="a"))]
    pair.server.receive_data(out[-1])
    out.append(pair.server.send(pair.server.make_welcome(7, 12.5)))
    pair.client.receive_data(out[-1])
    out.append(pair.client.send(Join(room="lab", streams=("head", "left", "right"), rate=20.0)))
    pair.server.receive_data(out[-1])
    out.append(
        pair.server.send(Joined(room="lab", streams={"head": 0, "left": 1, "right": 2}, rate=20.0))
    )
    pair.client.receive_data(out[-1])
    update = PoseUpdate.from_arrays(1, [0, 1], [1.0, 1.0], TWO_POSES, base_time=1.0)
    out.append(pair.client.send(update))
    assert [o.hex() for o in out] == RAW_SESSION
    [event] = pair.server.receive_data(out[-1])
    assert event == update
    assert pair.client.codec == pair.server.codec == "raw"


def test_codec_negotiation_and_join_fields() -> None:
    join = Join(room="r", streams=("head",), rate=10.0, codec="compact")
    assert encode_message(join) != encode_message(Join(room="r", streams=("head",), rate=10.0))
    assert decode_message(encode_message(join)) == join
    assert "codec" not in Join(room="r", streams=("head",), rate=10.0).to_wire()
    for bad in ("zstd", "", 3, None):
        with pytest.raises(LocalProtocolError) as info:
            Join(room="r", streams=("head",), rate=10.0, codec=bad)  # type: ignore[arg-type]
        assert info.value.code is ErrorCode.BAD_MESSAGE
    data = raw_frame("join", room="r", streams=["head"], rate=10.0, codec="gzip")
    with pytest.raises(RemoteProtocolError) as remote:
        decode_message(data)
    assert remote.value.code is ErrorCode.BAD_MESSAGE
    pair = SessionPair()
    _handshake(pair)
    assert pair.client.codec == pair.server.codec == "compact"
    assert pair.client.state is pair.server.state is State.JOINED


def test_welcome_states_the_volume_only_when_not_default() -> None:
    assert "volume" not in Welcome(user=1, server_time=0.0).to_wire()
    room = Volume((-4.0, 0.0, -4.0), (4.0, 3.0, 4.0))
    pair = SessionPair(server=ServerSession(volume=room))
    pair.client_send(Hello())
    welcome = pair.server.make_welcome(3, 0.0)
    assert welcome.to_wire()["volume"] == (-4.0, 0.0, -4.0, 4.0, 3.0, 4.0)
    pair.server_send(welcome)
    assert pair.client.volume == room
    for bad in ((0.0,) * 6, (1.0, 0, 0, 0, 1, 1), (0.0,) * 5, (0, 0, 0, 1, 1, float("nan"))):
        with pytest.raises(LocalProtocolError) as info:
            Welcome(user=1, server_time=0.0, volume=bad)  # type: ignore[arg-type]
        assert info.value.code is ErrorCode.BAD_MESSAGE


@pytest.mark.parametrize("velocities", [False, True])
def test_compact_round_trip_within_the_codec_error(velocities: bool) -> None:
    """ClientSession -> ServerSession: the same PoseUpdate events, within the codec's error."""
    pair = SessionPair()
    _handshake(pair, sends_velocities=velocities)
    poses, times = _motion(60)
    rng = np.random.default_rng(1)
    sizes = []
    for i in range(len(times)):
        vel = rng.uniform(-3, 3, (3, 6)) if velocities else None
        sent = PoseUpdate.from_arrays(
            i + 1, [0, 1, 2], np.full(3, times[i]) - [0.0, 0.004, 0.011], poses[i], velocities=vel
        )
        data = pair.client.send(sent)
        sizes.append(len(data))
        assert data[0] == 0xC1
        [got] = pair.server.receive_data(data)
        assert isinstance(got, PoseUpdate) and got.seq == sent.seq
        assert got.poses.dtype == np.float32 and got.streams.tolist() == [0, 1, 2]
        assert np.abs(got.poses[:, :3] - sent.poses[:, :3]).max() <= POS_ERR
        assert _angle(got.poses[:, 3:], sent.poses[:, 3:]).max() <= ROT_ERR_RAD
        assert np.abs(got.capture_times - sent.capture_times).max() <= TIME_ERR
        if velocities:
            assert got.velocities is not None and sent.velocities is not None
            err = np.abs(got.velocities.astype(float) - sent.velocities.astype(float))
            assert err.max() <= 2**-9 + 3 * 2**-9  # codec step, then float16 rounding
        else:
            assert got.velocities is None
    raw = len(encode_update(1, [0, 1, 2], np.full(3, times[0]), poses[0]))
    assert sizes[0] > max(sizes[1:])  # the key update, then deltas
    assert max(sizes[1:]) < raw / 2
    assert pair.server.statistics().errors == 0


def test_raw_update_refused_once_compact_agreed() -> None:
    pair = SessionPair()
    _handshake(pair)
    data = encode_update(1, [0], [1.0], [TWO_POSES[0]])
    [error] = pair.server.receive_data(data)
    assert isinstance(error, ProtocolError) and error.code is ErrorCode.BAD_MESSAGE
    assert error.fatal and pair.server.state is State.CLOSED


def test_compact_frame_refused_when_raw_agreed() -> None:
    """A codec frame to a raw session is no msgpack: a fatal bad-frame."""
    compact, raw = SessionPair(), SessionPair()
    _handshake(compact)
    _handshake(raw, codec="raw")
    data = compact.client.send(PoseUpdate.from_arrays(1, [0], [1.0], [TWO_POSES[0]]))
    [error] = raw.server.receive_data(data)
    assert isinstance(error, ProtocolError) and error.code is ErrorCode.BAD_FRAME
    assert raw.server.state is State.CLOSED


def test_compact_snapshot_frame_refused_as_an_update() -> None:
    pair = SessionPair()
    _handshake(pair)
    data = bytearray(pair.client.send(PoseUpdate.from_arrays(1, [0], [1.0], [TWO_POSES[0]])))
    data[1] &= ~1  # the flags' update bit: now a snapshot
    [error] = pair.server.receive_data(bytes(data))
    assert isinstance(error, ProtocolError) and error.fatal
    assert error.code is ErrorCode.BAD_MESSAGE and error.in_reply_to == "update"


def test_position_outside_the_volume_refused_client_side() -> None:
    pair = SessionPair()
    _handshake(pair)
    outside = [[0.0, 4.1, 0.0, 1, 0, 0, 0]]  # y over the default volume's 4 m
    with pytest.raises(LocalProtocolError) as info:
        pair.client.send(PoseUpdate.from_arrays(1, [0], [1.0], outside))
    assert info.value.code is ErrorCode.BAD_POSE
    assert pair.client.state is State.JOINED
    # Still in sync: the refused update changed no baseline.
    for seq, y in ((2, 4.0), (3, 3.99)):
        update = PoseUpdate.from_arrays(seq, [0], [1.0], [[0.0, y, 0.0, 1, 0, 0, 0]])
        [event] = pair.server.receive_data(pair.client.send(update))
        assert isinstance(event, PoseUpdate)


def test_delta_outside_the_volume_is_bad_pose_server_side() -> None:
    """A delta that walks a position past the volume's edge: a non-fatal bad-pose."""
    pair = SessionPair()
    _handshake(pair)
    top = PoseUpdate.from_arrays(1, [0], [1.0], [[0.0, 4.0, 0.0, 1, 0, 0, 0]])
    pair.server.receive_data(pair.client.send(top))
    below = PoseUpdate.from_arrays(2, [0], [1.0], [[0.0, 3.999, 0.0, 1, 0, 0, 0]])
    data = pair.client.send(below)
    codes = []
    for bit in range(8 * len(data)):  # flip the sign of the y difference, wherever it is
        forged = bytearray(data)
        forged[bit // 8] ^= 0x80 >> (bit % 8)
        server = copy.deepcopy(pair.server)
        [event] = server.receive_data(bytes(forged))
        if isinstance(event, ProtocolError):
            codes.append(event.code)
            if event.code is ErrorCode.BAD_POSE:
                assert not event.fatal and server.state is State.JOINED
    assert ErrorCode.BAD_POSE in codes


def test_corrupted_delta_chain_is_fatal() -> None:
    """A delta against a baseline the server does not hold: fatal bad-baseline."""
    pair = SessionPair()
    _handshake(pair)
    poses, times = _motion(3)
    frames = [
        pair.client.send(PoseUpdate.from_arrays(i + 1, [0, 1, 2], np.full(3, times[i]), poses[i]))
        for i in range(3)
    ]
    pair.server.receive_data(frames[0])
    # frame 1 lost (or altered): frame 2 is coded against baselines the server lacks.
    [error] = pair.server.receive_data(frames[2])
    assert isinstance(error, ProtocolError)
    assert error.code is ErrorCode.BAD_BASELINE and error.fatal
    assert error.in_reply_to == "update"
    assert pair.server.state is State.CLOSED
    # A delta for a stream the server has no baseline for at all.
    fresh = SessionPair()
    _handshake(fresh)
    [error] = fresh.server.receive_data(frames[1])
    assert isinstance(error, ProtocolError) and error.code is ErrorCode.BAD_BASELINE
    assert fresh.server.state is State.CLOSED


def test_stream_rules_still_apply_to_compact_updates() -> None:
    pair = SessionPair()
    _handshake(pair)
    with pytest.raises(LocalProtocolError) as info:
        pair.client.send(PoseUpdate.from_arrays(1, [5], [1.0], [TWO_POSES[0]]))
    assert info.value.code is ErrorCode.STREAM_NOT_OWNED
    with pytest.raises(LocalProtocolError) as info:
        pair.client.send(
            PoseUpdate.from_arrays(1, [0], [1.0], [TWO_POSES[0]], velocities=[[0] * 6])
        )
    assert info.value.code is ErrorCode.BAD_MESSAGE


def test_updates_after_the_first_carry_a_relative_header() -> None:
    """Sequence number and base time as differences from the previous update: smaller
    frames, the same decoded updates; a relative header with nothing before it (a new
    session, a lost frame) is a fatal bad-baseline."""
    pair = SessionPair()
    _handshake(pair)
    poses, times = _motion(4)
    frames = [
        pair.client.send(
            PoseUpdate.from_arrays(1000 + i, [0, 1, 2], np.full(3, 5000.0 + times[i]), poses[i])
        )
        for i in range(4)
    ]
    assert not frames[0][1] & F_RELATIVE and all(f[1] & F_RELATIVE for f in frames[1:])
    for i, frame in enumerate(frames):
        (update,) = pair.server.receive_data(frame)
        assert isinstance(update, PoseUpdate) and update.seq == 1000 + i
        assert update.base_time == pytest.approx(5000.0 + times[i], abs=1e-6)
    absolute_size = len(absolute(frames[1], relative(frames[0], None)[1])[0])
    assert len(frames[1]) < absolute_size
    fresh = SessionPair()
    _handshake(fresh)
    [error] = fresh.server.receive_data(frames[2])
    assert isinstance(error, ProtocolError) and error.code is ErrorCode.BAD_BASELINE


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=64), st.integers(0, 255))
def test_relative_headers_of_hostile_bytes_only_raise_protocol_errors(
    body: bytes, flags: int
) -> None:
    data = bytes([0xC1, flags]) + body
    for previous in (None, (5, 10**9)):
        try:
            whole, (number, base) = absolute(data, previous)
        except RemoteProtocolError:
            continue
        # What comes back is an absolute header the codec's own checks then judge;
        # one made from a relative header is in range.
        assert not whole[1] & F_RELATIVE
        if flags & F_RELATIVE:
            assert 0 <= number < 1 << 63 and abs(base) < 1 << 62
