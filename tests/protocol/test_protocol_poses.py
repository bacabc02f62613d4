"""Pose frames: record layouts, zero-copy decoding, time offsets, pose checks, bytes per pose."""

from __future__ import annotations

import numpy as np
import pytest

from posecast import protocol
from posecast.protocol import (
    QUAT_NORM_TOLERANCE,
    SNAPSHOT_DTYPE,
    SNAPSHOT_ENTRY_SIZE,
    UPDATE_DTYPE,
    UPDATE_ENTRY_SIZE,
    ErrorCode,
    LocalProtocolError,
    PoseUpdate,
    RemoteProtocolError,
    Snapshot,
    bytes_per_pose,
    decode_message,
    encode_snapshot,
    encode_update,
    frame_size,
    pose_problem,
)
from posecast.protocol.testing import raw_frame


def random_poses(n: int, seed: int = 0) -> np.ndarray:
    """n poses with random positions and random unit quaternions, float64."""
    rng = np.random.default_rng(seed)
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    return np.concatenate([rng.uniform(-3, 3, size=(n, 3)), quats], axis=1)


def test_record_sizes() -> None:
    """Records are packed: 34 bytes per update pose, 36 per snapshot pose."""
    assert UPDATE_ENTRY_SIZE == UPDATE_DTYPE.itemsize == 2 + 4 + 28
    assert SNAPSHOT_ENTRY_SIZE == SNAPSHOT_DTYPE.itemsize == 2 + 2 + 4 + 28
    assert not UPDATE_DTYPE.isalignedstruct


def test_update_round_trip() -> None:
    """An update decodes to the same ids, float32 poses and capture times (to float32 dt)."""
    poses = random_poses(5)
    times = 1000.0 + np.array([0.0, -0.01, -0.02, -0.033, -0.25])
    update = decode_message(encode_update(41, [0, 1, 2, 7, 9], times, poses))
    assert isinstance(update, PoseUpdate)
    assert update.seq == 41
    assert update.base_time == 1000.0
    assert update.streams.tolist() == [0, 1, 2, 7, 9]
    assert update.poses.dtype == np.float32
    assert update.poses.shape == (5, 7)
    np.testing.assert_array_equal(update.poses, poses.astype(np.float32))
    assert update.capture_times.dtype == np.float64
    np.testing.assert_allclose(update.capture_times, times, rtol=0, atol=1e-7)


def test_snapshot_round_trip() -> None:
    """A snapshot decodes to the same users, streams, poses and capture times."""
    poses = random_poses(4, seed=1)
    send_time = 5_000_000.0  # two months of uptime: dt keeps precision anyway
    times = send_time - np.array([0.05, 0.1, 0.0, 2.0])
    frame = encode_snapshot(12, send_time, [1, 1, 2, 3], [0, 1, 4, 9], times, poses)
    snapshot = decode_message(frame)
    assert isinstance(snapshot, Snapshot)
    assert (snapshot.tick, snapshot.send_time, len(snapshot)) == (12, send_time, 4)
    assert snapshot.users.tolist() == [1, 1, 2, 3]
    assert snapshot.streams.tolist() == [0, 1, 4, 9]
    np.testing.assert_array_equal(snapshot.poses, poses.astype(np.float32))
    np.testing.assert_allclose(snapshot.capture_times, times, rtol=0, atol=1e-6)


def test_decoding_is_zero_copy() -> None:
    """Decoded poses are read-only views into the received frame's bytes, not copies."""
    update = decode_message(encode_update(1, [0, 1], [0.0, 0.0], random_poses(2)))
    assert isinstance(update, PoseUpdate)
    assert not update.entries.flags.owndata
    assert not update.entries.flags.writeable
    assert np.shares_memory(update.poses, update.entries)
    assert np.shares_memory(update.streams, update.entries)


def test_default_base_time_is_newest_capture() -> None:
    """Without a base time the newest capture time is used, so every offset is <= 0."""
    update = PoseUpdate.from_arrays(0, [0, 1], [3.0, 2.5], random_poses(2))
    assert update.base_time == 3.0
    assert update.entries["dt"].tolist() == [0.0, -0.5]


def test_empty_frames() -> None:
    """An update or snapshot with no poses is valid and round-trips."""
    empty = np.empty((0, 7))
    update = decode_message(encode_update(0, np.empty(0, int), [], empty))
    snapshot = decode_message(
        encode_snapshot(0, 1.0, np.empty(0, int), np.empty(0, int), [], empty)
    )
    assert len(update) == 0  # type: ignore[arg-type]
    assert len(snapshot) == 0  # type: ignore[arg-type]
    assert pose_problem(snapshot.entries) is None  # type: ignore[union-attr]


