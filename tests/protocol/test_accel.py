"""The codec's compiled accelerator and its pure-Python twin give the same bytes and values.

Each test runs a path on both implementations (``protocol._accel.use``) and
compares: group encodes of relay snapshots (every subscriber's splice), upstream
update decodes (every record and code, or the same error), Exp-Golomb packing.
The golden vectors and the fast-path tests run on both as well (tests/protocol/
conftest.py). A process without the accelerator, or told ``POSECAST_PURE=1``,
runs pure Python and says which.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from posecast.protocol import _accel, bits, codec
from posecast.protocol._compact import UpstreamDecoder, UpstreamEncoder
from posecast.protocol.codec_quant import (
    _ANG_CODE_MAX,
    _LIN_CODE_MAX,
    DEFAULT_VOLUME,
    ROTATION_BITS,
    M,
    quantise,
)
from posecast.protocol.codec_relay import RelayEntry, encode_group, encode_stored
from posecast.protocol.codec_small import SMALL_FRAME
from posecast.protocol.codec_store import CodeHistory
from posecast.protocol.errors import ProtocolViolation
from posecast.protocol.poses import PoseUpdate

T = TypeVar("T")

needs_compiled = pytest.mark.skipif(
    _accel.compiled() is None, reason=f"accelerator not built: {_accel.IMPLEMENTATION}"
)


def both(run: Callable[[], T]) -> tuple[T | str, T | str]:
    """``run()`` on the compiled path, then on the pure one (an error as its text)."""
    out: list[T | str] = []
    was_pure = _accel.speedups is None
    try:
        for pure in (False, True):
            _accel.use(pure)
            try:
                out.append(run())
            except ProtocolViolation as exc:
                out.append(f"{type(exc).__name__}: {exc.code} {exc.message}")
    finally:
        _accel.use(was_pure)
    return out[0], out[1]


def _poses(rng: np.random.Generator, n: int, spread: float = 1.0) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    p = rng.uniform(-7.9 * spread, 7.9 * spread, size=(n, 3))
    p[:, 1] = rng.uniform(-1.9, 3.9, size=n)
    return np.concatenate([p, q], axis=1)


def _velocities(rng: np.random.Generator, n: int) -> np.ndarray:
    return rng.normal(scale=2.0, size=(n, 6))


def _entries(seed: int, users: int, velocity: bool, delta_share: float) -> list[RelayEntry]:
    """A room's entries: each user 1-4 streams, key or delta, times a few ms apart."""
    rng = np.random.default_rng(seed)
    out: list[RelayEntry] = []
    for user in rng.choice(np.arange(1, 400), size=users, replace=False).tolist():
        streams = sorted(rng.choice(np.arange(0, 40), size=int(rng.integers(1, 5)), replace=False))
        n = len(streams)
        poses = _poses(rng, n)
        vel = _velocities(rng, n) if velocity else None
        now = quantise(poses, DEFAULT_VOLUME, vel).tolist()
        moved = poses + np.concatenate([rng.normal(scale=0.02, size=(n, 3)), np.zeros((n, 4))], 1)
        moved[:, 3:] = _poses(rng, n)[:, 3:] if rng.random() < 0.3 else poses[:, 3:]
        moved[:, :3] = moved[:, :3].clip(-7.9, 3.9)
        before = quantise(moved, DEFAULT_VOLUME, vel).tolist()
        for s, row, base in zip(streams, now, before, strict=True):
            capture = 100.0 - float(rng.uniform(0.0, 0.4))
            out.append((user, int(s), capture, row, base if rng.random() < delta_share else None))
    return out


def _group_frames(entries: list[RelayEntry], velocity: bool) -> list[Any]:
    group = encode_group(7, 100.0, entries, DEFAULT_VOLUME, velocity, trusted=True)
    users = sorted({e[0] for e in entries})
    return [group.frame(None), *(group.frame(u) for u in users)]


@needs_compiled
@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    users=st.integers(1, 24),
    velocity=st.booleans(),
    delta_share=st.sampled_from([0.0, 0.5, 1.0]),
)
def test_group_encode_gives_the_same_bytes(
    seed: int, users: int, velocity: bool, delta_share: float
) -> None:
    """A relay group's snapshot, and every subscriber's splice of it, are the same bytes."""
    entries = _entries(seed, users, velocity, delta_share)
    compiled, pure = both(lambda: _group_frames(entries, velocity))
    assert compiled == pure


