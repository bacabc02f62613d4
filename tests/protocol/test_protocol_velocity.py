"""The velocity variant of pose frames: layout, pinned bytes, negotiation, hostile input."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from posecast import protocol
from posecast.protocol import (
    SNAPSHOT_ENTRY_SIZE,
    SNAPSHOT_VELOCITY_DTYPE,
    SNAPSHOT_VELOCITY_ENTRY_SIZE,
    UPDATE_ENTRY_SIZE,
    UPDATE_VELOCITY_DTYPE,
    UPDATE_VELOCITY_ENTRY_SIZE,
    VELOCITY_BYTES,
    VELOCITY_MAX,
    ErrorCode,
    Join,
    LocalProtocolError,
    PeerJoined,
    PoseUpdate,
    ProtocolError,
    RemoteProtocolError,
    Snapshot,
    State,
    decode_message,
    encode_message,
    encode_snapshot,
    encode_update,
    frame_size,
)
from posecast.protocol.testing import SessionPair, raw_frame

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])

IDENTITY = [0.0, 1.5, 0.0, 1.0, 0.0, 0.0, 0.0]
IDENTITY_AT_1_5 = struct.pack("<7f", *IDENTITY)
# Exactly representable in float16, so the bytes below are exact.
VEL = [0.5, -1.0, 2.0, 0.25, 8.0, -3.0]
VEL_F16 = struct.pack("<6e", *VEL)


def f64(value: float) -> bytes:
    return b"\xcb" + struct.pack(">d", value)


def velocity_pair(*, sends: bool = True, wants: bool = True) -> SessionPair:
    """A joined pair (user 1 owns head=0, left=1, right=2) that agreed on velocities."""
    pair = SessionPair()
    pair.handshake(sends_velocities=sends, wants_velocities=wants)
    return pair


def test_record_sizes_and_layout() -> None:
    """Velocity records are the plain ones plus 6 float16 (12 bytes) after the pose."""
    assert VELOCITY_BYTES == 12
    assert UPDATE_VELOCITY_ENTRY_SIZE == UPDATE_VELOCITY_DTYPE.itemsize == UPDATE_ENTRY_SIZE + 12
    assert SNAPSHOT_VELOCITY_ENTRY_SIZE == SNAPSHOT_VELOCITY_DTYPE.itemsize == 48
    assert SNAPSHOT_VELOCITY_ENTRY_SIZE == SNAPSHOT_ENTRY_SIZE + 12
    assert UPDATE_VELOCITY_DTYPE.fields is not None
    assert UPDATE_VELOCITY_DTYPE.fields["velocity"][1] == 34
    assert VELOCITY_MAX == 65504.0


def test_pinned_velocity_update_bytes() -> None:
    """A velocity update: key "vpose", 46-byte records ending in 6 little-endian float16."""
    frame = encode_update(2, [3], [1.0], [IDENTITY], base_time=1.0, velocities=[VEL])
    want = (
        b"\x84\xa4type\xa6update\xa3seq\x02\xa4time" + f64(1.0) + b"\xa5vpose\xc4\x2e"  # 46
        b"\x03\x00" + struct.pack("<f", 0.0) + IDENTITY_AT_1_5 + VEL_F16
    )
    assert frame == want
    decoded = decode_message(want)
    assert isinstance(decoded, PoseUpdate)
    assert decoded.has_velocities
    assert decoded.velocities is not None
    assert decoded.velocities.dtype == np.float16
    assert decoded.velocities.tolist() == [VEL]
    assert encode_message(decoded) == want


def test_pinned_velocity_snapshot_bytes() -> None:
    """A velocity snapshot: key "vpose", 48-byte records."""
    frame = encode_snapshot(3, 2.0, [7], [3], [1.5], [IDENTITY], velocities=[VEL])
    want = (
        b"\x84\xa4type\xa8snapshot\xa4tick\x03\xa4time" + f64(2.0) + b"\xa5vpose\xc4\x30"  # 48
        b"\x07\x00\x03\x00" + struct.pack("<f", -0.5) + IDENTITY_AT_1_5 + VEL_F16
    )
    assert frame == want
    decoded = decode_message(want)
    assert isinstance(decoded, Snapshot)
    assert decoded.velocities is not None and decoded.velocities.tolist() == [VEL]
    assert decoded.users.tolist() == [7] and decoded.capture_times.tolist() == [1.5]


def test_plain_frames_have_no_velocities() -> None:
    update = decode_message(encode_update(1, [0], [1.0], [IDENTITY]))
    assert isinstance(update, PoseUpdate)
    assert not update.has_velocities and update.velocities is None


def test_pinned_negotiation_bytes() -> None:
    """The join flags and peer_joined.velocities travel only when true."""
    join = Join(room="lab", streams=("head",), rate=20.0, sends_velocities=True)
    assert encode_message(join) == (
        b"\x87\xa4type\xa4join\xa4room\xa3lab\xa7streams\x91\xa4head\xa4rate"
        + f64(20.0)
        + b"\xa5token\xc0\xa5label\xc0\xb0sends_velocities\xc3"
    )
    both = Join(room="lab", streams=("head",), rate=20.0, wants_velocities=True)
    assert encode_message(both).endswith(b"\xa5label\xc0\xb0wants_velocities\xc3")
    assert decode_message(encode_message(both)) == both
    plain = Join(room="lab", streams=("head",), rate=20.0)
    assert b"velocities" not in encode_message(plain)
    peer = PeerJoined(user=9, streams={"head": 5}, velocities=True)
    assert encode_message(peer) == (
        b"\x85\xa4type\xabpeer_joined\xa4user\x09\xa7streams\x81\xa4head\x05\xa5label\xc0"
        b"\xaavelocities\xc3"
    )
    assert decode_message(encode_message(peer)) == peer
    # An explicit false is the default: accepted, and equal to leaving it out.
    explicit = raw_frame("peer_joined", user=9, streams={"head": 5}, velocities=False)
    assert decode_message(explicit) == PeerJoined(user=9, streams={"head": 5})


@pytest.mark.parametrize("value", [1, 0, "yes", None])
def test_negotiation_flags_must_be_bools(value: object) -> None:
    frame = raw_frame("join", room="lab", streams=["head"], rate=20.0, wants_velocities=value)
    with pytest.raises(RemoteProtocolError, match=r"join\.wants_velocities") as caught:
        decode_message(frame)
    assert caught.value.code is ErrorCode.BAD_MESSAGE


@pytest.mark.parametrize("n", [0, 1, 5, 6, 7, 40, 1400, 2000])
@pytest.mark.parametrize("kind", ["update", "snapshot"])
def test_frame_size_of_velocity_variant(n: int, kind: str) -> None:
    """frame_size(velocities=True) is exact: the plain frame + 12 B a pose (+ bin header growth)."""
    poses = np.tile(IDENTITY, (n, 1))
    vel = np.tile(VEL, (n, 1))
    if kind == "update":
        frame = encode_update(1 << 16, np.arange(n), np.ones(n), poses, velocities=vel)
        plain_entry = UPDATE_ENTRY_SIZE
    else:
        frame = encode_snapshot(
            1 << 16, 1.0, np.zeros(n, int), np.arange(n), np.ones(n), poses, vel
        )
        plain_entry = SNAPSHOT_ENTRY_SIZE
    assert len(frame) == frame_size(n, kind, velocities=True)  # type: ignore[arg-type]

    def bin_header(body: int) -> int:
        return 2 if body < 256 else 3 if body < 65536 else 5

    plain = frame_size(n, kind)  # type: ignore[arg-type]
    growth = bin_header(n * (plain_entry + 12)) - bin_header(n * plain_entry)
    assert frame_size(n, kind, velocities=True) == plain + 12 * n + growth  # type: ignore[arg-type]
    assert protocol.bytes_per_pose(max(n, 1), kind, velocities=True) > protocol.bytes_per_pose(  # type: ignore[arg-type]
        max(n, 1),
        kind,  # type: ignore[arg-type]
    )


def test_encoders_clamp_finite_velocities_to_float16() -> None:
    """Finite values beyond float16 clamp to +-65504 (65520 would round to inf); NaN stays."""
    vel = [[1e6, -1e9, 65519.0, 65520.0, -70000.0, 1e-9]]
    update = decode_message(encode_update(1, [0], [1.0], [IDENTITY], velocities=vel))
    assert isinstance(update, PoseUpdate) and update.velocities is not None
    got = update.velocities.astype(np.float64)[0]
    assert got[:5].tolist() == [65504.0, -65504.0, 65504.0, 65504.0, -65504.0]
    assert 0.0 <= got[5] < 1e-7
    assert protocol.velocity_problem(update.entries) is None
    nan = decode_message(encode_update(1, [0], [1.0], [IDENTITY], velocities=[[np.nan] + [0] * 5]))
    assert isinstance(nan, PoseUpdate)
    assert protocol.velocity_problem(nan.entries) == "non-finite velocity"


@pytest.mark.parametrize(
    "call",
    [
        lambda: encode_update(1, [0], [1.0], [IDENTITY], velocities=[[0.0] * 5]),
        lambda: encode_update(1, [0, 1], [1.0, 1.0], [IDENTITY] * 2, velocities=[[0.0] * 6]),
        lambda: encode_snapshot(1, 1.0, [0], [0], [1.0], [IDENTITY], velocities=[["a"] * 6]),
        lambda: PoseUpdate.from_arrays(1, [0], [1.0], [IDENTITY], velocities=np.zeros((1, 6, 1))),
    ],
)
def test_encoders_reject_bad_velocity_shapes(call: object) -> None:
    with pytest.raises(LocalProtocolError) as caught:
        call()  # type: ignore[operator]
    assert caught.value.code is ErrorCode.BAD_MESSAGE


def test_pack_velocity_snapshot_equals_encode_snapshot() -> None:
    """The relay's byte path builds the same velocity snapshot as the array encoder."""
    rng = np.random.default_rng(3)
    poses = np.tile(IDENTITY, (3, 1)).astype(np.float32)
    vel = rng.normal(scale=4.0, size=(3, 6)).astype(np.float16)
    caps = [9.5, 9.75, 10.0]
    want = encode_snapshot(5, 10.0, [1, 1, 2], [0, 1, 4], caps, poses, velocities=vel)
    got = protocol.pack_velocity_snapshot(
        5,
        10.0,
        [
            (u, s, c, p.tobytes(), v.tobytes())
            for u, s, c, p, v in zip([1, 1, 2], [0, 1, 4], caps, poses, vel, strict=True)
        ],
    )
    assert got == want


