"""A registered test window method whose output is a known function of its whole window.

``probe(keys (..., K, 7), times (..., K), t)`` returns, for a bracket with
``T[lb] < t``: position ``sum_j w_j keys[j, :3] + (sum_j w_j T_j, t, 0)`` with
distinct weights ``w_j = j + 1`` (so a wrong, missing or reordered keyframe or
time changes the result) and the quaternion of ``keys[lb]``; on a held bracket
(``T[lb] == T[lb + 1]``) or at ``t <= T[lb]`` it returns ``keys[lb]`` (the
registry's contract). Each call is recorded, so tests can count batched calls.
:func:`expected` computes the same thing for one window given as indices.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np
import pytest
from numpy.typing import ArrayLike, NDArray

from posecast import interp
from posecast.interp import registry

F64 = NDArray[np.float64]

#: (lookbehind, lookahead) of the probes registered by :func:`register_probes`.
PROBE_SIZES = ((2, 2), (0, 3))


@dataclass
class Probe:
    lookbehind: int
    lookahead: int
    calls: list[tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...]]] = field(
        default_factory=list
    )

    @property
    def name(self) -> str:
        return f"probe-{self.lookbehind}-{self.lookahead}"

    @property
    def size(self) -> int:
        return self.lookbehind + 2 + self.lookahead

    def weights(self) -> F64:
        return np.arange(1.0, self.size + 1.0)

    def __call__(self, keys: ArrayLike, times: ArrayLike, t: ArrayLike) -> F64:
        kk = np.asarray(keys, dtype=np.float64)
        tt = np.asarray(times, dtype=np.float64)
        q = np.asarray(t, dtype=np.float64)
        assert kk.shape[-2:] == (self.size, 7), kk.shape
        assert tt.shape == kk.shape[:-1] and q.shape == kk.shape[:-2], (tt.shape, q.shape)
        self.calls.append((kk.shape, tt.shape, q.shape))
        lb = self.lookbehind
        w = self.weights()
        out = np.empty((*kk.shape[:-2], 7))
        out[..., :3] = np.einsum("j,...jc->...c", w, kk[..., :3])
        out[..., 0] += tt @ w
        out[..., 1] += q
        out[..., 2] += 0.0
        out[..., 3:] = kk[..., lb, 3:]
        plain = (tt[..., lb + 1] <= tt[..., lb]) | (q <= tt[..., lb])
        out[plain] = kk[..., lb, :][plain]
        return out


def expected(probe: Probe, poses: F64, times: F64, window: list[int], t: float) -> F64:
    """What ``probe`` returns for the window ``window`` (keyframe indices) of one stream."""
    keys = poses[window]
    tt = times[window]
    lb = probe.lookbehind
    if tt[lb + 1] <= tt[lb] or t <= tt[lb]:
        out: F64 = keys[lb].copy()
        return out
    w = probe.weights()
    pos = w @ keys[:, :3] + np.array([tt @ w, t, 0.0])
    return np.concatenate([pos, keys[lb, 3:]])


@pytest.fixture
def probes(monkeypatch: pytest.MonkeyPatch) -> Iterator[dict[str, Probe]]:
    """Register the probes in a private copy of the registry; yields them by name."""
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    out: dict[str, Probe] = {}
    for lb, la in PROBE_SIZES:
        p = Probe(lb, la)
        interp.register(p.name, p, kind="window", lookbehind=lb, lookahead=la)
        out[p.name] = p
    yield out
