"""The session state machine: one table shared by client and server sessions.

Both sides of a connection walk the same states; a message moves both of them
(the sender when it sends, the receiver when it receives), so one table keyed by
(state, who sends, kind of message) serves both roles. Rules:

1. The client speaks first, with ``hello``; the server answers ``welcome``.
   Nothing else may come before (a join before hello is "unexpected-message").
2. After welcome, ``ping``/``pong`` may flow either way until the end.
3. Then the client sends ``join``. The server answers ``joined``, or refuses with
   a non-fatal ``error`` whose ``in_reply_to`` is "join"; after a refusal the
   client may join again. A second join while joining or joined is an error.
4. Pose traffic only once joined: ``update``, ``set_rate`` and ``renew`` (a fresh
   access token) from the client;
   ``snapshot``, ``peer_joined``, ``peer_left``, ``peer_stalled`` and
   ``peer_resumed`` (and ``rate``, the rate the server chose for a client that
   joined with ``rate="auto"``) from the server; ``event``
   either way; the shared objects' ``object_create``, ``request_ownership`` and
   ``release`` from the client, ``object``, ``owner`` and ``object_removed`` from
   the server (``protocol.objects``).
5. Non-fatal ``error`` messages may flow either way after hello and change
   nothing (except rule 3's refusal).
6. ``bye`` from either side, or a fatal error (sent, received or detected), ends
   the session in any state. A CLOSED session ignores everything it receives
   and can still send ``error`` and ``bye``, to tell the peer why.
7. A message from the wrong side (a snapshot from a client, a join from a
   server) is never allowed: "unexpected-message", fatal.

Kinds are message types, except that an ``error`` is the kind ``error!`` when
fatal and ``error@join`` when it refuses a join.
"""

from __future__ import annotations

from enum import Enum

__all__ = [
    "ERROR_FATAL",
    "ERROR_JOIN",
    "TRANSITIONS",
    "Role",
    "State",
    "moves",
    "next_state",
]


class Role(Enum):
    """Which end of the connection sends a message."""

    CLIENT = "client"
    SERVER = "server"


class State(Enum):
    """Where a session is; both ends agree on it after each message."""

    START = "start"
    HELLO = "hello"
    READY = "ready"
    JOINING = "joining"
    JOINED = "joined"
    CLOSED = "closed"


ERROR_FATAL = "error!"
ERROR_JOIN = "error@join"

_C, _S = Role.CLIENT, Role.SERVER
_EITHER = (_C, _S)


def _stay(state: State, *pairs: tuple[tuple[Role, ...], str]) -> dict[tuple[Role, str], State]:
    return {(role, kind): state for roles, kind in pairs for role in roles}


# Kinds that keep the state where they are once welcome has been exchanged.
_CLOCK = ((_EITHER, "ping"), (_EITHER, "pong"), (_EITHER, "error"))

TRANSITIONS: dict[State, dict[tuple[Role, str], State]] = {
    State.START: {
        (_C, "hello"): State.HELLO,
    },
    State.HELLO: {
        (_S, "welcome"): State.READY,
        **_stay(State.HELLO, (_EITHER, "error")),
    },
    State.READY: {
        (_C, "join"): State.JOINING,
        # A refusal of a join the server never let reach JOINING (bad rate,
        # bad stream name) is still a refusal: nothing to undo.
        **_stay(State.READY, *_CLOCK, ((_S,), ERROR_JOIN)),
    },
    State.JOINING: {
        (_S, "joined"): State.JOINED,
        (_S, ERROR_JOIN): State.READY,
        **_stay(State.JOINING, *_CLOCK),
    },
    State.JOINED: _stay(
        State.JOINED,
        *_CLOCK,
        ((_C,), "update"),
        ((_C,), "set_rate"),
        ((_C,), "renew"),
        ((_S,), "snapshot"),
        ((_S,), "peer_joined"),
        ((_S,), "peer_left"),
        ((_S,), "peer_stalled"),
        ((_S,), "peer_resumed"),
        ((_S,), "rate"),
        (_EITHER, "event"),
        ((_C,), "object_create"),
        ((_C,), "request_ownership"),
        ((_C,), "release"),
        ((_S,), "object"),
        ((_S,), "owner"),
        ((_S,), "object_removed"),
    ),
    State.CLOSED: _stay(State.CLOSED, (_EITHER, "error"), (_EITHER, ERROR_FATAL), (_EITHER, "bye")),
}

# Rule 6: from any state, bye and fatal errors close.
for _state in State:
    for _role in _EITHER:
        TRANSITIONS[_state][(_role, "bye")] = State.CLOSED
        TRANSITIONS[_state][(_role, ERROR_FATAL)] = State.CLOSED


def next_state(state: State, sender: Role, kind: str) -> State | None:
    """The state after ``sender`` sends a message of ``kind``, or None if not allowed."""
    return TRANSITIONS[state].get((sender, kind))


def moves(sender: Role, state: State) -> dict[str, State]:
    """The kinds ``sender`` may send in ``state``, each with the state it leads to.

    Sessions keep this dict for their current state, so the per-message check is
    one lookup by kind (string hashes are cached; Enum hashes are not).
    """
    return {kind: new for (role, kind), new in TRANSITIONS[state].items() if role is sender}