@needs_compiled
def test_group_encode_refuses_alike() -> None:
    """An entry the relay must refuse (capture time NaN, far from the base) fails the same."""
    entries = _entries(3, 5, False, 1.0)
    for bad_time in (float("nan"), 100.0 - 2e6):
        u, s, _, row, base = entries[2]
        broken = [*entries[:2], (u, s, bad_time, row, base), *entries[3:]]
        compiled, pure = both(lambda b=broken: _group_frames(b, False))  # type: ignore[misc]
        assert isinstance(compiled, str) and compiled == pure


@needs_compiled
@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    users=st.integers(1, 12),
    velocity=st.booleans(),
    trusted=st.booleans(),
    damage=st.sampled_from(["none", "twin", "user", "stream", "width", "code", "idx", "position"]),
)
def test_group_encode_refuses_what_the_pure_path_refuses(
    seed: int, users: int, velocity: bool, trusted: bool, damage: str
) -> None:
    """Entries with a stream twice, ids or codes out of range, rows of another width:
    the same error on both paths (trusted or not), or the same bytes where the pure
    path takes them; the group's users are the same."""
    entries = _entries(seed, users, velocity, 0.5)
    u, s, t, row, base = entries[0]
    row = list(row)
    if damage == "twin":
        entries.append((u, s, t - 0.001, row, None))
    elif damage == "user":
        entries[0] = (0x10000, s, t, row, base)
    elif damage == "stream":
        entries[0] = (u, -1, t, row, base)
    elif damage == "width":
        entries[0] = (u, s, t, row[:6], base)
    elif damage == "code":
        row[1] = M + 1
        entries[0] = (u, s, t, row, base)
    elif damage == "idx":
        row[0] = 4
        entries[0] = (u, s, t, row, base)
    elif damage == "position":
        row[4] = 1 << DEFAULT_VOLUME.bits[0]
        entries[0] = (u, s, t, row, None)

    def run() -> Any:
        try:
            group = encode_group(7, 100.0, entries, DEFAULT_VOLUME, velocity, trusted=trusted)
        except ProtocolViolation:
            raise
        except Exception as exc:  # trusted codes out of range: whatever the pure path does
            return type(exc).__name__
        users = sorted({e[0] for e in entries})
        return group.users, [group.frame(None), *(group.frame(x) for x in users)]

    compiled, pure = both(run)
    assert compiled == pure


@needs_compiled
@settings(max_examples=200, deadline=None)
@given(blob=st.binary(max_size=300), exclude=st.integers(-1, 5))
def test_splice_of_a_garbage_group_is_refused(blob: bytes, exclude: int) -> None:
    """A packed group is only ever the accelerator's own, but anything else given to its
    splice is refused with ValueError (or spliced within its bounds), never read past."""
    compiled = _accel.compiled()
    assert compiled is not None
    try:
        data, n = compiled.splice_packed(b"\xc1\x24\x01\x00", blob, [1, 2], [3, 4, 5], exclude)
    except ValueError:
        return
    assert isinstance(data, bytes) and n >= 0


@dataclass
class _Stored:
    """A relay's stored stream (codec_relay.StoredStream), as server.room keeps it."""

    user: int
    capture: float
    version: int
    pose: list[float]
    codes: list[int] | None
    history: deque[tuple[int, list[int]]] | CodeHistory = field(
        default_factory=lambda: deque(maxlen=4)
    )
    computed: int = 0

    def coded(self, volume: codec.Volume) -> list[int]:
        codes = self.codes
        if codes is None:
            self.computed += 1
            codes = self.codes = quantise(np.array([self.pose]), volume)[0].tolist() + [0] * 6
        h = self.history
        newest = h.last_version() if isinstance(h, CodeHistory) else (h[-1][0] if h else None)
        if newest != self.version:
            self.history.append((self.version, codes))
        return codes


