"""Relay snapshots (codec version 2): round trips, splicing, exact bytes, hostile input."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from posecast.protocol import ErrorCode, RemoteProtocolError
from posecast.protocol.codec import DEFAULT_VOLUME, BaselineMismatch, quantise
from posecast.protocol.codec_relay import RelayEntry, decode_relay_snapshot, encode_group

FAST = settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
V = DEFAULT_VOLUME
Row = list[int]


def _poses(
    n: int, rng: np.random.Generator, near: NDArray[np.float64] | None = None
) -> NDArray[np.float64]:
    if near is None:
        q = rng.normal(size=(n, 4))
        p = rng.uniform(-7.9, 7.9, size=(n, 3)) * np.array([1.0, 0.35, 1.0]) + [0.0, 1.0, 0.0]
    else:
        q = near[:, 3:] + rng.normal(0.0, 0.03, size=(n, 4))
        p = np.clip(near[:, :3] + rng.normal(0.0, 0.01, size=(n, 3)), -7.9, 3.9)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.concatenate([p, q], axis=1)


def _frame_inputs(
    seed: int, users: int, velocity: bool, delta_share: float
) -> tuple[list[RelayEntry], dict[tuple[int, int], Row]]:
    rng = np.random.default_rng(seed)
    n = 3 * users
    base = _poses(n, rng)
    now = _poses(n, rng, base)
    vel = rng.normal(0.0, 2.0, size=(n, 6)) if velocity else None
    base_codes = quantise(base, V, vel).tolist()
    codes = quantise(now, V, vel).tolist()
    ids = [(u * 7 + 2, u * 3 + j) for u in range(users) for j in range(3)]
    entries: list[RelayEntry] = []
    held: dict[tuple[int, int], Row] = {}
    for i, (u, s) in enumerate(ids):
        delta = rng.random() < delta_share
        t = 100.0 - float(rng.integers(0, 300)) / 1000.0
        entries.append((u, s, t, codes[i], base_codes[i] if delta else None))
        held[(u, s)] = base_codes[i]
    return entries, held


@FAST
@given(
    seed=st.integers(0, 2**32 - 1),
    users=st.integers(1, 12),
    velocity=st.booleans(),
    delta_share=st.sampled_from([0.0, 0.5, 1.0]),
)
def test_every_subscriber_decodes_exactly_its_share(
    seed: int, users: int, velocity: bool, delta_share: float
) -> None:
    """decode(frame(exclude)) gives every other user's codes exactly, times to 0.5 ms."""
    entries, held = _frame_inputs(seed, users, velocity, delta_share)
    group = encode_group(7, 100.0, entries, V, velocity)
    for exclude in [None, *sorted({e[0] for e in entries})]:
        data, n = group.frame(exclude)
        want = sorted((e for e in entries if e[0] != exclude), key=lambda e: (e[0], e[1]))
        assert n == len(want)
        if not want:
            assert data == b""
            continue
        snap = decode_relay_snapshot(data, V, held)
        assert snap.tick == 7 and snap.base_time == 100.0
        assert list(zip(snap.users, snap.streams, strict=True)) == [(e[0], e[1]) for e in want]
        assert snap.codes == [e[3] for e in want]
        assert max(abs(t - e[2]) for t, e in zip(snap.capture_times, want, strict=True)) <= 5e-4


