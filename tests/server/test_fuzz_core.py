"""Property: nothing a member sends makes the relay core raise or send an invalid frame.

Hypothesis drives a real :class:`server.core.RelayCore` (no sockets: the core is the
relay's every rule) with a live room: two honest members (raw and compact) that
publish and read, and fuzzing members that send generated frames of every message
type (client and server-only ones, each field swapped for arbitrary msgpack values),
valid raw and compact updates with arbitrary times and poses, byte-level mutations
of the golden frames, drops and resumes with real and forged resume tokens. After
every step:

- no exception escapes the core (``receive``, ``tick``, ``take``, ``expire``,
  ``disconnect``);
- every frame the core hands any connection decodes (a refusal is a valid
  ``error`` message), every close reason fits a close frame;
- the honest members are never closed, and their sessions see no protocol error.

``POSECAST_FUZZ_EXAMPLES`` runs more examples (the committed default keeps the suite
fast); ``scripts`` of long runs are in docs/guides/security.md.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from posecast.protocol import (
    MAX_TEXT_LENGTH,
    ClientSession,
    ErrorMessage,
    Hello,
    Join,
    LocalProtocolError,
    PoseUpdate,
    ProtocolError,
    Welcome,
    decode_message,
)
from posecast.protocol.errors import ProtocolViolation
from posecast.server.actions import Close
from posecast.server.auth import make_token
from posecast.server.core import RelayCore, ServerConfig

VECTORS = Path(__file__).resolve().parents[2] / "protocol" / "vectors"
EXAMPLES = int(os.environ.get("POSECAST_FUZZ_EXAMPLES", "60"))
SECRET = "fuzz-secret"
ROOM = "r"
STREAMS = ("head", "left", "right")
CODEC_FRAME_BYTE = 0xC1  # (msgpack's never-used byte: a compact frame, not a map)


def _vectors() -> tuple[dict[str, dict[str, Any]], list[bytes]]:
    """Field maps of every control message type, and the bytes of every golden frame."""
    maps: dict[str, dict[str, Any]] = {}
    frames: list[bytes] = []
    for path in sorted(VECTORS.glob("*.json")):
        vector = json.loads(path.read_text())
        if "hex" not in vector:
            continue
        frames.append(bytes.fromhex(vector["hex"]))
        message = vector.get("message")
        if vector.get("frame") == "msgpack" and isinstance(message, dict):
            maps.setdefault(str(message["type"]), msgpack.unpackb(frames[-1], raw=False))
    return maps, frames


MAPS, FRAMES = _vectors()

# -- strategies ------------------------------------------------------------------------------

_floats = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([1e240, -1e300, 1.7976931348623157e308, 5e-324, 0.0, -0.0, 1e9]),
)
_leaves = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(2**63), max_value=2**64 - 1),
    _floats,
    st.text(max_size=300),
    st.binary(max_size=64),
)
_values = st.recursive(
    _leaves,
    lambda inner: st.one_of(
        st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=8), inner, max_size=5)
    ),
    max_leaves=12,
)

#: Values a member of the room could mean (stream ids, object names, event kinds, times):
#: they pass the schema and reach the relay's own rules.
_plausible = st.one_of(
    st.integers(0, 12),
    st.sampled_from(["object:a", "object:b", "head", "grab", "release", "button", "lobby"]),
    st.sampled_from([ROOM, "r2", " r", "r\u202e"]),
    st.floats(-3.0, 1100.0),
    st.booleans(),
    st.none(),
    st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=7),
)
CLIENT_TYPES = ["event", "object_create", "request_ownership", "release", "set_rate", "ping",
                "renew", "join", "hello", "bye", "error"]  # fmt: skip


@st.composite
def mutated_map(draw: st.DrawFn) -> bytes:
    """A control message of any type, some fields swapped, dropped or added; mostly a
    client's type with plausible values (deeper into the relay), else anything."""
    plausible = draw(st.booleans())
    types = [t for t in CLIENT_TYPES if t in MAPS] if plausible else sorted(MAPS)
    type_ = draw(st.sampled_from(types))
    wire = dict(MAPS[type_])
    values = _plausible if plausible else _values
    for key in draw(st.lists(st.sampled_from(sorted(wire)), max_size=3)):
        choice = draw(st.integers(0, 3))
        if choice == 0 and not plausible:
            wire.pop(key, None)
        elif key != "type" or (choice == 1 and not plausible):
            wire[key] = draw(values)
    if not plausible and draw(st.booleans()):
        wire[draw(st.text(max_size=12))] = draw(_values)
    data: bytes = msgpack.packb(wire, use_bin_type=True)
    return data