def test_update_records_carry_velocity_bytes() -> None:
    vel = np.array([VEL, [0.0] * 6], dtype=np.float16)
    poses = np.tile(IDENTITY, (2, 1)).astype(np.float32)
    update = decode_message(encode_update(4, [7, 8], [10.0, 10.5], poses, velocities=vel))
    assert isinstance(update, PoseUpdate)
    recs = list(protocol.update_records(update))
    assert [r[0] for r in recs] == [7, 8]
    assert [r[1] for r in recs] == [10.0, 10.5]
    assert [r[2] for r in recs] == [p.tobytes() for p in poses]
    assert [r[3] for r in recs] == [v.tobytes() for v in vel]


# -- negotiation and session rules ------------------------------------------------


def test_agreement_is_recorded_on_both_sides() -> None:
    pair = velocity_pair(sends=True, wants=False)
    assert pair.client.sends_velocities and pair.server.sends_velocities
    assert not pair.client.wants_velocities and not pair.server.wants_velocities
    plain = SessionPair()
    plain.handshake()
    assert not plain.server.sends_velocities and not plain.client.wants_velocities


def test_velocity_update_accepted_when_agreed() -> None:
    pair = velocity_pair()
    update = PoseUpdate.from_arrays(1, [0, 2], [1.0, 1.0], [IDENTITY] * 2, velocities=[VEL] * 2)
    (event,) = pair.client_send(update)
    assert isinstance(event, PoseUpdate)
    assert event.velocities is not None and event.velocities.tolist() == [VEL, VEL]


