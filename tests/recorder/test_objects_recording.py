"""Shared objects in recordings: the records a real relay writes, info, export, offline replay.

One session (``objkit``: two real clients on a real recording relay on
loopback hand a drill over by throw, catch, release, request, steal and a
locked request, and leave) is recorded once; every test reads that file and
compares it with what the clients sent and what the relay told them.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from objkit import CUP, DRILL, SKEW_B, Session, record_handover_session
from typer.testing import CliRunner

from posecast.cli import app
from posecast.protocol import Owner
from posecast.recorder import PoseRecord, SessionReader, info, read_records, recover
from posecast.recorder.analyze import analyze
from posecast.recorder.export import export, read_session
from posecast.recorder.format import EVENTS_TOPIC, POSES_TOPIC
from posecast.recorder.objects import MIN_STEP, ROOM_USER, ObjectTrack, split_objects
from posecast.recorder.reader import StreamData, UserInfo
from posecast.recorder.replay import replay_offline

GRAVITY = 9.81
#: float16 velocities (recorded flight keyframes): 11 significant bits, |v| < 8 m/s.
F16_ABS = 8.0 * 2.0**-11


OWNER_KEYS = ("previous", "reason", "locked", "velocity", "angular")
#: The scene's changes of owner, in order (objkit's docstring).
SCRIPT = ["create", "throw", "catch", "release", "request", "steal", "throw", "request"]
SCRIPT += ["owner-left"]


def _list(v: tuple[float, ...] | None) -> list[float] | None:
    return None if v is None else list(v)


def _vectors(o: Owner) -> tuple[list[float] | None, list[float] | None]:
    return _list(o.velocity), _list(o.angular)


def _text(user: int | None) -> str:
    return "" if user is None else str(user)


@pytest.fixture(scope="module")
def session(tmp_path_factory: pytest.TempPathFactory) -> Session:
    return record_handover_session(tmp_path_factory.mktemp("objects"))


def _events(path: Path, kind: str) -> list[dict]:  # type: ignore[type-arg]
    recs = read_records(path, topics=(EVENTS_TOPIC,))
    return [r.data for r in recs if r.data.get("kind") == kind]


def _drill(session: Session) -> ObjectTrack:
    (track,) = [t for t in read_session(session.path).objects if t.name == "object:drill"]
    return track


def _steals_from(session: Session, user: int) -> int:
    return sum(o.reason == "steal" and o.previous == user for o in session.owners)


def test_events_hold_creates_owner_changes_and_removal_as_the_relay_announced(
    session: Session,
) -> None:
    """object_create, owner and object_remove records match the relay's messages."""
    a, b = session.a, session.b
    creates = [
        (d["payload"]["object"], d["stream"], d["user"], d["payload"]["keep"], d["payload"]["pose"])
        for d in _events(session.path, "object_create")
    ]
    assert creates == [
        ("object:drill", session.drill, a.user, True, list(DRILL)),
        ("object:cup", session.cup, b.user, False, list(CUP)),
    ]
    owners = [
        (d["time"], d["stream"], d["user"], *(d["payload"][k] for k in OWNER_KEYS))
        for d in _events(session.path, "owner")
    ]
    told = [
        (o.time, o.stream, o.owner, o.previous, o.reason, o.locked, *_vectors(o))
        for o in session.owners
    ]
    assert owners == told
    reasons = [o[4] for o in owners]
    assert reasons == SCRIPT
    removed = [
        (d["stream"], d["payload"]["reason"]) for d in _events(session.path, "object_remove")
    ]
    assert removed == [(session.cup, "creator-left")]


def test_owner_updates_carry_the_object_with_the_captures_the_owner_sent(session: Session) -> None:
    """An owner's object keyframes are recorded in its own updates, bit for bit, unshifted."""
    poses = [r for r in read_records(session.path, topics=(POSES_TOPIC,))]
    for actor in (session.a, session.b):
        recorded = [
            (float(r.capture_times[k]), r.poses[k])
            for r in poses
            if isinstance(r, PoseRecord) and r.user == actor.user
            for k in range(len(r.streams))
            if int(r.streams[k]) == session.drill
        ]
        sent = {cap: np.asarray(p, dtype=np.float32) for cap, _sid, p in actor.sent}
        for cap, pose in recorded:
            assert np.array_equal(pose.view(np.uint32), sent[cap].view(np.uint32))
        # A steal can strip the update that was on its way; nothing else is lost.
        assert len(sent) - _steals_from(session, actor.user) <= len(recorded) <= len(sent)
        assert recorded