@st.composite
def mutated_bytes(draw: st.DrawFn) -> bytes:
    """A golden frame with bytes flipped, cut or spliced in."""
    data = bytearray(draw(st.sampled_from(FRAMES)))
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.integers(0, 2))
        at = draw(st.integers(0, max(0, len(data) - 1)))
        if op == 0 and data:
            data[at] ^= draw(st.integers(1, 255))
        elif op == 1:
            del data[at:]
        else:
            data[at:at] = draw(st.binary(min_size=1, max_size=8))
    return bytes(data)


_times = st.one_of(
    st.floats(min_value=-5.0, max_value=5.0),
    st.floats(allow_nan=False, allow_infinity=False),
    st.sampled_from([1e240, -1e240, 1e300]),
)
_coords = st.one_of(st.floats(min_value=-3.0, max_value=3.0), st.floats(width=32), st.just(1e30))


@dataclass(frozen=True)
class Update:
    """A well-formed update through the member's own session (raw or compact)."""

    offset: float  # capture time minus now
    base: float  # base_time the frame says (raw updates only)
    position: tuple[float, float, float]


_updates = st.builds(Update, _times, _times, st.tuples(_coords, _coords, _coords))


@dataclass(frozen=True)
class Step:
    who: int  # which fuzzer (0..2)
    what: str
    frame: bytes | Update | None
    dt: float


_steps = st.one_of(
    st.builds(Step, st.integers(0, 2), st.just("frame"), mutated_map(), st.floats(0, 0.2)),
    st.builds(Step, st.integers(0, 2), st.just("frame"), mutated_bytes(), st.floats(0, 0.2)),
    st.builds(Step, st.integers(0, 2), st.just("update"), _updates, st.floats(0, 0.2)),
    st.builds(Step, st.integers(0, 2), st.just("drop"), st.none(), st.floats(0, 3.0)),
    st.builds(Step, st.integers(0, 2), st.just("resume"), st.none(), st.floats(0, 0.5)),
    st.builds(Step, st.integers(0, 2), st.just("steal"), st.none(), st.floats(0, 0.5)),
)

# -- members ---------------------------------------------------------------------------------


@dataclass
class Member:
    """One connection of the test: its session, what it read, its resume token."""

    core: RelayCore
    conn: int
    codec: str
    secret: str | None
    session: ClientSession = field(default_factory=ClientSession)
    resume: str | None = None
    closed: Close | None = None
    events: list[object] = field(default_factory=list)

    def read(self, now: float) -> list[object]:
        """What the core has for this connection, through its session."""
        frames, _ = self.core.take(self.conn, now)
        got: list[object] = []
        for data in frames:
            got.extend(self.session.receive_data(data))
        self.events.extend(got)
        return got

    def send_bytes(self, data: bytes, now: float, check: Callable[[list[object]], None]) -> None:
        check(self.core.receive(self.conn, data, now, wall=now))

    def hello_join(self, now: float, check: Callable[[list[object]], None], user: str) -> None:
        resume = self.resume
        self.send_bytes(self.session.send(Hello(agent=user, resumable=True, resume=resume)), now,
                        check)  # fmt: skip
        token = None if self.secret is None else make_token(self.secret, ROOM, user, 600, now)
        join = Join(room=ROOM, streams=STREAMS, rate=20.0, token=token, codec=self.codec)
        self.read(now)
        with_session(lambda: self.send_bytes(self.session.send(join), now, check))
        self.read(now)


def with_session(job: Callable[[], None]) -> None:
    """Run ``job``; a message the test's own session refuses to send is not sent."""
    with contextlib.suppress(LocalProtocolError, ProtocolViolation):
        job()