@pytest.mark.parametrize(
    "bits",
    [0x7C00, 0xFC00, 0x7E00, 0x7C01, 0xFFFF],
    ids=["inf", "-inf", "nan", "snan", "nan-neg"],
)
def test_non_finite_velocity_is_bad_velocity_and_not_fatal(bits: int) -> None:
    """A NaN/inf velocity drops that update with "bad-velocity"; the session goes on."""
    pair = velocity_pair()
    body = bytearray(
        PoseUpdate.from_arrays(1, [1], [1.0], [IDENTITY], velocities=[VEL]).entries.tobytes()
    )
    struct.pack_into("<H", body, UPDATE_ENTRY_SIZE + 2 * 4, bits)  # 5th velocity number
    (event,) = pair.server.receive_data(raw_frame("update", seq=1, time=1.0, vpose=bytes(body)))
    assert isinstance(event, ProtocolError)
    assert event.code is ErrorCode.BAD_VELOCITY and not event.fatal
    assert event.message == "non-finite velocity"
    assert pair.server.state is State.JOINED
    (ok,) = pair.server.receive_data(
        encode_update(2, [1], [1.1], [IDENTITY], velocities=[VEL]),
    )
    assert isinstance(ok, PoseUpdate)


def test_client_refuses_to_send_non_finite_velocity() -> None:
    pair = velocity_pair()
    update = PoseUpdate.from_arrays(1, [0], [1.0], [IDENTITY], velocities=[[np.inf] + [0] * 5])
    with pytest.raises(LocalProtocolError) as caught:
        pair.client.send(update)
    assert caught.value.code is ErrorCode.BAD_VELOCITY


