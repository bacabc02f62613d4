"""Golden vectors of msgpack frames: control messages, raw pose frames, msgpack errors.

Part of the golden vectors (``protocol.golden_vectors`` builds and writes them all):
the JSON helpers shared by every vector, and the vectors whose frame is a msgpack map.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import Any

import msgpack
import numpy as np

from posecast.protocol.errors import ErrorCode, ProtocolViolation
from posecast.protocol.events import Message
from posecast.protocol.messages import (
    Bye,
    ErrorMessage,
    Hello,
    Join,
    Joined,
    PeerJoined,
    PeerLeft,
    PeerResumed,
    PeerStalled,
    Ping,
    Pong,
    RateNotice,
    Renew,
    SetRate,
    UserEvent,
    Welcome,
)
from posecast.protocol.objects import (
    ObjectCreate,
    ObjectInfo,
    ObjectRemoved,
    Owner,
    Release,
    RequestOwnership,
)
from posecast.protocol.poses import PoseUpdate, Snapshot
from posecast.protocol.wire import decode_message, encode_message

__all__ = [
    "POSES",
    "VELOCITIES",
    "Vector",
    "control_vectors",
    "error_json",
    "error_vector",
    "floats",
    "frame_json",
    "message_json",
    "message_vector",
    "msgpack_error_vectors",
    "raw_pose_vectors",
    "raw_vector",
    "to_hex",
]

Vector = dict[str, Any]

#: Head and hands of a standing user (metres, w-first quaternions) and their
#: velocities: fixed decimals, the same on every machine.
POSES = (
    (0.1, 1.6, -0.2, 0.9238795, 0.0, 0.3826834, 0.0),
    (-0.25, 1.2, -0.4, 0.7071068, 0.7071068, 0.0, 0.0),
    (0.25, 1.2, -0.4, 0.0, 0.0, 0.0, 1.0),
)
VELOCITIES = (
    (0.12, -0.03, 0.0, 0.5, -1.25, 0.0),
    (-0.8, 0.4, 1.1, 3.0, 0.25, -2.0),
    (0.0, 0.0, -0.05, 0.0, 0.0, 7.5),
)


def to_hex(data: bytes) -> str:
    return data.hex()


def _plain(value: Any) -> Any:
    """A decoded msgpack value as JSON: bin as {"bin": hex}, tuples as lists."""
    if isinstance(value, bytes):
        return {"bin": value.hex()}
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def floats(values: Any) -> list[float]:
    return [float(x) for x in np.asarray(values, np.float64).reshape(-1)]


def message_json(data: bytes) -> dict[str, Any]:
    """The msgpack map of a frame, as JSON (``bin`` values as ``{"bin": hex}``)."""
    wire = msgpack.unpackb(data, raw=False)
    out: dict[str, Any] = _plain(wire)
    return out


def frame_json(frame: PoseUpdate | Snapshot) -> dict[str, Any]:
    """A raw pose frame's records as JSON entries (float32 values widened exactly)."""
    entries = []
    times = frame.capture_times
    velocities = frame.velocities
    for i, record in enumerate(frame.entries):
        entry: dict[str, Any] = {}
        if isinstance(frame, Snapshot):
            entry["user"] = int(record["user"])
        entry["stream"] = int(record["stream"])
        entry["dt"] = float(record["dt"])
        entry["capture_time"] = float(times[i])
        entry["pose"] = floats(record["pose"])
        entry["velocity"] = None if velocities is None else floats(velocities[i])
        entries.append(entry)
    if isinstance(frame, Snapshot):
        head = {"kind": "snapshot", "number": frame.tick, "time": frame.send_time}
    else:
        head = {"kind": "update", "number": frame.seq, "time": frame.base_time}
    return {**head, "entries": entries}


def error_json(exc: ProtocolViolation) -> dict[str, Any]:
    return {"code": str(exc.code), "fatal": exc.fatal, "close_code": exc.close_code}


def message_vector(name: str, description: str, message: Message, direction: str) -> Vector:
    data = encode_message(message)
    decode_message(data)  # every vector is a valid frame
    return {
        "name": name,
        "description": description,
        "direction": direction,
        "frame": "msgpack",
        "encode": direction != "server-to-client",
        "hex": to_hex(data),
        "message": message_json(data),
    }


def raw_vector(name: str, description: str, frame: PoseUpdate | Snapshot) -> Vector:
    data = encode_message(frame)
    decoded = decode_message(data)
    assert isinstance(decoded, PoseUpdate | Snapshot)
    client = isinstance(frame, PoseUpdate)
    return {
        "name": name,
        "description": description,
        "direction": "client-to-server" if client else "server-to-client",
        "frame": "msgpack",
        "encode": client,
        "hex": to_hex(data),
        "message": message_json(data),
        "pose_frame": frame_json(decoded),
    }


