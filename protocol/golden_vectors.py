"""The golden vectors: frames every posecast implementation must decode (and encode) alike.

:func:`build_vectors` makes them, deterministically, with the protocol's own
encoders and decoders (the session paths a client and the relay use);
:func:`write_vectors` writes one JSON file per vector plus ``index.json``
(``posecast vectors --out protocol/vectors``). The JSON schema is in
``protocol/vectors/README.md``. Pose values are fixed decimals, never random
or computed with transcendental functions, so the files are identical on
every machine.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from posecast.protocol._compact import SnapshotDecoder, UpstreamDecoder, relative
from posecast.protocol.codec import DEFAULT_VOLUME, Volume, encode_update_codes, quantise
from posecast.protocol.codec_quant import dequantise
from posecast.protocol.codec_relay import decode_relay_snapshot, encode_group
from posecast.protocol.golden_messages import (
    POSES,
    VELOCITIES,
    Vector,
    control_vectors,
    error_vector,
    floats,
    msgpack_error_vectors,
    raw_pose_vectors,
    to_hex,
)

__all__ = ["SCHEMA_VERSION", "build_vectors", "update_json", "write_vectors"]

#: Bumped when the JSON layout of a vector changes.
SCHEMA_VERSION = 1

# The poses of POSES a frame later, moved and turned (w first, normalised when
# quantised): fixed decimals, the same on every machine.
_MOVED = (
    (0.1012, 1.5987, -0.2031, 0.9186, 0.01, 0.395, -0.005),
    (-0.2461, 1.2104, -0.3978, 0.7, 0.71414284, 0.0, 0.0),
    (0.2577, 1.1892, -0.4105, -0.02, 0.01, 0.03, -0.9993),
)
_SMALL_ROOM = Volume((-2.0, 0.0, -2.0), (2.0, 2.5, 2.0))
# A rotation whose largest component moves from w to a negative x: the predictor
# flips the sign of the baseline re-expressed with idx 1.
_FLIP = (
    (0.3, 1.1, 0.2, 0.7214, -0.6907, 0.05, 0.0),
    (0.3, 1.1, 0.2, 0.6907, -0.7214, 0.05, 0.0),
)


def _entries_of(
    users: Sequence[int] | None,
    streams: Sequence[int],
    offsets: Sequence[int],
    codes: Sequence[Sequence[int]],
    delta: Sequence[bool],
    base_us: int,
    volume: Volume,
) -> list[dict[str, Any]]:
    width = len(codes[0]) if codes else 7
    poses, velocities = dequantise(np.array(codes, np.int64).reshape(len(codes), width), volume)
    out = []
    for i, stream in enumerate(streams):
        entry: dict[str, Any] = {}
        if users is not None:
            entry["user"] = int(users[i])
        entry["stream"] = int(stream)
        entry["offset_ms"] = int(offsets[i])
        entry["capture_time"] = base_us / 1e6 - offsets[i] / 1000.0
        entry["delta"] = bool(delta[i])
        entry["codes"] = [int(c) for c in codes[i]]
        entry["pose"] = floats(poses[i])
        entry["velocity"] = None if velocities is None else floats(velocities[i])
        out.append(entry)
    return out


def update_json(
    data: bytes,
    volume: Volume,
    baselines: Mapping[int, list[int]],
    previous: tuple[int, int] | None,
) -> tuple[dict[str, Any], dict[int, list[int]], tuple[int, int]]:
    """Decode a compact update as the relay does: (decoded JSON, baselines after, header)."""
    decoder = UpstreamDecoder(volume)
    decoder.baselines = {k: list(v) for k, v in baselines.items()}
    decoder._previous = previous
    update = decoder.decode(data)
    assert decoder._previous is not None
    number, base_us = decoder._previous
    order = sorted(decoder.last_codes)
    codes = [decoder.last_codes[s] for s in order]
    offsets = [round((base_us / 1e6 - float(t)) * 1000.0) for t in update.capture_times]
    by_stream = dict(zip(update.streams.tolist(), offsets, strict=True))
    delta = [s in baselines for s in order]
    entries = _entries_of(None, order, [by_stream[s] for s in order], codes, delta, base_us, volume)
    decoded = {"kind": "update", "number": number, "base_us": base_us, "entries": entries}
    return decoded, dict(decoder.baselines), (number, base_us)


def _baselines_json(baselines: Mapping[Any, Sequence[int]]) -> list[dict[str, Any]]:
    out = []
    for key in sorted(baselines):
        if isinstance(key, tuple):
            out.append(
                {"user": key[0], "stream": key[1], "codes": [int(c) for c in baselines[key]]}
            )
        else:
            out.append({"stream": key, "codes": [int(c) for c in baselines[key]]})
    return out


def _volume_json(volume: Volume) -> list[float]:
    return [*volume.lo, *volume.hi]


# --------------------------------------------------------------------------- compact updates


class _Upstream:
    """A client's compact update stream: codes in, frames and vectors out."""

    def __init__(self, volume: Volume, velocity: bool) -> None:
        self.volume = volume
        self.velocity = velocity
        self.baselines: dict[int, list[int]] = {}
        self.previous: tuple[int, int] | None = None

    def send(
        self,
        name: str,
        description: str,
        seq: int,
        base_us: int,
        streams: Sequence[int],
        offsets: Sequence[int],
        poses: Sequence[Sequence[float]],
        velocities: Sequence[Sequence[float]] | None = None,
    ) -> Vector:
        n = len(streams)
        codes = quantise(
            np.array(poses, np.float64).reshape(n, 7),
            self.volume,
            None if velocities is None else np.array(velocities, np.float64).reshape(n, 6),
        )
        base = base_us / 1e6
        times = [base - o / 1000.0 for o in offsets]
        held = {k: np.array(v, np.int64) for k, v in self.baselines.items()}
        encoded = encode_update_codes(seq, base, list(streams), times, codes, self.volume, held)
        data, _ = relative(encoded.data, self.previous)
        decoded, after, header = update_json(data, self.volume, self.baselines, self.previous)
        vector = {
            "name": name,
            "description": description,
            "direction": "client-to-server",
            "frame": "compact-update",
            "encode": True,
            "hex": to_hex(data),
            "volume": _volume_json(self.volume),
            "velocity": self.velocity,
            "baselines_before": _baselines_json(self.baselines),
            "previous_header": _header_json(self.previous),
            "pose_frame": decoded,
            "baselines_after": _baselines_json(after),
            "previous_header_after": _header_json(header),
        }
        self.baselines, self.previous = after, header
        return vector


