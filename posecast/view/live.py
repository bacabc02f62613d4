"""Live view: a spectator of a room, drawn in the browser through chosen interpolators.

:class:`LiveView` joins a room as a spectator (``Join.spectator``: it publishes
nothing and nobody is told about it) and receives snapshots exactly as a bot
does: it is an adapter over the client core (:class:`client.core.ClientCore`:
clock sync, per-stream jitter buffers, adaptive playout delay D; fed by a
:class:`client.receiver.Receiver`, as a bot is), minus publishing and scoring. Its
show loop renders every remote stream at ``server_now - D`` with
:meth:`client.core.ClientCore.render` (one batched call per method, as the
bots' render loop) at ``fps`` frames a second and poses the avatars of an
:class:`~posecast.view.scene.AvatarScene`: the first method solid, the others
as ghosts. The browser draws the scene at its own frame rate. The panel's table
shows per remote user the rate the relay sends it (``GET /rates``, coloured on
a 5-30 Hz scale, as is a ball above its head), its keyframe rate, D, kB/s and
recent stalls, under a
warning when the receiver is starving (:func:`starving`); ``view from`` puts the
camera in a user's eyes, and the camera frames the room as users join.
"""

from __future__ import annotations

import asyncio
import contextlib
import html
import time
from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import viser
from numpy.typing import NDArray
from websockets.exceptions import ConnectionClosed

from posecast.client.bot import BotConfig
from posecast.client.connection import ClientConnection
from posecast.client.core import ClientCore, Observer
from posecast.client.receiver import Receiver
from posecast.client.reconnect import Reconnect, SessionEnd
from posecast.client.remote import RemoteStream
from posecast.interp import info as interp_info
from posecast.protocol import ROOM_USER
from posecast.protocol.codec import DEFAULT_VOLUME
from posecast.view.rates import fetch_rates, legend_html, rate_colour
from posecast.view.scene import AvatarScene, user_colour

__all__ = ["STARVED_STALLS", "LiveConfig", "LiveView", "UserStats", "run_live_view", "starving"]

#: The received logs a bot keeps for scoring are cut to this many keyframes a stream.
_KEEP = 256
#: Window of the overlay's rates (s).
_STATS_WINDOW = 2.0
#: Window of the overlay's stall share (s).
_STALL_WINDOW = 5.0
#: The overlay warns of starvation above this share of stalled frames.
STARVED_STALLS = 0.05
_CELL = "padding:2px 5px;text-align:right;white-space:nowrap;font-variant-numeric:tabular-nums"


@dataclass(frozen=True)
class LiveConfig:
    """What ``posecast view --url`` sets."""

    url: str
    room: str = "lobby"
    methods: tuple[str, ...] = ("soa", "dq-slerp", "motor-hermite")
    #: The page is served here (port 0: any free port).
    host: str = "127.0.0.1"
    port: int = 8080
    #: Snapshot rate asked of the server (Hz).
    rate: float = 15.0
    #: How often new poses are pushed to the page (Hz).
    fps: float = 60.0
    token: str | None = None
    #: Stop after this many seconds (None: until cancelled).
    duration: float | None = None
    #: Draw users this far apart along x (m; 0: where they are; None: where they are
    #: unless crowded, see ``AvatarScene``).
    spread: float | None = None