def error_vector(
    name: str,
    description: str,
    frame: str,
    data: bytes,
    decode: Callable[[], object],
    context: dict[str, Any],
) -> Vector:
    try:
        decode()
    except ProtocolViolation as exc:
        error = error_json(exc)
    else:  # pragma: no cover - a vector generator bug
        raise AssertionError(f"{name}: the frame decodes")
    direction = "server-to-client" if frame == "compact-snapshot" else "client-to-server"
    return {
        "name": name,
        "description": description,
        "direction": direction,
        "frame": frame,
        "encode": False,
        "hex": to_hex(data),
        **context,
        "error": error,
    }


_C2S, _S2C, _BOTH = "client-to-server", "server-to-client", "either"
_POSE = (0.5, 1.0, -0.5, 1.0, 0.0, 0.0, 0.0)
_SMALL_ROOM_WIRE = (-2.0, 0.0, -2.0, 2.0, 2.5, 2.0)

#: (name, description, message, direction) of every control-message vector.
_CONTROL_CASES: list[tuple[str, str, Message, str]] = [
    ("hello", "hello with the defaults but agent", Hello(agent="my-app/1.0"), _C2S),
    (
        "hello-resume",
        "a resumable client resuming a dropped connection",
        Hello(agent="my-app/1.0", resumable=True, resume="Xb3kq0r-1yZAVtE5oWm2pQ8n"),
        _C2S,
    ),
    ("welcome", "welcome of a relay with default limits and volume", Welcome(3, 8312.25), _S2C),
    (
        "welcome-resumed",
        "welcome that honoured a resume token, other volume and limits",
        Welcome(
            user=3,
            server_time=8312.25,
            min_rate=10.0,
            max_rate=60.0,
            max_streams=8,
            volume=_SMALL_ROOM_WIRE,
            resume="N3w-t0ken_AbCdEfGhIjKlMn",
            resumed=True,
        ),
        _S2C,
    ),
    (
        "join",
        "a raw join: the optional fields at their defaults (token and label nil)",
        Join(room="lobby", streams=("head", "left", "right"), rate=30.0),
        _C2S,
    ),
    (
        "join-compact",
        "a compact join with every option",
        Join(
            room="lobby",
            streams=("head", "left", "right", "object:drill"),
            rate=20.0,
            token="v1.eyJyb29tIjoibG9iYnkifQ.c2ln",
            label="beat-saber-01",
            sends_velocities=True,
            wants_velocities=True,
            codec="compact",
            echo=True,
            spectator=False,
        ),
        _C2S,
    ),
    (
        "joined",
        "joined with the room's shared objects",
        Joined(
            room="lobby",
            streams={"head": 6, "left": 7, "right": 8},
            rate=30.0,
            objects={"object:drill": 2},
        ),
        _S2C,
    ),
    (
        "peer-joined",
        "another member, with a label and velocities",
        PeerJoined(user=2, streams={"head": 0, "left": 1}, label="walk", velocities=True),
        _S2C,
    ),
    ("peer-left", "a member left", PeerLeft(user=2, reason="gone"), _S2C),
    ("peer-stalled", "a member's connection dropped", PeerStalled(user=2), _S2C),
    ("peer-resumed", "a stalled member is back", PeerResumed(user=2), _S2C),
    ("ping", "a clock-sync probe", Ping(seq=1, time=12.5), _BOTH),
    (
        "pong",
        "the relay's answer (recv_time = send_time)",
        Pong(seq=1, ping_time=12.5, recv_time=8312.75, send_time=8312.75),
        _BOTH,
    ),
    ("set-rate", "change the snapshot rate", SetRate(rate=15.0), _C2S),
    ("rate", "the rate the relay chose for an auto-rate client", RateNotice(rate=12.0), _S2C),
    ("renew", "a fresh access token", Renew(token="v1.eyJyb29tIjoibG9iYnkifQ.c2ln"), _C2S),
    (
        "event-client",
        "an event as a client sends it (user nil)",
        UserEvent(kind="grab", stream=7, time=8313.0, payload={"object": "object:drill"}),
        _C2S,
    ),
    (
        "event-relayed",
        "the same event as the relay relays it (user set), nested payload",
        UserEvent(
            kind="button",
            stream=7,
            user=4,
            time=8313.0,
            payload={"button": "trigger", "value": 0.75, "path": [1, 2, {"deep": None}]},
        ),
        _S2C,
    ),
    (
        "error-refused-join",
        "a non-fatal refusal of a join",
        ErrorMessage.from_code(
            ErrorCode.BAD_RATE, "rate 50 hz outside [5, 30]", in_reply_to="join"
        ),
        _S2C,
    ),
    (
        "error-fatal",
        "a fatal error (the close follows)",
        ErrorMessage.from_code(
            ErrorCode.BAD_BASELINE, "baselines differ from the encoder's", in_reply_to="update"
        ),
        _BOTH,
    ),
    ("bye", "leaving", Bye(reason="done"), _BOTH),
    (
        "object-create",
        "create a shared object, held at once, with its capture time",
        ObjectCreate(
            name="object:drill", pose=_POSE, keep=False, steal=True, hold=True, time=8313.0
        ),
        _C2S,
    ),
    (
        "request-ownership",
        "take an object from its owner and lock it",
        RequestOwnership(stream=2, steal=True, lock=True),
        _C2S,
    ),
    (
        "release-thrown",
        "release an object with a throw",
        Release(stream=2, velocity=(1.5, 2.0, -0.25), angular=(0.0, 3.0, 0.0)),
        _C2S,
    ),
    (
        "object",
        "an object of the room, owned and locked",
        ObjectInfo(
            name="object:drill",
            stream=2,
            pose=_POSE,
            time=8313.0,
            creator=4,
            owner=4,
            steal=True,
            locked=True,
        ),
        _S2C,
    ),
    (
        "owner-throw",
        "an object was thrown",
        Owner(
            stream=2,
            owner=None,
            previous=4,
            reason="throw",
            time=8314.5,
            velocity=(1.5, 2.0, -0.25),
            angular=(0.0, 3.0, 0.0),
        ),
        _S2C,
    ),
    (
        "object-removed",
        "an object is gone",
        ObjectRemoved(stream=2, reason="creator left"),
        _S2C,
    ),
]


