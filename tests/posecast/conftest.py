"""The face's tests: helpers of the server tests (``relaykit``) are importable here too."""

from __future__ import annotations

import logging
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

_SERVER_TESTS = str(Path(__file__).resolve().parent.parent / "server")
if _SERVER_TESTS not in sys.path:
    sys.path.insert(0, _SERVER_TESTS)


@pytest.fixture(autouse=True)
def _restore_relay_log_level() -> Iterator[None]:
    """`posecast table1 --live` quiets the relay's logger in-process; later tests need it back."""
    logger = logging.getLogger("posecast.server")
    level = logger.level
    yield
    logger.setLevel(level)
