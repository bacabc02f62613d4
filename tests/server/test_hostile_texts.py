"""Refusals of inputs whose echo would be long, over the real relay: each is a valid
``error`` message (never a relay failure, 1011, nor a traceback in the log)."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from relaykit import GOOD, errors, joined_raw, update_bytes

from posecast.protocol import MAX_TEXT_LENGTH, decode_message

ServerFactory = Callable[..., Any]


async def _replies(ws: Any, n: int) -> list[object]:
    got: list[object] = []
    async with asyncio.timeout(5):
        while len(errors(got)) < n:
            got.append(decode_message(await ws.recv()))
    return got


@pytest.mark.parametrize("time", [1e240, -1e300, 1.7976931348623157e308])
async def test_a_huge_capture_time_is_a_bad_pose(
    server_factory: ServerFactory, caplog: pytest.LogCaptureFixture, time: float
) -> None:
    """An update stamped at a huge finite time gets bad-pose; the member stays."""
    async with server_factory() as srv:
        ws, _, ids = await joined_raw(f"ws://127.0.0.1:{srv.port}")
        with caplog.at_level(logging.ERROR, logger="posecast.server"):
            poses = np.repeat(GOOD, len(ids), axis=0)
            await ws.send(update_bytes(ids, poses, seq=1, now=time))
            refused = errors(await _replies(ws, 1))
        assert [e.code for e in refused] == ["bad-pose"]
        assert len(refused[0].message) <= MAX_TEXT_LENGTH
        assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
        await ws.ping()  # still open
        await ws.close()
