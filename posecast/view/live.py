"""Live view: a spectator of a room, drawn in the browser through chosen interpolators.

:class:`LiveView` joins a room as a spectator (``Join.spectator``: it publishes
nothing and nobody is told about it) and receives snapshots exactly as a bot
does: it *is* a bot's receive path (:class:`client.bot._Bot`: clock sync,
per-stream jitter buffers, adaptive playout delay D), minus publishing and
scoring. Its show loop renders every remote stream at ``server_now - D`` with
:func:`scenarios.receiver.render_buffers` (one batched call per method, as the
bots' render loop) at ``fps`` frames a second and poses the avatars of an
:class:`~posecast.view.scene.AvatarScene`: the first method solid, the others
as ghosts. The browser draws the scene at its own frame rate. An overlay shows
per remote user its keyframe rate, D, bytes/s and stalls.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import viser
from numpy.typing import NDArray
from websockets.exceptions import ConnectionClosed

from posecast.client.bot import BotConfig, _Bot
from posecast.client.connection import ClientConnection
from posecast.protocol import ROOM_USER, Join, Joined, PeerLeft, Snapshot
from posecast.protocol.codec import DEFAULT_VOLUME
from posecast.scenarios.receiver import render_buffers
from posecast.view.scene import AvatarScene

__all__ = ["LiveConfig", "LiveView", "UserStats", "run_live_view"]

#: The received logs a bot keeps for scoring are cut to this many keyframes a stream.
_KEEP = 256
#: Window of the overlay's rates (s).
_STATS_WINDOW = 2.0


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
    #: Draw users this far apart along x (m; 0: where they are, see ``AvatarScene``).
    spread: float = 0.0


@dataclass
class UserStats:
    """What the overlay shows for one remote user."""

    name: str
    #: (arrival time, new keyframes per stream, bytes) of the recent snapshots.
    recent: deque[tuple[float, float, float]] = field(default_factory=lambda: deque(maxlen=4096))
    stalls: int = 0
    frames: int = 0

    def rates(self, now: float) -> tuple[float, float]:
        """Keyframes/s (per stream) and bytes/s over the last window."""
        while self.recent and self.recent[0][0] < now - _STATS_WINDOW:
            self.recent.popleft()
        keys = sum(r[1] for r in self.recent)
        size = sum(r[2] for r in self.recent)
        return keys / _STATS_WINDOW, size / _STATS_WINDOW


def display_name(user: int, label: str | None) -> str:
    """``u3 walk01`` from a motion label (``trace:.../walk01.csv|t0=...``), else ``u3``."""
    if not label:
        return f"u{user}"
    source = label.split("|", 1)[0].rsplit("/", 1)[-1].removesuffix(".gz").removesuffix(".csv")
    return f"u{user} {source[:14]}"


class _Spectator(_Bot):
    """A bot that only watches: the bot's receive path, its buffers and its delay."""

    def __init__(
        self, cfg: BotConfig, view: LiveView, clock: Callable[[], float] = time.monotonic
    ) -> None:
        super().__init__(cfg, clock)
        self.view = view

    def _on_snapshot(self, snap: Snapshot, arrival: float, size: int) -> None:
        before = {k: len(rs.capture) for k, rs in self.remote.items()}
        super()._on_snapshot(snap, arrival, size)
        me = self.conn.user if self.conn else -1
        users = snap.users
        n = max(1, len(snap))
        per_user: dict[int, int] = {}
        for u in users.tolist():
            if u != me:
                per_user[u] = per_user.get(u, 0) + 1
        for user, count in per_user.items():
            mine = [(k, rs) for k, rs in self.remote.items() if k[0] == user]
            new = sum(len(rs.capture) - before.get(k, 0) for k, rs in mine)
            # Keyframes per stream (as the bots' report counts them) and a share of bytes.
            self.view.stats_for(user).recent.append(
                (arrival, new / max(1, len(mine)), size * count / n)
            )
        for rs in self.remote.values():  # nothing is scored: keep the logs short
            if len(rs.capture) > 2 * _KEEP:
                for log in (rs.capture, rs.arrival, rs.arrival_local, rs.sent, rs.poses):
                    del log[:-_KEEP]
                if rs.velocities:
                    del rs.velocities[:-_KEEP]

    def _on_event(self, ev: object, arrival: float, size: int) -> None:
        super()._on_event(ev, arrival, size)
        if isinstance(ev, PeerLeft):
            for key in [k for k in self.remote if k[0] == ev.user]:
                del self.remote[key]
            self.view.user_left(ev.user)

    async def watch(self, stop: float | None) -> None:
        cfg = self.cfg
        conn = await ClientConnection.connect(cfg.url, agent=cfg.name, clock=self.clock)
        self.conn = conn
        try:
            await self._sync(conn, cfg.initial_pings)
            await conn.send(
                Join(
                    room=cfg.room,
                    streams=("head",),  # nominal: a spectator owns nothing it may publish
                    rate=cfg.rate,
                    token=cfg.token,
                    wants_velocities=self.velocities,
                    spectator=True,
                )
            )
            joined = await conn._expect(Joined)
            assert isinstance(joined, Joined)
            conn.joined = joined
            for ev in conn.early_peers:
                self._add_peer(ev)
            async with asyncio.TaskGroup() as tg:
                tasks = [
                    tg.create_task(self._receive(conn)),
                    tg.create_task(self._pinger(conn, np.inf)),
                ]
                await self.view.show_loop(self, stop)
                for task in tasks:
                    task.cancel()
        except ConnectionClosed as exc:
            self._note_closed(exc)
        finally:
            with contextlib.suppress(ConnectionClosed):
                await conn.close()