@dataclass
class UserStats:
    """What the overlay shows for one remote user."""

    name: str
    #: (arrival time, new keyframes per stream, bytes) of the recent snapshots.
    recent: deque[tuple[float, float, float]] = field(default_factory=lambda: deque(maxlen=4096))
    stalls: int = 0
    frames: int = 0
    #: (time, frames, stalls) at each overlay refresh, for the recent stall share.
    marks: deque[tuple[float, int, int]] = field(default_factory=lambda: deque(maxlen=64))
    #: The snapshot rate the relay sends this user now (Hz; None: not known).
    rate: float | None = None

    def rates(self, now: float) -> tuple[float, float]:
        """Keyframes/s (per stream) and bytes/s over the last window."""
        while self.recent and self.recent[0][0] < now - _STATS_WINDOW:
            self.recent.popleft()
        keys = sum(r[1] for r in self.recent)
        size = sum(r[2] for r in self.recent)
        return keys / _STATS_WINDOW, size / _STATS_WINDOW

    def recent_stalls(self, now: float) -> float:
        """Share of frames stalled over the last :data:`_STALL_WINDOW` s (all frames
        until that long has passed)."""
        self.marks.append((now, self.frames, self.stalls))
        while len(self.marks) > 1 and self.marks[1][0] <= now - _STALL_WINDOW:
            self.marks.popleft()
        _, f0, s0 = self.marks[0] if len(self.marks) > 1 else (now, 0, 0)
        return (self.stalls - s0) / max(1, self.frames - f0)


def starving(d: float, interval: float, stalls: float, kps: float, rate: float) -> str | None:
    """Why this receiver is starving (one line), or None: D above twice its nominal
    value (one interval plus 100 ms), over :data:`STARVED_STALLS` of the frames stalled,
    or keyframes short of 80 % of the asked rate."""
    why = []
    nominal = interval + 0.1
    if d > 2 * nominal:
        why.append(f"D {1000 * d:.0f} ms (about {1000 * nominal:.0f} ms when fed)")
    if stalls > STARVED_STALLS:
        why.append(f"{100 * stalls:.0f} % of frames stalled")
    if 0 < kps < 0.8 * rate:
        why.append(f"{kps:.1f} keyframes/s of {rate:g} asked")
    return ", ".join(why) or None


def _rate_cell(rate: float | None) -> str:
    """The rate column's cell: the rate in its colour of the scale (``-``: not known)."""
    if rate is None:
        return f'<td style="{_CELL}">-</td>'
    r, g, b = rate_colour(rate)
    return f'<td style="{_CELL};color:rgb({r},{g},{b});font-weight:bold">{rate:.3g}</td>'


def display_name(user: int, label: str | None) -> str:
    """``u3 walk01`` from a motion label (``trace:.../walk01.csv|t0=...``; ``u3 orbit``
    from ``synthetic:orbit|...``), else ``u3``."""
    if not label:
        return f"u{user}"
    source = label.split("|", 1)[0].split(":", 1)[-1].rsplit("/", 1)[-1]
    source = source.removesuffix(".gz").removesuffix(".csv")
    return f"u{user} {source[:14]}"


class _ViewLog(Observer):
    """What the viewer keeps of the core's reports: a short keyframe log per stream
    (nothing is scored) and the overlay's per-user rates; users who left go."""

    def __init__(self, view: LiveView) -> None:
        self.view = view
        self.core: ClientCore | None = None
        self.remote: dict[tuple[int, int], RemoteStream] = {}

    def stream_added(
        self, key: tuple[int, int], name: str, label: str | None, velocities: bool
    ) -> None:
        self.remote[key] = RemoteStream(key[0], key[1], name, label, sends_velocities=velocities)

    def keyframe(
        self,
        key: tuple[int, int],
        capture: float,
        arrival: float,
        arrival_local: float,
        sent: float,
        pose: NDArray[np.float32],
        velocity: NDArray[np.float64] | None,
    ) -> None:
        rs = self.remote[key]
        rs.capture.append(capture)
        rs.arrival.append(arrival)
        rs.arrival_local.append(arrival_local)
        rs.sent.append(sent)
        rs.poses.append(pose)
        if len(rs.capture) > 2 * _KEEP:  # nothing is scored: keep the logs short
            for log in (rs.capture, rs.arrival, rs.arrival_local, rs.sent, rs.poses):
                del log[:-_KEEP]

    def snapshot(
        self,
        arrival: float,
        arrival_local: float,
        sent: float,
        size: int,
        users: Mapping[int, tuple[int, int]],
    ) -> None:
        """Keyframes per stream (as the bots' report counts them) and a share of bytes."""
        n = max(1, sum(seen for seen, _ in users.values()))
        core = self.core
        for user, (seen, new) in users.items():
            streams = len(core.streams_of(user)) if core is not None else 1
            self.view.stats_for(user).recent.append(
                (arrival_local, new / max(1, streams), size * seen / n)
            )

    def peer_left(self, users: Sequence[int]) -> None:
        gone = set(users)
        for key in [k for k in self.remote if k[0] in gone]:
            del self.remote[key]
        for user in users:
            self.view.user_left(user)


