"""How a browser's handshake meets the relay: the ``posecast.v1`` subprotocol, with real
websocket clients on a real relay."""

from __future__ import annotations

import asyncio

import pytest
from support import running_server
from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import InvalidStatus

from posecast.protocol import ClientSession, Hello, Welcome
from posecast.server.app import RelayServer


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
