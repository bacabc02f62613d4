"""A bot's part in the live throw-catch scene (:mod:`scenarios.throw_catch`).

:class:`ThrowCatchActor` turns the scene's script into shared-object requests
at the script's times (server time): the thrower creates or takes the drill at
the start of a cycle, throws it (a keyframe of the release sample, then
``release`` with the drill's velocity and the hand's angular velocity) and
takes it back at the grab; the catcher asks for it at the catch and lets it go
at rest at the hand-back; a watcher only watches. The bot's publisher asks it
which object to put in each update (:meth:`ThrowCatchActor.publishing`: the
drill while this bot owns it and has not let go of it) and when to wake up for
the next action (:meth:`ThrowCatchActor.next_at`).

An action that does not fit the room as it is does nothing: a catcher does not
ask for a drill it has not seen, a thrower does not throw what it does not hold
(say, because the catcher missed it and it lies on the floor; the thrower takes
it back at the next cycle's start).
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from posecast.client.connection import ClientConnection
from posecast.protocol import Owner
from posecast.scenarios.synthetic import NATIVE_RATE
from posecast.scenarios.throw_catch import (
    DRILL,
    PERIOD,
    Action,
    drill_label,
    scene_script,
)
from posecast.scenarios.traces import causal_velocities

__all__ = ["LEAD", "MAX_LATE", "OwnerChange", "ThrowCatchActor"]

#: The thrower brings the drill in at the first cycle that starts this long after
#: it joined (s), so the others have joined by then.
LEAD = 1.0
#: Added to an action's sample time when looking its sample up (float rounding).
_EPS = 1e-9
#: The relay keeps an object's keyframes at least this far apart (s).
HANDOVER_STEP = 1e-3
#: A release due longer ago than this (s) is skipped: the relay flies a throw from
#: its keyframe only if that is under 0.1 s old (``server.objects.RESTED``), and a
#: stale keyframe would be refused. The thrower keeps the drill for the next cycle.
MAX_LATE = 0.08


@dataclass(frozen=True, slots=True)
class OwnerChange:
    """An ``owner`` message as a bot received it (server time of the change)."""

    time: float
    stream: int
    owner: int | None
    previous: int | None
    reason: str


class ThrowCatchActor:
    """What one bot does with the drill, and when."""

    def __init__(self, role: str, seed: int, t0: float, start: float) -> None:
        self.role = role
        self.seed = seed
        self.t0 = t0
        script = scene_script(seed)
        self.drill = script.drill_trace()
        self._actions = [a for a in script.actions() if a.role == role]
        #: The drill's keyframe label (its ground truth for scoring).
        self.label = drill_label(seed, t0)
        #: The cycle and action index of the next action.
        self._cycle = max(0, int(np.floor((start - t0) / PERIOD)))
        self._i = 0
        self._first_hold = start + LEAD
        #: Objects let go of whose ``owner`` message has not come yet.
        self.released: set[int] = set()
        self._velocities: NDArray[np.float64] | None = None
        #: When this bot got each object it holds (server time of the change).
        self._held_since: dict[int, float] = {}
        #: Releases skipped because the bot was too late for them (a starved machine).
        self.skipped = 0
        self._skip_past(start)

    def _at(self) -> float:
        return self.t0 + self._cycle * PERIOD + self._actions[self._i].at

    def _advance(self) -> None:
        self._i += 1
        if self._i == len(self._actions):
            self._i, self._cycle = 0, self._cycle + 1

    def _skip_past(self, start: float) -> None:
        """Drop the actions before ``start`` (and the thrower's holds before its lead)."""
        while self._actions and (
            self._at() < start
            or (self._actions[self._i].kind == "hold" and self._at() < self._first_hold)
        ):
            self._advance()

    def next_at(self) -> float:
        """Server time of the next action (inf: this role has none)."""
        return self._at() if self._actions else float("inf")

    def due(self, now: float) -> list[tuple[float, Action]]:
        """The actions due by ``now``, each with its server time, in order."""
        out = []
        while self._actions and self._at() <= now:
            out.append((self._at(), self._actions[self._i]))
            self._advance()
        return out

    def publishing(self, conn: ClientConnection, capture: float | None = None) -> int | None:
        """The drill's stream if this bot owns it and has not let go of it, else None.

        With ``capture``: only for a sample captured after the change of owner that
        gave it to this bot (see :meth:`on_owner`).
        """
        sid = conn.session.objects.get(DRILL)
        if sid is None or sid not in conn.session.held or sid in self.released:
            return None
        if capture is not None and capture <= self._held_since.get(sid, -np.inf):
            return None
        return sid

    def velocity(self, index: int) -> NDArray[np.float64]:
        """The drill's causal velocity (6,) at sample ``index`` (a tracker's estimate)."""
        if self._velocities is None:
            self._velocities = causal_velocities(self.drill.times, self.drill.poses)[:, 0]
        row: NDArray[np.float64] = self._velocities[index]
        return row

    async def perform(
        self,
        conn: ClientConnection,
        action: Action,
        at: float,
        send_sample: Callable[[float], Awaitable[None]],
        now: float,
    ) -> None:
        """Do ``action`` (due at server time ``at``, now ``now``); ``send_sample(t)``
        publishes the sample at ``t`` (with the drill while this bot holds it)."""
        if action.keyframe and now - at > MAX_LATE:
            self.skipped += 1
            return
        sid = conn.session.objects.get(DRILL)
        mine = sid is not None and sid in conn.session.held
        if action.kind == "hold":
            if sid is None:
                idx = self._index(at)
                await conn.create_object(DRILL, self.drill.poses[idx, 0], hold=True, time=at)
            elif not mine:
                await conn.request_ownership(sid)
        elif action.kind in ("catch", "grab"):
            if sid is not None and not mine:
                await conn.request_ownership(sid)
        elif sid is not None and self.publishing(conn) == sid:  # throw, hand-back
            await send_sample(at + _EPS)
            self.released.add(sid)
            await conn.release_object(sid, action.velocity, action.angular)

    def _index(self, at: float) -> int:
        period_samples = self.drill.times.size
        return round((at - self.t0) * NATIVE_RATE) % period_samples

    def on_owner(self, ev: Owner, me: int) -> None:
        """Note an ``owner`` message: a let-go object is settled once the server says so.

        When it makes this bot (user ``me``) the owner, its first sample of the object is one
        captured after the change (and the 1 ms the relay keeps between two
        keyframes of an object): the object's last keyframe (the relay's flight
        keyframe, or its creation) is no later than the change, so the relay has
        no reason to shift this bot's capture times (``server.objects``, "Clocks at
        a handover"), which would stamp every keyframe it sends of it late.
        """
        self.released.discard(ev.stream)
        if ev.owner is not None and ev.owner == me:
            self._held_since[ev.stream] = ev.time + HANDOVER_STEP