def _store(
    seed: int, users: int, packed: bool = False
) -> tuple[dict[int, _Stored], list[tuple[int, int, list[float]]]]:
    """A store of 1-3 streams per user, then the updates that follow: (stream, version,
    pose). Some streams come with codes (a compact publisher), some without (raw).
    ``packed``: their histories are ``CodeHistory`` (as a relay's room keeps them)."""
    rng = np.random.default_rng(seed)
    store: dict[int, _Stored] = {}
    later = []
    version = 0
    for user in rng.choice(np.arange(1, 300), size=users, replace=False).tolist():
        for _ in range(int(rng.integers(1, 4))):
            sid = int(rng.integers(0, 2000))
            if sid in store:
                continue
            version += 1
            pose = _poses(rng, 1)[0].tolist()
            compact = bool(rng.random() < 0.6)
            codes = quantise(np.array([pose]), DEFAULT_VOLUME).tolist()[0] + [0] * 6
            store[sid] = _Stored(user, 50.0 - float(rng.uniform(0, 0.3)), version, pose,
                                 codes if compact else None)  # fmt: skip
            if packed:
                store[sid].history = CodeHistory(4)
    for _ in range(3 * len(store)):
        sid = int(rng.choice(list(store)))
        version += 1
        later.append((sid, version, _poses(rng, 1, 0.1)[0].tolist()))
    return store, later


def _stored_frames(
    seed: int, users: int, sinces: list[int], velocity: bool, packed: bool = False
) -> Any:
    """Frames of the store's group after each step of updates, from each ``since``,
    and what the store holds after: the history of every stream, codes computed."""
    store, later = _store(seed, users, packed)
    out: list[Any] = []
    step = max(1, len(later) // 3)
    for i in range(0, len(later) + 1, step):
        for sid, version, pose in later[i : i + step]:
            s = store[sid]
            s.version, s.pose, s.capture = version, pose, s.capture + 0.05
            s.codes = (
                quantise(np.array([pose]), DEFAULT_VOLUME).tolist()[0] + [0] * 6
                if version % 3
                else None
            )
        top = max(s.version for s in store.values())
        for since in sinces:
            group = encode_stored(i + 1, 50.0 + i, store, min(since, top), DEFAULT_VOLUME, velocity)
            if group is None:
                out.append(None)
                continue
            users_in = group.users
            out.append([users_in, group.frame(None), *(group.frame(u) for u in users_in)])
    out.append({sid: (list(s.history), s.codes, s.computed) for sid, s in store.items()})
    return out


@needs_compiled
@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    users=st.integers(1, 12),
    sinces=st.lists(st.integers(-1, 60), min_size=1, max_size=4),
    velocity=st.booleans(),
    packed=st.booleans(),
)
def test_stored_group_encode_gives_the_same_bytes_and_store(
    seed: int, users: int, sinces: list[int], velocity: bool, packed: bool
) -> None:
    """A group gathered from a relay's store (codes from updates or computed, deltas
    against the history as of ``since``, keys where there is none; histories as
    (version, codes) pairs or packed, ``CodeHistory``): the same frames for every
    subscriber, and the same history and codes left in the store."""
    compiled, pure = both(lambda: _stored_frames(seed, users, sinces, velocity, packed))
    assert compiled == pure


def test_code_history_keeps_the_newest_versions() -> None:
    """A CodeHistory is a deque of (version, codes) of its capacity, packed: the oldest
    goes when it is full; a baseline is the newest version at or before ``since``."""
    packed, pairs = CodeHistory(3), deque[tuple[int, list[int]]](maxlen=3)
    assert packed.last_version() is None and packed.baseline(10) is None
    for version in (2, 5, 6, 9):
        row = [version % 4, -4095, 4095, 7, 1 << 40, 0, 3] + ([] if version % 2 else [1] * 6)
        packed.append((version, row))
        pairs.append((version, row))
        assert packed.items() == list(pairs) and packed.last_version() == version
    assert [packed.baseline(s) for s in (4, 5, 8, 100)] == [
        None,
        pairs[0][1],
        pairs[1][1],
        pairs[2][1],
    ]
    with pytest.raises(ValueError, match="rows of 7 or 13"):
        packed.append((10, [1, 2, 3]))


def _updates(seed: int, frames: int, velocity: bool) -> list[bytes]:
    """A client's compact update frames: 1-3 streams a frame, some jumps, some new streams."""
    rng = np.random.default_rng(seed)
    enc = UpstreamEncoder(DEFAULT_VOLUME)
    poses = _poses(rng, 8)
    out = []
    for number in range(1, frames + 1):
        streams = np.sort(rng.choice(8, size=int(rng.integers(1, 4)), replace=False))
        poses[:, :3] = (poses[:, :3] + rng.normal(scale=0.01, size=(8, 3))).clip(-7.9, 3.9)
        if rng.random() < 0.2:
            poses[:, 3:] = _poses(rng, 8)[:, 3:]
        t = 10.0 + number / 20
        update = PoseUpdate.from_arrays(
            number,
            streams,
            t - rng.uniform(0, 0.05, size=streams.size),
            poses[streams],
            base_time=t,
            velocities=_velocities(rng, streams.size) if velocity else None,
        )
        out.append(enc.encode(update))
        enc.commit()
    return out