def _header_json(header: tuple[int, int] | None) -> dict[str, int] | None:
    return None if header is None else {"number": header[0], "base_us": header[1]}


_VELOCITIES_LATER = (
    (0.13, -0.03, 0.01, 0.5, -1.0, 0.0),
    (-0.7, 0.4, 1.0, 3.5, 0.25, -2.0),
    (0.0, 0.1, -0.05, 0.0, 0.0, 80.0),
)
#: The compact update streams of the vectors: name -> (volume, velocity variant).
_UPSTREAMS = {
    "plain": (DEFAULT_VOLUME, False),
    "flip": (DEFAULT_VOLUME, False),
    "velocity": (DEFAULT_VOLUME, True),
    "small": (_SMALL_ROOM, False),
}
#: Each update, in the order its stream sends them: (stream, name, description, seq,
#: base time us, stream ids, time offsets ms, poses, velocities).
_UPDATES: tuple[tuple[Any, ...], ...] = (
    ("plain", "update-key", "the first compact update: three key entries, absolute header",
     7, 100_000_000, [0, 1, 2], [0, 10, 20], POSES, None),
    ("plain", "update-delta-relative",
     "three delta entries, relative header; the left hand's idx changes 0 -> 1, the right"
     " hand's quaternion arrives negated (idx 3, folded positive)",
     8, 100_033_000, [0, 1, 2], [0, 0, 3], _MOVED, None),
    ("plain", "update-delta-partial",
     "one delta entry (only the head moved); the other streams are left out",
     9, 100_066_000, [0], [0], [(0.1015, 1.5987, -0.2031, 0.9186, 0.01, 0.395, -0.005)], None),
    ("plain", "update-mixed",
     "a key entry for a new stream (an object just taken, id 12) beside two deltas",
     10, 100_100_000, [0, 2, 12], [1, 0, 2],
     [POSES[0], POSES[2], (1.0, 0.9, 0.5, 0.5, 0.5, 0.5, 0.5)], None),
    ("plain", "update-empty", "an update with no entries (header only, relative)",
     11, 100_133_000, [], [], [], None),
    ("plain", "update-far-offsets",
     "large and negative time offsets and a big position jump (high Exp-Golomb orders)",
     12, 100_166_000, [0, 1, 2], [-3, 250, 900],
     [(7.9, 3.9, -7.9, 1.0, 0.0, 0.0, 0.0), POSES[1], (-7.5, -1.5, 7.5, 0.5, -0.5, 0.5, -0.5)],
     None),
    ("flip", "update-flip-key", "a key entry before a sign flip", 0, 0, [1], [0], _FLIP[:1], None),
    ("flip", "update-flip-delta",
     "a delta entry whose new idx (1) holds a negative component in the baseline:"
     " the predictor flips the sign",
     1, 33_000, [1], [0], _FLIP[1:], None),
    ("velocity", "update-velocity-key",
     "velocity variant: the first update, key entries with velocities",
     1, 5_000_000, [3, 4, 5], [0, 0, 0], POSES, VELOCITIES),
    ("velocity", "update-velocity-delta",
     "velocity variant: delta entries, velocities changed, one clamped to 64 rad/s",
     2, 5_011_111, [3, 4, 5], [0, 5, 11], _MOVED, _VELOCITIES_LATER),
    ("small", "update-small-volume-key",
     "a 4 x 2.5 x 4 m room volume (13, 13, 13 bits): key entries",
     100, 0, [0, 1, 2], [0, 10, 20], POSES, None),
    ("small", "update-small-volume-delta", "the same volume: delta entries, relative header",
     101, 50_000, [0, 1, 2], [0, 0, 0], _MOVED, None),
)  # fmt: skip