def test_flight_keyframes_are_room_user_updates_with_ballistic_velocities(session: Session) -> None:
    """The relay's flight keyframes: user 65535, the drill alone, stamped at its tick,
    velocities that fall at g and integrate to the positions, between a throw and the next
    change."""
    records = read_records(session.path, topics=(POSES_TOPIC,))
    flights = [r for r in records if isinstance(r, PoseRecord) and r.user == ROOM_USER]
    assert flights
    throws = [o for o in session.owners if o.reason == "throw"]
    for r in flights:
        assert r.streams.tolist() == [session.drill] and r.velocities is not None
        assert float(r.capture_times[0]) == r.arrival
        after = [o for o in session.owners if o.time <= r.arrival]
        assert after[-1].reason == "throw"
    ends = [next((o.time for o in session.owners if o.time > t.time), np.inf) for t in throws]
    segments = [
        [r for r in flights if t.time <= r.arrival < end]
        for t, end in zip(throws, ends, strict=True)
    ]
    assert [len(s) > 2 for s in segments] == [True] * len(throws)
    for throw, seg in zip(throws, segments, strict=True):
        assert throw.velocity is not None
        t = np.array([r.arrival for r in seg])
        y = np.array([float(r.poses[0][1]) for r in seg])
        v = np.array([r.velocities[0] for r in seg], dtype=np.float64)  # type: ignore[index]
        flying = np.flatnonzero(np.any(v != 0, axis=1))  # landed: velocity 0
        v, t, y = v[flying], t[flying], y[flying]
        assert np.allclose(v[:, 0], throw.velocity[0], atol=F16_ABS)
        dt = np.diff(t)
        assert np.allclose(np.diff(v[:, 1]), -GRAVITY * dt, atol=2 * F16_ABS)
        # Velocity linear in time: the trapezoid rule is exact for the height.
        assert np.allclose(np.diff(y), 0.5 * (v[1:, 1] + v[:-1, 1]) * dt, atol=F16_ABS * dt + 1e-6)


def test_room_times_are_the_times_the_relay_relayed(session: Session) -> None:
    """The track's times are the ones the clients saw in snapshots, b's shifted past the last."""
    track = _drill(session)
    seen = np.array(sorted(session.a.drill_times | session.b.drill_times))
    i = np.clip(np.searchsorted(track.times, seen), 1, len(track) - 1)
    nearest = np.minimum(np.abs(track.times[i] - seen), np.abs(track.times[i - 1] - seen))
    assert nearest.max() < 1e-6  # snapshot times: float32 offsets from a float64 base
    assert np.all(np.diff(track.times) > 0)
    # b's clock runs behind by more than a tick: after each grant its keyframes are
    # shifted to follow the newest one, which came before b's update arrived.
    shift = track.times - track.captures
    mine = track.publisher == session.b.user
    assert np.all(shift[~mine] == 0.0)
    late = track.arrival[mine] - track.captures[mine]
    assert np.all((shift[mine] > 0.0) & (shift[mine] <= late.max() + MIN_STEP))
    assert late.min() >= -SKEW_B  # the skew is there: captures behind arrivals
    shifted_seen = np.isin(np.round(track.times[mine], 5), np.round(seen, 5))
    assert shifted_seen.any()