def control_vectors() -> list[Vector]:
    """A vector of each control message, in both directions where it travels both."""
    return [message_vector(f"msg-{n}", d, m, dirn) for n, d, m, dirn in _CONTROL_CASES]


def raw_pose_vectors() -> list[Vector]:
    """Raw updates and snapshots, plain and velocity variant, and an empty snapshot."""
    poses = np.array(POSES)
    velocities = np.array(VELOCITIES)
    times = [100.0, 99.99, 99.98]
    update = PoseUpdate.from_arrays(41, [6, 7, 8], times, poses)
    update_v = PoseUpdate.from_arrays(42, [6, 7, 8], times, poses, velocities=velocities)
    snap = Snapshot.from_arrays(9, 100.05, [4, 4, 65535], [6, 7, 2], times, poses)
    snap_v = Snapshot.from_arrays(
        10, 100.05, [4, 4, 65535], [6, 7, 2], times, poses, velocities=velocities
    )
    empty = Snapshot.from_arrays(11, 100.1, [], [], [], np.zeros((0, 7)))
    return [
        raw_vector("raw-update", "a raw update of three poses", update),
        raw_vector("raw-update-velocity", "a raw update, velocity variant", update_v),
        raw_vector("raw-snapshot", "a raw snapshot with an object stream (user 65535)", snap),
        raw_vector("raw-snapshot-velocity", "a raw snapshot, velocity variant", snap_v),
        raw_vector("raw-snapshot-empty", "a raw snapshot with no records", empty),
    ]


def msgpack_error_vectors() -> list[Vector]:
    """Msgpack frames a receiver refuses, one per kind of error."""
    bad: list[tuple[str, str, bytes]] = [
        (
            "error-not-msgpack",
            "a frame that is not msgpack (0xc1 is never used by msgpack)",
            b"\xc1",
        ),
        ("error-not-a-map", "a msgpack array, not a map", msgpack.packb([1, 2])),
        ("error-unknown-type", "a type this version lacks", msgpack.packb({"type": "teleport"})),
        (
            "error-missing-field",
            "a join without its rate",
            msgpack.packb({"type": "join", "room": "lobby", "streams": ["head"]}),
        ),
        (
            "error-unknown-field",
            "a hello with a field this version lacks",
            msgpack.packb({"type": "hello", "version": 1, "agent": "", "color": "red"}),
        ),
        (
            "error-float-for-int",
            "a ping whose seq is a float",
            msgpack.packb({"type": "ping", "seq": 1.0, "time": 0.5}),
        ),
        (
            "error-version-mismatch",
            "a hello of protocol version 2, with fields version 1 lacks",
            msgpack.packb({"type": "hello", "version": 2, "agent": "", "caps": ["x"]}),
        ),
        (
            "error-raw-records",
            "a raw update whose records are not whole 34-byte records",
            msgpack.packb({"type": "update", "seq": 1, "time": 0.0, "poses": bytes(35)}),
        ),
    ]
    return [
        error_vector(name, description, "msgpack", data, partial(decode_message, data), {})
        for name, description, data in bad
    ]
