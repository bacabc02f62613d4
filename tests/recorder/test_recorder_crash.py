"""A recording process killed with SIGKILL loses at most its last second."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from posecast.recorder import PoseRecord, find_leftovers, read_records, recover

# The writer: 20 users' updates in bursts, ~2000 updates/s; after each burst a
# progress line "<updates offered so far> <time.monotonic()>".
_WRITER = """
import sys, time
import numpy as np
from posecast.recorder import SessionRecorder
rec = SessionRecorder.open(sys.argv[1], "crash", name="crash")
rng = np.random.default_rng(0)
poses = rng.normal(size=(3, 7)).astype(np.float32)
streams = np.arange(3, dtype=np.uint16)
seq = 0
while True:
    for _ in range(20):
        now = time.monotonic()
        assert rec.record_update(seq % 20, seq, now, streams, np.full(3, now), poses)
        seq += 1
    print(seq, time.monotonic(), flush=True)
    time.sleep(0.01)
"""


def test_sigkill_keeps_everything_older_than_one_second(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """After SIGKILL and recover(), every update offered over 1 s before the kill is there."""
    root = Path(__file__).resolve().parents[2]
    env = {**os.environ, "PYTHONPATH": str(root)}
    progress: list[tuple[int, float]] = []
    with subprocess.Popen(
        [sys.executable, "-c", _WRITER, str(tmp_path)],
        stdout=subprocess.PIPE,
        text=True,
        cwd=root,
        env=env,
    ) as proc:
        try:
            assert proc.stdout is not None
            for line in proc.stdout:
                count, t = line.split()
                progress.append((int(count), float(t)))
                # run for 2.5 s of the writer's own clock, then kill it mid-session
                if progress[-1][1] - progress[0][1] >= 2.5:
                    break
            assert progress, "the writer printed nothing"
            kill_time = time.monotonic()
            os.kill(proc.pid, signal.SIGKILL)
            for line in proc.stdout:  # lines written before the kill
                count, t = line.split()
                progress.append((int(count), float(t)))
        finally:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL

    [part] = find_leftovers(tmp_path)
    report = recover(part)
    seqs = [r.seq for r in read_records(report.output) if isinstance(r, PoseRecord)]
    offered = progress[-1][0]
    # No partial or corrupted record: a gap-free prefix of what was offered.
    assert seqs == list(range(len(seqs)))
    assert len(seqs) <= offered
    durable = max((c for c, t in progress if t <= kill_time - 1.0), default=0)
    assert durable > 0
    assert len(seqs) >= durable, f"{len(seqs)} recovered, {durable} offered before kill - 1 s"
    assert report.chunks_lost == 0 and report.lost_records == 0
    with capsys.disabled():
        print(
            f"\ncrash: {offered} updates offered, {durable} of them over 1 s before the kill,"
            f" {len(seqs)} recovered"
        )
