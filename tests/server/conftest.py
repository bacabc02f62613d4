"""The server tests' fixture: a factory of real relays on loopback (port 0)."""

from __future__ import annotations

from collections.abc import Callable

import pytest
from support import running_server


@pytest.fixture
def server_factory() -> Callable[..., object]:
    return running_server