def test_bad_pose_wins_over_bad_velocity() -> None:
    """A velocity record with a broken quaternion is reported as bad-pose."""
    pair = velocity_pair()
    frame = encode_update(1, [0], [1.0], [[0, 0, 0, 2, 0, 0, 0]], velocities=[[np.nan] * 6])
    (event,) = pair.server.receive_data(frame)
    assert isinstance(event, ProtocolError) and event.code is ErrorCode.BAD_POSE


@pytest.mark.parametrize(
    ("sends", "velocities", "message"),
    [
        (False, True, "update with velocities, not agreed at join"),
        (True, False, "update without velocities, agreed at join"),
    ],
)
def test_update_of_the_other_variant_is_fatal(sends: bool, velocities: bool, message: str) -> None:
    pair = velocity_pair(sends=sends)
    vel = [VEL] if velocities else None
    (event,) = pair.server.receive_data(encode_update(1, [0], [1.0], [IDENTITY], velocities=vel))
    assert isinstance(event, ProtocolError)
    assert event.code is ErrorCode.BAD_MESSAGE and event.fatal
    assert event.message == message
    assert pair.server.closed


@pytest.mark.parametrize(
    ("frame", "message"),
    [
        (raw_frame("update", seq=1, time=1.0, vpose=b"\x00" * 45), "whole 46-byte records"),
        (raw_frame("update", seq=1, time=1.0, vpose=b"\x00" * 34), "whole 46-byte records"),
        (raw_frame("snapshot", tick=1, time=1.0, vpose=b"\x00" * 36), "whole 48-byte records"),
        (raw_frame("update", seq=1, time=1.0, vpose="text"), "update.vpose must be bin"),
        (raw_frame("update", seq=1, time=1.0, vpose=b"", poses=b""), "needs exactly"),
        (raw_frame("snapshot", tick=1, time=1.0, vpose=None), "snapshot.vpose must be bin"),
    ],
)
def test_malformed_velocity_frames(frame: bytes, message: str) -> None:
    with pytest.raises(RemoteProtocolError, match=message) as caught:
        decode_message(frame)
    assert caught.value.code is ErrorCode.BAD_MESSAGE
    pair = velocity_pair()
    (event,) = pair.server.receive_data(frame) or pair.client.receive_data(frame)
    assert isinstance(event, ProtocolError) and event.code is ErrorCode.BAD_MESSAGE


