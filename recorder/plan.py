"""What a live replay publishes: each recorded user's updates and object actions.

:func:`plan_replay` reads a recording (no network) into one :class:`UserPlan`
per recorded user: its pose updates regrouped by arrival (the keyframes of the
shared objects it held among them, as it sent them), the stream names it joins
with, and its object actions (``recorder.objects.ObjectAction``). The relay's
flight keyframes (user ``ROOM_USER``) are no user's: a replay leaves the flight
to the live relay. :func:`select_plan` cuts a window and a set of users out of
a plan. ``client.replay`` runs the plan against a live server.
"""

from __future__ import annotations

import itertools
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from posecast.protocol import is_valid_stream_name
from posecast.recorder.export import read_session
from posecast.recorder.objects import ROOM_USER, ObjectAction, object_actions, owner_keyframes
from posecast.recorder.reader import StreamData, UserInfo
from posecast.recorder.replay import user_matches
from posecast.scenarios.motion import MotionSpec
from posecast.scenarios.spawn import Placement, layout_points, placement_for
from posecast.scenarios.traces import Trace

__all__ = ["ReplayPlan", "UserPlan", "merge_updates", "plan_replay", "select_plan", "spawn_plan"]

F64 = NDArray[np.float64]


@dataclass
class UserPlan:
    """One recorded user's updates, in arrival order.

    ``updates[i]`` is ``(recorded stream ids (n,), capture times (n,), poses (n, 7)
    float32)``, arriving at ``arrival[i]`` (recorded server clock).
    """

    user: int
    name: str
    label: str | None
    rate: float | None
    streams: dict[int, str]
    """Recorded stream id -> the name the bot joins with."""
    arrival: F64
    updates: list[tuple[NDArray[np.uint16], F64, NDArray[np.float32]]]
    joined: float | None = None
    left: float | None = None
    #: ``(n, 6)`` float32 velocities of each update (parallel to ``updates``) when
    #: every recorded update of the user carried them, else None.
    velocities: list[NDArray[np.float32]] | None = None
    #: Recorded stream id of each shared object the user published -> its name.
    objects: dict[int, str] = field(default_factory=dict)
    #: The user's object actions (create, request, release), in time order.
    actions: list[ObjectAction] = field(default_factory=list)

    @property
    def update_rate(self) -> float:
        """Mean recorded updates per second."""
        span = float(self.arrival[-1] - self.arrival[0]) if self.arrival.size > 1 else 0.0
        return (self.arrival.size - 1) / span if span > 0 else 0.0


@dataclass
class ReplayPlan:
    """What a replay publishes: the room, the time origin and every user's updates."""

    room: str
    origin: float
    end: float
    users: list[UserPlan] = field(default_factory=list)

    @property
    def updates(self) -> int:
        return sum(len(u.updates) for u in self.users)


def _stream_name(sid: int, name: str | None) -> str:
    return name if name is not None and is_valid_stream_name(name) else f"stream{sid}"


def _user_updates(
    streams: list[StreamData],
) -> tuple[
    F64,
    list[tuple[NDArray[np.uint16], F64, NDArray[np.float32]]],
    list[NDArray[np.float32]] | None,
]:
    """Regroup one user's per-stream keyframes into updates by arrival time.

    Keyframes recorded with the same arrival time came in one update (the
    server stamps each update on arrival); if a stream appears twice at one
    arrival time, its newest capture is kept. The third item holds each
    update's velocities if every keyframe of the user carried one.
    """
    sid = np.concatenate([np.full(len(s), s.stream, dtype=np.uint16) for s in streams])
    arr = np.concatenate([s.arrival for s in streams])
    cap = np.concatenate([s.times for s in streams])
    poses = np.concatenate([s.poses for s in streams])
    vel: NDArray[np.float32] | None = None
    if all(s.velocities is not None for s in streams):
        vel = np.concatenate([s.velocities for s in streams if s.velocities is not None])
        if np.isnan(vel).any():
            vel = None  # some updates carried none: replay the poses only
    order = np.lexsort((cap, sid, arr))
    sid, arr, cap, poses = sid[order], arr[order], cap[order], poses[order]
    if vel is not None:
        vel = vel[order]
    cuts = np.flatnonzero(np.diff(arr) != 0) + 1
    bounds = [0, *cuts.tolist(), arr.size]
    arrivals = []
    updates = []
    velocities: list[NDArray[np.float32]] | None = None if vel is None else []
    for lo, hi in itertools.pairwise(bounds):
        ids, caps, ps = sid[lo:hi], cap[lo:hi], poses[lo:hi]
        last = np.ones(ids.size, dtype=bool)
        last[:-1] = ids[1:] != ids[:-1]  # sorted by (sid, capture): keep the newest
        arrivals.append(float(arr[lo]))
        updates.append((ids[last], caps[last], ps[last]))
        if velocities is not None and vel is not None:
            velocities.append(vel[lo:hi][last])
    return np.asarray(arrivals, dtype=np.float64), updates, velocities


