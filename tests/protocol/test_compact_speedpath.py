"""The relay's fast decode of compact updates gives what the reference path gives, always.

``UpstreamDecoder`` reads small update frames with ``codec_fast.decode_update_rows``
and packs their ``PoseUpdate`` records itself; every other frame goes through
``codec.decode_update`` (the reference path). These tests run a reference decoder
(the decoder as it was before the fast path: ``absolute``, ``codec.decode_update``
with numpy baselines, ``PoseUpdate.from_arrays``) beside it on the same frames,
valid and hostile, and require the same update (bytes of every record), the same
codes, or the same error code and message.
"""

from __future__ import annotations

import copy
import functools
from typing import Any

import numpy as np
import pytest

from posecast.protocol import _compact
from posecast.protocol._compact import UpstreamDecoder, UpstreamEncoder, absolute
from posecast.protocol.codec import DEFAULT_VOLUME, Volume, decode_update
from posecast.protocol.errors import ProtocolViolation, RemoteProtocolError
from posecast.protocol.poses import PoseUpdate

SMALL_VOLUME = Volume((-3.0, -0.5, -4.0), (5.0, 2.5, 4.0))
#: One worker runs the whole module (pytest-xdist), so that the compiled and the pure
#: runs of a hostile test share the reference's answers (``functools.cache`` below).
pytestmark = pytest.mark.xdist_group("compact-speedpath")


class ReferenceDecoder:
    """``UpstreamDecoder.decode`` before the fast path (numpy baselines, one frame each)."""

    def __init__(self, volume: Volume) -> None:
        self.volume = volume
        self.baselines: dict[int, Any] = {}
        self.previous: tuple[int, int] | None = None
        self.last_codes: dict[int, list[int]] = {}

    def decode(self, data: bytes) -> PoseUpdate:
        try:
            whole, header = absolute(bytes(data), self.previous)
            frame = decode_update(whole, self.volume, self.baselines)
        except ProtocolViolation as exc:
            raise RemoteProtocolError(exc.code, exc.message, in_reply_to="update") from None
        self.previous = header
        frame.remember(self.baselines)
        self.last_codes = dict(zip(frame.streams.tolist(), frame.codes.tolist(), strict=True))
        return PoseUpdate.from_arrays(
            frame.number,
            frame.streams,
            frame.capture_times,
            frame.poses,
            base_time=frame.base_time,
            velocities=frame.velocities,
        )


Outcome = tuple[Any, ...]


def outcome(decoder: UpstreamDecoder | ReferenceDecoder, data: bytes) -> Outcome:
    """What decoding ``data`` gives: the update's every byte and codes, or the error."""
    try:
        update = decoder.decode(data)
    except RemoteProtocolError as exc:
        return ("error", exc.code, exc.message, exc.in_reply_to)
    return (
        "update",
        update.seq,
        update.base_time,
        update.entries.dtype,
        update.entries.tobytes(),
        sorted(decoder.last_codes.items()),
    )


def motion(rng: np.random.Generator, frames: int, n: int, volume: Volume) -> np.ndarray:
    """Smooth poses (frames, n, 7) inside ``volume``, with some fast turns and
    near-180-degree quaternions (the largest component changes: predicted rotations)."""
    lo, hi = np.array(volume.lo), np.array(volume.hi)
    start = rng.uniform(lo + 0.5, hi - 0.5, (n, 3))
    walk = np.cumsum(rng.normal(0.0, 0.01, (frames, n, 3)), axis=0)
    pos = np.clip(start + walk, lo, hi)
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    speed = rng.uniform(0.05, 0.6, n)  # rad per frame: the largest component moves
    angle = np.arange(frames)[:, None] * speed[None, :] + rng.uniform(0, 6.3, n)
    q = np.concatenate(
        [np.cos(angle / 2)[..., None], np.sin(angle / 2)[..., None] * axis[None]], axis=-1
    )
    return np.concatenate([pos, q], axis=-1)