def test_info_lists_objects_changes_holders_and_flight_keyframes(session: Session) -> None:
    """info() and `posecast info` list each object with its changes, holders and flights."""
    flights = sum(
        isinstance(r, PoseRecord) and r.user == ROOM_USER
        for r in read_records(session.path, topics=(POSES_TOPIC,))
    )
    data = info(session.path)
    drill, cup = data["objects"]
    assert (drill["name"], drill["stream"], drill["creator"], drill["keep"]) == (
        "object:drill",
        session.drill,
        session.a.user,
        True,
    )
    assert drill["owner_changes"] == len(session.owners)
    assert drill["holders"] == [session.a.user, session.b.user]
    assert drill["flight_keyframes"] == flights
    assert drill["reasons"]["throw"] == 2 and drill["reasons"]["steal"] == 1
    assert (cup["name"], cup["keep"], cup["owner_changes"], cup["removed_reason"]) == (
        "object:cup",
        False,
        0,
        "creator-left",
    )
    # The users keep their own streams; no user 65535, no object stream among them.
    assert {s["user"] for s in data["streams"]} == {session.a.user, session.b.user}
    assert not {s["stream"] for s in data["streams"]} & {session.drill, session.cup}
    assert ROOM_USER not in {u["user"] for u in data["users"]}
    res = CliRunner().invoke(app, ["info", str(session.path)])
    assert res.exit_code == 0, res.output
    assert "objects: 2" in res.output and "object:drill creator" in res.output
    assert "in flight" in res.output and "held by" in res.output


