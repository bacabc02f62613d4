"""Real head and hand traces in the ``shared/data/vr-traces`` CSV format.

One CSV per recording (plain ``.csv`` or gzip ``.csv.gz``): ``t`` then 7 columns
(``px, py, pz, qw, qx, qy, qz``) for each of ``head``, ``left``, ``right``.
:func:`load_trace` reads one into a :class:`Trace` (times ``(N,)``, poses
``(N, S, 7)`` float64); :func:`find_traces` resolves a trace set into paths:

- ``traces:sample``: the excerpt shipped inside the package
  (``scenarios/data/traces``: the first 60 s of four ``dev`` recordings), so
  tests and the demo stay quick;
- ``traces:dev`` / ``traces:eval``: the full sets, also shipped inside the package
  (``scenarios/data/traces/dev``, ``.../eval``), so a fresh clone re-runs Table 1
  on eval with nothing beside it; ``POSECAST_TRACES=/path/to/vr-traces`` points at
  another copy, used when it holds that split;
- a directory (every ``*.csv`` / ``*.csv.gz`` in it) or one file.

One correction is made on load (:data:`FLOOR_LIFTS`): X01's origin is where its
headset started, not the floor, so its heights are raised to a standing user's.
"""

from __future__ import annotations

import csv
import functools
import gzip
import io
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from posecast.protocol.errors import PosecastError

__all__ = [
    "BUNDLED_DIR",
    "CAUSAL_DEGREE",
    "CAUSAL_SAMPLES",
    "DEVICE_NAMES",
    "FLOOR_LIFTS",
    "SAMPLE_DIR",
    "VELOCITY_SOURCES",
    "Trace",
    "TraceError",
    "default_trace_root",
    "device_class",
    "find_traces",
    "full_traces_available",
    "load_trace",
]

DEVICE_NAMES = ("head", "left", "right")
_COMPONENTS = ("px", "py", "pz", "qw", "qx", "qy", "qz")

#: Where keyframe velocities come from: ``central`` differences (uses the next
#: native sample: not available at capture time) or a ``causal`` estimate (past
#: samples only: what a tracker runtime can report with the pose).
VELOCITY_SOURCES = ("central", "causal")
#: Native samples (the newest included) the causal estimator fits.
CAUSAL_SAMPLES = 4
#: Degree of the causal fit: a quadratic over the last 4 native samples (chosen on
#: `dev` among 2-6 samples, degree 1-3, for motor-hermite's hands p95 tip error at
#: 10-20 Hz; 2 samples, degree 1 is the backward difference).
CAUSAL_DEGREE = 2


#: The bundled excerpt of the real traces (``traces:sample``).
SAMPLE_DIR = Path(__file__).resolve().parent / "data" / "traces"
#: The bundled full sets: ``dev/`` and ``eval/`` under it (``traces:dev``, ``traces:eval``).
BUNDLED_DIR = SAMPLE_DIR
_SUFFIXES = (".csv", ".csv.gz")

#: Metres added to every y (height) of a trace on load, by trace name. X01
#: (questset, scripted head motion) has its origin where the headset started, not
#: on the floor: its head sits at y = 0.02 m (median) and its controllers below
#: the floor (-0.36 and -0.81 m). Raised by 1.677 m, its median head height is
#: 1.697 m, the median of the dev Beat Saber recordings' (S01-S05) median head
#: heights, and its lowest controller sample is at 0.50 m. A change of world
#: frame changes no interpolation error (every method commutes with it).
FLOOR_LIFTS: dict[str, float] = {"X01_quest2_scripted_head": 1.677}


class TraceError(PosecastError, ValueError):
    """A trace file or trace set that cannot be used, with the reason."""


def device_class(stream_name: str) -> str:
    """QoE device class of a stream: ``head``, ``hands`` or ``objects``."""
    if stream_name == "head":
        return "head"
    if stream_name in ("left", "right"):
        return "hands"
    return "objects"