def frames_of(
    rng: np.random.Generator,
    volume: Volume,
    streams: list[int],
    count: int,
    velocities: bool = False,
    late: list[int] | None = None,
) -> list[bytes]:
    """``count`` update frames of a real encoder (key, then deltas), relative headers;
    streams in ``late`` join from the middle on (key entries beside deltas)."""
    enc = UpstreamEncoder(volume)
    late = late or []
    poses = motion(rng, count, len(streams) + len(late), volume)
    out = []
    for i in range(count):
        ids = streams + (late if i >= count // 2 else [])
        t = 100.0 + i / 20.0
        times = t - rng.uniform(0.0, 0.03, len(ids))
        vel = rng.normal(0.0, 3.0, (len(ids), 6)) if velocities else None
        update = PoseUpdate.from_arrays(
            i + 1, ids, times, poses[i, : len(ids)], base_time=t, velocities=vel
        )
        out.append(enc.encode(update))
        enc.commit()
    return out


CASES = {
    "three-streams": dict(streams=[3, 4, 5]),
    "head-is-stream-0": dict(streams=[0, 1, 2]),
    "velocities": dict(streams=[6, 7, 8], velocities=True),
    "velocities-stream-0": dict(streams=[0, 9], velocities=True),
    "one-stream": dict(streams=[40000]),
    "late-streams": dict(streams=[3, 4, 5], late=[1, 9]),
    "late-velocities": dict(streams=[0, 4], velocities=True, late=[2]),
    "over-30-streams": dict(streams=list(range(10, 42))),
}


@pytest.mark.parametrize("volume", [DEFAULT_VOLUME, SMALL_VOLUME], ids=["default", "small"])
@pytest.mark.parametrize("case", sorted(CASES))
def test_valid_frames_decode_as_the_reference_path(case: str, volume: Volume) -> None:
    """Every frame of an encoder's sequence: the same update, record for record."""
    rng = np.random.default_rng(sorted(CASES).index(case))
    frames = frames_of(rng, volume, count=60, **CASES[case])  # type: ignore[arg-type]
    fast, ref = UpstreamDecoder(volume), ReferenceDecoder(volume)
    for data in frames:
        got = outcome(fast, data)
        assert got[0] == "update"
        assert got == outcome(ref, data)


def test_small_frames_take_the_fast_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """A relay's updates never reach the reference path (else the tests above prove little)."""
    rng = np.random.default_rng(1)
    frames = frames_of(rng, DEFAULT_VOLUME, [0, 1, 2], 40, velocities=False, late=[5])
    frames += frames_of(rng, DEFAULT_VOLUME, [3, 4], 20, velocities=True)[:1]
    fast = UpstreamDecoder(DEFAULT_VOLUME)

    def refuse(*_: object) -> None:
        raise AssertionError("the reference path decoded a small valid frame")

    monkeypatch.setattr(_compact, "decode_update", refuse)
    for data in frames[:-1]:
        fast.decode(data)
    fresh = UpstreamDecoder(DEFAULT_VOLUME)
    fresh.decode(frames[-1])  # a key frame with velocities
    assert sorted(fresh.last_codes) == [3, 4]


def mutations(rng: np.random.Generator, data: bytes) -> list[bytes]:
    """Hostile variants of a frame: bit flips, truncations, extra bytes, header bytes."""
    out = []
    for _ in range(12):
        b = bytearray(data)
        i = int(rng.integers(0, 8 * len(b)))
        b[i // 8] ^= 0x80 >> (i % 8)
        out.append(bytes(b))
    for _ in range(2):
        b = bytearray(data)
        for i in rng.integers(0, 8 * len(b), 3):
            b[int(i) // 8] ^= 0x80 >> (int(i) % 8)
        out.append(bytes(b))
    out.append(data[: int(rng.integers(0, len(data)))])
    out.append(data[:-1])
    out.append(data + b"\x00")
    out.append(data + bytes([int(rng.integers(1, 256))]))
    b = bytearray(data)
    b[1] = int(rng.integers(0, 256))
    out.append(bytes(b))
    b = bytearray(data)
    b[int(rng.integers(2, len(b)))] = int(rng.integers(0, 256))
    out.append(bytes(b))
    return out


def fork(decoder: UpstreamDecoder) -> UpstreamDecoder:
    """A copy in the same state: every attribute deep-copied but the volume and its
    geometry, which the decoder reads and never changes (so the copies share them)."""
    memo: dict[int, Any] = {id(decoder.volume): decoder.volume}
    memo[id(decoder._geometry)] = decoder._geometry
    return copy.deepcopy(decoder, memo)


#: What the reference decoder answers to a hostile frame: its outcome, then (if it
#: decoded an update) its baselines as lists and its outcome on the next valid frame.
Answer = tuple[Outcome, dict[int, list[int]] | None, Outcome | None]


@functools.cache
def hostile_reference(case: str) -> list[tuple[bytes, Outcome, list[tuple[bytes, Answer]]]]:
    """The sequence of ``case`` (24 frames), each frame's ~20 mutations and the
    reference path's answer to each, from a copy of the reference decoder in the
    state the frames before left it. The reference path runs no accelerated code
    (``codec.decode_update``), so both ``codec_impl`` runs of a process share this."""
    rng = np.random.default_rng(100 + sorted(CASES).index(case))
    frames = frames_of(rng, DEFAULT_VOLUME, count=24, **CASES[case])  # type: ignore[arg-type]
    ref = ReferenceDecoder(DEFAULT_VOLUME)
    out = []
    for k, data in enumerate(frames):
        nxt = frames[min(k + 1, len(frames) - 1)]
        answers = []
        for bad in mutations(rng, data):
            r = copy.deepcopy(ref, {id(ref.volume): ref.volume})
            got = outcome(r, bad)
            if got[0] == "update":
                rows = {s: row.tolist() for s, row in r.baselines.items()}
                answers.append((bad, (got, rows, outcome(r, nxt))))
            else:
                answers.append((bad, (got, None, None)))
        out.append((data, outcome(ref, data), answers))
    return out


@pytest.mark.parametrize("case", sorted(CASES))
def test_hostile_frames_get_the_reference_paths_answer(case: str) -> None:
    """Each frame of a sequence mutated ~20 ways, fed to copies of both decoders in the
    same state: the same update or the same error (code, message), and the same state."""
    sequence = hostile_reference(case)
    fast = UpstreamDecoder(DEFAULT_VOLUME)
    errors = updates = 0
    for k, (data, ref_valid, answers) in enumerate(sequence):
        nxt = sequence[min(k + 1, len(sequence) - 1)][0]
        for bad, (ref_got, ref_rows, ref_next) in answers:
            f = fork(fast)
            got = outcome(f, bad)
            assert got == ref_got, bad.hex()
            errors += got[0] == "error"
            updates += got[0] == "update"
            if got[0] == "update":  # then both hold the same baselines
                assert f.baselines == ref_rows
                # ... and decode the next frame alike (a bad baseline, typically)
                assert outcome(f, nxt) == ref_next
        assert outcome(fast, data) == ref_valid
    assert errors > 0 and updates >= 0


@functools.cache
def bit_flip_reference() -> list[tuple[bytes, Outcome, list[tuple[bytes, Outcome]]]]:
    """30 frames of three streams in SMALL_VOLUME, each with every single bit after the
    magic byte flipped, and the reference path's answer to each (from a copy of its
    decoder in the state the frames before left it; shared by both ``codec_impl`` runs)."""
    rng = np.random.default_rng(7)
    frames = frames_of(rng, SMALL_VOLUME, [3, 4, 5], 30)
    ref = ReferenceDecoder(SMALL_VOLUME)
    out = []
    for data in frames:
        answers = []
        for i in range(2 * 8, 8 * len(data)):  # every single bit after the magic byte
            b = bytearray(data)
            b[i // 8] ^= 0x80 >> (i % 8)
            r = copy.deepcopy(ref, {id(ref.volume): ref.volume})
            answers.append((bytes(b), outcome(r, bytes(b))))
        out.append((data, outcome(ref, data), answers))
    return out


def test_hostile_codes_are_refused_with_the_reference_codes() -> None:
    """Deltas that leave the volume or the rotation range: the reference's error code."""
    fast = UpstreamDecoder(SMALL_VOLUME)
    codes = set()
    for data, ref_valid, answers in bit_flip_reference():
        for bad, ref_got in answers:
            got = outcome(fork(fast), bad)
            assert got == ref_got
            if got[0] == "error":
                codes.add(got[1])
        assert outcome(fast, data) == ref_valid
    assert {"bad-frame", "bad-baseline", "bad-pose"} <= {str(c) for c in codes}
