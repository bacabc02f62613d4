"""SessionLog.keyframe_rate: new keyframes per remote stream per second."""

from __future__ import annotations

from posecast.client.log import SessionLog
from posecast.client.remote import RemoteStream


def _stream(user: int, rate: float, start: float, count: int) -> RemoteStream:
    rs = RemoteStream(user=user, stream=0, name="head", label=None)
    rs.capture = [start + k / rate for k in range(count)]
    rs.arrival = [t + 0.02 for t in rs.capture]
    return rs


def test_steady_streams_read_their_rate() -> None:
    log = SessionLog(("soa",))
    log.streams[(1, 0)] = _stream(1, 15.0, 0.0, 301)
    log.streams[(2, 0)] = _stream(2, 15.0, 3.0, 151)
    assert abs(log.keyframe_rate() - 15.0) < 1e-9


def test_a_stream_seen_briefly_does_not_inflate_the_rate() -> None:
    """Two keyframes 2 ms apart (a churning peer's key then delta) count 2 ms, not a
    stream's share: the mean of per-stream rates read 258 Hz here."""
    log = SessionLog(("soa",))
    log.streams[(1, 0)] = _stream(1, 15.0, 0.0, 301)
    log.streams[(2, 0)] = _stream(2, 500.0, 5.0, 2)
    assert 15.0 <= log.keyframe_rate() < 15.1
    assert SessionLog(("soa",)).keyframe_rate() == 0.0
