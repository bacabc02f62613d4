"""The pure-Python small-frame paths give the numpy paths' bytes and values exactly.

``FRAMES_SHA256`` was recorded with the codec before the small paths existed
(numpy only): a fixed-seed set of frames of every kind, their bytes, per-entry
bits and decoded values must hash to it for ever.
"""

from __future__ import annotations

import hashlib
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray

from posecast.protocol import codec
from posecast.protocol.codec_quant import dequantise, quantise

FRAMES_SHA256 = "7c17bc7a6e4264c5efea7fd20ca351ea8a33ea599b674039ad703f36a96093f7"


def _poses(rng: np.random.Generator, n: int, vol: Any) -> NDArray[np.float64]:
    q = rng.normal(size=(n, 4))
    near_180 = rng.random(n) < 0.3
    q[near_180, 0] = rng.normal(size=int(near_180.sum())) * 1e-4
    q /= np.linalg.norm(q, axis=1)[:, None]
    lo, hi, step = np.array(vol.lo), np.array(vol.hi), np.array(vol.step)
    p = rng.uniform(lo, hi, (n, 3))
    edge = rng.integers(0, 6, (n, 3))
    p = np.where(edge == 0, lo - 0.4 * step, np.where(edge == 1, hi + 0.4 * step, p))
    return np.concatenate([p, q], axis=1)


def frames_digest(m: ModuleType, count: int = 400) -> str:
    """Hash of ``count`` random frames (key/delta, snapshot/update, +-velocity)."""
    rng = np.random.default_rng(2024)
    vol = m.Volume((-3.0, -0.5, -4.0), (5.0, 2.5, 4.0))
    h = hashlib.sha256()
    for i in range(count):
        n = int(rng.integers(1, 31)) if i % 10 else int(rng.integers(31, 80))
        vel = rng.normal(size=(n, 6)) * 3 if i % 2 else None
        update = bool(i % 4 >= 2)
        users = np.zeros(n, np.int64) if update else rng.permutation(n * 3)[:n] // 3
        streams = rng.permutation(n) if update else rng.permutation(n * 3)[:n] % 3
        keys = (
            [int(s) for s in streams]
            if update
            else list(zip(users.tolist(), streams.tolist(), strict=True))
        )
        if len(set(keys)) < n:
            continue
        prev = m.quantise(_poses(rng, n, vol), vol, vel)
        base = {k: prev[j] for j, k in enumerate(keys) if i % 3 and rng.random() < 0.8}
        times = 50.0 - rng.uniform(0, 0.2, n)
        codes = m.quantise(_poses(rng, n, vol), vol, vel)
        if update:
            enc = m.encode_update_codes(i, 50.0, streams, times, codes, vol, base)
            dec = m.decode_update(enc.data, vol, base)
        else:
            enc = m.encode_snapshot_codes(i, 50.0, users, streams, times, codes, vol, base)
            dec = m.decode_snapshot(enc.data, vol, base)
        h.update(enc.data + enc.entry_bits.tobytes())
        for f in (enc.frame, dec):
            vels = f.velocities
            for a in (f.users, f.streams, f.capture_times, f.codes, f.delta, f.poses):
                h.update(a.tobytes())
            h.update(b"" if vels is None else vels.tobytes())
    return h.hexdigest()


def test_frames_bytes_and_values_unchanged() -> None:
    assert frames_digest(codec) == FRAMES_SHA256


def test_small_quantise_and_dequantise_match_the_numpy_paths() -> None:
    rng = np.random.default_rng(5)
    vol = codec.DEFAULT_VOLUME
    poses = _poses(rng, 3100, vol)
    poses[:, :3] = np.clip(poses[:, :3], vol.lo, vol.hi)
    vel = rng.normal(size=(3100, 6)) * 20
    whole = quantise(poses, vol, vel)  # numpy path (more than 30 rows)
    rows = np.concatenate(
        [quantise(poses[i : i + 25], vol, vel[i : i + 25]) for i in range(0, 3100, 25)]
    )
    assert rows.dtype == whole.dtype and np.array_equal(rows, whole)
    p_all, v_all = dequantise(whole, vol)
    parts = [dequantise(whole[i : i + 30], vol) for i in range(0, 3100, 30)]
    assert v_all is not None
    assert np.concatenate([p for p, _ in parts]).tobytes() == p_all.tobytes()
    assert np.concatenate([v for _, v in parts if v is not None]).tobytes() == v_all.tobytes()
