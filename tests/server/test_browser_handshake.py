"""How a browser's handshake meets the relay: the ``posecast.v1`` subprotocol and the
``Origin`` check (``--allow-origin``), with real websocket clients on a real relay."""

from __future__ import annotations

import asyncio
import logging

import pytest
from support import running_server
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import InvalidStatus

from posecast.protocol import ClientSession, Hello, Welcome
from posecast.server.app import RelayServer, ServerConfig
from posecast.server.http import OriginPolicy, normalise_origin, parse_allow_origin


async def _welcomed(ws: ClientConnection) -> Welcome:
    """Say hello over ``ws``; the welcome it gets."""
    session = ClientSession()
    await ws.send(session.send(Hello(agent="browser-test")))
    async with asyncio.timeout(10):
        while True:
            for event in session.receive_data(await ws.recv()):  # type: ignore[arg-type]
                if isinstance(event, Welcome):
                    return event


def _url(server: RelayServer) -> str:
    return f"ws://127.0.0.1:{server.port}"


async def test_posecast_v1_is_selected_when_offered() -> None:
    """A client offering posecast.v1 (alone or among others) gets it and a session."""
    async with running_server() as server:
        for offer in (["posecast.v1"], ["chat", "posecast.v1"]):
            async with connect(_url(server), subprotocols=offer) as ws:  # type: ignore[arg-type]
                assert ws.subprotocol == "posecast.v1"
                assert (await _welcomed(ws)).user >= 0


async def test_no_subprotocol_is_not_required() -> None:
    """A client that offers no subprotocol is served as before, with none selected."""
    async with running_server() as server, connect(_url(server)) as ws:
        assert ws.subprotocol is None
        assert (await _welcomed(ws)).user >= 0


async def test_only_unknown_subprotocols_get_a_clear_400() -> None:
    """Offering only subprotocols the relay does not speak: HTTP 400 saying which it speaks."""
    async with running_server() as server:
        with pytest.raises(InvalidStatus) as err:
            async with connect(_url(server), subprotocols=["posecast.v2"]):  # type: ignore[list-item]
                pass
        response = err.value.response
        assert response.status_code == 400
        assert b"unsupported subprotocol posecast.v2; this relay speaks posecast.v1" in (
            response.body or b""
        )


def test_origins_are_normalised_as_browsers_write_them() -> None:
    """Case, default ports and a trailing slash do not matter; junk is one clear line."""
    assert normalise_origin("HTTPS://App.Example.com:443/") == "https://app.example.com"
    assert normalise_origin("http://localhost:8080") == "http://localhost:8080"
    assert normalise_origin("http://[::1]:80") == "http://[::1]"
    assert parse_allow_origin("https://a.example, http://localhost:8080,") == (
        "https://a.example",
        "http://localhost:8080",
    )
    assert parse_allow_origin("*") is None and parse_allow_origin(" ") is None
    with pytest.raises(ValueError, match="is not an origin; write scheme://host"):
        parse_allow_origin("app.example.com")
    with pytest.raises(ValueError, match="out of range"):
        normalise_origin("http://a:70000")


def test_policy_allows_listed_and_originless_and_logs_any_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A list admits only its origins (and clients without one); no list admits all,
    noting the first browser origin once."""
    listed = OriginPolicy(("https://app.example.com",))
    assert listed.refusal(None) is None
    assert listed.refusal("https://APP.example.com") is None
    assert "not allowed" in (listed.refusal("https://evil.example") or "")
    assert listed.refusal("null") is not None and listed.refused == 2
    caplog.set_level(logging.INFO, "posecast.server")
    anyone = OriginPolicy(None)
    assert anyone.refusal("https://a.example") is None
    assert anyone.refusal("https://b.example") is None
    noted = [r for r in caplog.records if "any origin may connect" in r.getMessage()]
    assert len(noted) == 1 and "https://a.example" in noted[0].getMessage()


async def test_allow_origin_refuses_other_pages_with_403() -> None:
    """With --allow-origin, a page from elsewhere gets 403 at the upgrade; the listed
    page and a client without an Origin header get a session."""
    cfg = ServerConfig(host="127.0.0.1", port=0, allow_origins=("http://localhost:8080",))
    async with running_server(cfg) as server:
        with pytest.raises(InvalidStatus) as err:
            async with connect(_url(server), origin="http://evil.example"):  # type: ignore[arg-type]
                pass
        assert err.value.response.status_code == 403
        assert b"origin http://evil.example is not allowed" in (err.value.response.body or b"")
        async with connect(_url(server), origin="http://localhost:8080") as ws:  # type: ignore[arg-type]
            assert (await _welcomed(ws)).user >= 0
        async with connect(_url(server)) as ws:
            assert (await _welcomed(ws)).user >= 0
        assert server.origins.refused == 1


async def test_default_allows_any_origin() -> None:
    """Without --allow-origin any page connects (posecast web from a headset's LAN address)."""
    page = "http://192.168.1.20:8080"
    async with running_server() as server, connect(_url(server), origin=page) as ws:  # type: ignore[arg-type]
        assert (await _welcomed(ws)).user >= 0
