"""What a replay shows at any time: ground truth, interpolators, and their tip error.

:class:`ReplayModel` reads a recording once (``recorder.export.read_session``:
each stream's keyframes by capture time) and keeps, per stream, the ground
truth (every recorded update) and, per interpolator, the stream rebuilt from
keyframes sampled at a chosen rate (a sender at ``rate``: the newest recorded
sample at each send time, :func:`scenarios.qoe.sample_keyframes`), rendered at
every recorded sample time with :func:`interp.evaluate_track` (an ideal
network: the bracketing keyframes are there) and scored by tip error
(:func:`interp.metrics.tip_error_mm`). No clock, no I/O after loading.

Seeking is immediate: the state at time ``t`` is each stream's last recorded
sample at or before ``t`` (look back to the last keyframe, as Foxglove does),
found with ``searchsorted``; a stream with nothing yet at ``t`` is not shown.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from posecast.client.render import rendered_method
from posecast.interp import evaluate_track
from posecast.interp import info as interp_info
from posecast.interp.metrics import tip_error_mm
from posecast.recorder.export import read_session
from posecast.scenarios.qoe import sample_keyframes

__all__ = ["TRUTH", "ReplayModel", "Track"]

F64 = NDArray[np.float64]

#: The layer name of the ground truth (every recorded update).
TRUTH = "truth"


@dataclass
class Track:
    """One recorded stream: its samples by capture time and what each method makes of them."""

    user: int
    stream: int
    name: str
    user_name: str
    times: F64
    truth: F64
    velocities: F64 | None
    rendered: dict[str, F64] = field(default_factory=dict)
    tip_mm: dict[str, F64] = field(default_factory=dict)
    #: Capture times of the keyframes sampled at the model's rate.
    keyframes: F64 = field(default_factory=lambda: np.empty(0))

    def index_at(self, t: float) -> int:
        """The last sample at or before ``t`` (-1: none yet)."""
        return int(np.searchsorted(self.times, t, side="right")) - 1


class ReplayModel:
    """A recording's streams, rebuilt by ``methods`` from keyframes at ``rate`` Hz."""

    def __init__(
        self, path: str | os.PathLike[str], methods: Sequence[str], rate: float = 10.0
    ) -> None:
        for m in methods:
            interp_info(m)  # an unknown name fails here, in one line
        self.path = path
        self.methods = tuple(methods)
        data = read_session(path)
        self.tracks: list[Track] = []
        for s in data.streams:
            if len(s) == 0:
                continue
            user = data.users.get(s.user)
            uname = (user.name if user and user.name else None) or s.user_name or f"user{s.user}"
            vel = s.velocities
            self.tracks.append(
                Track(
                    user=s.user,
                    stream=s.stream,
                    name=s.name or f"stream{s.stream}",
                    user_name=uname,
                    times=np.asarray(s.times, dtype=np.float64),
                    truth=np.asarray(s.poses, dtype=np.float64),
                    velocities=None
                    if vel is None or np.isnan(vel).any()
                    else np.asarray(vel, dtype=np.float64),
                )
            )
        if not self.tracks:
            raise ValueError(f"{path}: no pose updates to show")
        self.start = min(float(tr.times[0]) for tr in self.tracks)
        self.end = max(float(tr.times[-1]) for tr in self.tracks)
        self.users = sorted({tr.user for tr in self.tracks})
        self.stream_names = sorted({tr.name for tr in self.tracks})
        self.selected_users: set[int] = set(self.users)
        self.selected_streams: set[str] = set(self.stream_names)
        self.rate = rate
        self.set_rate(rate)

    def set_rate(self, rate: float) -> None:
        """Resample every stream's keyframes at ``rate`` Hz and rebuild every method."""
        if not rate > 0:
            raise ValueError(f"keyframe rate must be positive, got {rate}")
        self.rate = rate
        for tr in self.tracks:
            _, idx = sample_keyframes(tr.times, rate)
            idx = np.unique(idx)
            kt, kp = tr.times[idx], tr.truth[idx]
            tr.keyframes = kt
            for m in self.methods:
                shown = rendered_method(m, tr.velocities is not None)
                vel = None
                if interp_info(shown).needs_velocity and tr.velocities is not None:
                    vel = tr.velocities[idx][:, None, :]
                res = evaluate_track(kt, kp, tr.times, shown, velocities=vel)
                tr.rendered[m] = res.poses[:, 0, :]
                tr.tip_mm[m] = tip_error_mm(tr.rendered[m], tr.truth)

    def selected(self) -> list[Track]:
        return [
            tr
            for tr in self.tracks
            if tr.user in self.selected_users and tr.name in self.selected_streams
        ]

    def state_at(
        self, t: float, layers: Iterable[str] | None = None
    ) -> dict[tuple[int, str], dict[str, F64]]:
        """Per selected stream with a sample by ``t``: {layer: pose (7,)} at its last sample."""
        names = [TRUTH, *self.methods] if layers is None else list(layers)
        out: dict[tuple[int, str], dict[str, F64]] = {}
        for tr in self.selected():
            i = tr.index_at(t)
            if i < 0:
                continue
            out[(tr.user, tr.name)] = {
                n: (tr.truth[i] if n == TRUTH else tr.rendered[n][i]) for n in names
            }
        return out

    def first_head(self, user: int) -> F64 | None:
        """``user``'s first recorded head pose (7,), None without a head stream."""
        for tr in self.tracks:
            if tr.user == user and tr.name == "head":
                first: F64 = tr.truth[0]
                return first
        return None

    def trails(self, t: float, seconds: float, layer: str) -> list[tuple[Track, F64]]:
        """Per selected hand stream (``left``, ``right``): its positions (K, 3) in
        ``layer`` over the recorded samples in ``(t - seconds, t]``."""
        out = []
        for tr in self.selected():
            if tr.name not in ("left", "right"):
                continue
            lo = int(np.searchsorted(tr.times, t - seconds, side="right"))
            hi = tr.index_at(t) + 1
            poses = tr.truth if layer == TRUTH else tr.rendered[layer]
            out.append((tr, poses[lo:hi, :3]))
        return out

    def step(self, t: float, direction: int) -> float:
        """The next (``direction`` > 0) or previous recorded sample time of the selected
        streams after (before) ``t``; ``t`` itself at either end."""
        best = t
        for tr in self.selected():
            if direction > 0:
                i = int(np.searchsorted(tr.times, t, side="right"))
                if i < tr.times.size and (best == t or tr.times[i] < best):
                    best = float(tr.times[i])
            else:
                i = int(np.searchsorted(tr.times, t, side="left")) - 1
                if i >= 0 and (best == t or tr.times[i] > best):
                    best = float(tr.times[i])
        return best

    def error_strip(self, method: str, bins: int = 200) -> tuple[F64, F64]:
        """Tip error over time of ``method``: (bin start times, the worst selected
        stream's error in each bin, mm; NaN where no sample falls)."""
        edges = np.linspace(self.start, self.end, bins + 1)
        worst = np.full(bins, np.nan)
        for tr in self.selected():
            b = np.clip(np.searchsorted(edges, tr.times, side="right") - 1, 0, bins - 1)
            err = tr.tip_mm[method]
            per = np.full(bins, -np.inf)
            np.maximum.at(per, b, err)
            per[~np.isfinite(per)] = np.nan
            worst = np.fmax(worst, per)
        return edges[:-1] - self.start, worst
