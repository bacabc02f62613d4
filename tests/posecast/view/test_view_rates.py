"""The relay's ``GET /rates`` as the live view reads it, on a real relay."""

from __future__ import annotations

import pytest
from support import running_server

from posecast.client.connection import ClientConnection
from posecast.view.rates import RATE_SCALE, fetch_rates, legend_html, rate_colour


async def test_rates_gives_each_members_rate_and_nothing_for_other_rooms() -> None:
    """A fixed 12 Hz member and an auto one (first choice: its max_rate, 24 Hz): the
    view reads both; another room has no users; a name with spaces is quoted."""
    async with running_server() as srv:
        url = f"ws://127.0.0.1:{srv.port}"
        fixed = await ClientConnection.open(url, room="a b", streams=("head",), rate=12)
        auto = await ClientConnection.open(
            url, room="a b", streams=("head",), rate=24, auto_rate=True
        )
        got = await fetch_rates(url, "a b")
        assert got == {fixed.user: 12.0, auto.user: 24.0}
        assert await fetch_rates(url, "elsewhere") == {}
        await fixed.close()
        await auto.close()


async def test_a_server_that_is_not_a_relay_is_a_clear_error() -> None:
    """Nothing listening: OSError (the view then leaves rates unknown)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(OSError):
        await fetch_rates(f"ws://127.0.0.1:{port}", "r")


def test_the_colour_scale_runs_red_to_green_and_clamps() -> None:
    lo, hi = RATE_SCALE
    red, green = rate_colour(lo), rate_colour(hi)
    assert red[0] > red[1] and green[1] > green[0]
    assert rate_colour(lo - 3) == red and rate_colour(hi + 10) == green
    assert rate_colour((lo + hi) / 2) not in (red, green)
    assert f"{lo:g} Hz" in legend_html() and f"{hi:g} Hz" in legend_html()
