"""Access tokens: HMAC-SHA256 over (room, user, expiry), checked at join.

A token is ``v1.<payload>.<signature>``, both parts base64url without padding;
the payload is compact JSON ``{"room": R, "user": U, "exp": UNIX_SECONDS}``.
Wall-clock seconds are passed in (``now``), never read here, so expiry is
tested with a fake clock.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import json
from dataclasses import dataclass

from posecast.protocol.errors import PosecastError

__all__ = ["TokenClaims", "TokenError", "make_token", "token_permits", "verify_token"]

_PREFIX = "v1"


class TokenError(PosecastError, ValueError):
    """Why a token was refused, or cannot be made (short lowercase message, safe to send back)."""


@dataclass(frozen=True, slots=True)
class TokenClaims:
    room: str
    user: str
    exp: float


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode("ascii")


def _unb64(text: str) -> bytes:
    return base64.urlsafe_b64decode(text + "=" * (-len(text) % 4))


def _sign(secret: str, payload: str) -> str:
    mac = hmac.new(secret.encode(), f"{_PREFIX}.{payload}".encode(), hashlib.sha256)
    return _b64(mac.digest())


def make_token(secret: str, room: str, user: str, ttl: float, now: float) -> str:
    """A token for ``user`` in ``room``, valid for ``ttl`` seconds from ``now``."""
    if not secret:
        raise TokenError("the secret must not be empty")
    if ttl <= 0:
        raise TokenError("ttl must be positive")
    body = json.dumps({"room": room, "user": user, "exp": now + ttl}, separators=(",", ":"))
    payload = _b64(body.encode())
    return f"{_PREFIX}.{payload}.{_sign(secret, payload)}"


def verify_token(secret: str, token: str | None, room: str, now: float) -> TokenClaims:
    """The token's claims, or :class:`TokenError` saying what is wrong."""
    if not token:
        raise TokenError("missing access token")
    parts = token.split(".")
    if len(parts) != 3 or parts[0] != _PREFIX:
        raise TokenError("malformed access token")
    _, payload, sig = parts
    # Bytes: compare_digest raises TypeError on non-ASCII str, and tokens come from peers.
    if not hmac.compare_digest(_sign(secret, payload).encode(), sig.encode()):
        raise TokenError("invalid access token signature")
    try:
        claims = json.loads(_unb64(payload))
        tc = TokenClaims(
            room=str(claims["room"]), user=str(claims["user"]), exp=float(claims["exp"])
        )
    except (ValueError, KeyError, TypeError):
        raise TokenError("malformed access token") from None
    if tc.room != room:
        raise TokenError(f"access token is for room {tc.room!r}, not {room!r}")
    if now >= tc.exp:
        raise TokenError("access token expired")
    return tc


def token_permits(secret: str | None, token: str | None, room: str, now: float) -> bool:
    """Whether ``token`` admits its holder to ``room`` (always, without a secret)."""
    if secret is None:
        return True
    try:
        verify_token(secret, token, room, now)
    except TokenError:
        return False
    return True