def plan_replay(path: str | os.PathLike[str], room: str | None = None) -> ReplayPlan:
    """Read a recording into per-user update lists (no network)."""
    data = read_session(path)
    by_user: dict[int, list[StreamData]] = {}
    for s in data.streams:
        if s.user != ROOM_USER:  # the objects: their owners send them, the relay flies them
            by_user.setdefault(s.user, []).append(s)
    objects: dict[int, dict[int, str]] = {}
    for t in data.objects:
        for user in {int(u) for u in t.publisher[1:].tolist()} - {ROOM_USER}:
            held = owner_keyframes(t, user)
            if held is not None:
                by_user.setdefault(user, []).append(held)
                objects.setdefault(user, {})[t.stream] = t.name
    actions = object_actions(data.objects)
    users: list[UserPlan] = []
    for user in sorted(by_user):
        info = data.users.get(user, UserInfo(user))
        arrival, updates, velocities = _user_updates(by_user[user])
        # Every stream the user joined with (those never published too), then any
        # published stream the presence records did not name.
        names = {sid: _stream_name(sid, n) for sid, n in info.streams.items()}
        for s in by_user[user]:
            if s.stream not in objects.get(user, {}):
                names.setdefault(s.stream, _stream_name(s.stream, None))
        users.append(
            UserPlan(
                user=user,
                name=info.name or f"user{user}",
                label=info.label,
                rate=info.rate,
                streams=names,
                arrival=arrival,
                updates=updates,
                joined=info.joined,
                left=info.left,
                velocities=velocities,
                objects=objects.get(user, {}),
                actions=actions.get(user, []),
            )
        )
    arrivals = [u.arrival for u in users if u.arrival.size]
    origin = float(min(a[0] for a in arrivals)) if arrivals else 0.0
    end = float(max(a[-1] for a in arrivals)) if arrivals else 0.0
    return ReplayPlan(room or data.session.get("room") or "replay", origin, end, users)


def _window_actions(users: list[UserPlan], lo: float, hi: float) -> dict[int, list[ObjectAction]]:
    """Each user's object actions in ``[lo, hi]``, the objects of before made at ``lo``."""
    out = {up.user: [a for a in up.actions if lo <= a.time <= hi] for up in users}
    earlier = sorted((a for up in users for a in up.actions if a.time < lo), key=lambda a: a.time)
    created: dict[str, ObjectAction] = {}
    holder: dict[str, int | None] = {}
    for a in earlier:
        if a.kind == "create":
            created[a.name], holder[a.name] = a, a.user if a.hold else None
        else:
            holder[a.name] = a.user if a.kind == "request" else None
    for name, create in created.items():
        first = out.setdefault(create.user, [])
        first.insert(0, replace(create, time=lo, hold=holder.get(name) == create.user))
        h = holder.get(name)
        if h is not None and h != create.user and h in out:
            out[h].insert(0, ObjectAction(lo, "request", name, h, None))
    return out


def _user_matches(up: UserPlan, wanted: str) -> bool:
    """``wanted`` names the user by id (``3`` or ``u3``) or by its recorded name."""
    return user_matches(up.user, up.name, wanted)


def select_plan(
    plan: ReplayPlan,
    start: float = 0.0,
    duration: float | None = None,
    users: Sequence[str] | None = None,
) -> ReplayPlan:
    """The part of ``plan`` a player was asked for (``replay --start --duration --users``).

    Object actions in the window are kept; an object created before it is created
    at its start (by its creator's bot, at its create pose), and requested at its
    start by the user that held it then.

    ``start`` and ``duration`` are seconds of the recording from its first
    arrival; the window keeps the updates arriving in ``[origin + start, origin +
    start + duration]`` and becomes the replay's time origin, so the replay begins
    at once. ``users`` keeps the users it names (id, ``u``-id or recorded name;
    ValueError for a name that matches nobody). Users left with no update go.
    """
    if start < 0 or (duration is not None and not duration > 0):
        raise ValueError("--start must be 0 or more and --duration positive")
    if users is not None:
        missing = [w for w in users if not any(_user_matches(up, w) for up in plan.users)]
        if missing:
            known = ", ".join(f"u{up.user} ({up.name})" for up in plan.users)
            raise ValueError(f"no recorded user {missing[0]!r}; the recording has {known}")
    lo = plan.origin + start
    hi = math.inf if duration is None else lo + duration
    if lo > plan.end:
        raise ValueError(
            f"--start {start:g} s is past the recording's end ({plan.end - plan.origin:.1f} s)"
        )
    actions = _window_actions(plan.users, lo, hi)
    kept: list[UserPlan] = []
    for up in plan.users:
        if users is not None and not any(_user_matches(up, w) for w in users):
            continue
        keep = np.flatnonzero((up.arrival >= lo) & (up.arrival <= hi))
        if keep.size == 0:
            continue
        vels = up.velocities
        kept.append(
            replace(
                up,
                arrival=up.arrival[keep],
                updates=[up.updates[i] for i in keep.tolist()],
                velocities=None if vels is None else [vels[i] for i in keep.tolist()],
                actions=actions.get(up.user, []),
                joined=up.joined if up.joined is not None and up.joined > lo else None,
                left=up.left if up.left is not None and up.left < hi else None,
            )
        )
    if not kept:
        raise ValueError("no pose updates in the chosen window and users")
    end = max(float(u.arrival[-1]) for u in kept)
    return ReplayPlan(plan.room, lo, end, kept)


