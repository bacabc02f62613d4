"""Rooms and ticks: the relay's rooms by name, when each is due, and their end.

:class:`RoomTable` is the part of :class:`server.core.RelayCore` that owns the
rooms: it creates a room on its first join (or when the adapter opened its
recording), refuses one over ``max_rooms`` or ``max_recorded_rooms`` and a join
over ``max_members`` (:meth:`~RoomTable.refusal`), keeps every room's earliest
due tick in a heap (:meth:`~RoomTable.next_deadline`; an entry a later change
made stale is dropped when met, so a wake-up costs O(log rooms), not
O(members)), ticks the due rooms, and removes an empty room (its recording is
finished: a ``FinishRecording`` action). A room whose tick fails (a bug) is
removed; the core closes its members with 1011. Sans I/O: time is an argument,
effects are actions added to ``out``, the core's list.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable

from posecast.protocol.codec import Volume
from posecast.server.actions import ERROR, INFO, Action, FinishRecording, Log, Reschedule
from posecast.server.config import ServerConfig
from posecast.server.limits import room_refusal
from posecast.server.room import LagHistogram, Room, room_phase
from posecast.server.view_rates import ViewRates

__all__ = ["RoomTable"]


class RoomTable:
    """The rooms of one relay and their tick schedule."""

    def __init__(
        self,
        config: ServerConfig,
        volume: Volume,
        out: list[Action],
        fly: Callable[[Room, float], None] | None = None,
    ):
        self.config = config
        self.volume = volume
        #: Where its actions and its rooms' go: the core's list, which it returns.
        self.out = out
        #: What moves a room's thrown objects at its tick (``server.objects.fly``).
        self.fly = fly
        self.rooms: dict[str, Room] = {}
        #: (due, seq, room) of every room with members (see the module docstring).
        self._dues: list[tuple[float, int, Room]] = []
        self._due_seq = 0
        #: Set by :meth:`close_all`: the server is stopping, no room is added.
        self.closed = False
        #: Pose updates are not recorded while set (see :meth:`pause_recording`).
        self.recording_paused = False
        #: Every room's member ticks by lag (``posecast_tick_lag_seconds``).
        self.tick_lags = LagHistogram()
        #: Per-peer rates of members with a budget (None: ``serve --no-view-rates``).
        self.view_rates = (
            ViewRates(config.min_rate, config.view_margin) if config.view_rates else None
        )
        #: Run after each room's tick: auto rates decide (``server.rates.adapt``).
        self.adapt: Callable[[Room, float], None] | None = None
        #: Run before each room's tick: pending presence notices go out (``server.presence``).
        self.notify: Callable[[Room], None] | None = None

    def refusal(self, name: str) -> str | None:
        """Why a join of room ``name`` is refused (``room-full``) now; None: it is not."""
        return room_refusal(self.config, self.rooms, name)

    def add(self, name: str, recorded: bool, now: float) -> bool:
        """Create room ``name``, ``recorded`` (its recording is open); False if it exists
        already or may not be created."""
        if name in self.rooms or self.closed or self.refusal(name) is not None:
            return False
        room = self.room_for(name)
        room.recorded = recorded
        if recorded and self.recording_paused:
            room.pause_recording(now)
        return True

    def room_for(self, name: str) -> Room:
        """Room ``name``, created if there is none."""
        room = self.rooms.get(name)
        if room is None:
            room = self.rooms[name] = Room(
                name,
                phase=room_phase(name),
                volume=self.volume,
                lags=self.tick_lags,
                views=self.view_rates,
                out=self.out,
                fly=self.fly,
            )
            self.out.append(Log(INFO, "room %r created", (name,)))
        return room

    def next_deadline(self) -> float | None:
        """When the next room tick is due (None: no member anywhere)."""
        dues = self._dues
        while dues:
            due, _, room = dues[0]
            if self.rooms.get(room.name) is room and room.next_due() == due:
                return due
            heapq.heappop(dues)  # stale: the room's schedule changed, or it is gone
        return None

    def _schedule(self, room: Room) -> None:
        """Room ``room``'s earliest due time may have moved: queue the new one."""
        due = room.next_due()
        if due is not None:
            self._due_seq += 1
            heapq.heappush(self._dues, (due, self._due_seq, room))

    def rescheduled(self, room: Room) -> None:
        """A member of ``room`` joined, left or changed its rate."""
        self._schedule(room)
        self.out.append(Reschedule())

    def tick(self, now: float, limit: int | None = None) -> list[Room]:
        """Tick every due room (at most ``limit``), the actions it decides (a Wake per
        snapshot offered, the log line of a failure) added to ``out``; returns the
        rooms that failed, removed already (their members are the caller's to close)."""
        out = self.out
        ticked = 0
        failed: list[Room] = []
        while limit is None or ticked < limit:
            due = self.next_deadline()
            if due is None or due > now + 1e-9:
                break
            ticked += 1
            room = heapq.heappop(self._dues)[2]
            try:
                if self.notify is not None:
                    self.notify(room)
                room.tick(now, out)
                room.flush_drops(now)
                if self.adapt is not None:
                    self.adapt(room, now)
            except Exception as exc:
                out.append(Log(ERROR, "room %r failed", (room.name,), exc))
                if self.rooms.get(room.name) is room:
                    del self.rooms[room.name]
                failed.append(room)
            else:
                self._schedule(room)
        return failed

    def forget_if_empty(self, room: Room, now: float) -> None:
        """Remove ``room`` once its last member is gone (its recording is finished)."""
        # A failed room is no longer in ``rooms``: its recording ends with its last member.
        if not room.members and not room.retired:
            if self.rooms.get(room.name) is room:
                del self.rooms[room.name]
            self.out.append(Log(INFO, "room %r removed", (room.name,)))
            self._retire(room, now)

    def _retire(self, room: Room, now: float) -> None:
        """A room is gone: its recording gets the last drops and is to be finished."""
        room.retire()
        if room.recorded:
            room.resume_recording(now)  # a pause in progress goes into the file
            room.flush_drops(now, force=True)  # the drops of the last second too
            room.recorded = False
            self.out.append(FinishRecording(room.name))

    def close_all(self, now: float) -> None:
        """Server shutdown: forget every room; recorded ones are to be finished."""
        for room in list(self.rooms.values()):
            room.members.clear()
            self._retire(room, now)
        self.rooms.clear()
        self._dues.clear()
        self.closed = True

    def pause_recording(self, now: float) -> None:
        """Stop recording pose updates in every room, and in rooms opened later."""
        if not self.recording_paused:
            self.recording_paused = True
            for room in self.rooms.values():
                room.pause_recording(now)

    def resume_recording(self, now: float) -> None:
        """Record pose updates again after :meth:`pause_recording`."""
        if self.recording_paused:
            self.recording_paused = False
            for room in self.rooms.values():
                room.resume_recording(now)
