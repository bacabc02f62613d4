"""Reading a viser page back: where a world point lands on the canvas, and what is there."""

from __future__ import annotations

import io
from collections.abc import Callable

import numpy as np
from matplotlib import image as mpimg
from numpy.typing import NDArray
from playwright.async_api import Page
from support import poll_until

FPS_JS = """() => new Promise(done => {
  let n = 0; const t0 = performance.now();
  function tick() {
    n++;
    if (performance.now() - t0 < 2000) requestAnimationFrame(tick);
    else done(n / ((performance.now() - t0) / 1000));
  }
  requestAnimationFrame(tick);
})"""


SCENE_READY_JS = """() => {
  const c = Array.from(document.querySelectorAll('canvas')).sort(
    (a, b) => b.width * b.height - a.width * a.height)[0];
  return c !== undefined && c.width > 100 && getComputedStyle(c).opacity === '1';
}"""


async def scene_ready(page: Page, limit: float = 300.0) -> None:
    """Wait until viser's 3D canvas is drawn at full opacity: it is kept at 5 % until
    its environment map is loaded, which takes a minute in software WebGL on a busy
    machine (a screenshot before then is nearly white)."""
    await page.wait_for_function(SCENE_READY_JS, timeout=limit * 1000)


async def until(condition: Callable[[], bool], limit: float = 30.0) -> None:
    """Wait (polling, no fixed sleep) until ``condition()`` holds; fail after ``limit`` s."""
    await poll_until(condition, limit=limit, every=0.05)


def project(
    points: NDArray[np.float64],
    position: NDArray[np.float64],
    look_at: NDArray[np.float64],
    fov: float,
    width: int,
    height: int,
) -> NDArray[np.float64]:
    """Pixel (x, y) of world points seen by a +y-up perspective camera (vertical ``fov``)."""
    fwd = look_at - position
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    d = np.atleast_2d(points) - position
    depth = d @ fwd
    f = 1.0 / np.tan(fov / 2)
    x_ndc = (d @ right) / depth * f / (width / height)
    y_ndc = (d @ up) / depth * f
    return np.stack([(x_ndc + 1) / 2 * width, (1 - y_ndc) / 2 * height], axis=-1)


async def canvas_rgb(page: Page) -> NDArray[np.float64]:
    """The 3D canvas as an (H, W, 3) array of 0..1 floats."""
    png = await page.locator("canvas").first.screenshot()
    img = mpimg.imread(io.BytesIO(png), format="png")
    return np.asarray(img[..., :3], dtype=np.float64)


async def settled_canvas(page: Page, limit: float = 60.0) -> NDArray[np.float64]:
    """The 3D canvas once it stopped changing: two reads in a row alike (what a paused
    view's page shows once its last frame arrived and was drawn)."""
    reads = [await canvas_rgb(page)]

    async def alike() -> bool:
        reads.append(await canvas_rgb(page))
        return bool(np.array_equal(reads[-2], reads[-1]))

    await poll_until(alike, limit=limit, every=0.2)
    return reads[-1]


def saturated_near(img: NDArray[np.float64], xy: NDArray[np.float64], radius: int = 8) -> float:
    """Share of coloured pixels (an avatar, not the white floor, the grey grid or the
    shadows) in the square of ``radius`` around pixel ``xy``."""
    x, y = round(xy[0]), round(xy[1])
    h, w = img.shape[:2]
    patch = img[
        max(0, y - radius) : min(h, y + radius + 1), max(0, x - radius) : min(w, x + radius + 1)
    ]
    if patch.size == 0:
        return 0.0
    sat = patch.max(axis=-1) - patch.min(axis=-1)
    return float((sat > 0.1).mean())
