"""Hostile input for the compact codec: every frame kind and variant, fuzzed.

Arbitrary bytes, truncations, bit flips and byte mutations of valid snapshots and
updates (plain and velocity, key and delta) either decode to a valid frame or
raise ``RemoteProtocolError`` with an ``ErrorCode``, nothing else; and a decoder
never allocates much more than the frame's size (a count of 10**9 entries is
refused from the header).
"""

from __future__ import annotations

import tracemalloc
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from posecast.protocol import ErrorCode, RemoteProtocolError
from posecast.protocol.codec import (
    DEFAULT_VOLUME,
    PoseFrame,
    decode_snapshot,
    decode_update,
    encode_snapshot_codes,
    encode_update,
    encode_update_codes,
    quantise,
)
from posecast.protocol.codec_quant import codes_problem

FAST = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
V = DEFAULT_VOLUME
I64 = NDArray[np.int64]
Decoder = Callable[[bytes, Mapping[Any, I64]], PoseFrame]


def _snapshot(data: bytes, baselines: Mapping[Any, I64]) -> PoseFrame:
    return decode_snapshot(data, V, baselines)


def _update(data: bytes, baselines: Mapping[Any, I64]) -> PoseFrame:
    return decode_update(data, V, baselines)


def _poses(n: int, seed: int) -> NDArray[np.float64]:
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    p = rng.uniform(-1.0, 1.0, size=(n, 3)) + np.array([0.0, 1.5, 0.0])
    return np.concatenate([p, q], axis=1)


def _corpus() -> dict[str, tuple[bytes, Decoder, dict[Any, I64]]]:
    """Valid frames of every kind: name -> (bytes, decoder, baselines it needs)."""
    out: dict[str, tuple[bytes, Decoder, dict[Any, I64]]] = {}
    users = np.array([1, 1, 1, 4, 4])
    streams = np.array([0, 1, 2, 0, 2])
    for velocity in (False, True):
        tag = "velocity " if velocity else ""
        vel0 = np.random.default_rng(5).normal(size=(5, 6)) if velocity else None
        vel1 = None if vel0 is None else vel0 * 1.1
        c0 = quantise(_poses(5, 1), V, vel0)
        moved = _poses(5, 1)
        moved[:, :3] += 0.004
        c1 = quantise(moved, V, vel1)
        for split in (True, False):
            name = f"{tag}snapshot{'' if split else ' no-split'}"
            key = encode_snapshot_codes(3, 2.0, users, streams, [1.99] * 5, c0, V, split=split)
            base: dict[Any, I64] = {}
            key.frame.remember(base)
            out[f"{name} key"] = (key.data, _snapshot, {})
            # Mixed: four deltas and one new stream (key section and delta section).
            del base[(4, 2)]
            delta = encode_snapshot_codes(
                4, 2.033, users, streams, [2.02] * 5, c1, V, base, split=split
            )
            out[f"{name} delta"] = (delta.data, _snapshot, base)
        ukey = encode_update_codes(9, 2.0, [0, 1, 2], [1.99, 1.99, 1.98], c0[:3], V)
        ubase: dict[Any, I64] = {}
        ukey.frame.remember(ubase)
        udelta = encode_update_codes(10, 2.011, [0, 1, 2], [2.0] * 3, c1[:3], V, ubase)
        out[f"{tag}update key"] = (ukey.data, _update, {})
        out[f"{tag}update delta"] = (udelta.data, _update, ubase)
    return out


CORPUS = _corpus()
NAMES = sorted(CORPUS)


def _check_valid(frame: PoseFrame, data: bytes) -> None:
    """Whatever decodes is a valid frame: ids, codes, times and order all in range."""
    n = len(frame)
    assert n <= 8 * len(data) // 9
    assert frame.users.shape == frame.streams.shape == frame.capture_times.shape == (n,)
    if not n:
        return
    assert codes_problem(frame.codes, V) is None
    assert int(frame.users.min()) >= 0 and int(frame.users.max()) <= 0xFFFF
    assert int(frame.streams.min()) >= 0 and int(frame.streams.max()) <= 0xFFFF
    key = (frame.users << 16) | frame.streams
    assert bool((np.diff(key) > 0).all())
    assert np.isfinite(frame.capture_times).all()
    q = frame.poses[:, 3:].astype(float)
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-5)
    assert (frame.poses[:, :3] >= np.array(V.lo) - 1e-3).all()
    assert (frame.poses[:, :3] <= np.array(V.hi) + 1e-3).all()


def _decode_or_refuse(decode: Decoder, data: bytes, baselines: Mapping[Any, I64]) -> bool:
    """True if ``data`` decoded (to a valid frame), False if refused with a code."""
    try:
        frame = decode(data, baselines)
    except RemoteProtocolError as exc:
        assert isinstance(exc.code, ErrorCode)
        assert isinstance(exc.message, str) and exc.message
        return False
    _check_valid(frame, data)
    return True


@pytest.mark.parametrize("name", NAMES)
def test_corpus_decodes(name: str) -> None:
    data, decode, baselines = CORPUS[name]
    assert _decode_or_refuse(decode, data, baselines)


@pytest.mark.parametrize("name", NAMES)
def test_every_truncation_refused(name: str) -> None:
    data, decode, baselines = CORPUS[name]
    for cut in range(len(data)):
        with pytest.raises(RemoteProtocolError) as info:
            decode(data[:cut], baselines)
        assert isinstance(info.value.code, ErrorCode)
    for extra in (b"\x00", b"\x80", b"\x00\x00"):
        with pytest.raises(RemoteProtocolError):
            decode(data + extra, baselines)


