"""Fixtures for protocol tests: session pairs before and after the handshake, and the
codec's two implementations (compiled accelerator, pure-Python twin)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest

from posecast.protocol import _accel
from posecast.protocol.testing import SessionPair

#: Test modules that run twice: on the compiled accelerator and on the pure twin.
BOTH_CODECS = frozenset(
    {
        "test_codec_relay",
        "test_codec_small",
        "test_compact_speedpath",
        "test_vectors",
    }
)


def pytest_generate_tests(metafunc: pytest.Metafunc) -> None:
    if metafunc.module.__name__.rsplit(".", 1)[-1] in BOTH_CODECS:
        metafunc.parametrize("codec_impl", ["compiled", "pure"], indirect=True)


@pytest.fixture(autouse=True)
def codec_impl(request: pytest.FixtureRequest) -> Iterator[str]:
    """What runs the codec's hot paths: "compiled" or "pure" in the modules of
    BOTH_CODECS (a compiled run skips where the accelerator is not built), else
    whatever this process runs."""
    wanted = getattr(request, "param", None)
    if wanted is None:
        yield _accel.IMPLEMENTATION
        return
    if wanted == "compiled" and _accel.compiled() is None:
        pytest.skip(f"the compiled accelerator does not run here: {_accel.IMPLEMENTATION}")
    was_pure = _accel.speedups is None
    try:
        yield _accel.use(pure=wanted == "pure")
    finally:
        _accel.use(pure=was_pure)


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