def test_near_half_turn_and_sign_and_volume_bounds() -> None:
    """Rotations near 180 degrees, q vs -q, positions on the volume's faces."""
    lo, hi = V.lo, V.hi
    poses = np.array(
        [
            [lo[0], lo[1], lo[2], 0.0, 1.0, 0.0, 0.0],
            [hi[0], hi[1], hi[2], 1e-4, -1.0, 0.0, 0.0],
            [0.0, 0.0, 0.0, -0.5, -0.5, -0.5, -0.5],
            [0.0, 0.0, 0.0, 0.5, 0.5, 0.5, 0.5],
        ]
    )
    poses[:, 3:] /= np.linalg.norm(poses[:, 3:], axis=1, keepdims=True)
    codes = quantise(poses, V).tolist()
    flipped = quantise(np.concatenate([poses[:, :3], -poses[:, 3:]], axis=1), V).tolist()
    assert codes == flipped
    entries: list[RelayEntry] = [(1, i, 5.0, codes[i], codes[(i + 1) % 4]) for i in range(4)]
    held = {(1, i): codes[(i + 1) % 4] for i in range(4)}
    data, _ = encode_group(1, 5.0, entries, V).frame()
    assert decode_relay_snapshot(data, V, held).codes == codes


def test_exact_bytes() -> None:
    """The layout is a contract: these bytes must not change by accident."""
    entries, _ = _frame_inputs(3, 4, False, 0.5)
    group = encode_group(12345, 100.25, entries, V)
    frames = [group.frame(x)[0] for x in (None, 2, 9)]
    digest = hashlib.sha256(b"".join(frames)).hexdigest()[:16]
    assert [len(f) for f in frames] == EXACT_SIZES
    assert digest == EXACT_DIGEST
    assert frames[0][:2] == bytes([0xC1, 0x24])  # magic; version 2, class split


EXACT_SIZES = [147, 120, 118]
EXACT_DIGEST = "4713a645ae836e9f"


def test_a_wrong_or_missing_baseline_is_bad_baseline() -> None:
    entries, held = _frame_inputs(5, 3, False, 1.0)
    data, _ = encode_group(1, 100.0, entries, V).frame()
    other = dict(held)
    key = next(iter(other))
    other[key] = [*other[key][:4], other[key][4] + 1, *other[key][5:]]
    for baselines in ({}, other):
        with pytest.raises(BaselineMismatch) as info:
            decode_relay_snapshot(data, V, baselines)
        assert info.value.code is ErrorCode.BAD_BASELINE


def _corpus() -> list[tuple[bytes, dict[tuple[int, int], Row]]]:
    out = []
    for seed, users, velocity, share in [(1, 1, False, 0.0), (2, 5, False, 0.5), (3, 4, True, 1.0)]:
        entries, held = _frame_inputs(seed, users, velocity, share)
        out.append((encode_group(9, 100.0, entries, V, velocity).frame()[0], held))
    return out


def _decodes_or_refuses(data: bytes, held: dict[tuple[int, int], Row]) -> None:
    try:
        snap = decode_relay_snapshot(data, V, held)
    except RemoteProtocolError as exc:
        assert isinstance(exc.code, ErrorCode)
        return
    assert len(snap) > 0 and all(0 <= u <= 0xFFFF for u in snap.users)


def test_every_truncation_is_refused_and_every_bit_flip_is_safe() -> None:
    for data, held in _corpus():
        for cut in range(len(data)):
            with pytest.raises(RemoteProtocolError):
                decode_relay_snapshot(data[:cut], V, held)
        for bit in range(8 * len(data)):
            flipped = bytearray(data)
            flipped[bit // 8] ^= 0x80 >> (bit % 8)
            _decodes_or_refuses(bytes(flipped), held)


@FAST
@given(st.binary(max_size=400), st.sampled_from([0x04, 0x06, 0x24, 0x26, 0x25, 0x2F]))
def test_arbitrary_bytes_behind_every_flags_byte(body: bytes, flags: int) -> None:
    held = _corpus()[1][1]
    _decodes_or_refuses(bytes([0xC1, flags]) + body, held)


def test_huge_counts_are_refused_from_the_header() -> None:
    data = bytes([0xC1, 0x24, 1, 2]) + bytes([0xFF, 0xFF, 0xFF, 0x7F, 0])
    with pytest.raises(RemoteProtocolError) as info:
        decode_relay_snapshot(data + bytes(8), V, {})
    assert info.value.code is ErrorCode.BAD_FRAME
