"""Bytes per pose on disk for a realistic room: 20 users x 20 Hz x 3 poses, real traces."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from posecast.protocol import PoseUpdate
from posecast.recorder import SessionRecorder, info, load_streams
from posecast.scenarios.traces import find_traces, load_trace

USERS, RATE, SECONDS = 20, 20.0, 15.0
#: Chunks close every 0.5 s in a live room (DEFAULT_FLUSH_INTERVAL); a 20-user room
#: at 20 Hz delivers 400 updates/s, so a chunk holds about 200 of them.
UPDATES_PER_CHUNK = {"0.5 s": 200, "1 s": 400}


def _room_updates(sample_dir: Path) -> list[tuple[float, int, PoseUpdate]]:
    """(arrival, user, update) for every user, as the server would receive them."""
    traces = [load_trace(p) for p in find_traces(sample_dir)]
    rng = np.random.default_rng(11)
    server_t0 = 8765.4321  # server monotonic clock at the start
    out = []
    for user in range(USERS):
        tr = traces[user % len(traces)]
        i0 = int(rng.integers(0, len(tr.times) // 2))
        phase = float(rng.uniform(0, 1 / RATE))
        clock_error = float(rng.normal(0, 0.002))  # the client's estimate of server time
        for k in range(int(SECONDS * RATE)):
            idx = int(np.searchsorted(tr.times, tr.times[i0] + k / RATE))
            capture = server_t0 + phase + clock_error + float(tr.times[idx] - tr.times[i0])
            update = PoseUpdate.from_arrays(
                k, np.arange(3 * user, 3 * user + 3), np.full(3, capture), tr.poses[idx]
            )
            arrival = capture + float(rng.uniform(0.02, 0.06))
            out.append((arrival, user, update))
    out.sort(key=lambda x: x[0])
    return out


def test_bytes_per_pose_on_disk(
    tmp_path: Path, sample_dir: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Real head/hand motion costs at most ~36 B per pose on disk (measured and reported)."""
    updates = _room_updates(sample_dir)
    results = {}
    for label, per_chunk in UPDATES_PER_CHUNK.items():
        rec = SessionRecorder.open(
            tmp_path, "size", name=f"size-{per_chunk}", chunk_records=per_chunk, queue_size=20_000
        )
        for arrival, user, u in updates:
            assert rec.record_update(user, u.seq, arrival, u.streams, u.capture_times, u.poses)
        path = rec.close()
        data = info(path)
        assert data["sizes"]["poses"] == 3 * len(updates)
        results[label] = data["sizes"]["bytes_per_pose"]
        if per_chunk == 200:
            # the stored poses are the float32 values of the wire, bit for bit
            streams = load_streams(path, users=[7])
            mine = [u for _, user, u in updates if user == 7]
            assert np.array_equal(streams[(7, 21)].poses, np.array([u.poses[0] for u in mine]))
            assert np.array_equal(streams[(7, 21)].times, [u.capture_times[0] for u in mine])
    with capsys.disabled():
        print(
            "\nrecorder bytes/pose (20 users x 20 Hz x 3 poses, real traces): "
            + ", ".join(f"chunks every {k}: {v:.1f} B" for k, v in results.items())
        )
    assert results["0.5 s"] <= 36.0 and results["1 s"] <= 36.0