def test_client_checks_snapshot_variant_and_velocities() -> None:
    vel_snap = encode_snapshot(1, 2.0, [2], [5], [1.9], [IDENTITY], velocities=[VEL])
    plain_snap = encode_snapshot(1, 2.0, [2], [5], [1.9], [IDENTITY])
    (event,) = velocity_pair(wants=True).client.receive_data(vel_snap)
    assert isinstance(event, Snapshot) and event.velocities is not None
    (event,) = velocity_pair(wants=True).client.receive_data(plain_snap)
    assert isinstance(event, ProtocolError) and event.code is ErrorCode.BAD_MESSAGE
    (event,) = velocity_pair(wants=False).client.receive_data(vel_snap)
    assert isinstance(event, ProtocolError) and event.code is ErrorCode.BAD_MESSAGE
    assert "not agreed" in event.message
    client = velocity_pair(wants=True).client
    bad = encode_snapshot(1, 2.0, [2], [5], [1.9], [IDENTITY], velocities=[[0, 0, np.inf, 0, 0, 0]])
    (event,) = client.receive_data(bad)
    assert isinstance(event, ProtocolError) and event.code is ErrorCode.BAD_VELOCITY
    assert client.state is State.JOINED


# -- properties -------------------------------------------------------------------

finite32 = st.floats(-1e4, 1e4, width=32)
any_finite = st.floats(-1e12, 1e12, allow_nan=False, allow_infinity=False)


@FUZZ
@given(
    arrays(np.float64, st.tuples(st.integers(0, 12), st.just(7)), elements=finite32),
    st.data(),
)
def test_velocity_snapshot_round_trip_property(poses: np.ndarray, data: st.DataObject) -> None:
    """Any finite velocities decode to their float16 rounding, clamped to +-65504."""
    n = len(poses)
    vel = data.draw(arrays(np.float64, (n, 6), elements=any_finite))
    frame = encode_snapshot(7, 100.0, np.arange(n) % 3, np.arange(n), np.full(n, 99.5), poses, vel)
    decoded = decode_message(frame)
    assert isinstance(decoded, Snapshot) and decoded.velocities is not None
    np.testing.assert_array_equal(decoded.poses, poses.astype(np.float32))
    want = np.clip(vel, -VELOCITY_MAX, VELOCITY_MAX).astype(np.float16)
    np.testing.assert_array_equal(decoded.velocities, want)
    assert np.isfinite(decoded.velocities).all()
    # frame_size counts a 32-bit tick (5 bytes); tick 7 packs in 1.
    assert len(frame) == frame_size(n, "snapshot", velocities=True) - 4


@FUZZ
@given(
    st.integers(min_value=0, max_value=6).flatmap(
        lambda n: st.binary(
            min_size=n * UPDATE_VELOCITY_ENTRY_SIZE, max_size=n * UPDATE_VELOCITY_ENTRY_SIZE
        )
    )
)
def test_random_velocity_records_never_raise(body: bytes) -> None:
    """Random velocity records give a PoseUpdate with finite velocities or a ProtocolError."""
    pair = velocity_pair()
    (event,) = pair.server.receive_data(raw_frame("update", seq=1, time=0.0, vpose=body))
    assert isinstance(event, PoseUpdate | ProtocolError)
    if isinstance(event, PoseUpdate):
        assert event.velocities is not None
        assert np.isfinite(event.velocities.astype(np.float64)).all()
        assert set(event.streams.tolist()) <= {0, 1, 2}
    else:
        assert event.code in (
            ErrorCode.BAD_POSE,
            ErrorCode.BAD_VELOCITY,
            ErrorCode.STREAM_NOT_OWNED,
            ErrorCode.DUPLICATE_STREAM,
            ErrorCode.TOO_MANY_STREAMS,
        )
