"""Resume tokens and the members parked under them, with their windows. Sans I/O.

The rules of parking and resuming (when a member is parked, what a resume
re-binds, who may claim it) are ``server.resume``'s; this module is the table
they keep: each parked member (``server.parked.Parked``) under the id part of its
resume token, the deadline its window closes at, and the counters the metrics
show. A token's first :data:`ID_LENGTH` characters name the parked member, the
rest is a secret compared in constant time (``hmac.compare_digest``).
"""

from __future__ import annotations

import hmac
import secrets

from posecast.server.limits import Deadlines
from posecast.server.parked import Parked

__all__ = ["ID_LENGTH", "Parking"]

#: Characters of a resume token that name its parked member (the rest is its secret).
ID_LENGTH = 12


class Parking:
    """Resume tokens of live connections and the members parked under them."""

    def __init__(self, window: float) -> None:
        self.window = window
        #: token id -> parked member (a token names one user; it is spent by a resume).
        self._parked: dict[str, Parked] = {}
        self._deadlines = Deadlines(self._still_parked)
        self._by_conn: dict[int, str] = {}
        #: Resumes done, windows closed, and resumes refused (a wrong secret, another
        #: user's access token: ``posecast_resumes_refused_total``).
        self.resumes = self.expired = self.refused = 0

    @staticmethod
    def new_token() -> str:
        """A token id and its secret (36 URL-safe characters: 72 + 144 random bits)."""
        return secrets.token_urlsafe(ID_LENGTH * 3 // 4) + secrets.token_urlsafe(18)

    def _still_parked(self, conn: int, deadline: float) -> bool:
        key = self._by_conn.get(conn)
        parked = None if key is None else self._parked.get(key)
        return parked is not None and parked.deadline == deadline

    def park(self, conn: int, parked: Parked) -> None:
        key = parked.token[:ID_LENGTH]
        self._parked[key] = parked
        self._by_conn[conn] = key
        self._deadlines.add(conn, parked.deadline)

    def find(self, token: str, now: float) -> Parked | None:
        """The member parked under ``token``'s id, window open (its secret unchecked)."""
        parked = self._parked.get(token[:ID_LENGTH])
        return None if parked is None or parked.deadline <= now else parked

    @staticmethod
    def matches(parked: Parked, token: str) -> bool:
        """Whether ``token`` is ``parked``'s whole token (constant time in its secret)."""
        return hmac.compare_digest(parked.token.encode(), token.encode())

    def claim(self, token: str | None, now: float) -> Parked | None:
        """The member parked under ``token`` if its window is still open (spent)."""
        parked = None if token is None else self.find(token, now)
        if parked is None or token is None or not self.matches(parked, token):
            return None
        del self._parked[parked.token[:ID_LENGTH]]
        self._by_conn.pop(parked.conn, None)
        self.resumes += 1
        return parked

    def has(self, token: str) -> bool:
        """Whether a member is parked under ``token``'s id (its secret unchecked)."""
        return token[:ID_LENGTH] in self._parked

    def tokens(self) -> dict[int, str]:
        """Parked users and the tokens they resume with."""
        return {p.user: p.token for p in self._parked.values()}

    def holds(self, user: int) -> bool:
        """Whether ``user`` is parked (its id must not be given to anyone else)."""
        return any(p.user == user for p in self._parked.values())

    def next(self) -> float | None:
        return self._deadlines.next()

    def expire(self, now: float) -> list[Parked]:
        """The parked members whose window closed by ``now``, removed."""
        out = []
        for conn in self._deadlines.pop_due(now):
            key = self._by_conn.pop(conn)
            parked = self._parked.pop(key, None)
            if parked is not None:
                self.expired += 1
                out.append(parked)
        return out
