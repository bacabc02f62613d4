"""The pose message layout and JSON records of recorder.format."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posecast.recorder.format import (
    CHANNELS,
    FormatError,
    decode_json,
    decode_pose,
    encode_json,
    encode_pose,
    pose_message_size,
    to_ns,
)

_Update = tuple[int, int, float, np.ndarray, np.ndarray, np.ndarray]


@st.composite
def updates(draw: st.DrawFn) -> _Update:
    n = draw(st.integers(0, 6))
    user = draw(st.integers(0, 0xFFFF))
    seq = draw(st.integers(0, (1 << 64) - 1))
    arrival = draw(st.floats(allow_nan=False, allow_infinity=False))
    streams = np.array(draw(st.lists(st.integers(0, 0xFFFF), min_size=n, max_size=n)), np.uint16)
    cap_bits = draw(st.lists(st.integers(0, (1 << 64) - 1), min_size=n, max_size=n))
    pose_bits = draw(st.lists(st.integers(0, (1 << 32) - 1), min_size=7 * n, max_size=7 * n))
    caps = np.array(cap_bits, dtype=np.uint64).view(np.float64)
    poses = np.array(pose_bits, dtype=np.uint32).view(np.float32).reshape(n, 7)
    return user, seq, arrival, streams, caps, poses


@settings(max_examples=100, deadline=None)
@given(updates())
def test_pose_round_trip_is_bit_exact(u: _Update) -> None:
    """Any update (all float bit patterns, NaN payloads included) decodes bit for bit."""
    user, seq, arrival, streams, caps, poses = u
    data = encode_pose(user, seq, arrival, streams, caps, poses)
    assert len(data) == pose_message_size(len(streams))
    rec = decode_pose(data)
    assert (rec.user, rec.seq, rec.arrival) == (user, seq, arrival)
    assert rec.streams.tolist() == streams.tolist()
    assert rec.capture_times.view(np.uint64).tolist() == caps.view(np.uint64).tolist()
    assert rec.poses.shape == (len(streams), 7)
    assert rec.poses.view(np.uint32).tolist() == poses.view(np.uint32).tolist()


def test_decoded_arrays_are_read_only() -> None:
    """Decoded arrays cannot be modified by accident."""
    rec = decode_pose(encode_pose(1, 2, 3.0, [0], [2.9], np.ones((1, 7), np.float32)))
    for arr in (rec.streams, rec.capture_times, rec.poses):
        with pytest.raises(ValueError):
            arr[0] = 0


def test_float64_poses_are_stored_as_float32() -> None:
    """Float64 poses are rounded to float32, as on the wire."""
    p = np.full((2, 7), 0.1)
    rec = decode_pose(encode_pose(0, 0, 1.0, [0, 1], [1.0, 1.0], p))
    assert rec.poses.dtype == np.float32
    assert np.array_equal(rec.poses, p.astype(np.float32))


@pytest.mark.parametrize(
    ("user", "streams", "caps", "poses"),
    [
        (70000, [0], [1.0], np.zeros((1, 7))),
        (-1, [0], [1.0], np.zeros((1, 7))),
        (0, [0, 1], [1.0], np.zeros((2, 7))),
        (0, [0], [1.0], np.zeros((1, 6))),
        (0, [70000], [1.0], np.zeros((1, 7))),
        (0, [[0]], [1.0], np.zeros((1, 7))),
    ],
)
def test_bad_updates_are_refused(
    user: int, streams: list[int] | list[list[int]], caps: list[float], poses: np.ndarray
) -> None:
    """Out-of-range ids and mismatched shapes raise FormatError."""
    with pytest.raises(FormatError):
        encode_pose(user, 0, 1.0, streams, caps, poses)


@pytest.mark.parametrize(
    "data", [b"", b"\x01" * 21, b"\x02" + b"\x00" * 21, b"\x01" + b"\x00" * 40]
)
def test_bad_pose_messages_are_refused(data: bytes) -> None:
    """Short, unknown-version or wrongly sized messages raise FormatError."""
    with pytest.raises(FormatError):
        decode_pose(data)


def test_json_records_take_numpy_values() -> None:
    """Numpy scalars and arrays become JSON numbers and lists."""
    data = encode_json({"kind": "x", "n": np.int64(3), "a": np.arange(2), "f": np.float32(0.5)})
    assert json.loads(data) == {"kind": "x", "n": 3, "a": [0, 1], "f": 0.5}
    assert decode_json(data)["n"] == 3


def test_channels_have_json_schemas() -> None:
    """The JSON channels carry a parseable jsonschema (other tools can decode them)."""
    for spec in CHANNELS[1:]:
        assert spec.message_encoding == "json"
        assert spec.schema_encoding == "jsonschema"
        assert json.loads(spec.schema_data)["type"] == "object"


def test_to_ns_rounds_and_clamps() -> None:
    """Seconds become u64 nanoseconds, rounded, clamped at zero."""
    assert to_ns(1.5) == 1_500_000_000
    assert to_ns(-3.0) == 0
    assert to_ns(float("nan")) == 0
    assert to_ns(float("inf")) == (1 << 64) - 1


def test_decode_poses_matches_decode_pose_one_by_one() -> None:
    """The public batch decoder: mixed sizes, bit-exact, in message order."""
    from posecast.recorder import decode_poses

    rng = np.random.default_rng(7)
    datas, want = [], []
    for k in range(50):
        n = int(rng.integers(0, 4))
        streams = rng.integers(0, 9, n).astype(np.uint16)
        caps = 100.0 + rng.uniform(0, 1, n)
        poses = rng.normal(size=(n, 7)).astype(np.float32)
        datas.append(encode_pose(k % 5, k, 100.5 + k, streams, caps, poses))
        want.append(decode_pose(datas[-1]))
    cols = decode_poses(datas)
    assert len(cols.user) == sum(len(r.streams) for r in want)
    np.testing.assert_array_equal(
        cols.user, np.concatenate([[r.user] * len(r.streams) for r in want])
    )
    np.testing.assert_array_equal(cols.stream, np.concatenate([r.streams for r in want]))
    np.testing.assert_array_equal(cols.capture, np.concatenate([r.capture_times for r in want]))
    np.testing.assert_array_equal(
        cols.poses.view(np.uint32), np.concatenate([r.poses for r in want]).view(np.uint32)
    )
    with pytest.raises(FormatError):
        decode_poses([datas[1][:-3]])


def test_pose_messages_with_velocities_round_trip_bit_exact() -> None:
    """Flags bit 0: float16 velocities after the poses, 12 B a stream; mixed batches decode."""
    from posecast.recorder import decode_poses
    from posecast.recorder.format import VELOCITY_FLAG, pose_message_size

    rng = np.random.default_rng(3)
    streams = np.array([4, 5, 6], np.uint16)
    caps = 10.0 + rng.uniform(0, 1, 3)
    poses = rng.normal(size=(3, 7)).astype(np.float32)
    vel = rng.normal(size=(3, 6)).astype(np.float16)
    vel[0, 0] = np.float16(-0.0)
    data = encode_pose(2, 9, 10.5, streams, caps, poses, vel)
    assert data[1] == VELOCITY_FLAG and len(data) == pose_message_size(3, True)
    assert len(data) == pose_message_size(3) + 36
    rec = decode_pose(data)
    assert rec.velocities is not None
    assert rec.velocities.tobytes() == vel.astype("<f2").tobytes()
    assert rec.poses.tobytes() == poses.tobytes()
    plain = encode_pose(3, 1, 10.6, streams[:2], caps[:2], poses[:2])
    assert decode_pose(plain).velocities is None
    cols = decode_poses([data, plain, data])
    assert cols.velocities is not None and cols.velocities.shape == (8, 6)
    np.testing.assert_array_equal(cols.velocities[:3], vel.astype(np.float32))
    assert np.isnan(cols.velocities[3:5]).all()
    np.testing.assert_array_equal(cols.user, [2, 2, 2, 3, 3, 2, 2, 2])
    assert decode_poses([plain]).velocities is None
    with pytest.raises(FormatError, match="velocities must have shape"):
        encode_pose(2, 9, 10.5, streams, caps, poses, vel[:2])
    with pytest.raises(FormatError, match="flags"):
        decode_pose(data[:1] + b"\x02" + data[2:])
    with pytest.raises(FormatError):
        decode_pose(data[:-2])


def test_info_says_which_streams_carry_velocities(tmp_path: Path) -> None:
    from posecast.recorder import format_info, info
    from posecast.recorder.replay import synthesize_recording

    plain = info(synthesize_recording(tmp_path / "a", users=1, duration=1.0))
    assert [s["velocities"] for s in plain["streams"]] == [False] * 3
    with_v = info(synthesize_recording(tmp_path / "b", users=1, duration=1.0, velocities=True))
    assert [s["velocities"] for s in with_v["streams"]] == [True] * 3
    assert format_info(with_v).count("+ velocities") == 3
    assert "+ velocities" not in format_info(plain)


@pytest.mark.parametrize("n", [0, 1, 3])
@pytest.mark.parametrize("with_velocities", [False, True])
def test_encode_pose_batch_is_encode_pose_row_by_row(n: int, with_velocities: bool) -> None:
    """The writer process's vectorised encoder makes the same bytes, NaN payloads included."""
    from posecast.recorder.format import encode_pose_batch

    rng = np.random.default_rng(n)
    m = 17
    users = rng.integers(0, 65536, m)
    seqs = rng.integers(0, 2**63, m, dtype=np.uint64)
    arrivals = 1000.0 + rng.uniform(0, 100, m)
    streams = rng.integers(0, 65536, (m, n))
    caps = arrivals[:, None] - rng.uniform(0, 0.1, (m, n))
    poses = rng.normal(size=(m, n, 7)).astype(np.float32)
    if n:
        poses.view(np.uint32)[0, 0, 0] = 0x7FC00123  # a NaN with a payload
    vel = rng.normal(size=(m, n, 6)).astype(np.float16) if with_velocities else None
    got = encode_pose_batch(users, seqs, arrivals, streams, caps, poses, vel)
    assert len(got) == m
    for i in range(m):
        want = encode_pose(
            int(users[i]),
            int(seqs[i]),
            float(arrivals[i]),
            streams[i],
            caps[i],
            poses[i],
            None if vel is None else vel[i],
        )
        assert got[i] == want
    with pytest.raises(FormatError):
        encode_pose_batch(users[:3], seqs, arrivals, streams, caps, poses)
