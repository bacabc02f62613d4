"""The checks of ``posecast serve``'s options (and options of its own): each refusal is one
line (exit 2)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, TypedDict

import typer

from posecast.cli.common import _fail

if TYPE_CHECKING:
    from posecast.protocol.codec import Volume

__all__ = [
    "SERVE_LIMITS",
    "AllowOriginOption",
    "BudgetDegOption",
    "CapacityBacklogOption",
    "CapacityCpuOption",
    "CapacityLagOption",
    "HandshakeTimeoutOption",
    "MaxConnectRateOption",
    "MaxEventRateOption",
    "MaxJoinRateOption",
    "StallAfterOption",
    "StampLagOption",
    "ViewRatesOption",
    "allowed_origins",
    "check_serve_args",
    "check_tls_files",
    "cluster_config",
    "room_volume",
]

_LOG_LEVELS = ("debug", "info", "warning", "error")

#: The options of ``serve`` that are ServerConfig limits of the same name (none negative).
SERVE_LIMITS = (
    "ping_interval",
    "ping_timeout",
    "max_capture_age",
    "max_capture_ahead",
    "stamp_lag",
    "misbehaviour_burst",
    "misbehaviour_refill",
    "join_timeout",
    "handshake_timeout",
    "max_connect_rate",
    "max_join_rate",
    "max_event_rate",
    "max_connections",
    "max_connections_per_address",
    "max_rooms",
    "max_members",
    "max_recorded_rooms",
    "max_objects",
    "stall_after",
    "capacity_cpu",
    "capacity_lag",
    "capacity_backlog",
    "view_rates",
)

StampLagOption = Annotated[
    float,
    typer.Option(
        help="Move a stream's capture times later when they are older than its link "
        "explains by more than this (s; a lagging liar, server/stamps.py). 0: off.",
        envvar="POSECAST_STAMP_LAG",
    ),
]
HandshakeTimeoutOption = Annotated[
    float,
    typer.Option(
        help="Drop TCP connections whose websocket handshake is not done within this (s).",
        envvar="POSECAST_HANDSHAKE_TIMEOUT",
    ),
]
MaxConnectRateOption = Annotated[
    float,
    typer.Option(
        help="Connections a second from one address, across reconnects (bursts of 10 s "
        "worth); over it: closed 1013. 0: off.",
        envvar="POSECAST_MAX_CONNECT_RATE",
    ),
]
MaxJoinRateOption = Annotated[
    float,
    typer.Option(
        help="Joins a second from one address or token user, across reconnects (bursts of "
        "10 s worth); over it: room-full. 0: off.",
        envvar="POSECAST_MAX_JOIN_RATE",
    ),
]
MaxEventRateOption = Annotated[
    float,
    typer.Option(
        help="Events a second from one address or token user, across reconnects (bursts "
        "of 10 s worth); over it: closed 1008. 0: off.",
        envvar="POSECAST_MAX_EVENT_RATE",
    ),
]
ViewRatesOption = Annotated[
    bool,
    typer.Option(
        "--view-rates/--no-view-rates",
        help="Honour a join's error budget (budget_deg): send each peer to that subscriber "
        "at the lowest rate whose expected error, seen from its head, stays within it. "
        "Off: every peer at the snapshot rate.",
        envvar="POSECAST_VIEW_RATES",
    ),
]


def _budget(value: float | None) -> float | None:
    if value is not None and not 0.0 < value < 90.0:
        raise typer.BadParameter(f"{value:g} is not in (0, 90) degrees")
    return value


BudgetDegOption = Annotated[
    float | None,
    typer.Option(
        help="Join with this error budget (degrees of visual angle): the relay sends each "
        "peer at the lowest rate whose expected error, seen from the bot's head, stays "
        "within it (join.budget_deg). Default: every peer at the snapshot rate.",
        callback=_budget,
    ),
]
StallAfterOption = Annotated[
    float,
    typer.Option(
        help="Tell a member's peers it stalled (peer_stalled) when its updates stop this "
        "long (s) while its connection stays up, e.g. a frozen browser tab; 0: off.",
        envvar="POSECAST_STALL_AFTER",
    ),
]
# The capacity budget (server/capacity.py, docs/guides/deployment.md): over it, a
# hello or join is refused server-full (close 1013).
CapacityCpuOption = Annotated[
    float,
    typer.Option(
        help="Refuse new members (server-full, close 1013) when one more would make the "
        "relay use over this share of one CPU core, as measured; 0: off.",
        envvar="POSECAST_CAPACITY_CPU",
    ),
]
CapacityLagOption = Annotated[
    float,
    typer.Option(
        help="... or while over 1 % of its room ticks run later than this (s) and it uses "
        "at least 0.2 of a core or holds 16 members; 0: off.",
        envvar="POSECAST_CAPACITY_LAG",
    ),
]
CapacityBacklogOption = Annotated[
    int,
    typer.Option(
        help="... or while more than this many bytes wait unsent, over all connections; 0: off.",
        envvar="POSECAST_CAPACITY_BACKLOG",
    ),
]
AllowOriginOption = Annotated[
    str | None,
    typer.Option(
        help="Browser origins allowed to connect, comma-separated (e.g. "
        "https://app.example.com,http://localhost:8080); other pages get HTTP 403. "
        "Clients that send no Origin (not browsers) are not affected. [default: any]",
        envvar="POSECAST_ALLOW_ORIGIN",
    ),
]


class ClusterFields(TypedDict):
    cluster: str | None
    node: str | None


def cluster_config(cluster: str | None, node: str | None) -> ClusterFields:
    """--cluster and --node, checked now (a NATS that does not answer is a later line),
    as ``ServerConfig`` fields."""
    import re

    if cluster is not None:
        for url in cluster.split(","):
            if not re.fullmatch(r"(nats|tls)://[^\s/]+(:\d+)?/?", url.strip()):
                raise _fail(f"--cluster {url!r}: give a NATS URL such as nats://127.0.0.1:4222")
    if node is not None:
        if cluster is None:
            raise _fail("--node names this relay in a cluster: give --cluster too")
        if not re.fullmatch(r"[A-Za-z0-9_-]{1,64}", node):
            raise _fail(f"--node {node!r}: use 1-64 letters, digits, '-' or '_'")
    return {"cluster": cluster, "node": node}


def allowed_origins(text: str | None) -> tuple[str, ...] | None:
    """--allow-origin as ``ServerConfig.allow_origins`` (None: any origin)."""
    from posecast.server.http import parse_allow_origin

    if text is None:
        return None
    try:
        return parse_allow_origin(text)
    except ValueError as exc:
        raise _fail(f"--allow-origin: {exc}") from None


def check_tls_files(certfile: Path | None, keyfile: Path | None) -> None:
    """--certfile and --keyfile, checked now: both or neither, readable, a valid pair."""
    if (certfile is None) != (keyfile is None):
        raise _fail("give both --certfile and --keyfile for wss://, or neither")
    if certfile is not None and keyfile is not None:
        import ssl

        try:
            ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER).load_cert_chain(certfile, keyfile)
        except (OSError, ssl.SSLError) as exc:
            raise _fail(
                f"--certfile {certfile} / --keyfile {keyfile}: not a usable PEM "
                f"certificate chain and key ({exc})"
            ) from None


def room_volume(text: str, extent: float | None) -> Volume:
    """The room volume of --volume / --room-extent; a clear one-line error if unusable."""
    from posecast.protocol.codec import Volume
    from posecast.protocol.errors import PosecastError

    if extent is not None:
        if not 0 < extent <= 2048:
            raise _fail(f"--room-extent must be in (0, 2048] m, not {extent:g}")
        return Volume((-extent,) * 3, (extent,) * 3)
    try:
        values = [float(v) for v in text.split(",")]
        if len(values) != 6:
            raise ValueError("give six numbers")
        return Volume((values[0], values[1], values[2]), (values[3], values[4], values[5]))
    except (ValueError, PosecastError) as exc:
        raise _fail(f"--volume {text!r}: {exc} (X0,Y0,Z0,X1,Y1,Z1 in m, X0 < X1 ...)") from None


def check_serve_args(
    port: int,
    rate: float,
    min_rate: float,
    max_rate: float,
    record: Path | None,
    record_writer: str,
    log_level: str,
) -> None:
    """Refuse, in one line, a serve option that cannot be used (exit 2)."""
    if not 0 <= port <= 65535:
        raise _fail(f"--port must be in 0..65535 (0 picks a free port), not {port}")
    if not 0 < min_rate <= rate <= max_rate:
        raise _fail("need 0 < --min-rate <= --rate <= --max-rate")
    if record_writer not in ("process", "thread"):
        raise _fail(f"--record-writer must be process or thread, not {record_writer!r}")
    if log_level.lower() not in _LOG_LEVELS:
        raise _fail(f"--log-level must be one of {', '.join(_LOG_LEVELS)}, not {log_level!r}")
    if record is not None and record.exists() and not record.is_dir():
        raise _fail(
            f"--record {record} is a file; give a folder for the recordings "
            "(it is created if missing)"
        )