@dataclass(frozen=True)
class Trace:
    """A recording: sample times ``(N,)`` (s) and poses ``(N, S, 7)`` (float64)."""

    name: str
    times: NDArray[np.float64]
    poses: NDArray[np.float64]
    streams: tuple[str, ...]

    @property
    def duration(self) -> float:
        return float(self.times[-1] - self.times[0])

    @functools.cached_property
    def native_rate(self) -> float:
        """Median sample rate in Hz (computed once: a looping sender asks at every send)."""
        return float(1.0 / np.median(np.diff(self.times)))

    def velocities(self) -> NDArray[np.float64]:
        """Tracker-style velocities ``(N, S, 6)``: linear (m/s) then angular (rad/s).

        World frame, by central differences over the native samples (one-sided
        at the ends), standing in for what headset runtimes report with poses.
        """
        t = self.times
        p = self.poses
        nxt = np.r_[1 : len(t), len(t) - 1]
        prv = np.r_[0, 0 : len(t) - 1]
        dt = (t[nxt] - t[prv])[:, None, None]
        lin = (p[nxt, :, :3] - p[prv, :, :3]) / dt
        q1, q0 = p[nxt, :, 3:], p[prv, :, 3:]
        # Angular velocity from the world-frame rotation q1 q0*, via its log.
        w = q1[..., 0] * q0[..., 0] + np.einsum("...i,...i->...", q1[..., 1:], q0[..., 1:])
        v = (
            -q1[..., :1] * q0[..., 1:]
            + q0[..., :1] * q1[..., 1:]
            - np.cross(q1[..., 1:], q0[..., 1:])
        )
        sign = np.where(w < 0, -1.0, 1.0)
        w, v = w * sign, v * sign[..., None]
        nv = np.linalg.norm(v, axis=-1)
        angle = 2.0 * np.arctan2(nv, w)
        axis = v / np.where(nv > 0, nv, 1.0)[..., None]
        ang = axis * (angle / dt[..., 0])[..., None]
        return np.concatenate([lin, ang], axis=-1)

    def causal_velocities(
        self, samples: int = CAUSAL_SAMPLES, degree: int = CAUSAL_DEGREE
    ) -> NDArray[np.float64]:
        """Velocities ``(N, S, 6)`` as a tracker could report them at each sample's capture.

        See :func:`causal_velocities`: a polynomial fit over the newest
        ``samples`` native samples up to and including each one, differentiated
        at that sample; world frame, linear (m/s) then angular (rad/s).
        """
        return causal_velocities(self.times, self.poses, samples, degree)

    def velocities_from(self, source: str) -> NDArray[np.float64]:
        """Velocities from one of :data:`VELOCITY_SOURCES` (default parameters)."""
        if source == "central":
            return self.velocities()
        if source == "causal":
            return self.causal_velocities()
        raise ValueError(f"unknown velocity source {source!r}; known: {VELOCITY_SOURCES}")

    def select(self, streams: list[str] | tuple[str, ...]) -> Trace:
        """The same trace restricted to ``streams`` (by name, in that order)."""
        missing = [s for s in streams if s not in self.streams]
        if missing:
            raise TraceError(f"trace {self.name} has no stream(s) {missing}; has {self.streams}")
        idx = [self.streams.index(s) for s in streams]
        return Trace(self.name, self.times, self.poses[:, idx], tuple(streams))

    def window(self, start: float, end: float) -> Trace:
        """Samples with ``start <= t <= end`` (times unchanged)."""
        m = (self.times >= start) & (self.times <= end)
        return Trace(self.name, self.times[m], self.poses[m], self.streams)