class Harness:
    """A core with a live room: honest members that must never notice the fuzzers."""

    def __init__(self, secret: str | None) -> None:
        cfg = ServerConfig(secret=secret, resume_window=2.0, join_timeout=1.0)
        self.core = RelayCore(cfg)
        self.secret = secret
        self.now = 1000.0
        self.honest = [self._member("raw", "honest-raw"), self._member("compact", "honest-c")]
        self.fuzzers = [
            self._member(codec, f"fuzzer{i}") for i, codec in enumerate(("raw", "compact", "raw"))
        ]
        self.stolen: list[str] = []

    def _member(self, codec: str, user: str) -> Member:
        m = Member(self.core, self.core.connect(self.now, address="10.0.0.1"), codec, self.secret)
        self.check(self.core.pending())
        m.hello_join(self.now, self.check, user)
        return m

    def check(self, actions: list[object]) -> None:
        """Every close is well formed; no honest member is closed."""
        for action in actions:
            if isinstance(action, Close):
                assert 1000 <= action.code <= 4999 and action.code not in (1005, 1006, 1015)
                assert len(action.reason.encode()) <= 123
                for m in self.honest:
                    assert action.conn != m.conn, f"honest member closed: {action}"
                for m in self.fuzzers:
                    if m.conn == action.conn and m.closed is None:
                        m.closed = action

    def read_all(self) -> None:
        for m in self.honest:
            for event in m.read(self.now):
                assert not isinstance(event, ProtocolError), f"honest member got {event}"
                if isinstance(event, ErrorMessage):
                    raise AssertionError(f"honest member refused: {event}")
        for m in self.fuzzers:
            frames, _ = self.core.take(m.conn, self.now)
            for data in frames:
                if data[:1] == bytes([CODEC_FRAME_BYTE]):
                    continue  # a compact snapshot (its decoder is the session's)
                message = decode_message(data)  # raises on an invalid frame
                if isinstance(message, ErrorMessage):
                    assert len(message.message) <= MAX_TEXT_LENGTH
                if isinstance(message, Welcome) and message.resume:
                    m.resume = message.resume
                    self.stolen.append(message.resume)

    def publish_honest(self) -> None:
        for m in self.honest:
            if m.session.streams:
                ids = list(m.session.streams.values())
                pose = np.array([[0.0, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0]] * len(ids))
                update = PoseUpdate.from_arrays(1, ids, np.full(len(ids), self.now), pose)
                self.check(self.core.receive(m.conn, m.session.send(update), self.now, self.now))

    def step(self, step: Step) -> None:
        self.now += step.dt
        m = self.fuzzers[step.who]
        if m.closed is not None:  # closed: it comes back, as a fuzzer does
            self.check(self.core.disconnect(m.conn, self.now))
            self._reconnect(step.who, m, m.resume)
            m = self.fuzzers[step.who]
        if step.what == "frame":
            assert isinstance(step.frame, bytes)
            self.check(self.core.receive(m.conn, step.frame, self.now, self.now))
        elif step.what == "update":
            assert isinstance(step.frame, Update)
            self._update(m, step.frame)
        elif step.what == "drop":
            self.check(self.core.disconnect(m.conn, self.now))
            self._reconnect(step.who, m, m.resume)
        elif step.what == "steal" and self.stolen:
            # Another member's resume token (a hijack): the owner must not notice.
            self.check(self.core.disconnect(m.conn, self.now))
            self._reconnect(step.who, m, self.stolen[step.who % len(self.stolen)])
        elif step.what == "resume":
            self.check(self.core.disconnect(m.conn, self.now, said_bye=True))
            self._reconnect(step.who, m, None)
        self.check(self.core.expire(self.now))
        self.publish_honest()
        while (due := self.core.next_deadline()) is not None and due <= self.now:
            self.check(self.core.tick(self.now))
        self.read_all()

    def _update(self, m: Member, u: Update) -> None:
        ids = list(m.session.streams.values())
        if not ids:
            return
        pose = np.array([[*u.position, 1.0, 0.0, 0.0, 0.0]] * len(ids))
        times = np.full(len(ids), self.now + u.offset)
        try:
            update = PoseUpdate.from_arrays(7, ids, times, pose)
            data = m.session.send(update)
        except (LocalProtocolError, ProtocolViolation, ValueError, OverflowError):
            return  # the test's own encoder refuses it: nothing to send
        self.check(self.core.receive(m.conn, data, self.now, self.now))

    def _reconnect(self, who: int, old: Member, resume: str | None) -> None:
        m = Member(self.core, self.core.connect(self.now, address="10.0.0.2"), old.codec,
                   self.secret, resume=resume)  # fmt: skip
        self.check(self.core.pending())
        self.fuzzers[who] = m
        m.hello_join(self.now, self.check, f"fuzzer{who}")


@settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=os.environ.get("POSECAST_FUZZ_EXAMPLES") is None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(secret=st.sampled_from([None, SECRET]), steps=st.lists(_steps, min_size=1, max_size=25))
def test_nothing_a_member_sends_makes_the_relay_raise(
    secret: str | None, steps: list[Step]
) -> None:
    """Generated and mutated frames of every type, drops and hijacks: no exception
    escapes, every refusal is a valid message, the honest members never notice."""
    harness = Harness(secret)
    for step in steps:
        harness.step(step)


def test_huge_capture_time_is_refused_as_bad_pose() -> None:
    """An update whose time is a huge finite float gets bad-pose, not a relay error."""
    harness = Harness(None)
    m = harness.fuzzers[0]
    harness.step(Step(0, "update", Update(0.0, 0.0, (0.0, 1.0, 0.0)), 0.0))
    ids = list(m.session.streams.values())
    pose = np.array([[0.0, 1.6, 0.0, 1.0, 0.0, 0.0, 0.0]] * len(ids))
    update = PoseUpdate.from_arrays(8, ids, np.full(len(ids), 1e300), pose)
    harness.check(harness.core.receive(m.conn, m.session.send(update), harness.now))
    errors = [e for e in m.read(harness.now) if isinstance(e, ErrorMessage)]
    assert [e.code for e in errors] == ["bad-pose"] and m.closed is None
    assert len(errors[0].message) <= MAX_TEXT_LENGTH
