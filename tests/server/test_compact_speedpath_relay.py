"""The relay's other fast paths keep their answers: snapshot bytes, splices, rotation
predictions, update refusals, the room's next due time, and the checks a decoded
compact update no longer needs.

(They test ``protocol.codec_relay``, ``protocol.codec_small``, ``server.limits`` and
``server.room``; they sit here with the decoder's tests of the same change.)
"""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest

from posecast.protocol import PoseUpdate
from posecast.protocol._compact import _update_of_rows
from posecast.protocol.codec import DEFAULT_VOLUME, Volume, quantise
from posecast.protocol.codec_quant import _ANG_CODE_MAX, _LIN_CODE_MAX, M, predict_rotation
from posecast.protocol.codec_relay import GroupSnapshot, RelayEntry, encode_group
from posecast.protocol.codec_small import predict_row
from posecast.protocol.poses import pose_problem, velocity_problem
from posecast.server import limits
from posecast.server.limits import update_refusal
from posecast.server.room import Member, Outbox, Room

SMALL_VOLUME = Volume((-3.0, -0.5, -4.0), (5.0, 2.5, 4.0))

#: sha256 of ``relay_digest()``, recorded with the codec of commit 92c0d0d (before
#: the splicing, ordering and prediction changes): the bytes are a contract.
RELAY_DIGEST = "dcb80ad5d654e48269ac38aa2110412568028e91e8796b477746061a54420430"


