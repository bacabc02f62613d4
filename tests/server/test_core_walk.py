"""The walk of one pose update through a real relay, read as a reader follows calls
(``posecast.bench.update_path``): no part calls up into whoever called it.

The tick's Wakes are returned by the room in the core's list of actions (no outbox
calling the core), a socket's unsent bytes are a number the core holds (no call into
the adapter), the connection hands the transport's messages to the core itself (no
hook called back), a snapshot's entries reach the codec as a list (no generator of
the room run by the protocol). The files entered from more than one caller file are
bounded by what the walk reaches today: core, room, member and the protocol's poses.
"""

from __future__ import annotations

import pytest

from posecast.bench.update_path import Walk, walk

#: Files entered from more than one caller file (core from connection and app; room
#: from core and rooms; member from room and core; protocol/poses.py from the decode
#: and the raw encoder): a regression adds one.
MULTI_PLACE = 4


def test_callbacks_and_places_are_read_from_the_calls() -> None:
    """A call into a file below the caller on the stack is a callback; a file entered
    from two caller files is in more than one place; the event loop is no caller."""
    w = Walk(
        ["a.py", "b.py", "a.py"],
        calls=[
            (None, "a.py", "read", False),
            ("a.py", "b.py", "parse", False),
            ("b.py", "a.py", "hook", True),
            ("b.py", "a.py", "hook", True),  # counted once
            (None, "c.py", "timer", False),
            ("c.py", "b.py", "tick", False),
        ],
    )
    assert w.callback_calls == ["b.py -> a.py:hook"] and w.callbacks == 1
    assert w.places == {"b.py": ["a.py", "c.py"]}  # a.py's other entry is the loop's
    assert w.multi_place == 1


@pytest.mark.parametrize("codec", ["compact", "raw"])
async def test_the_update_walk_calls_nothing_back(codec: str) -> None:
    got = await walk(codec, warmup=2)
    assert got.calls, "the walk saw no call"
    assert got.callback_calls == []
    assert got.multi_place <= MULTI_PLACE, got.places