def test_frame_size_and_bytes_per_pose() -> None:
    """frame_size is exact for a 32-bit tick, and bytes per pose tends to 36 (34 for updates)."""
    send_time, poses = 1.0, random_poses(300)
    for n in (1, 3, 7, 8, 100, 300):
        frame = encode_snapshot(1 << 20, send_time, [1] * n, range(n), [0.5] * n, poses[:n])
        assert len(frame) == frame_size(n, "snapshot")
        frame = encode_update(1 << 20, range(n), [0.5] * n, poses[:n])
        assert len(frame) == frame_size(n, "update")
    assert bytes_per_pose(1) == frame_size(1)
    assert 36 < bytes_per_pose(100) < 36.5
    assert 34 < bytes_per_pose(100, "update") < 34.5
    assert bytes_per_pose(1000) == pytest.approx(36, abs=0.05)


@pytest.mark.parametrize(
    ("row", "problem"),
    [
        ([0.0, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0], None),
        ([np.nan, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0], "non-finite pose"),
        ([np.inf, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0], "non-finite pose"),
        ([0.0, 1.6, 0.0, np.nan, 0.0, 0.0, 0.0], "non-finite pose"),
        ([0.0, 1.6, 0.0, -np.inf, 0.0, 0.0, 0.0], "non-finite pose"),
        ([0.0, 1.6, 0.0, 1.002, 0.0, 0.0, 0.0], "quaternion not unit"),
        ([0.0, 1.6, 0.0, 0.0, 0.0, 0.0, 0.0], "quaternion not unit"),
        ([0.0, 1.6, 0.0, 0.5, 0.5, 0.5, 0.5], None),
        ([0.0, 1.6, 0.0, -1.0, 0.0, 0.0, 0.0], None),
    ],
)
@pytest.mark.parametrize("n", [1, 200], ids=["loop", "numpy"])
def test_pose_problem(row: list[float], problem: str | None, n: int) -> None:
    """Non-finite numbers and non-unit quaternions are found, in small and large frames."""
    poses = np.tile([0.0, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0], (n, 1))
    poses[n // 2] = row
    snapshot = Snapshot.from_arrays(0, 0.0, np.zeros(n, int), np.arange(n), np.zeros(n), poses)
    update = PoseUpdate.from_arrays(0, np.arange(n), np.zeros(n), poses, base_time=0.0)
    assert pose_problem(snapshot.entries) == problem
    assert pose_problem(update.entries) == problem


@pytest.mark.parametrize("n", [1, 200], ids=["loop", "numpy"])
def test_pose_problem_catches_bad_time_offset(n: int) -> None:
    """A NaN time offset makes the pose unusable too."""
    snapshot = Snapshot.from_arrays(
        0, 0.0, np.zeros(n, int), np.arange(n), np.zeros(n), random_poses(n)
    )
    entries = snapshot.entries.copy()
    entries["dt"][-1] = np.nan
    assert pose_problem(entries) == "non-finite pose"


@pytest.mark.parametrize("n", [1, 200], ids=["loop", "numpy"])
def test_quaternion_tolerance_boundary(n: int) -> None:
    """Norms within QUAT_NORM_TOLERANCE of 1 pass; just beyond it they fail."""
    poses = np.tile([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], (n, 1))
    for scale, problem in [
        (1 + 0.9 * QUAT_NORM_TOLERANCE, None),
        (1 - 0.9 * QUAT_NORM_TOLERANCE, None),
        (1 + 1.1 * QUAT_NORM_TOLERANCE, "quaternion not unit"),
        (1 - 1.1 * QUAT_NORM_TOLERANCE, "quaternion not unit"),
    ]:
        poses[0, 3] = scale
        update = PoseUpdate.from_arrays(0, np.arange(n), np.zeros(n), poses)
        assert pose_problem(update.entries) == problem, scale


def test_pose_problem_on_non_contiguous_records() -> None:
    """A strided slice of records is checked like a contiguous one."""
    poses = random_poses(10)
    poses[3, 3:] *= 2
    update = PoseUpdate.from_arrays(0, np.arange(10), np.zeros(10), poses)
    assert pose_problem(update.entries[::2]) is None
    assert pose_problem(update.entries[1::2]) == "quaternion not unit"


@pytest.mark.parametrize(
    "call",
    [
        lambda: encode_update(0, [0, 1], [0.0], np.zeros((2, 7))),
        lambda: encode_update(0, [0], [0.0], np.zeros((1, 6))),
        lambda: encode_update(0, [70000], [0.0], np.zeros((1, 7))),
        lambda: encode_update(0, [-1], [0.0], np.zeros((1, 7))),
        lambda: encode_update(0, [0.5], [0.0], np.zeros((1, 7))),
        lambda: encode_update(-1, [0], [0.0], np.zeros((1, 7))),
        lambda: encode_update(0, [0], ["soon"], np.zeros((1, 7))),
        lambda: encode_snapshot(0, np.nan, [0], [0], [0.0], np.zeros((1, 7))),
        lambda: encode_snapshot(0, 0.0, [0, 1], [0], [0.0], np.zeros((1, 7))),
        lambda: PoseUpdate(0, 0.0, np.zeros(3)),
        lambda: Snapshot(0, 0.0, np.zeros(3, UPDATE_DTYPE)),
    ],
)
def test_encoders_reject_bad_shapes(call: object) -> None:
    """Mismatched lengths, wrong shapes, out-of-range ids raise LocalProtocolError."""
    with pytest.raises(LocalProtocolError) as caught:
        call()  # type: ignore[operator]
    assert caught.value.code is ErrorCode.BAD_MESSAGE


@pytest.mark.parametrize(
    ("frame", "message"),
    [
        (raw_frame("update", seq=0, time=0.0, poses=b"\x00" * 35), "not whole 34-byte records"),
        (raw_frame("snapshot", tick=0, time=0.0, poses=b"\x00" * 34), "not whole 36-byte"),
        (raw_frame("update", seq=0, time=0.0, poses="text"), "must be bin"),
        (raw_frame("update", seq=0, time=0.0), r"needs exactly seq, time and poses \(or vpose\)"),
        (raw_frame("update", seq=0, time=0.0, poses=b"", extra=1), "needs exactly"),
        (raw_frame("update", seq=-5, time=0.0, poses=b""), "update.seq"),
        (raw_frame("update", seq=0, time=float("nan"), poses=b""), "update.time"),
        (raw_frame("snapshot", tick=True, time=0.0, poses=b""), "snapshot.tick"),
    ],
)
def test_malformed_pose_frames(frame: bytes, message: str) -> None:
    """Pose frames with bad fields or ragged records are bad-message."""
    with pytest.raises(RemoteProtocolError, match=message) as caught:
        decode_message(frame)
    assert caught.value.code is ErrorCode.BAD_MESSAGE


def test_huge_values_become_bad_pose_not_warnings() -> None:
    """Values beyond float32 are stored as inf (no warning) and reported as bad poses."""
    poses = np.tile([1e300, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], (40, 1))
    update = PoseUpdate.from_arrays(0, np.arange(40), np.zeros(40), poses)
    assert pose_problem(update.entries) == "non-finite pose"
    assert pose_problem(update.entries[:2]) == "non-finite pose"


def test_pose_frames_compare_by_content() -> None:
    """Two frames with the same header and records are equal; other types are not."""
    a = PoseUpdate.from_arrays(1, [0], [0.0], random_poses(1))
    b = decode_message(encode_update(1, [0], [0.0], random_poses(1)))
    assert a == b
    assert a != PoseUpdate.from_arrays(2, [0], [0.0], random_poses(1))
    assert a != "update"


def test_pack_snapshot_equals_encode_snapshot_bytes() -> None:
    """The relay's byte path builds exactly the frame encode_snapshot builds."""
    rng = np.random.default_rng(5)
    n = 7
    users = rng.integers(0, 1000, n)
    streams = rng.integers(0, 60000, n)
    send = 1234.5
    caps = send - rng.uniform(0, 0.1, n)
    poses = rng.normal(size=(n, 7)).astype(np.float32)
    want = protocol.encode_snapshot(99, send, users, streams, caps, poses)
    got = protocol.pack_snapshot(
        99,
        send,
        [
            (int(u), int(s), float(c), p.tobytes())
            for u, s, c, p in zip(users, streams, caps, poses, strict=True)
        ],
    )
    assert got == want


def test_update_records_yield_streams_times_and_pose_bytes() -> None:
    """update_records gives each entry's stream, capture time and raw 28 pose bytes."""
    poses = np.arange(21, dtype=np.float32).reshape(3, 7)
    update = protocol.decode_message(
        protocol.encode_update(4, [7, 8, 9], [10.0, 10.25, 10.5], poses, base_time=10.5)
    )
    assert isinstance(update, protocol.PoseUpdate)
    recs = list(protocol.update_records(update))
    assert [r[0] for r in recs] == [7, 8, 9]
    assert [r[1] for r in recs] == [10.0, 10.25, 10.5]
    assert [r[2] for r in recs] == [p.tobytes() for p in poses]
    assert [r[3] for r in recs] == [None, None, None]  # plain update: no velocity bytes