class _Spectator:
    """The viewer's receive side: a :class:`~client.receiver.Receiver` over a
    :class:`~client.core.ClientCore`, joined as a spectator (it publishes nothing)."""

    def __init__(
        self, cfg: BotConfig, view: LiveView, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.cfg = cfg
        self.view = view
        self.clock = clock
        velocities = any(interp_info(m).needs_velocity for m in cfg.methods)
        self.log = _ViewLog(view)
        self.core = ClientCore(cfg.methods, cfg.rate, velocities=velocities, observer=self.log)
        self.log.core = self.core
        self.policy = Reconnect((cfg.url,), enabled=False)
        self.receiver = Receiver(self.core, self.policy, clock, ping_interval=cfg.ping_interval)

    @property
    def remote(self) -> dict[tuple[int, int], RemoteStream]:
        """The received keyframes of each remote stream (the recent ones)."""
        return self.log.remote

    @property
    def ending(self) -> SessionEnd | None:
        return self.policy.ending

    async def watch(self, stop: float | None) -> None:
        cfg, receiver = self.cfg, self.receiver
        conn = await ClientConnection.connect(cfg.url, agent=cfg.name, clock=self.clock)
        receiver.attach(conn)
        try:
            await receiver.sync(conn, cfg.initial_pings)
            await conn.join(
                room=cfg.room,
                streams=("head",),  # nominal: a spectator owns nothing it may publish
                rate=cfg.rate,
                token=cfg.token,
                wants_velocities=self.core.velocities,
                spectator=True,
            )
            receiver.attach(conn)
            async with asyncio.TaskGroup() as tg:
                tasks = [
                    tg.create_task(receiver.receive(conn)),
                    tg.create_task(receiver.ping(conn, np.inf)),
                ]
                await self.view.show_loop(self, stop)
                for task in tasks:
                    task.cancel()
        except ConnectionClosed as exc:
            receiver.closed(exc)
        finally:
            with contextlib.suppress(ConnectionClosed):
                await conn.close()


class LiveView:
    """The live page: a viser server, the scene, the overlay and the spectator."""

    def __init__(self, cfg: LiveConfig, clock: Callable[[], float] = time.monotonic) -> None:
        self.cfg = cfg
        self.clock = clock
        self.server = viser.ViserServer(host=cfg.host, port=cfg.port, verbose=False)
        self.server.gui.configure_theme(show_logo=False, control_width="large")
        self.server.gui.main_panel.dock_right()
        self.scene = AvatarScene(self.server, cfg.methods, DEFAULT_VOLUME, cfg.spread)
        self.stats: dict[int, UserStats] = {}
        self.frames = 0
        #: While set, the page keeps the last frame (receiving goes on).
        self.paused = False
        #: The view's clock when the last frame was rendered.
        self.last_local = 0.0
        #: The last frame shown: (playout time, D, {(user, stream id): {method: pose}}).
        self.last_frame: tuple[float, float, dict[tuple[int, int], dict[str, NDArray[np.float64]]]]
        self.last_frame = (0.0, 0.0, {})
        #: Why the receiver is starving, as the overlay last found (None: it is fed).
        self.starving: str | None = None
        gui = self.server.gui
        gui.add_markdown(f"**posecast** room `{cfg.room}` at {cfg.url}")
        pause = gui.add_checkbox("pause", False)
        pause.on_update(lambda _: setattr(self, "paused", pause.value))
        self._ghosts = {m: gui.add_checkbox(f"show {m}", True) for m in cfg.methods}
        for m, box in self._ghosts.items():
            box.on_update(self.scene.layer_toggle(m))
        self.eyes = gui.add_dropdown("view from", ["room"], initial_value="room")
        self.eyes.on_update(lambda _: self._set_eyes(str(self.eyes.value)))
        reframe = gui.add_button("frame the room")
        reframe.on_click(lambda _: self.scene.frame_users())
        self._warning = gui.add_html("")
        self._overlay = gui.add_html("waiting for users ...")
        self._framed: set[int] = set()
        #: Users who left while the page was paused.
        self._left: set[int] = set()
        self.bot = _Spectator(
            BotConfig(
                url=cfg.url,
                room=cfg.room,
                rate=cfg.rate,
                methods=cfg.methods,
                render_rate=cfg.fps,
                token=cfg.token,
                name="posecast-view",
            ),
            self,
            clock,
        )

    @property
    def port(self) -> int:
        return int(self.server.get_port())

    @property
    def url(self) -> str:
        return f"http://{self.cfg.host}:{self.port}"

    def stats_for(self, user: int) -> UserStats:
        st = self.stats.get(user)
        if st is None:
            st = self.stats[user] = UserStats(f"user {user}")
        return st

    def user_left(self, user: int) -> None:
        """Forget a user who left (while paused: once unpaused, the frozen frame keeps it)."""
        if self.paused:
            self._left.add(user)
            return
        self.stats.pop(user, None)
        self.scene.remove_user(user)
        self._framed.discard(user)
        self._eye_options()

    def _set_eyes(self, name: str) -> None:
        """``view from``: the room camera, or a user's eyes (``u3 ...``)."""
        user = None if name == "room" else int(name.split()[0][1:])
        self.scene.set_first_person(user if user in self.scene.avatars else None)

    def _eye_options(self) -> None:
        names = {u: av.name for u, av in self.scene.avatars.items() if u != ROOM_USER}
        options = ("room", *(names[u] for u in sorted(names)))
        if tuple(self.eyes.options) != options:
            self.eyes.options = options

    def _names(self, core: ClientCore) -> dict[int, str]:
        names = {u: display_name(u, peer.label) for u, peer in core.peers.items()}
        names[ROOM_USER] = "shared objects"
        return names

    def show_frame(self, core: ClientCore, local: float) -> None:
        """Render every remote stream at ``server_now - D`` (the room's D for all, as
        a spectator shows them) and pose the avatars."""
        playout = replace(core.playout(local), own={})
        t_play, d = playout.time, playout.delay
        keys = core.shown()
        frame = core.render(playout).frame
        names = self._names(core)
        shown: dict[tuple[int, int], dict[str, NDArray[np.float64]]] = {}
        with self.server.atomic():
            for j, key in enumerate(keys):
                poses = {m: frame.poses[m][j] for m in self.cfg.methods}
                shown[key] = poses
                stream = core.stream_name(key)
                st = self.stats.get(key[0])
                label = names.get(key[0], f"user {key[0]}")
                if st is not None and st.rate is not None:
                    label += f" {st.rate:.3g} Hz"
                self.scene.show(key[0], label, stream, poses)
                if st is not None:
                    st.frames += 1
                    st.stalls += int(frame.stalled[j])
        self.last_frame = (t_play, d, shown)
        self.frames += 1
        users = {k[0] for k in keys if k[0] != ROOM_USER}
        if users - self._framed:  # someone new: the room grew, frame it again
            self._framed |= users
            self.scene.frame_users()
            self._eye_options()

    def overlay_text(self, core: ClientCore, now_local: float) -> str:
        """The overlay: a table with one row per remote user (HTML, aligned columns)."""
        d = self.last_frame[1]
        names = self._names(core)
        head = "".join(
            f'<th style="{_CELL}">{h}</th>'
            for h in ("rate (Hz)", "keyframes/s", "D (ms)", "kB/s", "stalls (%)")
        )
        rows = [
            '<table style="border-collapse:collapse;font-size:12px;width:100%">',
            f'<tr><th style="text-align:left;padding:2px 6px">user</th>{head}</tr>',
        ]
        worst: tuple[float, str] | None = None
        for user in sorted(self.stats):
            st = self.stats[user]
            kps, bps = st.rates(now_local)
            share = st.recent_stalls(now_local)
            r, g, b = user_colour(user)
            swatch = f'<span style="color:rgb({r},{g},{b})">&#9679;</span>'
            cells = _rate_cell(st.rate) + "".join(
                f'<td style="{_CELL}">{v}</td>'
                for v in (
                    f"{kps:.1f}",
                    f"{1000 * d:.0f}",
                    f"{bps / 1000:.1f}",
                    f"{100 * share:.1f}",
                )
            )
            name = html.escape(names.get(user, st.name))
            rows.append(
                f'<tr><td style="padding:2px 6px;white-space:nowrap">{swatch} {name}</td>'
                f"{cells}</tr>"
            )
            why = starving(d, core.delay.interval, share, kps, self.cfg.rate)
            if why is not None and (worst is None or share > worst[0]):
                worst = (share, why)
        rows.append("</table>" + legend_html())
        self.starving = None if worst is None else worst[1]
        return "\n".join(rows) if self.stats else "waiting for users ..."

    def warning_text(self) -> str:
        """The starvation warning (empty while the receiver is fed)."""
        if self.starving is None:
            return ""
        return (
            '<div style="background:#fde8e8;border-left:4px solid #d33;padding:6px 8px;'
            'font-size:13px"><b>receiver starving</b>: '
            f"{html.escape(self.starving)}. What you see lags and stutters: this machine "
            "(or the link) is not keeping up; close other work, lower --fps, or ask a "
            "lower --rate.</div>"
        )

    async def show_loop(self, bot: _Spectator, stop: float | None) -> None:
        period = 1.0 / self.cfg.fps
        nxt = self.clock()
        next_overlay = nxt
        while bot.ending is None and (stop is None or self.clock() < stop):
            local = self.clock()
            if not self.paused:
                while self._left:
                    self.user_left(self._left.pop())
                self.last_local = local
                self.show_frame(bot.core, local)
            if local >= next_overlay:
                self._overlay.content = self.overlay_text(bot.core, local)
                self._warning.content = self.warning_text()
                next_overlay = local + 0.5
            nxt += period
            if nxt < local:  # fell behind: resume on the grid, never burst
                nxt = local + period
            await asyncio.sleep(max(0.0, nxt - self.clock()))

    async def run(self) -> None:
        """Watch until ``duration`` (or until cancelled); the page stays up until :meth:`close`."""
        dur = self.cfg.duration
        stop = None if dur is None else self.clock() + dur
        async with asyncio.TaskGroup() as tg:
            poll = tg.create_task(self.poll_rates())
            await self.bot.watch(stop)
            poll.cancel()

    async def poll_rates(self, period: float = 1.0) -> None:
        """Every ``period`` s, the rate the relay sends each user (``GET /rates``);
        a relay that does not answer it leaves the rates unknown."""
        while True:
            with contextlib.suppress(OSError, TimeoutError, ValueError, KeyError):
                for user, rate in (await fetch_rates(self.cfg.url, self.cfg.room)).items():
                    if user in self.stats:
                        self.stats[user].rate = rate
                        self.scene.set_rate_colour(user, rate_colour(rate))
            await asyncio.sleep(period)

    def close(self) -> None:
        self.server.stop()


async def run_live_view(cfg: LiveConfig, ready: Callable[[LiveView], None] | None = None) -> None:
    """Serve the live page and watch the room until ``cfg.duration`` or cancellation."""
    view = LiveView(cfg)
    try:
        if ready is not None:
            ready(view)
        await view.run()
    finally:
        view.close()
