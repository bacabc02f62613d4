"""Access tokens: make/verify with a fake clock, and the server refusing bad ones at join."""

from __future__ import annotations

import base64
import json
import time
from collections.abc import Callable
from typing import Any

import msgpack
import pytest
from relaykit import HELLO, errors, frame, raw_connect, until_closed

from posecast.client.connection import ClientConnection, JoinRefused
from posecast.server.app import RelayServer, ServerConfig
from posecast.server.auth import TokenClaims, TokenError, make_token, verify_token

ServerFactory = Callable[..., Any]
SECRET = "correct horse battery staple"
NOW = 1_700_000_000.0


# -- make_token / verify_token, no sockets, fake clock --------------------------------


def test_token_round_trip() -> None:
    """A fresh token verifies and yields its room, user and expiry."""
    token = make_token(SECRET, "lab", "alice", ttl=60.0, now=NOW)
    assert token.startswith("v1.")
    assert verify_token(SECRET, token, "lab", NOW + 59.9) == TokenClaims("lab", "alice", NOW + 60)


def test_token_expires_at_exp() -> None:
    """A token is refused from its expiry time on, never before."""
    token = make_token(SECRET, "lab", "alice", ttl=60.0, now=NOW)
    verify_token(SECRET, token, "lab", NOW + 59.999)
    for later in (NOW + 60.0, NOW + 3600.0):
        with pytest.raises(TokenError, match="expired"):
            verify_token(SECRET, token, "lab", later)


def test_token_wrong_secret_refused() -> None:
    """A token signed with another secret fails the signature check."""
    token = make_token("another secret", "lab", "alice", ttl=60.0, now=NOW)
    with pytest.raises(TokenError, match="signature"):
        verify_token(SECRET, token, "lab", NOW)


def test_token_other_room_refused() -> None:
    """A token for one room does not open another."""
    token = make_token(SECRET, "lab", "alice", ttl=60.0, now=NOW)
    with pytest.raises(TokenError, match="room 'lab', not 'office'"):
        verify_token(SECRET, token, "office", NOW)


def test_token_tampered_payload_refused() -> None:
    """Changing the payload (a later expiry) breaks the signature."""
    token = make_token(SECRET, "lab", "alice", ttl=60.0, now=NOW)
    prefix, _, sig = token.split(".")
    body = json.dumps({"room": "lab", "user": "alice", "exp": NOW + 1e6}, separators=(",", ":"))
    forged = base64.urlsafe_b64encode(body.encode()).rstrip(b"=").decode()
    with pytest.raises(TokenError, match="signature"):
        verify_token(SECRET, f"{prefix}.{forged}.{sig}", "lab", NOW + 100)


@pytest.mark.parametrize(
    ("token", "why"),
    [
        (None, "missing"),
        ("", "missing"),
        ("v1.abc", "malformed"),
        ("v2.abc.def", "malformed"),
        ("a.b.c.d", "malformed"),
        ("v1.abc.\u00e9t\u00e9", "signature"),
        ("v1.\u00e9t\u00e9.abc", "signature"),
    ],
)
def test_token_missing_or_malformed(token: str | None, why: str) -> None:
    """No token, a malformed one or a non-ASCII signature is refused with a reason."""
    with pytest.raises(TokenError, match=why):
        verify_token(SECRET, token, "lab", NOW)


def test_token_signed_garbage_payload_refused() -> None:
    """A correctly signed payload that is not the claims map is "malformed", not a crash."""
    from posecast.server.auth import _b64, _sign

    for body in (b"not json", b"[1, 2]", b'{"room": "lab"}'):
        payload = _b64(body)
        with pytest.raises(TokenError, match="malformed"):
            verify_token(SECRET, f"v1.{payload}.{_sign(SECRET, payload)}", "lab", NOW)


def test_make_token_rejects_bad_arguments() -> None:
    """An empty secret or a non-positive ttl is a programming error."""
    with pytest.raises(ValueError, match="secret"):
        make_token("", "lab", "alice", ttl=60.0, now=NOW)
    with pytest.raises(ValueError, match="ttl"):
        make_token(SECRET, "lab", "alice", ttl=0.0, now=NOW)


# -- the server refuses bad tokens at join ------------------------------------------------


def url_of(srv: RelayServer) -> str:
    return f"ws://127.0.0.1:{srv.port}"


def secured() -> ServerConfig:
    return ServerConfig(host="127.0.0.1", port=0, secret=SECRET)


async def join_with(srv: RelayServer, token: str | None) -> tuple[list[object], int | None]:
    """hello, then a join carrying ``token``; everything received and the close code."""
    ws = await raw_connect(url_of(srv))
    await ws.send(HELLO)
    assert msgpack.unpackb(await ws.recv())["type"] == "welcome"
    fields: dict[str, object] = {"room": "lab", "streams": ["head"], "rate": 10.0}
    if token is not None:
        fields["token"] = token
    await ws.send(frame("join", **fields))
    return await until_closed(ws, limit=5.0)


def token_cases() -> dict[str, tuple[str | None, str]]:
    now = time.time()
    return {
        "wrong secret": (make_token("not the secret", "lab", "eve", 600, now), "signature"),
        "expired": (make_token(SECRET, "lab", "bob", 60, now - 3600), "expired"),
        "missing": (None, "missing"),
        "other room": (make_token(SECRET, "office", "bob", 600, now), "room"),
        "garbage": ("v1.%%%.!!!", "signature"),
        "non-ascii": ("v1.abc.\u00e9t\u00e9", "signature"),
    }


@pytest.mark.parametrize("case", list(token_cases()))
async def test_bad_token_refused_unauthorized_1008(
    server_factory: ServerFactory, case: str
) -> None:
    """A wrong, expired, missing or foreign token: fatal "unauthorized" error, then close 1008."""
    token, why = token_cases()[case]
    async with server_factory(secured()) as srv:
        got, close_code = await join_with(srv, token)
        assert close_code == 1008
        errs = errors(got)
        assert [(e.code, e.fatal, e.in_reply_to) for e in errs] == [("unauthorized", True, "join")]
        assert why in errs[0].message
        assert not srv.rooms  # nothing was created for it


async def test_right_token_accepted(server_factory: ServerFactory) -> None:
    """A valid token joins; its user claim names the member in the room."""
    async with server_factory(secured()) as srv:
        token = make_token(SECRET, "lab", "alice", 600, time.time())
        conn = await ClientConnection.open(
            url_of(srv), room="lab", streams=("head",), rate=10.0, token=token
        )
        assert conn.joined is not None and conn.joined.room == "lab"
        assert srv.rooms["lab"].members[conn.user].name == "alice"
        await conn.close()


async def test_client_sees_join_refused(server_factory: ServerFactory) -> None:
    """ClientConnection.open raises JoinRefused("unauthorized") for an expired token."""
    async with server_factory(secured()) as srv:
        token = make_token(SECRET, "lab", "bob", 60, time.time() - 3600)
        with pytest.raises(JoinRefused) as info:
            await ClientConnection.open(
                url_of(srv), room="lab", streams=("head",), rate=10.0, token=token
            )
        assert info.value.code == "unauthorized"


async def test_open_server_ignores_tokens(server_factory: ServerFactory) -> None:
    """Without a secret any join is accepted, with or without a token."""
    async with server_factory() as srv:
        for token in (None, "v1.whatever.sig"):
            conn = await ClientConnection.open(
                url_of(srv), room="lab", streams=("head",), rate=10.0, token=token
            )
            assert conn.joined is not None
            await conn.close()
