"""The viewer's screenshots in docs/ show users (not an empty room): checked by pixels.

They are written by ``tests/posecast/view/make_screenshots.py``; this test reads the
committed PNGs, so it fails when one is replaced by an empty or washed-out shot.
"""

from __future__ import annotations

import colorsys
from pathlib import Path

import numpy as np
import pytest
from matplotlib import image as mpimg

DOCS = Path(__file__).resolve().parents[3] / "docs"
#: The 3D view is the left part of the page; the panel (docked right) is left out.
VIEW_SHARE = 0.65


def coloured_pixels(path: Path) -> tuple[int, int]:
    """In the 3D view of a screenshot: how many pixels are strongly coloured (an avatar,
    a trail: not the white floor, the grey grid, the shadows or the text), and in how
    many of 12 hue bins at least 150 of them fall (users have hues of their own)."""
    img = np.asarray(mpimg.imread(path))[..., :3].astype(np.float64)
    if img.max() > 1.0:
        img /= 255.0
    view = img[:, : int(img.shape[1] * VIEW_SHARE)].reshape(-1, 3)
    sat = view.max(axis=1) - view.min(axis=1)
    strong = view[(sat > 0.25) & (view.max(axis=1) > 0.3)]
    hues = np.array([colorsys.rgb_to_hsv(*px)[0] for px in strong[::7]])
    counts = np.bincount((hues * 12).astype(int) % 12, minlength=12) * 7
    return int(strong.shape[0]), int((counts >= 150).sum())


@pytest.mark.parametrize(("name", "min_hues"), [("live", 3), ("replay", 3), ("drill", 2)])
def test_screenshots_show_users(name: str, min_hues: int) -> None:
    """Each screenshot's 3D view holds thousands of avatar-coloured pixels, in several
    hues (one per user); an empty room ("waiting for users") or a canvas shot before
    it was drawn has almost none."""
    pixels, hues = coloured_pixels(DOCS / f"viewer-{name}.png")
    assert pixels > 3000, (name, pixels)
    assert hues >= min_hues, (name, hues)