def _rotation_vector(q1: NDArray[np.float64], q0: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rotation vectors ``(..., 3)`` of the world-frame rotations ``q1 q0*`` (w-first quats)."""
    w = q1[..., 0] * q0[..., 0] + np.einsum("...i,...i->...", q1[..., 1:], q0[..., 1:])
    v = -q1[..., :1] * q0[..., 1:] + q0[..., :1] * q1[..., 1:] - np.cross(q1[..., 1:], q0[..., 1:])
    sign = np.where(w < 0, -1.0, 1.0)
    w, v = w * sign, v * sign[..., None]
    nv = np.linalg.norm(v, axis=-1)
    angle = 2.0 * np.arctan2(nv, w)
    out: NDArray[np.float64] = v * (angle / np.where(nv > 0, nv, 1.0))[..., None]
    return out


def _first_row_of_inverse(m: NDArray[np.float64]) -> NDArray[np.float64]:
    """First rows of the inverses of symmetric positive definite matrices ``(N, D, D)``.

    Closed forms for D = 1, 2 (no LAPACK call per tiny matrix); a batched solve above.
    """
    d = m.shape[-1]
    if d == 1:
        one: NDArray[np.float64] = 1.0 / m[:, 0, :]
        return one
    if d == 2:
        det = m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0]
        two: NDArray[np.float64] = np.stack([m[:, 1, 1], -m[:, 0, 1]], axis=-1) / det[:, None]
        return two
    e0 = np.zeros((m.shape[0], d, 1))
    e0[:, 0, 0] = 1.0
    # Symmetric: the first row of the inverse is the solution of M x = e0.
    solved: NDArray[np.float64] = np.linalg.solve(m, e0)[:, :, 0].astype(np.float64)
    return solved


def causal_velocities(
    times: NDArray[np.float64],
    poses: NDArray[np.float64],
    samples: int = CAUSAL_SAMPLES,
    degree: int = CAUSAL_DEGREE,
) -> NDArray[np.float64]:
    """Causal velocities ``(N, S, 6)`` of poses ``(N, S, 7)`` sampled at ``times (N,)``.

    At each sample ``n`` only samples ``n - samples + 1 .. n`` are used: the
    displacements ``p_i - p_n`` and rotation vectors ``log(q_i q_n*)`` (world
    frame) of those samples are fitted by a polynomial in ``t_i - t_n`` of
    ``degree`` through the origin (least squares), whose slope at ``t_n`` is the
    linear (m/s) and angular (rad/s) velocity. ``samples=2, degree=1`` is the
    backward difference. Early samples use what they have (fewer samples, the
    degree capped below their count); the first sample has velocity zero.
    """
    if samples < 2 or not 1 <= degree < samples:
        raise ValueError(f"need samples >= 2 and 1 <= degree < samples, got {samples}, {degree}")
    t = np.asarray(times, dtype=np.float64)
    p = np.asarray(poses, dtype=np.float64)
    n = t.shape[0]
    out = np.zeros((*p.shape[:2], 6))
    if n < 2:
        return out
    # Per sample, per lag j = 1 .. samples-1: the past sample's offsets (zero
    # where it does not exist yet, which removes that row from the fit).
    lags = np.arange(1, samples)
    idx = np.arange(n)[:, None] - lags[None, :]  # (N, L)
    exists = idx >= 0
    idx = np.maximum(idx, 0)
    dt = np.where(exists, t[idx] - t[:, None], 0.0)  # (N, L), <= 0
    disp = p[idx, :, :3] - p[:, None, :, :3]  # (N, L, S, 3)
    rot = _rotation_vector(p[idx, :, 3:], np.broadcast_to(p[:, None, :, 3:], (*disp.shape[:3], 4)))
    y = np.concatenate([disp, rot], axis=-1) * exists[:, :, None, None]  # (N, L, S, 6)
    # Design matrix rows [dt, dt^2, ...]; the degree is capped by the samples available.
    available = exists.sum(axis=1)  # (N,)
    powers = np.arange(1, degree + 1)
    a = dt[:, :, None] ** powers[None, None, :]  # (N, L, D)
    used = powers[None, :] <= available[:, None]  # (N, D)
    a = a * used[:, None, :]
    # Least squares through the normal equations: the slope's weights per lag are
    # the first row of (A^T A)^-1 A^T. An unused power gets a unit diagonal, which
    # decouples it (its column of A is zero); no past sample at all gives zeros.
    m = np.einsum("nld,nle->nde", a, a)
    diag = np.arange(degree)
    m[:, diag, diag] = np.where(used, m[:, diag, diag], 1.0)
    weights = _first_row_of_inverse(m)  # (N, D)
    w = np.einsum("nd,nld->nl", weights, a)  # (N, L)
    coef = np.einsum("nl,nlsk->nsk", w, y)  # slope at t_n
    out[1:] = coef[1:]
    return out


def load_trace(path: str | os.PathLike[str]) -> Trace:
    """Read a trace CSV; errors name the file and the problem."""
    p = Path(path)
    try:
        with _open_text(p) as fh:
            header = next(csv.reader(fh))
            data = np.loadtxt(fh, delimiter=",", dtype=np.float64, ndmin=2)
    except FileNotFoundError:
        raise TraceError(f"{p}: no such trace file") from None
    except IsADirectoryError:
        raise TraceError(f"{p}: is a directory, not a trace file") from None
    except StopIteration:
        raise TraceError(f"{p}: empty file") from None
    except (ValueError, UnicodeDecodeError, gzip.BadGzipFile, EOFError) as exc:
        raise TraceError(f"{p}: not a numeric trace CSV ({exc})") from None
    expected = ["t"] + [f"{d}_{c}" for d in DEVICE_NAMES for c in _COMPONENTS]
    if [h.strip() for h in header] != expected:
        raise TraceError(f"{p}: unexpected columns; expected {','.join(expected)}")
    if data.shape[0] < 2 or data.shape[1] != len(expected):
        raise TraceError(f"{p}: expected at least 2 rows of {len(expected)} values")
    if not np.all(np.isfinite(data)):
        raise TraceError(f"{p}: non-finite values")
    times = data[:, 0].copy()
    if not np.all(np.diff(times) > 0):
        raise TraceError(f"{p}: times are not strictly increasing")
    poses = data[:, 1:].reshape(-1, len(DEVICE_NAMES), 7).copy()
    q = poses[..., 3:]
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    name = _trace_name(p)
    poses[..., 1] += FLOOR_LIFTS.get(name, 0.0)
    return Trace(name, times, poses, DEVICE_NAMES)


def _trace_name(p: Path) -> str:
    """``S02_riftS`` for ``S02_riftS.csv`` and ``S02_riftS.csv.gz`` alike."""
    name = p.name
    for suffix in (".csv.gz", ".gz", ".csv"):
        if name.endswith(suffix):
            return name[: -len(suffix)]
    return p.stem


def _open_text(p: Path) -> io.TextIOWrapper:
    """A text reader of ``p``, gunzipped when it is a gzip file (by its magic bytes)."""
    with p.open("rb") as probe:
        gz = probe.read(2) == b"\x1f\x8b"
    if gz:
        return io.TextIOWrapper(gzip.open(p, "rb"), encoding="utf-8", newline="")
    return p.open(newline="", encoding="utf-8")


def default_trace_root() -> Path:
    """The folder of the full sets: ``POSECAST_TRACES`` when it holds one, else the bundled."""
    env = os.environ.get("POSECAST_TRACES")
    if env and any(_trace_files(Path(env) / split) for split in ("dev", "eval")):
        return Path(env)
    return BUNDLED_DIR


def _split_dir(split: str) -> Path:
    """Where ``traces:SPLIT`` is read: ``$POSECAST_TRACES/SPLIT`` if it holds traces, else
    the bundled copy."""
    env = os.environ.get("POSECAST_TRACES")
    if env and _trace_files(Path(env) / split):
        return Path(env) / split
    return BUNDLED_DIR / split


def full_traces_available(split: str = "dev") -> bool:
    """Whether the full ``split`` set (``dev`` or ``eval``) can be found."""
    return _trace_files(_split_dir(split)) != []


def _trace_files(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    return sorted(f for f in folder.iterdir() if f.name.endswith(_SUFFIXES) and f.is_file())


def find_traces(spec: str | os.PathLike[str]) -> list[Path]:
    """Trace files for ``traces:sample|dev|eval``, a directory or a file."""
    s = str(spec)
    if s.startswith("traces:"):
        split = s.split(":", 1)[1]
        if split == "sample":
            path = SAMPLE_DIR
        elif split in ("dev", "eval"):
            path = _split_dir(split)
            if not _trace_files(path):
                raise TraceError(
                    f"the full {split!r} traces are not here ({path}, nor under "
                    "POSECAST_TRACES): set POSECAST_TRACES=/path/to/vr-traces, "
                    "or use traces:sample (bundled)"
                )
        else:
            raise TraceError(
                f"unknown trace set {s!r}: use traces:sample, traces:dev or traces:eval"
            )
    else:
        path = Path(s)
    if path.is_file():
        return [path]
    if path.is_dir():
        files = _trace_files(path)
        if not files:
            raise TraceError(f"{path}: no .csv or .csv.gz traces in this directory")
        return files
    raise TraceError(f"{path}: no such trace file or directory")
