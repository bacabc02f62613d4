"""The relay's HTTP side: ``GET /healthz``, ``GET /metrics`` (Prometheus text), quiet logs.

Both answer on the websocket port, before the opening handshake
(:func:`process_request`, called by the adapter with websockets' sans-I/O
``ServerProtocol`` and the parsed request); any other path goes on to the
websocket handshake, and a plain HTTP request that asks for no upgrade gets
426. Plain HTTP requests are logged at DEBUG, not at websockets' INFO, so that
a scraper every 15 s fills no log.

Browser origins (:class:`OriginPolicy`, asked by the adapter before each
handshake): which browser pages may open a websocket to the relay. A browser
sends the page's origin (``scheme://host[:port]``) with every websocket
handshake; other clients (the Python bot, ``websocat``, a game engine) send
none. ``posecast serve --allow-origin`` (``POSECAST_ALLOW_ORIGIN``) lists the
origins allowed, comma-separated: a handshake from any other origin is refused
with HTTP 403 before it becomes a websocket. A handshake without an ``Origin``
header is never refused here (it is not a browser; tokens are what gate joins).

Without ``--allow-origin`` any origin may connect, as any client may connect to
a relay without ``--secret``: that keeps ``posecast web`` (served from whatever
address a headset on the LAN uses) and local development working, and the relay
logs the first browser origin it sees once, saying how to restrict them.
``docs/security.md`` says why this is safe for posecast (no cookies, no ambient
credentials: a page can do nothing a script could not) and when to set it.

Origins are compared after normalising both sides as browsers write them:
lowercase scheme and host, no default port (``:443`` for https, ``:80`` for
http), no trailing slash. ``null`` (a ``file://`` page, a sandboxed frame) is
allowed only if listed; ``*`` allows any origin (the default, said explicitly).
"""

from __future__ import annotations

import json
import logging
import math
import re
from collections.abc import Callable
from http import HTTPStatus
from typing import Any
from urllib.parse import parse_qs

from websockets.http11 import Request, Response
from websockets.server import ServerProtocol

from posecast.protocol import codec
from posecast.server import rates
from posecast.server.core import TICK_LAG_BUCKETS, RelayCore

__all__ = [
    "OriginPolicy",
    "QuietHttpLog",
    "metrics_text",
    "normalise_origin",
    "parse_allow_origin",
    "process_request",
]

log = logging.getLogger("posecast.server")


def process_request(
    core: RelayCore,
    clock: Callable[[], float] | None = None,
    extra: Callable[[], str] | None = None,
) -> Callable[[ServerProtocol, Request], Response | None]:
    """The hook answering /healthz and /metrics from ``core`` before the handshake
    (``clock``: the core's, for the tick overdue gauge; ``extra``: more metric lines,
    the cluster's); None: go on to the handshake."""

    def respond(protocol: ServerProtocol, request: Request) -> Response | None:
        path = request.path.split("?", 1)[0]
        if path == "/healthz":
            return protocol.reject(HTTPStatus.OK, "ok\n")
        if path == "/metrics":
            now = None if clock is None else clock()
            text = metrics_text(core, now) + ("" if extra is None else extra())
            response = protocol.reject(HTTPStatus.OK, text)
            # Same headers as /healthz (Date, Connection: close), Prometheus' type.
            del response.headers["Content-Type"]
            response.headers["Content-Type"] = "text/plain; version=0.0.4; charset=utf-8"
            return response
        if path == "/rates":
            room = parse_qs(request.path.partition("?")[2]).get("room", [""])[0]
            response = protocol.reject(HTTPStatus.OK, rates_json(core, room) + "\n")
            del response.headers["Content-Type"]
            response.headers["Content-Type"] = "application/json"
            return response
        if "upgrade" not in request.headers.get("Connection", "").lower():
            # A browser or a probe, not a websocket client: answer plainly here
            # (websockets' handshake would log the failed handshake as an error).
            return protocol.reject(
                HTTPStatus.UPGRADE_REQUIRED,
                "posecast relay: connect with a websocket client; GET /healthz, /metrics\n",
            )
        return None

    return respond


