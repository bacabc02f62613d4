"""The starved-machine judgement of a finished swarm: a pure function of its reports."""

from __future__ import annotations

import pytest

from posecast.client.bot import BotReport, RemoteStream
from posecast.client.swarm import (
    STARVED_KEYFRAME_SHARE,
    STARVED_RENDER_LATE,
    Starvation,
    starvation,
    swarm_report,
)


def _report(
    rate_hz: float,
    frames: int = 900,
    late: int = 0,
    asked: float = 10.0,
    send: float = 30.0,
    streams: bool = True,
) -> BotReport:
    got = {(9, 0): RemoteStream(9, 0, "head", None)} if streams else {}
    return BotReport(
        user=1,
        name="b",
        qoe={},
        rate_hz=rate_hz,
        delay_ms=100.0,
        render_stall_fraction=0.0,
        frames_rendered=frames,
        render_cpu_s=0.0,
        snapshot_bytes=0,
        poses_received=0,
        bytes_in=0,
        bytes_out=0,
        duration=10.0,
        clock_rtt_ms=0.1,
        frames_late=late,
        asked_hz=asked,
        granted_hz=asked,
        send_hz=send,
        streams=got,
    )


def test_a_session_on_time_is_not_starved() -> None:
    st = starvation([_report(10.0), _report(9.95, late=8)])
    assert not st.starved and st.warning() is None
    assert st.keyframe_hz == pytest.approx(9.975)
    assert st.render_late_fraction == pytest.approx(8 / 1800)


def test_keyframe_rate_under_90_percent_of_asked_is_starved() -> None:
    st = starvation([_report(8.0), _report(8.2, late=18)])
    assert st.keyframes_short and not st.render_late and st.starved
    assert st.warning() == (
        "warning: this machine starved the session (keyframe rate 8.1 Hz of 10 asked; "
        "render loop late 1 % of frames): figures may read worse than the method is"
    )
    # The threshold itself: 90 % of the rate is still fine, just under it is not.
    assert not starvation([_report(STARVED_KEYFRAME_SHARE * 10.0)]).starved
    assert starvation([_report(STARVED_KEYFRAME_SHARE * 10.0 - 1e-6)]).starved


def test_a_late_render_loop_is_starved() -> None:
    late = int(0.23 * 900)
    st = starvation([_report(10.0, late=late)])
    assert st.render_late and not st.keyframes_short
    assert st.warning() == (
        "warning: this machine starved the session (keyframe rate 10.0 Hz of 10 asked; "
        "render loop late 23 % of frames): figures may read worse than the method is"
    )
    edge = int(STARVED_RENDER_LATE * 900)
    assert not starvation([_report(10.0, late=edge)]).starved
    assert starvation([_report(10.0, late=edge + 1)]).starved


def test_expected_rate_is_the_publish_rate_when_lower() -> None:
    """Asking 30 Hz of senders that publish at 20 Hz: 19 keyframes/s is all there is."""
    st = starvation([_report(19.0, asked=30.0, send=20.0)])
    assert st.expected_hz == 20.0 and not st.starved
    st = starvation([_report(15.0, asked=30.0, send=20.0)])
    assert st.starved
    assert "keyframe rate 15.0 Hz of 20 possible" in (st.warning() or "")


def test_a_lone_bot_receives_nothing_and_is_not_starved_for_it() -> None:
    st = starvation([_report(0.0, streams=False)])
    assert st.keyframe_hz is None and not st.starved
    assert starvation([]) == Starvation(None, 0.0, 0.0, None)


def test_swarm_report_carries_the_judgement() -> None:
    report = swarm_report([_report(8.0)])
    assert report["starvation"]["starved"] is True
    assert report["starvation"]["warning"].startswith("warning: this machine starved")
    assert report["bots"][0]["render_late_fraction"] == 0.0
    assert report["ending"] == {"complete": True, "lines": [], "exit_code": 0}
