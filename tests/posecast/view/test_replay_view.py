"""The replay viewer: its model on a real recording, and its page in a real headless Chromium."""

from __future__ import annotations

import asyncio
from pathlib import Path

import numpy as np
import pytest
from pagekit import project, saturated_near, scene_ready, settled_canvas, until
from playwright.async_api import Page
from support import poll_until

from posecast.recorder.reader import SessionReader
from posecast.recorder.replay import synthesize_recording
from posecast.view.replay import ReplayView
from posecast.view.timeline import TRUTH, ReplayModel

METHODS = ("soa", "dq-slerp", "motor-hermite")


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """3 users playing the bundled real traces for 6 s, with velocities, through the recorder."""
    folder = tmp_path_factory.mktemp("rec")
    return synthesize_recording(folder, users=3, rate=30.0, duration=6.0, velocities=True)


def recorded_at(path: Path, user: int, stream: str, t: float) -> np.ndarray:
    """The recorded pose of a stream at ``t``: its last update captured by then."""
    with SessionReader(path) as reader:
        data = reader.load_stream(user, stream)
    order = np.argsort(data.times, kind="stable")
    times, poses = data.times[order], data.poses[order]
    return poses[np.flatnonzero(times <= t)[-1]].astype(np.float64)


def test_state_at_is_the_recording_at_that_time(recording: Path) -> None:
    """Seeking anywhere shows each stream's last recorded update; interpolators end on it."""
    model = ReplayModel(recording, METHODS, rate=5.0)
    assert len(model.users) == 3 and {"head", "left", "right"} <= set(model.stream_names)
    for frac in (0.1, 0.5, 0.93):
        t = model.start + frac * (model.end - model.start)
        state = model.state_at(t)
        for (user, stream), layers in state.items():
            assert np.allclose(layers[TRUTH], recorded_at(recording, user, stream, t), atol=1e-7)
            assert set(layers) == {TRUTH, *METHODS}
    # Before the first update nothing is shown; at the last one every stream is.
    assert model.state_at(model.start - 1.0) == {}
    assert len(model.state_at(model.end)) == len(model.tracks)


def test_step_visits_every_sample_in_order(recording: Path) -> None:
    """Frame steps go to the next (previous) recorded sample of the shown streams."""
    model = ReplayModel(recording, ("soa",), rate=10.0)
    model.selected_users = {model.users[0]}
    model.selected_streams = {"head"}
    (track,) = model.selected()
    t = float(track.times[3])
    assert model.step(t, +1) == float(track.times[4])
    assert model.step(t, -1) == float(track.times[2])
    assert model.step(float(track.times[-1]), +1) == float(track.times[-1])


def test_error_strip_follows_the_keyframe_rate(recording: Path) -> None:
    """Fewer keyframes, larger tip error: the strip shows it (keyframes themselves are exact)."""
    model = ReplayModel(recording, ("soa",), rate=30.0)
    _, fine = model.error_strip("soa")
    model.set_rate(5.0)
    x, coarse = model.error_strip("soa")
    assert x[0] == 0.0 and np.all(np.diff(x) > 0)
    assert np.nanpercentile(coarse, 95) > np.nanpercentile(fine, 95)
    for tr in model.tracks:  # at a keyframe the rendered pose is the recorded one
        at_key = np.isin(tr.times, tr.keyframes)
        assert np.allclose(tr.tip_mm["soa"][at_key], 0.0, atol=1e-6)


def test_play_loops_or_stops_at_the_end(recording: Path) -> None:
    """Playing past the end wraps with loop on, and stops (paused) at the end without."""
    view = ReplayView(recording, ("soa",), port=0, rate=10.0)
    try:
        span = view.model.end - view.model.start
        view.set_playing(True)
        view.seek(view.model.end - 0.1)
        view.advance(0.2)
        assert view.playing and view.t < view.model.start + 0.2
        view.loop = False
        view.seek(view.model.end - 0.1)
        view.speed = 2.0
        view.advance(0.2)
        assert not view.playing and view.t == view.model.end
        assert span > 1.0
    finally:
        view.close()


async def test_dragging_the_timeline_shows_that_time(recording: Path, page: Page) -> None:
    """In the browser: drag the time slider; the scene holds the recorded poses of the
    time it says, and the page shows a head where each user's head was."""
    view = ReplayView(recording, METHODS, port=0, rate=5.0, spread=1.0)
    try:
        runner = asyncio.create_task(view.run())
        await page.goto(view.url)
        await scene_ready(page)
        thumb = page.locator('[role="slider"]').first
        await thumb.wait_for(timeout=30_000)
        track = await page.locator(".mantine-Slider-root").first.bounding_box()
        box = await thumb.bounding_box()
        assert track is not None and box is not None
        y = box["y"] + box["height"] / 2
        await page.mouse.move(box["x"] + box["width"] / 2, y)
        await page.mouse.down()
        for frac in (0.3, 0.5, 0.6):
            await page.mouse.move(track["x"] + frac * track["width"], y, steps=4)
        await page.mouse.up()
        await until(lambda: view.t > view.model.start + 0.5)

        async def slider_says_view_time() -> bool:  # once the last drag event settled
            shown_value = float(await thumb.get_attribute("aria-valuenow") or "nan")
            return abs(view.t - view.model.start - shown_value) < 0.011

        await poll_until(slider_says_view_time, limit=30.0, every=0.1)
        t = view.t
        heads = {}
        for user in view.model.users:
            want = recorded_at(recording, user, "head", t)
            got = view.scene.shown[(user, "head")][TRUTH]
            assert np.allclose(got, want, atol=1e-7)
            heads[user] = want[:3] + np.array([view.scene.offset(user), 0.0, 0.0])
        img = await settled_canvas(page)
        cam = next(iter(view.server.get_clients().values())).camera
        h, w = img.shape[:2]
        pix = project(
            np.array(list(heads.values())),
            np.asarray(cam.position),
            np.asarray(cam.look_at),
            cam.fov,
            w,
            h,
        )
        # View from the first user: the page's camera goes to its eyes and looks its
        # way; its own head is hidden; back to the room, it shows again.
        first = view.model.users[0]
        view.eyes.value = f"u{first}"
        await until(lambda: bool(np.allclose(cam.position, heads[first], atol=1e-3)))
        w_, x_, y_, z_ = view.scene.shown[(first, "head")][TRUTH][3:]
        forward = -np.array(
            [2 * (x_ * z_ + w_ * y_), 2 * (y_ * z_ - w_ * x_), 1 - 2 * (x_**2 + y_**2)]
        )
        assert np.allclose(cam.look_at - cam.position, forward, atol=1e-3)
        assert not view.scene.avatars[first].nodes[(TRUTH, "head")].visible
        view.eyes.value = "room"
        await until(lambda: view.scene.first_person is None)
        assert view.scene.avatars[first].nodes[(TRUTH, "head")].visible
        runner.cancel()
    finally:
        view.close()
    assert page.errors == []  # type: ignore[attr-defined]
    for xy in pix:
        assert 0 <= xy[0] < w and 0 <= xy[1] < h
        assert saturated_near(img, xy) > 0.05, xy
    assert saturated_near(img, np.array([w / 2, 40.0]), radius=20) == 0.0