#: What websockets logs at INFO for every connection that never became a
#: websocket (a health probe, a metrics scrape, a rejected handshake).
_HTTP_ONLY_MESSAGES = frozenset({"HTTP response sent (%d %s)", "connection rejected (%d %s)"})


class QuietHttpLog(logging.LoggerAdapter):  # type: ignore[type-arg]
    """websockets' logger with plain HTTP requests demoted from INFO to DEBUG.

    websockets logs each HTTP response it sends instead of a handshake, and the
    end of that connection, at INFO: one scrape of /metrics every 15 s would be
    two lines of log each time. A websocket's own open and close stay at INFO.
    """

    def process(self, msg: Any, kwargs: Any) -> tuple[Any, Any]:
        return msg, kwargs  # keep websockets' own ``extra`` (its connection)

    def log(self, level: int, msg: Any, *args: Any, **kwargs: Any) -> None:
        if level == logging.INFO and _http_only(msg, kwargs.get("extra")):
            level = logging.DEBUG
        super().log(level, msg, *args, **kwargs)


def _http_only(msg: Any, extra: Any) -> bool:
    if not isinstance(msg, str):
        return False
    if msg in _HTTP_ONLY_MESSAGES:
        return True
    if msg != "connection closed" or not isinstance(extra, dict):
        return False
    try:
        response = extra["websocket"].response
    except (KeyError, AttributeError, ReferenceError):
        return False
    # No response yet: the peer left during the handshake, it never was a websocket.
    return response is None or response.status_code != HTTPStatus.SWITCHING_PROTOCOLS


def rates_json(core: RelayCore, room: str) -> str:
    """``GET /rates?room=NAME``: the snapshot rate the relay sends each member of a room
    now, ``{"room": NAME, "users": {"3": {"rate": 12.0, "asked_rate": 30.0, "auto": true}}}``
    (no such room: no users); a member with an error budget adds ``budget_deg`` and
    ``peers`` (peer id -> the rate it sends that peer's streams to the member now).
    User ids and rates only, no labels or streams."""
    found = core.rooms.get(room)
    users: dict[str, dict[str, Any]] = {
        str(m.user): {"rate": m.rate, "asked_rate": m.asked_rate, "auto": m.link_rate is not None}
        for m in (found.members.values() if found is not None else ())
    }
    for m in found.members.values() if found is not None else ():
        if m.view is not None:  # join.budget_deg: each peer's rate, the snapshot rate / k
            peers = {str(p): m.rate / k for p, k in sorted(m.view.k.items())}
            users[str(m.user)] |= {"budget_deg": m.view.budget_deg, "peers": peers}
    return json.dumps({"room": room, "users": users}, separators=(",", ":"))


