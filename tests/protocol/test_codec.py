"""The compact pose codec: exact bytes, round trips (hypothesis), baselines, hostile input."""

from __future__ import annotations

import math
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from posecast.protocol import ErrorCode, LocalProtocolError, RemoteProtocolError
from posecast.protocol.bits import BitReader, BitWriter, best_k, bit_length, unzz, zz
from posecast.protocol.codec import (
    DEFAULT_VOLUME,
    ROTATION_ERROR_MAX_DEG,
    BaselineMismatch,
    Volume,
    decode_snapshot,
    decode_update,
    dequantise,
    encode_delta_snapshot,
    encode_key_snapshot,
    encode_update,
    quantise,
)

FAST = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
V = DEFAULT_VOLUME
SMALL = Volume((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))  # 11 bits per axis


def angle_deg(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    sign = np.where(np.einsum("ij,ij->i", a, b) < 0.0, -1.0, 1.0)
    chord = np.linalg.norm(a - sign[:, None] * b, axis=1)
    return np.degrees(4.0 * np.arcsin(np.clip(chord / 2.0, 0.0, 1.0)))


IDENTITY = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0]

# ------------------------------------------------------------------ exact bytes


def test_key_snapshot_exact_bytes() -> None:
    # One pose: user 1, stream 0, identity at the volume's origin, captured 2 ms
    # before the base time 1.5 s, in the unit-cube volume (11 bits per axis).
    enc = encode_key_snapshot(7, 1.5, [1], [0], [1.498], [IDENTITY], SMALL)
    # magic, flags (version 1, class split), tick 7, base 1_500_000 us (zigzag
    # LEB128), n_key 1, n_delta 0, nibbles: t_first k = 2 and a zero pad
    header = bytes([0xC1, 0x14, 7, 0xC0, 0x8D, 0xB7, 0x01, 1, 0, 0x20])
    # bits: ug 1 '01', sg 0 '1', t_first zigzag(2) = 4 at k 2 '01' '00', idx 0
    # '00', a, b, c = 0 + 4095 in 13 bits each, x, y, z = 0 in 11 bits each
    bits = "01" + "1" + "01" + "00" + "00" + "0111111111111" * 3 + "0" * 33
    bits += "0" * (-len(bits) % 8)
    assert enc.data == header + int(bits, 2).to_bytes(len(bits) // 8, "big")
    assert len(enc.data) == 21
    frame = decode_snapshot(enc.data, SMALL)
    assert frame.number == 7 and frame.base_time == 1.5
    assert frame.users.tolist() == [1] and frame.streams.tolist() == [0]
    assert frame.capture_times.tolist() == [1.5 - 0.002]
    assert frame.poses.tolist() == [IDENTITY]


def test_delta_unchanged_pose_exact_bytes() -> None:
    key = encode_key_snapshot(1, 2.0, [3], [1], [2.0], [IDENTITY], SMALL)
    baselines: dict[tuple[int, int], NDArray[np.int64]] = {}
    key.frame.remember(baselines)
    enc = encode_delta_snapshot(2, 2.0, [3], [1], [2.0], [IDENTITY], SMALL, baselines)
    crc = zlib.crc32(np.array([0, 0, 0, 0, 0, 0, 0], "<i4").tobytes())
    header = bytes([0xC1, 0x14, 2, 0x80, 0x92, 0xF4, 0x01, 0, 1]) + crc.to_bytes(4, "little")
    header += bytes(3)  # nibbles t_first, rot0, rot1, pos0, pos1 = 0, and a pad
    # ug 3 '0011', sg 1 '01', t 0 '1', idx change 0 '1', 3 rotation and 3
    # position differences of 0 (class 1: a hand) '1' each
    bits = "0011" + "01" + "1" + "1" + "111" + "111"
    bits += "0" * (-len(bits) % 8)
    assert enc.data == header + int(bits, 2).to_bytes(len(bits) // 8, "big")
    frame = decode_snapshot(enc.data, SMALL, baselines)
    assert frame.poses.tolist() == [IDENTITY] and frame.delta.tolist() == [True]


def test_bitwriter_reader_columns() -> None:
    w = BitWriter()
    vals = np.array([0, 1, 2, 3, 1000, 7], np.int64)
    own = np.arange(6)
    w.exp_golomb(vals, 0, own)
    w.exp_golomb(vals, 3, own)
    w.fixed(np.array([5, 0, 1]), 3, own[:3])
    r = BitReader(w.getvalue())
    assert r.exp_golomb(6, 0).tolist() == vals.tolist()
    assert r.exp_golomb(6, 3).tolist() == vals.tolist()
    assert r.fixed(3, 3).tolist() == [5, 0, 1]
    r.finish()
    assert w.bits_per_owner(6).sum() == len(w.getvalue()) * 8 - (-w.bits_per_owner(6).sum() % 8)


# ------------------------------------------------------------------ round trips

unit = st.floats(-1.0, 1.0, allow_nan=False)


@st.composite
def quaternions(draw: st.DrawFn) -> list[float]:
    kind = draw(st.sampled_from(["any", "tiny", "half-turn", "axis"]))
    if kind == "axis":
        q = [0.0] * 4
        q[draw(st.integers(0, 3))] = draw(st.sampled_from([1.0, -1.0]))
        return q
    v = [draw(unit) for _ in range(4)]
    if kind == "tiny":
        v = [1.0, v[1] * 1e-4, v[2] * 1e-4, v[3] * 1e-4]
    elif kind == "half-turn":
        v = [v[0] * 1e-4, v[1], v[2], v[3] + 0.1]
    norm = math.sqrt(sum(x * x for x in v))
    if norm < 1e-3:
        return [1.0, 0.0, 0.0, 0.0]
    return [x / norm for x in v]


@st.composite
def positions(draw: st.DrawFn) -> list[float]:
    out = []
    for lo, hi in zip(V.lo, V.hi, strict=True):
        out.append(draw(st.one_of(st.floats(lo, hi), st.sampled_from([lo, hi]))))
    return out


poses = st.builds(lambda p, q: p + q, positions(), quaternions())


@FAST
@given(st.lists(poses, min_size=1, max_size=12), st.booleans())
def test_round_trip_exact_and_within_bounds(items: list[list[float]], negate: bool) -> None:
    x = np.array(items)
    if negate:  # q and -q are the same rotation and quantise alike
        x[:, 3:] *= -1
    n = len(x)
    users = np.arange(n) // 3
    streams = np.arange(n) % 3
    times = 5.0 - np.arange(n) * 0.0123
    codes = quantise(x, V)
    key = encode_key_snapshot(1, 5.0, users, streams, times, x, V)
    frame = decode_snapshot(key.data, V)
    assert np.array_equal(frame.codes, codes)
    expected, _ = dequantise(codes, V)
    assert frame.poses.tobytes() == expected.tobytes()
    assert np.abs(frame.poses[:, :3] - x[:, :3]).max() <= max(V.step) / 2 + 1e-6
    assert (
        angle_deg(frame.poses[:, 3:].astype(float), x[:, 3:]).max() <= ROTATION_ERROR_MAX_DEG + 1e-4
    )
    assert np.abs(frame.capture_times - times).max() <= 0.0005 + 1e-9
    # A delta against itself and against a rotated copy decodes to the same codes.
    baselines: dict[tuple[int, int], NDArray[np.int64]] = {}
    key.frame.remember(baselines)
    y = x.copy()
    y[:, 3:] = np.roll(x[:, 3:], 1, axis=0)
    for target in (x, y):
        enc = encode_delta_snapshot(2, 5.0, users, streams, times, target, V, baselines)
        got = decode_snapshot(enc.data, V, baselines)
        assert np.array_equal(got.codes, quantise(target, V))
        assert got.delta.all()


def test_negated_quaternion_same_codes() -> None:
    rng = np.random.default_rng(1)
    q = rng.normal(size=(500, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    x = np.concatenate([np.zeros((500, 3)), q], axis=1)
    y = x.copy()
    y[:, 3:] *= -1
    assert np.array_equal(quantise(x, V), quantise(y, V))


def test_rotation_error_bound_worst_case() -> None:
    # Many random quaternions plus the worst family (three equal small components).
    rng = np.random.default_rng(2)
    q = rng.normal(size=(200_000, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    x = np.concatenate([np.zeros((len(q), 3)), q], axis=1)
    got, _ = dequantise(quantise(x, V), V)
    assert angle_deg(got[:, 3:].astype(float), q).max() <= ROTATION_ERROR_MAX_DEG
    assert ROTATION_ERROR_MAX_DEG <= 0.05


def test_update_round_trip_with_velocity() -> None:
    rng = np.random.default_rng(3)
    x = np.tile(np.array([[0.1, 1.6, -0.2, 1.0, 0.0, 0.0, 0.0]]), (3, 1))
    vel = rng.normal(size=(3, 6))
    enc = encode_update(4, 10.0, [0, 1, 2], [9.99, 9.99, 9.98], x, V, velocities=vel)
    got = decode_update(enc.data, V)
    assert got.velocities is not None
    assert np.abs(got.velocities[:, :3] - vel[:, :3]).max() <= 2.0**-10 + 1e-6
    assert np.abs(got.velocities[:, 3:] - vel[:, 3:]).max() <= 2.0**-9 + 1e-6
    base: dict[int, NDArray[np.int64]] = {}
    enc.frame.remember(base)
    enc2 = encode_update(5, 10.03, [0, 1, 2], [10.02] * 3, x, V, base, vel * 1.01)
    got2 = decode_update(enc2.data, V, base)
    assert np.array_equal(got2.codes, quantise(x, V, vel * 1.01))
    assert len(enc2.data) < len(enc.data)


# ------------------------------------------------------------------ refusals


def test_position_outside_volume_refused() -> None:
    x = [[8.01, 1.0, 0.0, *IDENTITY[3:]]]
    with pytest.raises(LocalProtocolError) as info:
        encode_key_snapshot(0, 0.0, [1], [0], [0.0], x, V)
    assert info.value.code == ErrorCode.BAD_POSE
    assert "outside the room volume" in info.value.message


@pytest.mark.parametrize(
    ("pose", "code"),
    [
        ([0.0, 0.0, math.nan, 1.0, 0.0, 0.0, 0.0], ErrorCode.BAD_POSE),
        ([0.0, 0.0, 0.0, 0.9, 0.0, 0.0, 0.0], ErrorCode.BAD_POSE),
    ],
)
def test_bad_poses_refused(pose: list[float], code: ErrorCode) -> None:
    with pytest.raises(LocalProtocolError) as info:
        quantise([pose], V)
    assert info.value.code == code


def test_nan_velocity_refused() -> None:
    with pytest.raises(LocalProtocolError) as info:
        quantise([IDENTITY], V, [[math.nan, 0, 0, 0, 0, 0]])
    assert info.value.code == ErrorCode.BAD_VELOCITY


def test_duplicate_stream_refused() -> None:
    with pytest.raises(LocalProtocolError) as info:
        encode_key_snapshot(0, 0.0, [1, 1], [0, 0], [0.0, 0.0], [IDENTITY, IDENTITY], V)
    assert info.value.code == ErrorCode.DUPLICATE_STREAM


def _delta_frame() -> tuple[bytes, dict[tuple[int, int], NDArray[np.int64]]]:
    x = np.array([IDENTITY, [0.1, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0]])
    key = encode_key_snapshot(1, 1.0, [1, 1], [0, 1], [1.0, 1.0], x, V)
    baselines: dict[tuple[int, int], NDArray[np.int64]] = {}
    key.frame.remember(baselines)
    x[:, 0] += 0.01
    return encode_delta_snapshot(
        2, 1.03, [1, 1], [0, 1], [1.03, 1.03], x, V, baselines
    ).data, baselines


def test_delta_without_baseline_refused() -> None:
    data, baselines = _delta_frame()
    with pytest.raises(BaselineMismatch) as info:
        decode_snapshot(data, V, {})
    assert info.value.code == ErrorCode.BAD_BASELINE
    del baselines[(1, 1)]
    with pytest.raises(RemoteProtocolError):
        decode_snapshot(data, V, baselines)


def test_delta_with_other_baseline_refused() -> None:
    data, baselines = _delta_frame()
    other = dict(baselines)
    row = other[(1, 1)].copy()
    row[4] += 1  # half a millimetre elsewhere
    other[(1, 1)] = row
    with pytest.raises(BaselineMismatch, match="CRC"):
        decode_snapshot(data, V, other)


def test_kind_mismatch_refused() -> None:
    data = encode_update(0, 0.0, [0], [0.0], [IDENTITY], V).data
    with pytest.raises(RemoteProtocolError) as info:
        decode_snapshot(data, V)
    assert info.value.code == ErrorCode.BAD_MESSAGE


# ------------------------------------------------------------------ hostile input


def _check_decode(data: bytes, baselines: dict[tuple[int, int], NDArray[np.int64]]) -> None:
    try:
        frame = decode_snapshot(data, V, baselines)
    except RemoteProtocolError as exc:
        assert isinstance(exc.code, ErrorCode)
        return
    # Whatever decodes is valid: codes in range, poses unit and inside the volume.
    assert len(frame) <= 8 * len(data)
    if len(frame):
        q = frame.poses[:, 3:].astype(float)
        assert np.allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-5)
        assert (frame.poses[:, :3] >= np.array(V.lo) - 1e-3).all()


@FAST
@given(st.binary(max_size=200))
def test_fuzz_random_bytes(data: bytes) -> None:
    _check_decode(data, {})
    _check_decode(b"\xc1\x14" + data, {})


@FAST
@given(st.data())
def test_fuzz_mutated_frames(draw: st.DataObject) -> None:
    data, baselines = _delta_frame()
    key = encode_key_snapshot(1, 1.0, [1, 2], [0, 5], [1.0, 0.9], [IDENTITY, IDENTITY], V).data
    frame = bytearray(draw.draw(st.sampled_from([data, key])))
    for _ in range(draw.draw(st.integers(1, 4))):
        i = draw.draw(st.integers(0, len(frame) - 1))
        frame[i] = draw.draw(st.integers(0, 255))
    cut = draw.draw(st.integers(0, len(frame) + 2))
    mutated = bytes(frame[:cut]) + draw.draw(st.binary(max_size=3))
    _check_decode(mutated, baselines)
    with pytest.raises(RemoteProtocolError):
        decode_snapshot(data + b"\x00", V, baselines)


def test_huge_counts_refused_without_allocating() -> None:
    # n_key = 2**60 in a 20-byte frame: refused from the header alone.
    data = bytes([0xC1, 0x14, 0, 0]) + b"\x80" * 8 + b"\x10" + b"\x00" + b"\x00" * 6
    with pytest.raises(RemoteProtocolError) as info:
        decode_snapshot(data, V)
    assert info.value.code == ErrorCode.BAD_FRAME


# ------------------------------------------------------------------ fast and long paths


@FAST
@given(
    st.lists(st.integers(0, 2**40 - 1), min_size=1, max_size=40),
    st.integers(0, 15),
    st.integers(1, 40),
)
def test_small_and_long_bit_paths_agree(values: list[int], k: int, copies: int) -> None:
    """Short columns use Python ints, long ones numpy: same bits, same values back."""
    column = np.array(values * copies, np.int64)
    own = np.zeros(column.size, np.int64)
    w = BitWriter()
    w.exp_golomb(column, k, own)
    w.fixed(column & 0x1FFF, 13, own)
    packed = w.getvalue()
    assert packed == w._getvalue_numpy()
    for small in (True, False):
        r = BitReader(packed)
        if small:
            got = np.concatenate([r.exp_golomb(column.size, k), r.fixed(column.size, 13)])
        else:
            got = np.concatenate([r._exp_golomb_numpy(column.size, k), np.zeros(0, np.int64)])
            got = np.concatenate([got, _numpy_fixed(r, column.size, 13)])
        assert got.tolist() == column.tolist() + (column & 0x1FFF).tolist()
        r.finish()


def _numpy_fixed(r: BitReader, n: int, width: int) -> NDArray[np.int64]:
    chunk = r._bits[r.pos : r.pos + n * width].reshape(n, width).astype(np.int64)
    r.pos += n * width
    return chunk @ (np.int64(1) << np.arange(width - 1, -1, -1, dtype=np.int64))


@FAST
@given(st.lists(st.integers(0, 2**47), min_size=1, max_size=300))
def test_best_k_small_matches_the_vectorised_search(values: list[int]) -> None:
    v = np.array(values, np.int64)
    lengths = bit_length(v[None, :] >> np.arange(16)[:, None])
    costs = (2 * lengths + (lengths == 0)).sum(axis=1) + np.arange(16) * v.size
    assert best_k(v) == (int(np.argmin(costs)), int(costs.min()))


def test_big_frame_round_trip_takes_the_long_paths() -> None:
    """A 600-pose frame (columns over bits.SMALL) round-trips like a small one."""
    rng = np.random.default_rng(7)
    n = 600
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    x = np.concatenate([rng.uniform(-1, 1, (n, 3)), q], axis=1)
    users, streams = np.arange(n) // 3, np.arange(n) % 3
    key = encode_key_snapshot(1, 5.0, users, streams, [4.99] * n, x, V)
    baselines: dict[tuple[int, int], NDArray[np.int64]] = {}
    key.frame.remember(baselines)
    x[:, :3] += 0.003
    enc = encode_delta_snapshot(2, 5.03, users, streams, [5.0] * n, x, V, baselines)
    got = decode_snapshot(enc.data, V, baselines)
    assert np.array_equal(got.codes, quantise(x, V))
    assert np.array_equal(decode_snapshot(key.data, V).codes, key.frame.codes)


def test_zigzag_round_trips_the_whole_int64_range() -> None:
    """``zz``/``unzz`` on Python ints, int64 arrays (codes under 2**63, which every
    frame field is) and the recorder's uint64 views of the codes, where every int64
    comes back exactly, the ends included (an arithmetic shift on a code >= 2**63
    would keep the sign)."""
    assert [zz(v) for v in (0, -1, 1, -2, 2)] == [0, 1, 2, 3, 4]
    assert [unzz(zz(v)) for v in (-(2**63), 2**63 - 1, -5)] == [-(2**63), 2**63 - 1, -5]
    rng = np.random.default_rng(27)
    small = rng.integers(-(2**62), 2**62 - 1, 10_000, dtype=np.int64, endpoint=True)
    assert (unzz(zz(small)) == small).all()
    v = rng.integers(-(2**63), 2**63 - 1, 10_000, dtype=np.int64, endpoint=True)
    v[:3] = [-(2**63), 2**63 - 1, 0]
    codes = zz(v).view(np.uint64)
    assert int(codes[0]) == 2**64 - 1 and int(codes[1]) == 2**64 - 2
    assert (unzz(codes).view(np.int64) == v).all()
