"""The rate the relay sends each user of a room, for the live view's colours.

The relay answers ``GET /rates?room=NAME`` on its websocket port (``server.http``):
per member, the snapshot rate it sends that member now (with ``rate: "auto"``, the
one it chose from the member's link). :func:`fetch_rates` asks it without blocking
the event loop; :func:`rate_colour` maps a rate onto the view's scale
(:data:`RATE_SCALE`, red at the low end, green at the high), :func:`legend_html`
draws that scale for the panel.
"""

from __future__ import annotations

import asyncio
import json
import ssl
from typing import Any
from urllib.parse import quote, urlsplit

__all__ = ["RATE_SCALE", "fetch_rate_table", "fetch_rates", "legend_html", "rate_colour"]

#: The rates (Hz) the colour scale spans: the relay's default range.
RATE_SCALE = (5.0, 30.0)
#: The longest answer read (bytes): a full room's rates are far less.
_MAX_ANSWER = 256 * 1024


async def fetch_rates(url: str, room: str) -> dict[int, float]:
    """User id -> the rate (Hz) the relay at ``url`` (``ws://`` or ``wss://``) sends
    that member of ``room`` now; within 2 s. Raises OSError, TimeoutError or
    ValueError when the relay does not answer it (one that predates ``/rates``
    answers 426)."""
    users = await fetch_rate_table(url, room)
    return {int(u): float(v["rate"]) for u, v in users.items()}


async def fetch_rate_table(url: str, room: str) -> dict[str, dict[str, Any]]:
    """The ``users`` of the relay's ``/rates`` answer as it is (user id -> its rate,
    and per-peer rates for a member with an error budget); as :func:`fetch_rates`."""
    parts = urlsplit(url)
    secure = parts.scheme == "wss"
    host, port = parts.hostname or "127.0.0.1", parts.port or (443 if secure else 80)
    ctx = ssl.create_default_context() if secure else None
    async with asyncio.timeout(2.0):
        reader, writer = await asyncio.open_connection(host, port, ssl=ctx)
        try:
            path = f"/rates?room={quote(room)}"
            writer.write(
                f"GET {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n".encode()
            )
            answer = await reader.read(_MAX_ANSWER)
            while len(answer) < _MAX_ANSWER and (more := await reader.read(_MAX_ANSWER)):
                answer += more
        finally:
            writer.close()
    head, _, body = answer.partition(b"\r\n\r\n")
    status = head.split(b"\r\n", 1)[0].split(b" ")
    if len(status) < 2 or status[1] != b"200":
        raise ValueError(f"/rates answered {head[:40]!r}")
    users: dict[str, dict[str, Any]] = json.loads(body)["users"]
    return users


def rate_colour(rate: float) -> tuple[int, int, int]:
    """The colour of ``rate`` on :data:`RATE_SCALE`: red at 5 Hz, amber, green at 30 Hz."""
    lo, hi = RATE_SCALE
    s = min(1.0, max(0.0, (rate - lo) / (hi - lo)))
    # Red (220, 50, 40) -> amber (230, 170, 30) -> green (40, 170, 70).
    a, b, t = (
        ((220, 50, 40), (230, 170, 30), 2 * s)
        if s < 0.5
        else ((230, 170, 30), (40, 170, 70), 2 * s - 1)
    )
    r, g, bl = (round(x + (y - x) * t) for x, y in zip(a, b, strict=True))
    return r, g, bl


def legend_html() -> str:
    """The colour scale as a bar with its ends labelled (HTML for the panel)."""
    lo, hi = RATE_SCALE
    stops = ", ".join(f"rgb{rate_colour(lo + (hi - lo) * k / 4)}" for k in range(5))
    return (
        '<div style="font-size:11px;margin-top:4px">rate the relay sends each user '
        f'<div style="height:8px;background:linear-gradient(to right, {stops})"></div>'
        f'<div style="display:flex;justify-content:space-between"><span>{lo:g} Hz</span>'
        f"<span>{(lo + hi) / 2:g}</span><span>{hi:g} Hz</span></div></div>"
    )
