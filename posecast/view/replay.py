"""Replay view: a recording in the browser, with a timeline a recording player has.

:class:`ReplayView` draws a :class:`~posecast.view.timeline.ReplayModel`: the
ground truth of every selected user solid in the user's colour and each
interpolator (keyframes at a chosen rate) as a ghost in its own colour. Its
panel holds the timeline: play/pause, speed (0.1x-10x), the time slider (drag
to seek: the state at that time shows at once), frame steps back and forth,
loop, the keyframe rate, which users and streams to show, which methods to
ghost, and a strip with the chosen method's tip error over time.

GUI callbacks run on viser's thread; they only set fields of the view (and show
the state of a seek at once, under the view's lock); :meth:`ReplayView.run`
advances time and shows frames on the caller's event loop.
"""

from __future__ import annotations

import asyncio
import os
import threading
import time
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

import numpy as np
import viser
import viser.uplot

from posecast.view.scene import AvatarScene, method_colour, user_colour
from posecast.view.timeline import TRUTH, ReplayModel

__all__ = ["MAX_SPEED", "MIN_SPEED", "TRAIL_SECONDS", "ReplayView"]

MIN_SPEED, MAX_SPEED = 0.1, 10.0
#: Seconds of hand motion a trail shows.
TRAIL_SECONDS = 1.0


