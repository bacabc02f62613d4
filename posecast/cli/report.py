"""What ``demo`` and ``bots`` print: QoE and bots tables that fit 80 columns, each
with a legend, the wire figures, a verdict computed from the run, and next steps."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from posecast.cli.common import _fmt, _qoe_cells, _qoe_table, console, plain, small_table

__all__ = [
    "DEMO_DOC",
    "QOE_LEGEND",
    "demo_next_steps",
    "motion_note",
    "print_swarm",
    "verdict",
]

#: Where the verdict sends a reader for what the figures mean and what else was measured.
DEMO_DOC = "docs/concepts/qoe.md"

QOE_LEGEND = (
    "pos/rot: how far each remote head and hand is shown from where its sender "
    "truly had it; tip: the same for a point 20 cm in front of the device, a held tool's "
    "tip (the headline); p50/p95: median and 95th percentile; stall: share of "
    "frames with no newer keyframe to move toward (the pose is held)."
)
_BOTS_LEGEND = (
    "keyframes/s: new poses received per remote device a second; D: playout delay, "
    "how far behind real time others are shown (network and the gap between "
    "keyframes); render: CPU per 90 Hz frame; age: a snapshot's send-to-receipt time."
)
_WIRE_LEGEND = (
    "bytes per remote pose: what the relay sends for one device of one other user "
    "(framing included); the fewer, the more users a link carries."
)
#: Two methods within this share of each other's hands p95 tip error are a tie.
TIE_SHARE = 0.02


def print_swarm(report: dict[str, Any], title: str) -> None:
    """The demo/bots result: QoE per method and class, then bots and wire figures."""
    has_qoe = any(report["methods"].values())
    if has_qoe:
        table = _qoe_table(title, ("method", "class"))
        for method, classes in report["methods"].items():
            for cls, st in classes.items():
                table.add_row(method, cls, *_qoe_cells(st))
            table.add_section()
        console.print(table)
        plain(QOE_LEGEND)
    else:
        why = (
            "a lone bot has nobody to watch (run 2 or more bots)"
            if len(report["bots"]) == 1
            else "no bot received another's poses before the run ended"
        )
        plain(f"{title}: no QoE: {why}")
    _print_objects(report)
    _print_bots(report)
    wire = report["wire"]
    per_pose = wire["bytes_per_pose"]
    if per_pose == per_pose:  # no remote pose at all (a lone bot): nothing to divide
        plain(
            f"wire: {per_pose:.1f} bytes per remote pose, "
            f"{wire['bytes_per_s'] / 1000:.1f} kB/s per bot downstream"
            + (
                " (velocity keyframes, 12 B a pose included)"
                if wire.get("velocity_keyframes")
                else ""
            )
        )
        plain(_WIRE_LEGEND)
    else:
        plain("wire: no remote poses received, so no bytes per pose")  # not "nan"


def _print_bots(report: dict[str, Any]) -> None:
    """One row per bot; with a cluster, its snapshot gap and node."""
    from posecast.cli.cluster import print_cluster

    cluster = report.get("cluster")
    bots = small_table("bots")
    auto = any(b.get("auto_rate") for b in report["bots"])  # --rate auto: the relay's choice
    asked = auto and "rates" in report  # the demo asked the relay its rates (GET /rates)
    cols: tuple[str, ...] = ("id", "name", *(("chosen\nHz",) if auto else ()))
    cols += ("relay\nmean Hz",) if asked else ()
    cols += ("keyframes\n/s",)
    cols += ("D\nms", "render\nms/frame", "clock rtt\nms", "age\nms")
    cols += ("gap\ns",) if cluster else ()
    for col in (*cols, *(("node",) if cluster else ())):
        bots.add_column(col, justify="right")
    for b in report["bots"]:
        bots.add_row(
            str(b["id"]),
            b["name"],
            *((_fmt(b["granted_hz"]),) if auto else ()),
            *((_fmt(b.get("relay_mean_hz", float("nan"))),) if asked else ()),
            _fmt(b["rate_hz"]),
            _fmt(b["delay_ms"]),
            _fmt(b["render_cpu_ms_per_frame"], 2),
            _fmt(b["clock_rtt_ms"], 2),
            _fmt(b["snapshot_age_ms_p50"], 2),
            *((_fmt(b["snapshot_gap_s"], 2),) if cluster else ()),
            *((str(b.get("node")) + (" (owner)" if b.get("node") == cluster["owner"] else ""),)
              if cluster else ()),
        )  # fmt: skip
    console.print(bots)
    plain(_BOTS_LEGEND)
    if auto:
        plain("chosen: the snapshot rate the relay chose last for the bot (--rate auto).")
    if asked:
        plain(
            "relay mean: the mean of the rates the relay said it sent the bot, asked "
            f"{report['rates']['answers']} times ({report['rates']['source']})."
        )
    if cluster:
        print_cluster(cluster)
    _print_peer_rates(report)


def _print_peer_rates(report: dict[str, Any]) -> None:
    """With an error budget (``--budget-deg``): the mean rate the relay sent each peer's
    streams to each bot, as it said (``GET /rates``); one column a peer up to 8 peers,
    else their lowest, mean and highest."""
    bots = [b for b in report["bots"] if b.get("relay_peer_mean_hz")]
    if not bots:
        return
    peers = sorted({int(p) for b in bots for p in b["relay_peer_mean_hz"]})
    wide = len(peers) > 8
    table = small_table("rates per peer (Hz)")
    cols = ("lowest", "mean", "highest") if wide else tuple(str(p) for p in peers)
    for col in ("id", "name", *cols):
        table.add_column(col, justify="right")
    for b in bots:
        got = {int(p): r for p, r in b["relay_peer_mean_hz"].items()}
        cells = (
            [_fmt(min(got.values())), _fmt(sum(got.values()) / len(got)), _fmt(max(got.values()))]
            if wide
            else [_fmt(got[p]) if p in got else "-" for p in peers]
        )
        table.add_row(str(b["id"]), b["name"], *cells)
    console.print(table)
    plain(
        "rates per peer: the mean rate the relay said it sent each peer's streams (columns: "
        "peer ids) to the bot within its error budget (--budget-deg): near peers more "
        "often, far ones less; a bot's own column is its own streams, echoed."
    )


def _print_objects(report: dict[str, Any]) -> None:
    """The shared object's smoothness (velocity error of its tip), its tip error as
    each receiving bot saw it, and its handovers."""
    rows = [
        (method, cls, st)
        for method, classes in report["methods"].items()
        for cls, st in classes.items()
        if cls.startswith("object")
    ]
    if not rows:
        return
    seen = [b for b in report["bots"] if b.get("object")]
    table = small_table("object: tip velocity error, and tip error per bot")
    for col in ("method", "class"):
        table.add_column(col, no_wrap=True)
    for col in (
        "vel p50\nm/s",
        "vel p95\nm/s",
        *(f"tip p95 mm\n{b['role'] or b['name']}" for b in seen),
    ):
        table.add_column(col, justify="right")
    for method, cls, st in rows:
        per_bot = [b["object"].get(method, {}).get(cls, {}).get("tip_p95_mm") for b in seen]
        table.add_row(
            method,
            cls,
            _fmt(st["vel_p50_mps"], 2),
            _fmt(st["vel_p95_mps"], 2),
            *(_fmt(x) if x is not None else "-" for x in per_bot),
        )
    console.print(table)
    counts = report.get("objects", {}).get("handovers")
    if counts:
        told = ", ".join(f"{n} {reason}" for reason, n in counts.items())
        plain(f"object handovers: {told}")


def motion_note(motion: str) -> str:
    """What the motion is, in a few words, for the verdict."""
    if motion.startswith("traces:"):
        return "Beat Saber, a worst case for hands"
    if motion.startswith("synthetic"):
        return "synthetic motion, calmer than a game"
    if motion == "throw-catch":
        return "the throw-catch scene"
    return f"the trace {Path(motion).name}"


def verdict(
    methods: dict[str, dict[str, dict[str, float]]],
    rate: float | str,
    motion: str,
    starved: bool = False,
    doc: str = DEMO_DOC,
    lone: bool = False,
) -> str:
    """One line from the run's own numbers: which method shows the hands closest to
    the truth at p95 (tip error), by how much against ``soa`` (what engines do today,
    or the runner-up when soa wins); a tie within :data:`TIE_SHARE`."""
    hands = {
        m: classes["hands"]["tip_p95_mm"]
        for m, classes in methods.items()
        if "hands" in classes and classes["hands"]["tip_p95_mm"] == classes["hands"]["tip_p95_mm"]
    }
    at = f"{rate:g} Hz" if isinstance(rate, int | float) else rate  # or: auto rates
    where = f"at {at} on this motion ({motion_note(motion)})"
    tail = "; this machine starved the session: rerun on an idle one" if starved else ""
    tail += f"; see {doc}"
    if not hands:
        why = "a lone bot sees nobody (run 2 or more bots)" if lone else "no hands were received"
        return f"verdict: none {where}: {why}{tail}"
    ranked = sorted(hands, key=lambda m: hands[m])
    best = ranked[0]
    if len(ranked) == 1:
        return f"verdict: {where}, {best} shows the hands {hands[best]:.1f} mm off (p95 tip){tail}"
    other = "soa" if best != "soa" and "soa" in hands else ranked[1]
    lo, hi = hands[best], hands[other]
    if hi - lo <= TIE_SHARE * hi:
        return (
            f"verdict: {where}, {best} and {other} tie on the hands: {lo:.1f} vs "
            f"{hi:.1f} mm p95 tip error (within {100 * TIE_SHARE:g} %){tail}"
        )
    return (
        f"verdict: {where}, {best} beats {other} by {hi - lo:.1f} mm p95 on the hands "
        f"({lo:.1f} vs {hi:.1f} mm tip error){tail}"
    )


def demo_next_steps(recording: str | None, motion: str) -> list[str]:
    """The commands to try after the demo, one per line, each with what it shows."""
    steps = [("posecast demo --view", "watch the room in 3D in your browser")]
    if not motion.startswith("synthetic"):
        steps.append(("posecast demo --motion synthetic", "calmer motion than Beat Saber"))
    steps.append(("posecast demo --rate 30", "the same at the rate engines send today"))
    steps.append(("posecast demo --adaptive", "the relay chooses each bot's rate"))
    if recording:
        steps.append((f"posecast replay --offline {recording}", "score the recording again"))
    steps.append(("posecast table1 --traces traces:sample --out t1", "the paper's Table 1"))
    width = min(34, max(len(cmd) for cmd, _ in steps))  # a line fits 80 columns
    return ["next:", *(f"  {cmd:<{width}}  # {what}" for cmd, what in steps)]