def _group_inputs(rng: np.random.Generator, i: int) -> tuple[Volume, bool, list[RelayEntry]]:
    """Group ``i`` of a fixed set: 1-13 users, key and delta entries mixed, small to
    huge differences and time offsets, with and without velocities."""
    vol = DEFAULT_VOLUME if i % 3 else SMALL_VOLUME
    users = int(rng.integers(1, 14))
    velocity = bool(i % 2)
    n = 3 * users
    lo, hi = np.array(vol.lo), np.array(vol.hi)
    q0 = rng.normal(size=(n, 4))
    q0[rng.random(n) < 0.3, 0] *= 1e-3
    spread = [1e-3, 0.03, 0.5, 2.0][i % 4]
    q1 = q0 + rng.normal(0.0, spread, (n, 4))
    q0 /= np.linalg.norm(q0, axis=1, keepdims=True)
    q1 /= np.linalg.norm(q1, axis=1, keepdims=True)
    p0 = rng.uniform(lo, hi, (n, 3))
    p1 = np.clip(p0 + rng.normal(0.0, [1e-4, 0.01, 0.3, 3.0][i % 4], (n, 3)), lo, hi)
    v0 = rng.normal(0.0, 3.0, (n, 6)) if velocity else None
    v1 = rng.normal(0.0, 30.0, (n, 6)) if velocity else None
    base = quantise(np.concatenate([p0, q0], 1), vol, v0).tolist()
    now = quantise(np.concatenate([p1, q1], 1), vol, v1).tolist()
    share = [0.0, 0.5, 0.9, 1.0][(i // 4) % 4]
    uids = rng.permutation(60)[:users] * int(rng.integers(1, 1000))
    entries: list[RelayEntry] = []
    for j in range(n):
        u = int(uids[j // 3])
        s = (u % 20000) * 3 + j % 3 if i % 5 else j
        lag = float(rng.integers(0, [50, 300, 4000, 900000][i % 4]))
        t = 100.0 - lag / 1000.0 + float(rng.uniform(-4e-4, 4e-4))
        entries.append((u, s, t, now[j], base[j] if rng.random() < share else None))
    order = rng.permutation(n)
    return vol, velocity, [entries[k] for k in order]


def relay_digest(count: int = 300) -> str:
    """Hash of ``count`` groups' frames for everyone and without each of 3 users."""
    rng = np.random.default_rng(2026)
    h = hashlib.sha256()
    for i in range(count):
        vol, velocity, entries = _group_inputs(rng, i)
        group = encode_group(i + 1, 100.0 + i * 1e-3, entries, vol, velocity)
        for exclude in [None, *sorted({e[0] for e in entries})[:3]]:
            data, n = group.frame(exclude)
            h.update(data + n.to_bytes(4, "little"))
    return h.hexdigest()


def test_relay_snapshot_bytes_unchanged() -> None:
    """Every byte of 300 groups' frames is what the codec wrote before the fast paths."""
    assert relay_digest() == RELAY_DIGEST


def test_spliced_frames_equal_joined_frames() -> None:
    """After the first frame, frames are spliced: the same bytes as joining every block,
    for every user left out (in one section, in both, the first, the last) and none."""
    rng = np.random.default_rng(11)
    for i in range(60):
        vol, velocity, entries = _group_inputs(rng, i)
        group = encode_group(i, 50.0, entries, vol, velocity)
        users = sorted({e[0] for e in entries})
        excludes = [None, *users, max(users) + 1]
        joined = [group._frame_joined(x) for x in excludes]
        assert group.frame() == joined[0]  # the first frame: joined (and splicing made)
        assert [group.frame(x) for x in excludes] == joined
        fresh = encode_group(i, 50.0, entries, vol, velocity)
        assert [fresh.frame(x) for x in reversed(excludes)] == joined[::-1]


def test_a_group_of_one_user_splices_to_nothing() -> None:
    """The only user left out: no frame, as before."""
    codes = quantise(np.array([[0.0, 1.0, 0.0, 1.0, 0.0, 0.0, 0.0]]), DEFAULT_VOLUME).tolist()
    group = encode_group(1, 5.0, [(3, 9, 5.0, codes[0], None)], DEFAULT_VOLUME)
    assert isinstance(group, GroupSnapshot)
    assert group.frame(3) == (b"", 0)
    assert group.frame(3) == (b"", 0)
    assert group.frame()[1] == 1


def test_predict_row_equals_the_numpy_predictor() -> None:
    """Every (largest index, new index), in range and out (the encoder's inputs are its own)."""
    rng = np.random.default_rng(3)
    rows = []
    for i0 in range(4):
        for idx in range(4):
            abc = rng.integers(-M - 40, M + 41, (400, 3))
            abc[:40] = rng.choice([-M, 0, M], (40, 3))
            rows += [([i0, *map(int, r), 0, 0, 0], idx) for r in abc]
    base = np.array([r for r, _ in rows], np.int64)
    idx = np.array([i for _, i in rows], np.int64)
    assert [predict_row(r, i) for r, i in rows] == predict_rotation(base, idx).tolist()


def _extreme_rows(rng: np.random.Generator, volume: Volume, n: int) -> list[list[int]]:
    """Valid code rows (13 wide) at the edges of every range, and random ones."""
    top = [(1 << b) - 1 for b in volume.bits]
    rows = []
    for i in range(n):
        idx = i % 4
        kind = i % 5
        if kind == 0:  # a^2 + b^2 + c^2 == 2 M^2 exactly: the dropped component is 0
            abc = [M, M, 0] if i % 2 else [-M, 0, -M]
        elif kind == 1:
            abc = [0, 0, 0]
        else:
            abc = [int(v) for v in rng.integers(-M, M + 1, 3)]
            while sum(v * v for v in abc) > 2 * M * M:
                abc = [v // 2 for v in abc]
        pos = [int(rng.choice([0, t, int(rng.integers(0, t + 1))])) for t in top]
        lin = [int(rng.choice([-_LIN_CODE_MAX, _LIN_CODE_MAX, 0, 5])) for _ in range(3)]
        ang = [int(rng.choice([-_ANG_CODE_MAX, _ANG_CODE_MAX, 0, -7])) for _ in range(3)]
        rows.append([idx, *abc, *pos, *lin, *ang])
    return rows


@pytest.mark.parametrize("volume", [DEFAULT_VOLUME, SMALL_VOLUME], ids=["default", "small"])
def test_decoded_compact_updates_always_pass_the_pose_checks(volume: Volume) -> None:
    """Why the session skips ``pose_problem`` / ``velocity_problem`` for decoded compact
    updates: dequantised valid codes are finite unit poses and finite velocities."""
    rng = np.random.default_rng(5)
    rows = _extreme_rows(rng, volume, 4000)
    for at in range(0, len(rows), 25):
        chunk = rows[at : at + 25]
        streams = list(range(len(chunk)))
        offsets = [int(v) for v in rng.integers(-(1 << 29), 1 << 29, len(chunk))]
        for width in (7, 13):
            update = _update_of_rows(
                7, 123_456_789, streams, offsets, [r[:width] for r in chunk], volume
            )
            assert pose_problem(update.entries) is None
            assert velocity_problem(update.entries) is None


def _updates(rng: np.random.Generator) -> list[tuple[PoseUpdate, float]]:
    """Updates near every refusal boundary, with NaN, inf, -0.0 and both record layouts."""
    out = []
    lo, hi = np.array(DEFAULT_VOLUME.lo), np.array(DEFAULT_VOLUME.hi)
    for i in range(600):
        n = int(rng.integers(1, 6)) if i % 50 else 70
        pos = rng.uniform(lo - 0.5, hi + 0.5, (n, 3))
        if i % 3 or i % 7 == 0:
            pos = np.clip(pos, lo, hi)
        if i % 7 == 0:
            at = int(rng.integers(0, n))  # NaN first or not: Python's min differs then
            pos[at, i % 3] = [lo[i % 3], hi[i % 3], -0.0, math.nan, math.inf][(i // 7) % 5]
        poses = np.concatenate([pos, np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))], axis=1)
        now = 1000.0
        # Mostly in time (then the positions decide), else around both limits.
        times = now - (rng.uniform(-0.45, 0.95, n) if i % 4 else rng.uniform(-0.6, 1.2, n))
        if i % 11 == 0:
            times[int(rng.integers(0, n))] = [math.nan, math.inf, -math.inf][(i // 11) % 3]
        vel = rng.normal(size=(n, 6)) if i % 2 else None
        update = PoseUpdate.from_arrays(i, list(range(n)), times, poses, velocities=vel)
        out.append((update, now))
    return out


def test_update_refusal_answers_as_numpy_did(monkeypatch: pytest.MonkeyPatch) -> None:
    """The pure-Python check accepts exactly what the numpy check accepts, and every
    refusal (kind and message) is numpy's."""
    rng = np.random.default_rng(9)
    cases = _updates(rng)
    fast = [update_refusal(u, now, 1.0, 0.5, DEFAULT_VOLUME) for u, now in cases]
    monkeypatch.setattr(limits, "_SMALL_UPDATE", -1)  # numpy for every update
    slow = [update_refusal(u, now, 1.0, 0.5, DEFAULT_VOLUME) for u, now in cases]
    assert fast == slow
    kinds = {r.kind for r in fast if r is not None}
    assert kinds == {"stale-capture", "future-capture", "out-of-bounds"}
    assert sum(r is None for r in fast) > 100


def test_next_due_follows_every_change() -> None:
    """The cached earliest due time equals the minimum over the members after joins,
    leaves, rate changes, ticks (parked members too) and a cleared member table."""
    rng = np.random.default_rng(4)
    room = Room("r", phase=0.3)
    now = 0.0
    users = 0
    for step in range(3000):
        op = int(rng.integers(0, 6))
        if op == 0 or not room.members:
            users += 1
            m = Member(users, f"u{users}", {}, float(rng.choice([5.0, 10.0, 20.0, 30.0])), Outbox())
            room.add(m, now)
        elif op == 1:
            room.remove(int(rng.choice(list(room.members))))
        elif op == 2:
            room.set_rate(int(rng.choice(list(room.members))), float(rng.integers(5, 31)), now)
        elif op == 3:
            m = room.members[int(rng.choice(list(room.members)))]
            m.parked = not m.parked
        elif op == 4 and step % 500 == 0:
            room.members.clear()
        else:
            due = room.next_due()
            assert due is not None
            now = max(now, due) + float(rng.uniform(0.0, 0.02))
            room.tick(now)
        expected = min((m.next_due for m in room.members.values()), default=None)
        assert room.next_due() == expected
