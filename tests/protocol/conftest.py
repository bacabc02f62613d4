"""Fixtures for protocol tests: session pairs before and after the handshake."""

from __future__ import annotations

import pytest

from posecast.protocol.testing import SessionPair


@pytest.fixture
def pair() -> SessionPair:
    """A client and a server session that have exchanged nothing yet."""
    return SessionPair()


@pytest.fixture
def joined() -> SessionPair:
    """A pair after hello/welcome/join/joined: user 1 owns head=0, left=1, right=2."""
    sessions = SessionPair()
    sessions.handshake(user=1, streams=("head", "left", "right"), rate=20.0)
    return sessions