def _update_vectors() -> list[Vector]:
    """Every compact update vector, each stream's in the order it sends them."""
    streams = {name: _Upstream(*config) for name, config in _UPSTREAMS.items()}
    return [streams[step[0]].send(*step[1:]) for step in _UPDATES]


# --------------------------------------------------------------------------- compact snapshots


def _codes(poses: Sequence[Sequence[float]], volume: Volume, vel: Any = None) -> list[list[int]]:
    rows: list[list[int]] = quantise(np.array(poses, np.float64), volume, vel).tolist()
    return rows


def _snapshot_vector(
    name: str,
    description: str,
    data: bytes,
    volume: Volume,
    baselines: dict[tuple[int, int], list[int]],
    velocity: bool,
) -> Vector:
    decoder = SnapshotDecoder(volume)
    decoder.baselines = {k: list(v) for k, v in baselines.items()}
    frame = decode_relay_snapshot(data, volume, baselines)
    decoder.decode(data)
    base_us = round(frame.base_time * 1e6)
    offsets = [round((frame.base_time - t) * 1000.0) for t in frame.capture_times]
    delta = [(u, s) in baselines for u, s in zip(frame.users, frame.streams, strict=True)]
    entries = _entries_of(frame.users, frame.streams, offsets, frame.codes, delta, base_us, volume)
    return {
        "name": name,
        "description": description,
        "direction": "server-to-client",
        "frame": "compact-snapshot",
        "encode": False,
        "hex": to_hex(data),
        "volume": _volume_json(volume),
        "velocity": velocity,
        "baselines_before": _baselines_json(baselines),
        "pose_frame": {
            "kind": "snapshot",
            "number": frame.tick,
            "base_us": base_us,
            "entries": entries,
        },
        "baselines_after": _baselines_json(decoder.baselines),
    }