def _decode_all(frames: list[bytes], mutate: int | None = None) -> list[Any]:
    dec = UpstreamDecoder(DEFAULT_VOLUME)
    got: list[Any] = []
    for i, data in enumerate(frames):
        if mutate is not None and i == len(frames) - 1:
            data = bytearray(data)
            data[mutate % len(data)] ^= 1 << (mutate % 7)
            data = bytes(data)
        try:
            u = dec.decode(data)
            got.append((u.entries.tobytes(), u.seq, u.base_time, sorted(dec.last_codes.items())))
        except ProtocolViolation as exc:
            got.append((exc.code, exc.message))
            break
    return got


@needs_compiled
@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    frames=st.integers(1, 12),
    velocity=st.booleans(),
    mutate=st.none() | st.integers(0, 10_000),
)
def test_update_decode_gives_the_same_values(
    seed: int, frames: int, velocity: bool, mutate: int | None
) -> None:
    """The relay's decode of a client's updates gives the same records, codes and
    baselines, or the same error for a frame with one bit flipped."""
    stream = _updates(seed, frames, velocity)
    compiled, pure = both(lambda: _decode_all(stream, mutate))
    assert compiled == pure


def _decoder_after(frames: list[bytes]) -> UpstreamDecoder:
    """A decoder (pure path) that has decoded ``frames``."""
    was_pure = _accel.speedups is None
    _accel.use(True)
    try:
        dec = UpstreamDecoder(DEFAULT_VOLUME)
        for data in frames:
            dec.decode(data)
    finally:
        _accel.use(was_pure)
    return dec


def _one_call(dec: UpstreamDecoder, data: bytes) -> Any:
    """The compiled whole-update decode of ``data`` against a copy of ``dec``'s state,
    as ``_decode_fast`` gives it: (seq, base time, records, codes, baselines) or None."""
    compiled = _accel.compiled()
    assert compiled is not None
    baselines = {s: list(r) for s, r in dec.baselines.items()}
    before = {s: list(r) for s, r in baselines.items()}
    got = compiled.decode_update(data, dec._previous, dec._geometry.packed, baselines, *dec._scale)
    if got is None:
        assert baselines == before, "a refused frame changed the baselines"
        return None
    number, base_us, records, codes = got
    assert baselines == before | codes
    return number, base_us / 1e6, records, sorted(codes.items())


def _fast_twin(dec: UpstreamDecoder, data: bytes) -> Any:
    """The pure ``_decode_fast`` of ``data`` against a copy of ``dec``'s state."""
    twin = UpstreamDecoder(DEFAULT_VOLUME)
    twin.baselines = {s: list(r) for s, r in dec.baselines.items()}
    twin._previous = dec._previous
    was_pure = _accel.speedups is None
    _accel.use(True)
    try:
        u = twin._decode_fast(data)
    finally:
        _accel.use(was_pure)
    if u is None:
        return None
    return u.seq, u.base_time, u.entries.tobytes(), sorted(twin.last_codes.items())