class ReplayView:
    """The replay page: a viser server, the scene, the timeline panel and the model."""

    def __init__(
        self,
        path: str | os.PathLike[str],
        methods: Sequence[str] = ("soa", "dq-slerp", "motor-hermite"),
        *,
        rate: float = 10.0,
        host: str = "127.0.0.1",
        port: int = 8080,
        fps: float = 60.0,
        loop: bool = True,
        spread: float | None = None,
        model: ReplayModel | None = None,
        trail: float = TRAIL_SECONDS,
    ) -> None:
        self.model = model or ReplayModel(path, methods, rate)
        self.fps = fps
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.gui.configure_theme(show_logo=False)
        self.server.gui.main_panel.dock_right()
        self.scene = AvatarScene(self.server, (TRUTH, *self.model.methods), spread=spread)
        firsts = []
        for user in self.model.users:  # users keep their recorded order across the page
            head = self.model.first_head(user)
            if head is not None:
                self.scene.anchor(user, head)
                firsts.append(head[:3] + np.array([self.scene.offset(user), 0.0, 0.0]))
            else:
                self.scene.offset(user)
        if firsts:
            self.scene.frame(np.array(firsts))
        #: Seconds of hand motion drawn behind each controller (0: no trails).
        self.trail = trail
        self.lock = threading.Lock()
        self.t = self.model.start
        self.playing = False
        self.speed = 1.0
        self.loop = loop
        self.frames = 0
        self._build_gui(rate)
        self.show(self.t)

    # -- the panel ------------------------------------------------------------------

    def _build_gui(self, rate: float) -> None:
        gui, m = self.server.gui, self.model
        gui.add_markdown(f"**posecast replay** `{os.path.basename(str(m.path))}`")
        self.play_button = gui.add_button("Play", icon=viser.Icon.PLAYER_PLAY)
        self.play_button.on_click(lambda _: self.set_playing(not self.playing))
        self.time_slider = gui.add_slider("time (s)", 0.0, max(0.01, m.end - m.start), 0.01, 0.0)
        self.time_slider.on_update(self._on_seek)
        back = gui.add_button("◀ frame")
        fwd = gui.add_button("frame ▶")
        back.on_click(lambda _: self.step(-1))
        fwd.on_click(lambda _: self.step(+1))
        self.speed_slider = gui.add_slider("speed", MIN_SPEED, MAX_SPEED, 0.1, 1.0)
        self.speed_slider.on_update(lambda _: setattr(self, "speed", self.speed_slider.value))
        self.loop_box = gui.add_checkbox("loop", self.loop)
        self.loop_box.on_update(lambda _: setattr(self, "loop", self.loop_box.value))
        self.rate_slider = gui.add_slider("keyframe rate (Hz)", 1, 30, 1, round(rate))
        self.rate_slider.on_update(lambda _: self._set_rate(float(self.rate_slider.value)))
        with gui.add_folder("methods"):
            for meth in m.methods:
                box = gui.add_checkbox(f"ghost {meth}", True)
                box.on_update(self.scene.layer_toggle(meth))
            self.error_method = gui.add_dropdown("tip error of", m.methods)
            self.error_method.on_update(lambda _: self._update_strip())
            self.trail_box = gui.add_checkbox("hand trails", self.trail > 0)
            self.trail_box.on_update(lambda _: self.show(self.t))
        names = ("room", *(f"u{u}" for u in m.users))
        self.eyes = gui.add_dropdown("view from", names, initial_value="room")
        self.eyes.on_update(lambda _: self._set_eyes(str(self.eyes.value)))
        with gui.add_folder("users and streams"):
            for user in m.users:
                name = next(tr.user_name for tr in m.tracks if tr.user == user)
                ubox = gui.add_checkbox(f"u{user} {name}"[:32], True)
                ubox.on_update(partial(self._select_user, user))
            for sname in m.stream_names:
                sbox = gui.add_checkbox(sname, True)
                sbox.on_update(partial(self._select_stream, sname))
        self.strip: Any = None
        self._update_strip()

    def _update_strip(self) -> None:
        method = str(self.error_method.value)
        x, y = self.model.error_strip(method)
        data = (x, np.nan_to_num(y, nan=0.0))
        if self.strip is None:
            self.strip = self.server.gui.add_uplot(
                data,
                (
                    viser.uplot.Series(label="t (s)"),
                    viser.uplot.Series(label="tip mm", stroke="red", width=1),
                ),
                title="worst tip error (mm)",
                scales={"x": {"time": False}},
                aspect=3.0,
            )
        else:
            self.strip.data = data
        self.strip.title = f"{method}: worst tip error (mm) at {self.model.rate:g} Hz"

    # -- controls (any thread) -------------------------------------------------------

    def set_playing(self, playing: bool) -> None:
        self.playing = playing
        self.play_button.label = "Pause" if playing else "Play"
        self.play_button.icon = viser.Icon.PLAYER_PAUSE if playing else viser.Icon.PLAYER_PLAY

    def _on_seek(self, event: viser.GuiEvent[Any]) -> None:
        if event.client is None:  # the play loop moved the slider: not a seek
            return
        self.seek(self.model.start + float(self.time_slider.value))

    def seek(self, t: float) -> None:
        """Jump to ``t`` (recorded server time) and show that state at once."""
        self.t = min(max(t, self.model.start), self.model.end)
        self.show(self.t)

    def step(self, direction: int) -> None:
        """Pause and move to the next (previous) recorded sample of the shown streams."""
        self.set_playing(False)
        self.seek(self.model.step(self.t, direction))

    def _set_rate(self, rate: float) -> None:
        with self.lock:
            self.model.set_rate(rate)
        self._update_strip()
        self.show(self.t)

    def _set_eyes(self, name: str) -> None:
        """``view from``: the room camera, or a user's eyes (``u3``)."""
        with self.lock:
            self.scene.set_first_person(None if name == "room" else int(name[1:]))

    def _select_user(self, user: int, event: viser.GuiEvent[Any]) -> None:
        on = bool(event.target.value)
        (self.model.selected_users.add if on else self.model.selected_users.discard)(user)
        self.scene.set_user_visible(user, on)
        self._update_strip()
        self.show(self.t)

    def _select_stream(self, name: str, event: viser.GuiEvent[Any]) -> None:
        on = bool(event.target.value)
        (self.model.selected_streams.add if on else self.model.selected_streams.discard)(name)
        for user in self.model.users:
            (self.scene.unhide_stream if on else self.scene.hide_stream)(user, name)
        self._update_strip()
        self.show(self.t)

    # -- drawing ---------------------------------------------------------------------

    def show(self, t: float) -> None:
        """Pose every selected stream as it was at ``t``; move the time slider there."""
        with self.lock:
            state = self.model.state_at(t)
            names = {tr.user: tr.user_name for tr in self.model.tracks}
            with self.server.atomic():
                for (user, stream), poses in state.items():
                    if user in self.model.selected_users:
                        self.scene.show(user, f"u{user} {names[user]}", stream, poses)
                self._draw_trails(t)
                self.time_slider.value = round(t - self.model.start, 2)  # type: ignore[misc]
            self.frames += 1

    def _draw_trails(self, t: float) -> None:
        """The hands' last ``trail`` seconds: the truth in the user's colour, the
        ``tip error of`` method in its own (where it strays is its error)."""
        scene = self.server.scene
        method = str(self.error_method.value)
        on = self.trail > 0 and bool(self.trail_box.value)
        for layer, colour_of in (
            (TRUTH, user_colour),
            (method, lambda _u: method_colour(method)),
        ):
            segs, cols = [], []
            for tr, path in self.model.trails(t, self.trail, layer) if on else []:
                if len(path) < 2:
                    continue
                path = path + np.array([self.scene.offset(tr.user), 0.0, 0.0])
                segs.append(np.stack([path[:-1], path[1:]], axis=1))
                cols.append(np.broadcast_to(colour_of(tr.user), (len(path) - 1, 2, 3)))
            name = f"/trails/{'truth' if layer == TRUTH else 'method'}"
            if segs:
                scene.add_line_segments(
                    name,
                    np.concatenate(segs),
                    np.concatenate(cols).astype(np.uint8),
                    thickness=4.0,
                    thickness_units="screen",
                )
            else:
                scene.remove_by_name(name)

    def advance(self, dt: float) -> None:
        """Move time on by ``dt`` wall seconds at the current speed (loop or stop at the end)."""
        if not self.playing:
            return
        m = self.model
        t = self.t + dt * self.speed
        if t > m.end:
            if self.loop:
                t = m.start + (t - m.end) % max(1e-9, m.end - m.start)
            else:
                t = m.end
                self.set_playing(False)
        self.t = t
        self.show(t)

    async def run(
        self, duration: float | None = None, clock: Callable[[], float] = time.monotonic
    ) -> None:
        """Play (when playing) until ``duration`` seconds passed, or until cancelled."""
        period = 1.0 / self.fps
        start = last = clock()
        while duration is None or clock() - start < duration:
            await asyncio.sleep(period)
            now = clock()
            self.advance(now - last)
            last = now

    @property
    def port(self) -> int:
        return int(self.server.get_port())

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def close(self) -> None:
        self.server.stop()