_OBJECT = ((1.0, 0.9, 0.5, 0.5, 0.5, 0.5, 0.5), (1.2, 0.7, 0.5, 0.5, 0.5, 0.5, 0.5))


def _snapshot_key_delta_vectors() -> list[Vector]:
    """Key, delta and mixed snapshots, whole and spliced (a subscriber's own user cut out)."""
    v = DEFAULT_VOLUME
    a, b, obj, (fa, fb) = _codes(POSES, v), _codes(_MOVED, v), _codes(_OBJECT, v), _codes(_FLIP, v)
    keys = [
        (1, 0, 99.99, a[0], None),
        (1, 1, 99.98, a[1], None),
        (1, 2, 99.98, a[2], None),
        (2, 3, 99.95, fa, None),
        (2, 5, 99.96, a[2], None),
        (65535, 9, 99.9, obj[0], None),
    ]
    group = encode_group(20, 100.0, keys, v)
    held = {(u, s): row for u, s, _, row, _ in keys}
    deltas = [
        (1, 0, 100.03, b[0], a[0]),
        (1, 1, 100.02, b[1], a[1]),
        (1, 2, 100.02, b[2], a[2]),
        (2, 3, 100.0, fb, fa),
        (2, 5, 99.99, b[0], a[2]),
        (65535, 9, 100.0, obj[1], obj[0]),
    ]
    delta_group = encode_group(21, 100.033, deltas, v)
    mixed = [(1, 0, 100.05, a[0], b[0]), (3, 0, 100.05, a[1], None), (3, 1, 100.04, a[2], None)]
    not_2 = {k: r for k, r in held.items() if k[0] != 2}
    return [
        _snapshot_vector(
            "snapshot-key", "a key snapshot: two users and a shared object (user 65535)",
            group.frame(None)[0], v, {}, False,
        ),
        _snapshot_vector(
            "snapshot-key-spliced",
            "the same group's frame for user 1, who does not get its own streams back",
            group.frame(1)[0], v, {}, False,
        ),
        _snapshot_vector(
            "snapshot-delta",
            "a delta snapshot: index changes, a sign flip, a clamped prediction, an object",
            delta_group.frame(None)[0], v, held, False,
        ),
        _snapshot_vector(
            "snapshot-delta-spliced",
            "the same group's frame for user 2 (its block cut out, user 65535 joined to user 1)",
            delta_group.frame(2)[0], v, not_2, False,
        ),
        _snapshot_vector(
            "snapshot-mixed", "a key section (a new user 3) and a delta section in one frame",
            encode_group(22, 100.066, mixed, v).frame(None)[0], v, {(1, 0): b[0]}, False,
        ),
    ]  # fmt: skip


def _snapshot_variant_vectors() -> list[Vector]:
    """Snapshots of the velocity variant and of another room volume."""
    v, s = DEFAULT_VOLUME, _SMALL_ROOM
    vel = np.array(VELOCITIES)
    av, bv = _codes(POSES, v, vel), _codes(_MOVED, v, vel[::-1])
    vkey = [(1, 0, 9.99, av[0], None), (1, 1, 9.99, av[1], None), (2, 0, 9.98, av[2], None)]
    vdelta = [(1, 0, 10.02, bv[0], av[0]), (1, 1, 10.02, bv[1], av[1]), (2, 0, 10.01, bv[2], av[2])]
    vheld = {(1, 0): av[0], (1, 1): av[1], (2, 0): av[2]}
    sa, sb = _codes(POSES, s), _codes(_MOVED, s)
    skey = [(7, 0, 1.0, sa[0], None), (7, 1, 1.0, sa[1], None)]
    sdelta = [(7, 0, 1.05, sb[0], sa[0]), (7, 1, 1.05, sb[1], sa[1])]
    return [
        _snapshot_vector(
            "snapshot-velocity-key", "velocity variant: key entries",
            encode_group(3, 10.0, vkey, v, True).frame(None)[0], v, {}, True,
        ),
        _snapshot_vector(
            "snapshot-velocity-delta", "velocity variant: delta entries",
            encode_group(4, 10.033, vdelta, v, True).frame(None)[0], v, vheld, True,
        ),
        _snapshot_vector(
            "snapshot-small-volume-key", "a 4 x 2.5 x 4 m room volume: key entries",
            encode_group(1, 1.0, skey, s).frame(None)[0], s, {}, False,
        ),
        _snapshot_vector(
            "snapshot-small-volume-delta", "the same volume: delta entries",
            encode_group(2, 1.05, sdelta, s).frame(None)[0], s,
            {(7, 0): sa[0], (7, 1): sa[1]}, False,
        ),
    ]  # fmt: skip


