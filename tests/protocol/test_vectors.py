"""The golden vectors (protocol/vectors/) hold, both ways, and are what the generator writes.

Each vector is decoded by the protocol's own session paths (``decode_message``, the
relay's ``UpstreamDecoder``, the client's ``SnapshotDecoder``) and, for compact
frames, by ``protocol.golden_walk``, the reader written from docs/protocol.md; both
must give what the vector states. Frames a client sends are encoded again from the
vector's content and must give its bytes.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest

from posecast.protocol._compact import relative
from posecast.protocol.codec import Volume, encode_update_codes
from posecast.protocol.codec_relay import decode_relay_snapshot, encode_group
from posecast.protocol.errors import ProtocolViolation
from posecast.protocol.golden_messages import frame_json, message_json
from posecast.protocol.golden_vectors import build_vectors, update_json, write_vectors
from posecast.protocol.golden_walk import WalkError, predict, walk_snapshot, walk_update
from posecast.protocol.poses import PoseUpdate, Snapshot
from posecast.protocol.wire import MESSAGE_TYPES, decode_message, encode_message

VECTORS = Path(__file__).resolve().parents[2] / "protocol" / "vectors"
NAMES = [v["name"] for v in json.loads((VECTORS / "index.json").read_text())["vectors"]]


def _load(name: str) -> dict[str, Any]:
    data: dict[str, Any] = json.loads((VECTORS / f"{name}.json").read_text())
    return data


def _volume(v: dict[str, Any]) -> Volume:
    x = v["volume"]
    return Volume((x[0], x[1], x[2]), (x[3], x[4], x[5]))


def _walk_volume(v: dict[str, Any]) -> tuple[tuple[float, ...], tuple[float, ...]]:
    x = v["volume"]
    return tuple(x[:3]), tuple(x[3:])


def _update_baselines(v: dict[str, Any], key: str = "baselines_before") -> dict[int, list[int]]:
    return {b["stream"]: b["codes"] for b in v[key]}


def _snapshot_baselines(
    v: dict[str, Any], key: str = "baselines_before"
) -> dict[tuple[int, int], list[int]]:
    return {(b["user"], b["stream"]): b["codes"] for b in v[key]}


def _previous(v: dict[str, Any], key: str = "previous_header") -> tuple[int, int] | None:
    h = v[key]
    return None if h is None else (h["number"], h["base_us"])


def _wire(value: Any) -> Any:
    """JSON back to the msgpack value: {"bin": hex} -> bytes."""
    if isinstance(value, dict):
        if set(value) == {"bin"}:
            return bytes.fromhex(value["bin"])
        return {k: _wire(x) for k, x in value.items()}
    if isinstance(value, list):
        return [_wire(x) for x in value]
    return value


def _walked(entries: list[dict[str, Any]]) -> list[tuple[Any, ...]]:
    return sorted(
        (e.get("user", 0), e["stream"], e["offset_ms"], e["delta"], list(e["codes"]))
        for e in entries
    )


def test_committed_vectors_are_what_the_generator_writes(tmp_path: Path) -> None:
    """`posecast vectors` run now writes exactly the committed files (it is deterministic)."""
    written = write_vectors(tmp_path)
    fresh = {p.name: p.read_bytes() for p in written}
    committed = {p.name: p.read_bytes() for p in VECTORS.glob("*.json")}
    assert sorted(fresh) == sorted(committed)
    stale = [name for name in fresh if fresh[name] != committed[name]]
    assert not stale, f"stale vectors {stale}: run posecast vectors --out protocol/vectors"
    assert write_vectors(tmp_path) and {p.name: p.read_bytes() for p in written} == fresh


@pytest.mark.parametrize("name", NAMES)
def test_vector(name: str) -> None:
    """The vector decodes to what it states (and fails as it states), and encodes back."""
    v = _load(name)
    data = bytes.fromhex(v["hex"])
    if "error" in v:
        _check_error(v, data)
    elif v["frame"] == "msgpack":
        _check_msgpack(v, data)
    elif v["frame"] == "compact-update":
        _check_update(v, data)
    else:
        _check_snapshot(v, data)


def _check_msgpack(v: dict[str, Any], data: bytes) -> None:
    message = decode_message(data)
    assert message_json(data) == v["message"]
    assert encode_message(message) == data
    # The map of the vector, packed as msgpack packs it, is the frame: the canonical form.
    assert msgpack.packb(_wire(v["message"])) == data
    if isinstance(message, PoseUpdate | Snapshot):
        assert frame_json(message) == v["pose_frame"]


def _check_update(v: dict[str, Any], data: bytes) -> None:
    volume = _volume(v)
    before, previous = _update_baselines(v), _previous(v)
    decoded, after, header = update_json(data, volume, before, previous)
    assert decoded == v["pose_frame"]
    assert after == _update_baselines(v, "baselines_after")
    assert header == _previous(v, "previous_header_after")
    walked = walk_update(data, _walk_volume(v), before, previous)
    assert (walked.number, walked.base_us) == header
    assert _walked(walked.entries) == _walked(decoded["entries"])
    # Encode again from the vector's codes, times and baselines: the same bytes.
    entries = decoded["entries"]
    base_us = decoded["base_us"]
    width = 13 if v["velocity"] else 7
    encoded = encode_update_codes(
        decoded["number"],
        base_us / 1e6,
        [e["stream"] for e in entries],
        [base_us / 1e6 - e["offset_ms"] / 1000.0 for e in entries],
        np.array([e["codes"] for e in entries], np.int64).reshape(len(entries), width),
        volume,
        {s: np.array(c, np.int64) for s, c in before.items()},
    )
    assert relative(encoded.data, previous)[0] == data


def _check_snapshot(v: dict[str, Any], data: bytes) -> None:
    volume = _volume(v)
    before = _snapshot_baselines(v)
    frame = decode_relay_snapshot(data, volume, before)
    entries = v["pose_frame"]["entries"]
    assert frame.tick == v["pose_frame"]["number"]
    assert round(frame.base_time * 1e6) == v["pose_frame"]["base_us"]
    assert [[e["user"], e["stream"]] for e in entries] == [
        [u, s] for u, s in zip(frame.users, frame.streams, strict=True)
    ]
    assert [e["codes"] for e in entries] == frame.codes
    poses, velocities = frame.arrays()
    assert [e["pose"] for e in entries] == poses.astype(np.float64).tolist()
    if v["velocity"]:
        assert velocities is not None
        assert [e["velocity"] for e in entries] == velocities.astype(np.float64).tolist()
    after = dict(before)
    frame.remember(after)
    assert after == _snapshot_baselines(v, "baselines_after")
    walked = walk_snapshot(data, _walk_volume(v), before)
    assert (walked.number, walked.base_us) == (frame.tick, v["pose_frame"]["base_us"])
    assert _walked(walked.entries) == _walked(entries)
    if "spliced" not in v["name"]:
        # The relay's group encoder gives these bytes from the entries (a spliced
        # frame keeps the orders of the whole group, so it cannot be re-encoded alone).
        base = v["pose_frame"]["base_us"] / 1e6
        group = encode_group(
            frame.tick,
            base,
            [
                (
                    e["user"],
                    e["stream"],
                    base - e["offset_ms"] / 1000.0,
                    e["codes"],
                    before.get((e["user"], e["stream"])),
                )
                for e in entries
            ],
            volume,
            v["velocity"],
        )
        assert group.frame(None)[0] == data


def _check_error(v: dict[str, Any], data: bytes) -> None:
    want = v["error"]
    got: ProtocolViolation | None = None
    try:
        if v["frame"] == "msgpack":
            decode_message(data)
        elif v["frame"] == "compact-update":
            update_json(data, _volume(v), _update_baselines(v), _previous(v))
        else:
            decode_relay_snapshot(data, _volume(v), _snapshot_baselines(v))
    except ProtocolViolation as exc:
        got = exc
    assert got is not None, "the frame decodes"
    assert {"code": str(got.code), "fatal": got.fatal, "close_code": got.close_code} == want
    if v["frame"] == "compact-update":
        with pytest.raises(WalkError) as walked:
            walk_update(data, _walk_volume(v), _update_baselines(v), _previous(v))
        assert walked.value.code == want["code"]
    elif v["frame"] == "compact-snapshot":
        with pytest.raises(WalkError) as walked_snap:
            walk_snapshot(data, _walk_volume(v), _snapshot_baselines(v))
        assert walked_snap.value.code == want["code"]


def test_vectors_cover_what_the_spec_promises() -> None:
    """Every message type, both pose frame kinds in both codecs and variants, key and
    delta entries, index changes, the predictor's sign flip and clamp, empty sections,
    relative headers, other volumes and each decoding error are in some vector."""
    vectors = [_load(n) for n in NAMES]
    types = {v["message"]["type"] for v in vectors if "message" in v}
    assert types == MESSAGE_TYPES
    frames = {(v["frame"], v.get("velocity", False)) for v in vectors if "error" not in v}
    assert {
        ("compact-update", False),
        ("compact-update", True),
        ("compact-snapshot", False),
        ("compact-snapshot", True),
    } <= frames
    assert any("vpose" in v.get("message", {}) for v in vectors)
    seen: set[str] = set()
    for v in vectors:
        if "error" in v or v["frame"] == "msgpack":
            continue
        entries = v["pose_frame"]["entries"]
        n_delta = sum(e["delta"] for e in entries)
        seen.add("key" if n_delta < len(entries) else "no key section")
        seen.add("delta" if n_delta else "no delta section")
        if v["volume"] != [-8.0, -2.0, -8.0, 8.0, 4.0, 8.0]:
            seen.add("other volume")
        if v.get("previous_header"):
            seen.add("relative")
        held = {(b.get("user", 0), b["stream"]): b["codes"] for b in v["baselines_before"]}
        for e in entries:
            base = held.get((e.get("user", 0), e["stream"]))
            if not e["delta"] or base is None:
                continue
            idx = e["codes"][0]
            if idx != base[0]:
                seen.add("index change")
                full = [0, 0, 0, 0]
                others = [o for o in range(4) if o != base[0]]
                for o, x in zip(others, base[1:4], strict=True):
                    full[o] = x
                if full[idx] < 0:
                    seen.add("sign flip")
                rest = max(0, 2 * 4095**2 - sum(x * x for x in base[1:4]))
                full[base[0]] = round(rest**0.5)
                raw = [full[o] for o in range(4) if o != idx]
                if max(abs(x) for x in raw) > 4095 and predict(base, idx) != raw:
                    seen.add("clamp")
    assert seen >= {
        "key",
        "delta",
        "no key section",
        "no delta section",
        "other volume",
        "relative",
        "index change",
        "sign flip",
        "clamp",
    }
    errors = {(v["frame"], v["error"]["code"]) for v in vectors if "error" in v}
    assert {
        ("compact-update", "bad-baseline"),
        ("compact-update", "bad-frame"),
        ("compact-snapshot", "bad-baseline"),
        ("compact-snapshot", "bad-frame"),
        ("msgpack", "bad-frame"),
        ("msgpack", "bad-message"),
        ("msgpack", "unknown-type"),
        ("msgpack", "version-mismatch"),
    } <= errors


def test_build_is_deterministic() -> None:
    """Two builds in one process give equal vectors (no state leaks between them)."""
    assert build_vectors() == build_vectors()


def _random_codes(rng: np.random.Generator, n: int, width: int, volume: Volume) -> list[list[int]]:
    """Valid code rows: any idx, a rotation inside the ball, any position, any velocity."""
    rows = []
    top = [(1 << b) - 1 for b in volume.bits]
    while len(rows) < n:
        a, b, c = (int(x) for x in rng.integers(-4095, 4096, 3))
        if a * a + b * b + c * c > 2 * 4095**2:
            continue
        row = [int(rng.integers(0, 4)), a, b, c, *(int(rng.integers(0, t + 1)) for t in top)]
        if width == 13:
            row += [int(x) for x in rng.integers(-32768, 32769, 3)]
            row += [int(x) for x in rng.integers(-16384, 16385, 3)]
        rows.append(row)
    return rows


@pytest.mark.parametrize("velocity", [False, True])
def test_spec_reader_agrees_on_random_frames(velocity: bool) -> None:
    """golden_walk, written from the spec, reads random update and snapshot frames (many
    users, both classes, index changes, big differences, splicing) as the codec wrote them."""
    rng = np.random.default_rng(26)
    volume = Volume((-3.0, 0.0, -5.0), (3.0, 2.5, 5.0))
    walk_volume = (volume.lo, volume.hi)
    width = 13 if velocity else 7
    for _ in range(40):
        n = int(rng.integers(1, 9))
        streams = sorted(int(s) for s in rng.choice(40, n, replace=False))
        old = _random_codes(rng, n, width, volume)
        new = _random_codes(rng, n, width, volume)
        held = {s: old[i] for i, s in enumerate(streams) if rng.random() < 0.7}
        offsets = [int(x) for x in rng.integers(-50, 2000, n)]
        base_us = int(rng.integers(0, 1 << 40))
        encoded = encode_update_codes(
            int(rng.integers(0, 1 << 20)),
            base_us / 1e6,
            streams,
            [base_us / 1e6 - o / 1000.0 for o in offsets],
            np.array(new, np.int64),
            volume,
            {s: np.array(r, np.int64) for s, r in held.items()},
        )
        previous = (int(rng.integers(0, 1 << 20)), int(rng.integers(0, 1 << 40)))
        data = relative(encoded.data, previous)[0]
        walked = walk_update(data, walk_volume, held, previous)
        assert sorted((e["stream"], e["delta"], e["codes"]) for e in walked.entries) == sorted(
            (s, s in held, new[i]) for i, s in enumerate(streams)
        )
        users = [int(u) for u in rng.integers(0, 6, n)]
        sent = [
            (users[i], s, base_us / 1e6 - offsets[i] / 1000.0, new[i], held.get(s))
            for i, s in enumerate(streams)
        ]
        group = encode_group(7, base_us / 1e6, sent, volume, velocity)
        for exclude in (None, users[0]):
            frame, count = group.frame(exclude)
            if not count:
                continue
            bases = {(u, s): b for u, s, _, _, b in sent if b is not None}
            got = walk_snapshot(frame, walk_volume, bases)
            want = sorted((u, s, b is not None, r) for u, s, _, r, b in sent if u != exclude)
            assert (
                sorted((e["user"], e["stream"], e["delta"], e["codes"]) for e in got.entries)
                == want
            )