def merge_updates(
    updates: list[tuple[NDArray[np.uint16], F64, NDArray[np.float32]]],
    velocities: list[NDArray[np.float32]] | None = None,
) -> tuple[NDArray[np.uint16], F64, NDArray[np.float32], NDArray[np.float32] | None]:
    """The newest keyframe of each stream (and its velocity, if given)."""
    newest: dict[int, tuple[float, NDArray[np.float32], NDArray[np.float32] | None]] = {}
    for u, (ids, caps, poses) in enumerate(updates):
        for k, sid in enumerate(ids.tolist()):
            c = float(caps[k])
            if sid not in newest or c > newest[sid][0]:
                v = None if velocities is None else velocities[u][k]
                newest[sid] = (c, poses[k], v)
    keys = sorted(newest)
    vel = None
    if velocities is not None:
        vel = np.stack([v for k in keys if (v := newest[k][2]) is not None]).astype(np.float32)
    return (
        np.array(keys, dtype=np.uint16),
        np.array([newest[k][0] for k in keys], dtype=np.float64),
        np.stack([newest[k][1] for k in keys]).astype(np.float32),
        vel,
    )


def spawn_plan(plan: ReplayPlan, layout: str) -> ReplayPlan:
    """``plan`` with user ``i`` moved onto spawn point ``i`` of ``layout``
    (:mod:`scenarios.spawn`; ``none``: ``plan`` itself). Each user's every pose and
    velocity goes through the rigid map that puts its first recorded head pose on
    the point, facing the point's way; a motion label gains that map (after any it
    had), so live receivers score against the moved ground truth. A user without a
    ``head`` stream stays where it is. Object actions are not moved."""
    points = layout_points(layout, max(1, len(plan.users)))
    if points is None or not plan.users:
        return plan
    users = []
    for up, point in zip(plan.users, points, strict=False):
        head = [k for k, name in up.streams.items() if name == "head"]
        rows = [(c[i], p[i]) for ids, c, p in up.updates for i in np.flatnonzero(ids == head[:1])]
        if not rows:
            users.append(up)
            continue
        times = np.array([r[0] for r in rows], dtype=np.float64)
        order = np.argsort(times, kind="stable")
        poses = np.array([r[1] for r in rows], dtype=np.float64)[order][:, None, :]
        at = placement_for(Trace(up.name, times[order], poses, ("head",)), point)
        updates = [(ids, c, at.apply(p).astype(np.float32)) for ids, c, p in up.updates]
        vels = None
        if up.velocities is not None:  # world-frame linear and angular: both turn
            turn = replace(at, x=0.0, z=0.0)
            vels = [
                np.concatenate([_turned(turn, v[:, :3]), _turned(turn, v[:, 3:])], axis=1).astype(
                    np.float32
                )
                for v in up.velocities
            ]
        label = up.label
        try:
            spec = MotionSpec.parse(label) if label else None
        except ValueError:
            spec = None
        if spec is not None:
            label = replace(
                spec, placement=at if spec.placement is None else spec.placement.then(at)
            ).label()
        users.append(replace(up, updates=updates, velocities=vels, label=label))
    return replace(plan, users=users)


def _turned(turn: Placement, v: NDArray[np.float32]) -> F64:
    """Vectors (n, 3) turned by a placement's rotation (no shift)."""
    pose = np.zeros((v.shape[0], 7))
    pose[:, :3], pose[:, 3] = v, 1.0
    out: F64 = turn.apply(pose)[:, :3]
    return out