# --------------------------------------------------------------------------- errors

_SAME = object()


def _update_case(
    base: Vector,
    name: str,
    description: str,
    data: bytes,
    baselines: Any = _SAME,
    previous: Any = _SAME,
) -> Vector:
    """An update a relay refuses: ``data`` decoded in ``base``'s context, changed so."""
    baselines = base["baselines_before"] if baselines is _SAME else baselines
    previous = base["previous_header"] if previous is _SAME else previous
    volume = _volume_of(base["volume"])
    held = {b["stream"]: b["codes"] for b in baselines}
    prev = None if previous is None else (previous["number"], previous["base_us"])
    context = {
        "volume": base["volume"],
        "velocity": base["velocity"],
        "baselines_before": baselines,
        "previous_header": previous,
    }
    decode: Callable[[], object] = lambda: update_json(data, volume, held, prev)  # noqa: E731
    return error_vector(name, description, "compact-update", data, decode, context)


def _snapshot_case(
    base: Vector, name: str, description: str, data: bytes, baselines: Any = _SAME
) -> Vector:
    """A snapshot a client refuses: ``data`` decoded in ``base``'s context, changed so."""
    baselines = base["baselines_before"] if baselines is _SAME else baselines
    decoder = SnapshotDecoder(_volume_of(base["volume"]))
    decoder.baselines = {(b["user"], b["stream"]): b["codes"] for b in baselines}
    context = {
        "volume": base["volume"],
        "velocity": base["velocity"],
        "baselines_before": baselines,
    }
    decode: Callable[[], object] = lambda: decoder.decode(data)  # noqa: E731
    return error_vector(name, description, "compact-snapshot", data, decode, context)


def _with_code(baselines: list[dict[str, Any]], column: int, step: int) -> list[dict[str, Any]]:
    """``baselines`` with the first one's code ``column`` moved by ``step``."""
    first = dict(baselines[0])
    codes = list(first["codes"])
    codes[column] += step
    return [{**first, "codes": codes}, *baselines[1:]]


def _update_error_vectors(by_name: dict[str, Vector]) -> list[Vector]:
    """Compact updates a relay refuses: bad baselines, bad bytes."""
    delta, keyed = by_name["update-delta-relative"], by_name["update-key"]
    data, key = bytes.fromhex(delta["hex"]), bytes.fromhex(keyed["hex"])
    wrong = _with_code(delta["baselines_before"], 4, 1)
    return [
        _update_case(
            delta, "error-update-bad-crc",
            "a delta update against other baselines (the head's px differs by one): CRC mismatch",
            data, baselines=wrong,
        ),
        _update_case(
            delta, "error-update-no-baseline",
            "a delta update naming a stream the relay holds no baseline for",
            data, baselines=delta["baselines_before"][1:],
        ),
        _update_case(
            delta, "error-update-relative-first", "a relative header with no update before it",
            data, previous=None,
        ),
        _update_case(
            keyed, "error-update-truncated", "a key update missing its last byte", key[:-1]
        ),
        _update_case(
            keyed, "error-update-trailing", "a key update with one byte too many", key + b"\x00"
        ),
        _update_case(
            keyed, "error-update-version", "a version-2 flags byte on an update",
            key[:1] + bytes([key[1] & 0x0F | 0x20]) + key[2:],
        ),
        _update_case(
            keyed, "error-update-is-snapshot",
            "an update frame with the update flag clear (a snapshot where an update is expected)",
            key[:1] + bytes([key[1] & ~1]) + key[2:],
        ),
    ]  # fmt: skip