def test_export_carries_object_streams_and_ownership_changes(
    session: Session, tmp_path: Path
) -> None:
    """CSV, NPZ and Foxglove exports: the drill as a stream named by it, and the changes."""
    track = _drill(session)
    out = export(session.path, "csv", tmp_path / "csv")
    with (out / "object_drill.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(track)
    assert [int(r["publisher"]) for r in rows] == track.publisher.tolist()
    assert np.allclose([float(r["time"]) for r in rows], track.times, rtol=0, atol=1e-9)
    assert np.allclose([float(r["py"]) for r in rows], track.poses[:, 1], rtol=0, atol=1e-7)
    with (out / "ownership.csv").open() as f:
        changes = list(csv.DictReader(f))
    assert [(r["owner"], r["previous"], r["reason"]) for r in changes] == [
        (_text(o.owner), _text(o.previous), o.reason) for o in session.owners
    ]
    throw = next(r for r in changes if r["reason"] == "throw")
    assert float(throw["vy"]) == 2.5 and float(throw["wy"]) == 3.0
    index = json.loads((out / "streams.json").read_text())
    assert {e["file"] for e in index} >= {"object_drill.csv", "object_cup.csv"}
    assert not any(e["user"] == ROOM_USER and e["name"] is None for e in index)

    npz = np.load(export(session.path, "npz", tmp_path / "x.npz"))
    assert np.array_equal(npz["object.drill.poses"].view(np.uint32), track.poses.view(np.uint32))
    assert np.array_equal(npz["object.drill.publisher"], track.publisher)
    assert [c["reason"] for c in json.loads(str(npz["ownership"]))] == [
        o.reason for o in session.owners
    ]

    fox = export(session.path, "foxglove", tmp_path / "fox.mcap")
    with fox.open("rb") as f:
        msgs = [(ch.topic, m.data) for _s, ch, m in make_reader(f).iter_messages()]
    topics = {t for t, _d in msgs}
    assert {"/objects/drill", "/objects/ownership"} <= topics
    frames = [json.loads(d) for t, d in msgs if t == "/objects/drill"]
    assert len(frames) == len(track) and frames[0]["child_frame_id"] == "objects/drill"
    assert [json.loads(d)["reason"] for t, d in msgs if t == "/objects/ownership"] == [
        o.reason for o in session.owners
    ]


def test_offline_replay_reconstructs_the_object_with_its_ownership_changes(
    session: Session,
) -> None:
    """The drill is one stream of class ``objects``; the report lists its changes."""
    report = replay_offline(session.path, ["soa", "dq-slerp"], 10.0, None)
    drill = next(o for o in report["objects"] if o["name"] == "object:drill")
    track = _drill(session)
    assert drill["keyframes"] == len(track)
    assert drill["flight_keyframes"] == track.flight_keyframes
    assert [(c["owner"], c["previous"], c["reason"]) for c in drill["changes"]] == [
        (o.owner, o.previous, o.reason) for o in session.owners
    ]
    for method in ("soa", "dq-slerp"):
        assert report["qoe"][method]["objects"]["tip_p95_mm"] >= 0.0
    # A window: only the changes inside it.
    late = replay_offline(session.path, ["soa"], 10.0, None, start=1.5)
    kept = next(o for o in late["objects"] if o["name"] == "object:drill")["changes"]
    lo = min(float(s.arrival.min()) for s in read_session(session.path).streams) + 1.5
    assert [c["time"] for c in kept] == [o.time for o in session.owners if o.time >= lo]
    assert 0 < len(kept) < len(session.owners)


def test_recovery_linear_reading_and_analyze_accept_object_records(
    session: Session, tmp_path: Path
) -> None:
    """A .part of the session recovers with its objects; read linearly it gives the same
    tracks; analyze scores the drill as an object and takes no user 65535."""
    part = tmp_path / "copy.mcap.part"
    shutil.copy(session.path, part)
    recovered = tmp_path / "copy.mcap"
    recover(part, recovered)
    want = info(session.path)["objects"]
    assert info(recovered)["objects"] == want
    with SessionReader(session.path, linear=True) as r:
        assert r.info()["objects"] == want
    slow = read_session(part).objects  # the SessionReader path of read_session
    fast = read_session(session.path).objects
    for x, y in zip(slow, fast, strict=True):
        assert x.name == y.name and np.array_equal(x.times, y.times)
        assert np.array_equal(x.poses.view(np.uint32), y.poses.view(np.uint32))
    result = analyze(session.path, [2], ["soa"])
    assert "objects" in json.dumps(result)


def _piece(user: int, stream: int, rows: list[tuple[float, float, float]]) -> StreamData:
    """Keyframes (arrival, capture, height) of one (user, stream), as a reader gives them."""
    poses = np.array([[0.1, y, 0, 1, 0, 0, 0] for _a, _c, y in rows], dtype=np.float32)
    return StreamData(
        user=user,
        stream=stream,
        name=None,
        user_name=None,
        times=np.array([c for _a, c, _y in rows]),
        arrival=np.array([a for a, _c, _y in rows]),
        poses=poses,
    )


def test_tracks_shift_a_late_owner_and_leave_out_what_the_relay_would_not_store() -> None:
    """server/objects.py's rule: a new owner's first keyframe 1 ms after the newest, the
    same shift after it; a keyframe not newer than the newest is not stored."""

    def owner(time: float, user: int | None, previous: int | None, reason: str) -> dict:  # type: ignore[type-arg]
        payload = {"object": "object:drill", "previous": previous, "reason": reason}
        return {"kind": "owner", "user": user, "stream": 9, "time": time, "payload": payload}

    create = {"object": "object:drill", "pose": list(DRILL), "keep": True}
    events = [
        {"kind": "object_create", "user": 1, "stream": 9, "time": 1.0, "payload": create},
        owner(1.0, 1, None, "create"),
        owner(2.02, None, 1, "release"),
        owner(2.03, 2, None, "request"),
    ]
    users = {1: UserInfo(1, streams={0: "head"}), 2: UserInfo(2, streams={1: "head"})}
    pieces = {
        (1, 0): _piece(1, 0, [(2.01, 2.00, 1.6)]),  # a's own head: stays a's
        (1, 9): _piece(1, 9, [(2.01, 2.00, 1.2)]),
        # b's estimate runs 30 ms behind: 1.98 -> 2.001, 2.03 -> 2.051; 1.97 is old.
        (2, 9): _piece(2, 9, [(2.04, 1.98, 1.3), (2.09, 2.03, 1.4), (2.10, 1.97, 1.5)]),
    }
    own, (track,) = split_objects(events, pieces, users)
    assert set(own) == {(1, 0)}
    assert np.allclose(track.times, [1.0, 2.00, 2.001, 2.051], rtol=0, atol=1e-12)
    assert track.publisher.tolist() == [1, 1, 2, 2] and track.stale == 1
    assert np.allclose(track.poses[:, 1], [1.0, 1.2, 1.3, 1.4])
    assert [c.reason for c in track.changes] == ["create", "release", "request"]
    assert track.holders == [1, 2] and track.flight_keyframes == 0