@needs_compiled
@settings(max_examples=150, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    frames=st.integers(2, 8),
    velocity=st.booleans(),
    cut=st.integers(0, 200),
    tail=st.binary(max_size=40),
    flips=st.lists(st.integers(0, 8 * 200), max_size=4),
)
def test_one_call_update_decode_matches_its_twin_on_any_bytes(
    seed: int, frames: int, velocity: bool, cut: int, tail: bytes, flips: list[int]
) -> None:
    """``_speedups.decode_update`` on a valid frame cut short, with garbage after it,
    with bits flipped: None (the reference path decides; the baselines untouched) or
    exactly the pure fast path's update, codes and baselines; never a crash."""
    stream = _updates(seed, frames, velocity)
    dec = _decoder_after(stream[:-1])
    data = bytearray(stream[-1][:cut] + tail)
    for bit in flips:
        if data:
            data[(bit // 8) % len(data)] ^= 0x80 >> (bit % 8)
    for candidate in (stream[-1], bytes(data)):
        got = _one_call(dec, candidate)
        if got is not None:
            assert got == _fast_twin(dec, candidate)
    assert _one_call(dec, stream[-1]) is not None  # the valid frame takes this path


@needs_compiled
@settings(max_examples=100, deadline=None)
@given(data=st.binary(max_size=80), relative=st.booleans())
def test_one_call_update_decode_survives_garbage(data: bytes, relative: bool) -> None:
    """Arbitrary bytes after an update frame's magic and flags: no crash, no read past the
    end, and the whole decoder answers as the pure one does (same update or error)."""
    head = bytes([0xC1, 0x11 | (8 if relative else 0)])
    stream = _updates(5, 3, False)
    for frame in (head + data, data):
        compiled, pure = both(lambda f=frame: _decode_all([*stream, f]))  # type: ignore[misc]
        assert compiled == pure


@needs_compiled
@settings(max_examples=200, deadline=None)
@given(
    values=st.lists(
        st.one_of(st.integers(0, 3000), st.integers(0, 2**62)), min_size=0, max_size=40
    ),
    k=st.integers(0, bits.MAX_K),
)
def test_eg_pack_gives_the_same_bits(values: list[int], k: int) -> None:
    """Exp-Golomb packing gives the same bits for short and long values, every order."""
    orders = [(k + i) % (bits.MAX_K + 1) for i in range(len(values))]
    compiled, pure = both(lambda: bits.eg_pack(values, orders))
    assert compiled == pure


@needs_compiled
def test_compiled_constants_are_the_codecs() -> None:
    """The constants compiled into the accelerator are the codec's."""
    compiled = _accel.compiled()
    assert compiled is not None
    assert compiled.CONSTANTS == {
        "MAX_EG_BITS": bits.MAX_EG_BITS,
        "MAX_K": bits.MAX_K,
        "SMALL_FRAME": SMALL_FRAME,
        "M": M,
        "ROTATION_BITS": ROTATION_BITS,
        "LIN_CODE_MAX": _LIN_CODE_MAX,
        "ANG_CODE_MAX": _ANG_CODE_MAX,
    }


def test_use_switches_what_runs() -> None:
    """``use`` switches the running path, and codec.IMPLEMENTATION follows it."""
    was_pure = _accel.speedups is None
    try:
        assert _accel.use(True) == codec.IMPLEMENTATION == "pure Python (POSECAST_PURE=1)"
        assert _accel.speedups is None
        now = _accel.use(False)
        assert now == codec.IMPLEMENTATION
        assert (now == _accel.COMPILED) == (_accel.compiled() is not None)
    finally:
        _accel.use(was_pure)


def _python(code: str, **env: str) -> subprocess.CompletedProcess[str]:
    environment = {k: v for k, v in os.environ.items() if k != _accel.PURE_ENV} | env
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, env=environment, timeout=60
    )


def test_pure_env_runs_pure_python() -> None:
    """POSECAST_PURE=1 runs the pure twin, silently, and --version's codec line says so."""
    code = (
        "from posecast.cli.common import version_lines; from posecast.protocol import _accel;"
        "print(_accel.speedups is None); print(version_lines()[2])"
    )
    got = _python(code, POSECAST_PURE="1")
    assert got.returncode == 0, got.stderr
    assert got.stdout.splitlines() == ["True", "codec: pure Python (POSECAST_PURE=1)"]
    assert got.stderr == ""


def test_without_the_extension_it_falls_back_and_the_relay_says_so_once() -> None:
    """With the extension missing (no compiler at install), the codec runs pure Python;
    importing it prints nothing (a CLI error stays one line), and a relay starting
    logs the one line that says so."""
    code = (
        "import sys, asyncio, logging; sys.modules['posecast.protocol._speedups'] = None\n"
        "from posecast.protocol import codec, codec_relay, _compact, bits\n"
        "from posecast.protocol import _accel\n"
        "print(codec.IMPLEMENTATION, _accel.speedups is None, flush=True)\n"
        "from posecast.server.app import RelayServer, ServerConfig, serving\n"
        "logging.basicConfig(level=logging.WARNING, format='%(message)s')\n"
        "async def main():\n"
        "    server = RelayServer(ServerConfig(host='127.0.0.1', port=0, secret='s' * 32))\n"
        "    async with serving(server):\n"
        "        pass\n"
        "asyncio.run(main())\n"
    )
    got = _python(code)
    assert got.returncode == 0, got.stderr
    assert got.stdout.strip() == "pure Python (accelerator not built) True"
    lines = got.stderr.splitlines()
    assert len(lines) == 1 and "not built" in lines[0], got.stderr