def _snapshot_error_vectors(by_name: dict[str, Vector]) -> list[Vector]:
    """Compact snapshots a client refuses: bad baselines, bad bytes."""
    delta, keyed = by_name["snapshot-delta"], by_name["snapshot-key"]
    data, key = bytes.fromhex(delta["hex"]), bytes.fromhex(keyed["hex"])
    at = _nibble_offset(key)  # one order nibble (key t_first), then the padding nibble
    return [
        _snapshot_case(
            delta, "error-snapshot-bad-crc",
            "a delta snapshot against other baselines (one pz differs by one): check mismatch",
            data, _with_code(delta["baselines_before"], 6, -1),
        ),
        _snapshot_case(
            delta, "error-snapshot-no-baseline",
            "a delta snapshot naming a stream the client holds no baseline for",
            data, delta["baselines_before"][1:],
        ),
        _snapshot_case(
            delta, "error-snapshot-truncated", "a delta snapshot missing its last byte", data[:-1]
        ),
        _snapshot_case(
            keyed, "error-snapshot-padding-nibble",
            "a key snapshot whose padding nibble is not zero",
            key[:at] + bytes([key[at] | 1]) + key[at + 1 :],
        ),
    ]  # fmt: skip


def _nibble_offset(data: bytes) -> int:
    """Where the order nibbles of a frame with no check (n_delta = 0) start."""
    pos = 2
    for _ in range(4):  # number, base time, n_key, n_delta
        while data[pos] & 0x80:
            pos += 1
        pos += 1
    return pos


def _volume_of(values: Sequence[float]) -> Volume:
    return Volume((values[0], values[1], values[2]), (values[3], values[4], values[5]))


# --------------------------------------------------------------------------- all


def build_vectors() -> list[Vector]:
    """Every golden vector, in a fixed order."""
    updates = _update_vectors()
    snapshots = _snapshot_key_delta_vectors() + _snapshot_variant_vectors()
    by_name = {v["name"]: v for v in updates + snapshots}
    vectors = (
        control_vectors()
        + raw_pose_vectors()
        + updates
        + snapshots
        + _update_error_vectors(by_name)
        + _snapshot_error_vectors(by_name)
        + msgpack_error_vectors()
    )
    names = [v["name"] for v in vectors]
    assert len(set(names)) == len(names)
    return [{"schema": SCHEMA_VERSION, **v} for v in vectors]


def _dump(value: Any, indent: str = "") -> str:
    """JSON with one key a line, but arrays of numbers (codes, poses) on one line."""
    inner = indent + " "
    if isinstance(value, dict) and value:
        items = [f"{inner}{json.dumps(k)}: {_dump(v, inner)}" for k, v in value.items()]
        text = "{\n" + ",\n".join(items) + "\n" + indent + "}"
    elif isinstance(value, list) and value and any(isinstance(v, dict | list) for v in value):
        items = [f"{inner}{_dump(v, inner)}" for v in value]
        text = "[\n" + ",\n".join(items) + "\n" + indent + "]"
    else:
        text = json.dumps(value, ensure_ascii=False)
    return text + ("\n" if not indent else "")


def write_vectors(out: Path) -> list[Path]:
    """Write every vector as ``out/NAME.json`` and ``out/index.json``; the paths written.

    Stale vector files (``*.json`` not in the set) are removed; README.md is kept.
    """
    out.mkdir(parents=True, exist_ok=True)
    vectors = build_vectors()
    written = []
    keep = {f"{v['name']}.json" for v in vectors} | {"index.json"}
    for path in out.glob("*.json"):
        if path.name not in keep:
            path.unlink()
    for vector in vectors:
        path = out / f"{vector['name']}.json"
        path.write_text(_dump(vector), encoding="utf-8")
        written.append(path)
    index = {
        "schema": SCHEMA_VERSION,
        "vectors": [
            {"name": v["name"], "frame": v["frame"], "description": v["description"]}
            for v in vectors
        ],
    }
    path = out / "index.json"
    path.write_text(_dump(index), encoding="utf-8")
    written.append(path)
    return written
