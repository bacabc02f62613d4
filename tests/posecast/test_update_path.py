"""The update-path walk (posecast/bench/update_path.py): one traced update, real relay."""

from __future__ import annotations

from posecast.bench.update_path import Walk, walk


def test_walk_counts_files_and_returns() -> None:
    """A file visited again after another one counts as a return, once per visit."""
    w = Walk(["a.py", "b.py", "a.py", "c.py", "b.py"])
    assert (w.files, w.returns) == (3, 2)
    assert (Walk(["a.py", "b.py"]).files, Walk(["a.py", "b.py"]).returns) == (2, 0)


async def test_one_update_walks_through_the_relay() -> None:
    """The traced update goes in through the transport, the core and the room, and out
    through the transport again; the clients' and the library's files are not counted."""
    got = await walk("compact", warmup=2)
    relay = {"server/transport.py", "server/core.py", "server/room.py", "server/app.py"}
    assert relay <= set(got.visits)
    assert not any(v.startswith((".venv", "client/", "posecast/bench")) for v in got.visits)
    assert got.returns == len(got.visits) - got.files > 0
