"""A member parked after its connection dropped: the record the resume rules keep.

:class:`Parked` is plain data on a room and its member. It lives apart from
``server.resume`` (the rules of parking and resuming) so that a connection's
record (``server.peer``) can name the parked member its hello claimed without
importing those rules.
"""

from __future__ import annotations

from dataclasses import dataclass

from posecast.server.member import Member
from posecast.server.room import Room

__all__ = ["Parked"]


@dataclass
class Parked:
    """A member whose connection dropped, waiting for its client to come back."""

    user: int
    name: str
    room: Room
    member: Member
    since: float
    deadline: float
    token: str
    conn: int