class LiveView:
    """The live page: a viser server, the scene, the overlay and the spectator."""

    def __init__(self, cfg: LiveConfig, clock: Callable[[], float] = time.monotonic) -> None:
        self.cfg = cfg
        self.clock = clock
        self.server = viser.ViserServer(host=cfg.host, port=cfg.port, verbose=False)
        self.server.gui.configure_theme(show_logo=False)
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
        gui = self.server.gui
        gui.add_markdown(f"**posecast** room `{cfg.room}` at {cfg.url}")
        pause = gui.add_checkbox("pause", False)
        pause.on_update(lambda _: setattr(self, "paused", pause.value))
        self._ghosts = {m: gui.add_checkbox(f"show {m}", True) for m in cfg.methods}
        for m, box in self._ghosts.items():
            box.on_update(self.scene.layer_toggle(m))
        self._overlay = gui.add_markdown("waiting for users ...")
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
        self.stats.pop(user, None)
        self.scene.remove_user(user)

    def _names(self, bot: _Bot) -> dict[int, str]:
        names = {u: display_name(u, label) for u, (_, label) in bot.peers.items()}
        names[ROOM_USER] = "shared objects"
        return names

    @staticmethod
    def _stream_name(bot: _Bot, key: tuple[int, int], name: str) -> str:
        """A shared object's stream by its object name (``object`` messages), others as is."""
        if key[0] == ROOM_USER and bot.conn is not None:
            for obj, sid in bot.conn.session.objects.items():
                if sid == key[1]:
                    return obj
        return name

    def show_frame(self, bot: _Bot, now_srv: float) -> None:
        """Render every remote stream at ``now_srv - D`` and pose the avatars."""
        d = bot.delay.update(now_srv)
        t_play = now_srv - d
        keys = [k for k, rs in bot.remote.items() if len(rs.buffer)]
        frame = render_buffers([bot.remote[k].buffer for k in keys], t_play, self.cfg.methods)
        names = self._names(bot)
        shown: dict[tuple[int, int], dict[str, NDArray[np.float64]]] = {}
        with self.server.atomic():
            for j, key in enumerate(keys):
                rs = bot.remote[key]
                poses = {m: frame.poses[m][j] for m in self.cfg.methods}
                shown[key] = poses
                stream = self._stream_name(bot, key, rs.name)
                self.scene.show(key[0], names.get(key[0], f"user {key[0]}"), stream, poses)
                st = self.stats.get(key[0])
                if st is not None:
                    st.frames += 1
                    st.stalls += int(frame.stalled[j])
        self.last_frame = (t_play, d, shown)
        self.frames += 1

    def overlay_text(self, bot: _Bot, now_local: float) -> str:
        """The overlay: one row per remote user."""
        d_ms = 1000.0 * self.last_frame[1]
        names = self._names(bot)
        rows = [
            "| user | keyframes/s | D ms | B/s | stalls |",
            "|---|---:|---:|---:|---:|",
        ]
        for user in sorted(self.stats):
            st = self.stats[user]
            kps, bps = st.rates(now_local)
            share = st.stalls / max(1, st.frames)
            rows.append(
                f"| {names.get(user, st.name)} | {kps:.1f} | {d_ms:.0f} | {bps:.0f} "
                f"| {100 * share:.1f} % |"
            )
        return "\n".join(rows) if self.stats else "waiting for users ..."

    async def show_loop(self, bot: _Bot, stop: float | None) -> None:
        period = 1.0 / self.cfg.fps
        nxt = self.clock()
        next_overlay = nxt
        while bot.ending is None and (stop is None or self.clock() < stop):
            local = self.clock()
            if not self.paused:
                self.last_local = local
                self.show_frame(bot, local + bot.est.offset)
            if local >= next_overlay:
                self._overlay.content = self.overlay_text(bot, local)
                next_overlay = local + 0.5
            nxt += period
            if nxt < local:  # fell behind: resume on the grid, never burst
                nxt = local + period
            await asyncio.sleep(max(0.0, nxt - self.clock()))

    async def run(self) -> None:
        """Watch until ``duration`` (or until cancelled); the page stays up until :meth:`close`."""
        dur = self.cfg.duration
        stop = None if dur is None else self.clock() + dur
        await self.bot.watch(stop)

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