@pytest.mark.parametrize("name", NAMES)
def test_every_bit_flip(name: str) -> None:
    data, decode, baselines = CORPUS[name]
    decoded = 0
    for bit in range(8 * len(data)):
        flipped = bytearray(data)
        flipped[bit // 8] ^= 0x80 >> (bit % 8)
        decoded += _decode_or_refuse(decode, bytes(flipped), baselines)
    assert decoded < 8 * len(data)  # most flips are caught (padding, CRC, lengths...)


@FAST
@given(st.sampled_from(range(0x10, 0x18)), st.binary(max_size=300), st.booleans())
def test_fuzz_random_bytes_every_variant(flags: int, body: bytes, with_base: bool) -> None:
    for name in ("velocity snapshot delta", "update delta", "velocity update delta"):
        _, decode, baselines = CORPUS[name]
        _decode_or_refuse(decode, bytes([0xC1, flags]) + body, baselines if with_base else {})
    _decode_or_refuse(_snapshot, body, {})
    _decode_or_refuse(_update, body, {})


@FAST
@given(st.sampled_from(NAMES), st.data())
def test_fuzz_mutated_frames_every_kind(name: str, draw: st.DataObject) -> None:
    data, decode, baselines = CORPUS[name]
    frame = bytearray(data)
    for _ in range(draw.draw(st.integers(1, 4))):
        i = draw.draw(st.integers(0, len(frame) - 1))
        if draw.draw(st.booleans()):
            frame[i] = draw.draw(st.integers(0, 255))
        else:
            frame[i] ^= 1 << draw.draw(st.integers(0, 7))
    cut = draw.draw(st.integers(0, len(frame) + 2))
    mutated = bytes(frame[:cut]) + draw.draw(st.binary(max_size=3))
    _decode_or_refuse(decode, mutated, baselines)


@FAST
@given(st.lists(st.integers(0, 3), min_size=1, max_size=3, unique=True), st.data())
def test_fuzz_update_round_trip_then_flip(streams: list[int], draw: st.DataObject) -> None:
    n = len(streams)
    x = _poses(n, draw.draw(st.integers(0, 1000)))
    vel = np.array(draw.draw(st.lists(st.floats(-70, 70), min_size=6 * n, max_size=6 * n)))
    enc = encode_update(1, 3.0, streams, [2.99] * n, x, V, velocities=vel.reshape(n, 6))
    got = decode_update(enc.data, V)
    assert np.array_equal(got.codes, enc.frame.codes)
    flipped = bytearray(enc.data)
    bit = draw.draw(st.integers(0, 8 * len(flipped) - 1))
    flipped[bit // 8] ^= 0x80 >> (bit % 8)
    _decode_or_refuse(_update, bytes(flipped), {})


# ------------------------------------------------------------------ allocation


def _uvarint(value: int) -> bytes:
    out = bytearray()
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    return bytes([*out, value])


def _bits(text: str) -> bytes:
    text += "0" * (-len(text) % 8)
    return int(text, 2).to_bytes(len(text) // 8, "big") if text else b""


@pytest.mark.parametrize("flags", [0x14, 0x15, 0x16, 0x17, 0x10, 0x13])
@pytest.mark.parametrize("section", ["key", "delta"])
def test_huge_counts_refused_from_the_header(flags: int, section: str) -> None:
    counts = _uvarint(10**9) + b"\x00" if section == "key" else b"\x00" + _uvarint(10**9)
    data = bytes([0xC1, flags, 1, 0]) + counts + bytes(64)
    decode = _update if flags & 1 else _snapshot
    with pytest.raises(RemoteProtocolError) as info:
        decode(data, {})
    assert info.value.code == ErrorCode.BAD_FRAME
    assert "more entries" in info.value.message


def _peak(decode: Decoder, data: bytes, baselines: Mapping[Any, I64]) -> int:
    tracemalloc.start()
    try:
        _decode_or_refuse(decode, data, baselines)
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def _hostile_frames() -> list[tuple[str, bytes, Decoder]]:
    n = 4000
    # One long Exp-Golomb code then many one-bit codes: a reader that gathers the
    # suffixes as n x longest-suffix would allocate n * 47 words here.
    column = "0" * 46 + "1" + "1" * (n - 1) + "1" * 45
    pad = "1" * (10 * n)
    delta_snapshot = bytes([0xC1, 0x14, 1, 0, 0]) + _uvarint(n) + bytes(4 + 3)
    delta_update = bytes([0xC1, 0x15, 1, 0, 0]) + _uvarint(n) + bytes(2 + 3)
    key_snapshot = bytes([0xC1, 0x16, 1, 0]) + _uvarint(n // 60) + b"\x00" + bytes(2)
    return [
        ("snapshot ug column", delta_snapshot + _bits(column + pad), _snapshot),
        ("update sg column", delta_update + _bits(column + pad), _update),
        ("update all ones", delta_update + _bits("1" * 12 * n), _update),
        ("velocity key snapshot", key_snapshot + _bits("1" + column + pad), _snapshot),
        ("snapshot zeros", bytes([0xC1, 0x14, 1, 0]) + _uvarint(n) + bytes(8 * n), _snapshot),
    ]


@pytest.mark.parametrize("case", range(5))
def test_decoding_allocates_in_proportion_to_the_frame(case: int) -> None:
    name, data, decode = _hostile_frames()[case]
    assert len(data) >= 1000, name
    peak = _peak(decode, data, {})
    # unpackbits (8 B per byte), a few int64 arrays of one word per bit or entry.
    assert peak <= 400 * len(data) + 200_000, (name, peak, len(data))


def test_decoding_valid_frames_allocates_in_proportion() -> None:
    for name in NAMES:
        data, decode, baselines = CORPUS[name]
        assert _peak(decode, data, baselines) <= 400 * len(data) + 200_000, name