def metrics_text(core: RelayCore, now: float | None = None) -> str:
    """Prometheus text of the relay's counters (``now``: the core's clock, for gauges)."""
    conns = core.connection_statistics()
    lines: list[str] = []

    def metric(name: str, kind: str, help_: str, samples: list[tuple[str, float]]) -> None:
        lines.append(f"# HELP {name} {help_}")
        lines.append(f"# TYPE {name} {kind}")
        for labels, value in samples:
            lines.append(f"{name}{labels} {_number(value)}")

    def total(*keys: str) -> list[tuple[str, float]]:
        # Ended connections plus live ones: a counter never goes down.
        return [("", sum(core.totals[k] + sum(getattr(c, k) for c in conns) for k in keys))]

    metric("posecast_connections", "gauge", "Open websocket connections.", [("", len(conns))])
    metric(
        "posecast_connections_closed_total",
        "counter",
        "Websocket connections that have ended.",
        [("", core.closed_connections)],
    )
    metric("posecast_rooms", "gauge", "Rooms with members.", [("", len(core.rooms))])
    metric(
        "posecast_recording_paused",
        "gauge",
        "1 while the recording of pose updates is paused (SIGUSR1; SIGUSR2 resumes).",
        [("", int(core.recording_paused))],
    )
    metric(
        "posecast_codec_info",
        "gauge",
        "Always 1; the label says what runs the compact codec: the compiled C accelerator"
        " or its pure-Python twin.",
        [(f'{{implementation="{_label(codec.IMPLEMENTATION)}"}}', 1)],
    )
    metric("posecast_frames_in_total", "counter", "Frames received.", total("frames_in"))
    metric("posecast_bytes_in_total", "counter", "Bytes received.", total("bytes_in"))
    metric("posecast_frames_out_total", "counter", "Frames sent.", total("frames_out"))
    metric("posecast_bytes_out_total", "counter", "Bytes sent.", total("bytes_out"))
    metric(
        "posecast_snapshot_skips_total",
        "counter",
        "Snapshots not delivered because a subscriber had not drained the previous one.",
        total("skips", "congestion_skips"),
    )
    metric(
        "posecast_flood_drops_total",
        "counter",
        "Pose updates and events dropped for exceeding the per-connection rate.",
        total("flood_drops"),
    )
    metric(
        "posecast_event_drops_total",
        "counter",
        "Reliable messages refused by a full event queue (the connection is closed).",
        total("event_drops"),
    )
    metric(
        "posecast_protocol_errors_total",
        "counter",
        "Protocol errors detected in what clients sent.",
        total("protocol_errors"),
    )
    metric(
        "posecast_recording_errors_total",
        "counter",
        "Room recordings that stopped writing (disk full, I/O error); the rooms keep serving.",
        [("", core.recording_errors)],
    )
    _limit_metrics(core, metric, total)
    _room_metrics(core, metric)
    _tick_lag_histogram(core, lines)
    lines += _rate_lines(core)
    if now is not None:
        _overdue_metric(core, metric, now)
        _capacity_metric(core, metric, now)
    return "\n".join(lines) + "\n"


Metric = Callable[[str, str, str, list[tuple[str, float]]], None]


def _rate_lines(core: RelayCore) -> list[str]:
    """The rates the relay chose: auto rates (per subscriber) and view rates (per peer)."""
    lines = []
    if isinstance(core.table.adapt, rates.AutoRates):
        lines += core.table.adapt.metric_lines(core.rooms.values())
    if core.table.view_rates is not None:
        budgets = sum(m.view is not None for r in core.rooms.values() for m in r.members.values())
        lines += core.table.view_rates.metric_lines(budgets)
    return lines


def _room_metrics(core: RelayCore, metric: Metric) -> None:
    """Members, poses sent and the largest tick lag of each room."""
    rooms = [r.statistics() for r in core.rooms.values()]
    metric(
        "posecast_room_members",
        "gauge",
        "Members per room.",
        [(f'{{room="{_label(r.name)}"}}', r.members) for r in rooms],
    )
    metric(
        "posecast_room_poses_out_total",
        "counter",
        "Poses sent in snapshots per room.",
        [(f'{{room="{_label(r.name)}"}}', r.poses_out) for r in rooms],
    )
    metric(
        "posecast_room_tick_lag_max_ms",
        "gauge",
        "Largest delay of a room tick behind its due time, since the room was created.",
        [(f'{{room="{_label(r.name)}"}}', r.tick_lag_max_ms) for r in rooms],
    )


def _tick_lag_histogram(core: RelayCore, lines: list[str]) -> None:
    """``posecast_tick_lag_seconds``: every member tick's lag behind its due time."""
    name = "posecast_tick_lag_seconds"
    lines.append(
        f"# HELP {name} Delay of each member's snapshot tick behind its due time "
        "(one observation per member tick, each room ticked at its own clock reading)."
    )
    lines.append(f"# TYPE {name} histogram")
    cumulative = 0
    for bound, count in zip((*TICK_LAG_BUCKETS, math.inf), core.tick_lag_counts, strict=True):
        cumulative += count
        le = "+Inf" if math.isinf(bound) else f"{bound:g}"
        lines.append(f'{name}_bucket{{le="{le}"}} {cumulative}')
    lines.append(f"{name}_sum {_number(core.tick_lag_sum)}")
    lines.append(f"{name}_count {cumulative}")


def _capacity_metric(core: RelayCore, metric: Metric, now: float) -> None:
    members = sum(len(r.members) for r in core.rooms.values())
    metric(
        "posecast_capacity_used_ratio",
        "gauge",
        "Each capacity signal with one more member, as a share of its budget (over 1: new"
        " members are refused server-full): cpu, lag (ticks over budget), backlog, growth"
        " (members admitted since the last CPU reading).",
        [(f'{{signal="{k}"}}', v) for k, v in core.capacity.usage(members, now).items()],
    )
    cap = core.capacity
    metric(
        "posecast_join_cpu_seconds_total",
        "counter",
        "CPU time spent on connections not yet members: handshakes, hellos, joins and"
        " refusals (a join storm's cost, kept out of the members' in the capacity).",
        [("", cap.join_cpu)],
    )
    metric(
        "posecast_ticks_late_total",
        "counter",
        "Room ticks later than the capacity's lag budget.",
        [("", cap.ticks_late)],
    )
    metric(
        "posecast_ticks_late_for_joins_total",
        "counter",
        "Of those, ticks on time but for the work on connections not yet members that ran"
        " after they were due (not counted against the lag budget).",
        [("", cap.ticks_late_for_joins)],
    )


def _overdue_metric(core: RelayCore, metric: Metric, now: float) -> None:
    due = core.next_deadline()
    metric(
        "posecast_tick_overdue_seconds",
        "gauge",
        "How far the earliest due room tick is behind the server clock right now "
        "(0: on time); grows while the relay is overloaded, before any tick runs late.",
        [("", 0.0 if due is None else max(0.0, now - due))],
    )


def _limit_metrics(
    core: RelayCore, metric: Metric, total: Callable[..., list[tuple[str, float]]]
) -> None:
    """What the limits refused or closed (docs/guides/security.md)."""
    metric(
        "posecast_updates_refused_total",
        "counter",
        "Pose updates refused: capture time too old or ahead of the server, position out of"
        " the room volume.",
        [
            ('{reason="stale-capture"}', total("stale_captures")[0][1]),
            ('{reason="future-capture"}', total("future_captures")[0][1]),
            ('{reason="out-of-bounds"}', total("out_of_bounds")[0][1]),
        ],
    )
    metric(
        "posecast_stamps_moved_total",
        "counter",
        "Pose updates whose capture times the relay moved later: older than the"
        " publisher's link explains by over stamp_lag (server/stamps.py, a lagging liar).",
        total("stamps_moved"),
    )
    metric(
        "posecast_connections_refused_total",
        "counter",
        "Connections closed at once (1013) for exceeding a connection limit.",
        [("", core.refused_connections)],
    )
    refused = dict(core.capacity.joins_refused)
    refused["room-full"] = refused.get("room-full", 0) + core.handshakes.guard.joins_refused
    metric(
        "posecast_joins_refused_total",
        "counter",
        "Hellos and joins refused: server-full (the relay at its measured capacity, close"
        " 1013), room-full (over max_rooms, max_members or max_recorded_rooms, or over"
        " the join rate of an address or token user).",
        [(f'{{code="{code}"}}', refused.get(code, 0)) for code in ("server-full", "room-full")],
    )
    metric(
        "posecast_join_timeouts_total",
        "counter",
        "Connections closed (1008) for not joining a room in time.",
        [("", core.join_timeouts)],
    )
    metric(
        "posecast_misbehaviour_closes_total",
        "counter",
        "Connections closed (1008) for exceeding their misbehaviour budget.",
        [("", core.misbehaviour_closes)],
    )
    shakes = core.handshakes
    metric(
        "posecast_handshakes_pending",
        "gauge",
        "TCP connections whose websocket handshake is under way (they count against"
        " max_connections and max_connections_per_address), and those over a cap held on a"
        " spare place that answers only /healthz and /metrics.",
        [('{place="handshake"}', shakes.pending), ('{place="spare"}', shakes.probes)],
    )
    metric(
        "posecast_handshakes_refused_total",
        "counter",
        "TCP connections dropped before their handshake: over a connection cap with no"
        " spare place left, not done within handshake_timeout, or pending for"
        " 0.5 s or more when a new connection came at the total cap.",
        [
            ('{reason="over-cap"}', shakes.refused),
            ('{reason="timeout"}', shakes.timeouts),
            ('{reason="evicted"}', shakes.evicted),
        ],
    )
    metric(
        "posecast_resumes_refused_total",
        "counter",
        "Resumes refused (unauthorized, 1008): a resume token with the wrong secret, or a"
        " resumed join with another user's access token; the parked member is untouched.",
        [("", core.parking.refused)],
    )


def _number(value: float) -> str:
    """A sample value: integers exactly (``:g`` would round 1234567 to 1.23457e+06)."""
    if isinstance(value, int) or (math.isfinite(value) and value == int(value)):
        return str(int(value))
    if math.isnan(value):
        return "NaN"
    if math.isinf(value):
        return "+Inf" if value > 0 else "-Inf"
    return repr(float(value))


def _label(value: str) -> str:
    return value.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n")


# -- browser origins ------------------------------------------------------------
_ORIGIN = re.compile(
    r"(?P<scheme>[a-z][a-z0-9+.-]*)://"
    r"(?P<host>\[[0-9a-f:.]+\]|[^\s/:@\[\]]+)(?::(?P<port>\d{1,5}))?/?"
)
_DEFAULT_PORTS = {"http": "80", "https": "443", "ws": "80", "wss": "443"}
#: Refused origins logged (once each) at most; the rest are counted only.
_LOGGED_REFUSALS = 32


def normalise_origin(text: str) -> str:
    """``text`` as a browser writes an origin; ValueError (one line) if it is not one."""
    value = text.strip().lower()
    if value in ("null", "*"):
        return value
    m = _ORIGIN.fullmatch(value)
    if m is None:
        raise ValueError(
            f"{text.strip()!r} is not an origin; write scheme://host[:port], "
            "e.g. https://app.example.com or http://localhost:8080"
        )
    scheme, host, port = m["scheme"], m["host"], m["port"]
    if port is not None:
        if int(port) > 65535:
            raise ValueError(f"{text.strip()!r}: port {port} is out of range")
        port = None if _DEFAULT_PORTS.get(scheme) == str(int(port)) else str(int(port))
    return f"{scheme}://{host}" + ("" if port is None else f":{port}")


def parse_allow_origin(text: str) -> tuple[str, ...] | None:
    """The origins of a ``--allow-origin`` list (None: any origin, ``*`` or empty)."""
    items = [normalise_origin(part) for part in text.split(",") if part.strip()]
    if not items or "*" in items:
        return None
    return tuple(dict.fromkeys(items))


class OriginPolicy:
    """Decides on each handshake's ``Origin`` header; sans I/O apart from its log lines."""

    def __init__(self, allowed: tuple[str, ...] | None) -> None:
        #: Normalised allowed origins (None: any).
        self.allowed = None if allowed is None else frozenset(map(normalise_origin, allowed))
        self.refused = 0
        self._noted_any = False
        self._logged: set[str] = set()

    def refusal(self, origin: str | None) -> str | None:
        """Why a handshake with this ``Origin`` header is refused (None: it is not)."""
        if origin is None:
            return None  # not a browser
        allowed = self.allowed
        if allowed is None:
            if not self._noted_any:
                self._noted_any = True
                log.info(
                    "a browser page from %s connected; any origin may connect "
                    "(restrict with --allow-origin)",
                    origin[:200],
                )
            return None
        try:
            key = normalise_origin(origin)
        except ValueError:
            key = origin
        if key in allowed:
            return None
        self.refused += 1
        shown = origin[:200]
        if shown not in self._logged and len(self._logged) < _LOGGED_REFUSALS:
            self._logged.add(shown)
            log.info("refused a browser page from %s: not in --allow-origin", shown)
        return f"origin {shown} is not allowed by this relay (--allow-origin)"
