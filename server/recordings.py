"""The adapter's recordings (``posecast serve --record``): files, threads, a writer process.

The relay core decides when a room needs a recording (a join opening a
recorded room is held until it is open), what goes into it (``Record``,
``RecordPose`` actions) and when it is finished (``FinishRecording``);
:class:`Recordings` holds the rooms' recorders and carries those actions out.
The blocking part runs off the event loop: it recovers leftover ``.part``
files at start, starts the one writer process every recorded room shares (and
a new one for the next room after a crash of the previous), opens a room's
recorder in a worker thread while the join that needs it waits, and closes it
when the room is gone.

A recording that stops writing (disk full, I/O error) costs one ERROR line and
one ``posecast_recording_errors_total`` (``on_error``) as soon as the room's next
tick sees it; the room keeps serving unrecorded and the ``.part`` file stays.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from collections.abc import Callable, Container
from pathlib import Path
from typing import TYPE_CHECKING

from posecast.server.actions import Action, PollRecording, Record, RecordPose
from posecast.server.config import ServerConfig

if TYPE_CHECKING:
    from posecast.recorder import RecorderHost, RecordOptions, RoomRecorder

__all__ = ["Recordings"]

log = logging.getLogger("posecast.server")

#: Adds an opened room (recorded or not) to the core; False: it may not be added.
AddRoom = Callable[[str, bool, float], bool]


class Recordings:
    """Recorders of a relay's rooms, opened and closed off the event loop."""

    def __init__(
        self,
        config: ServerConfig,
        clock: Callable[[], float],
        wall_clock: Callable[[], float],
        add_room: AddRoom,
        metadata: Callable[[str], dict[str, str] | None],
        *,
        on_error: Callable[[], None] = lambda: None,
    ) -> None:
        self.config = config
        self.clock = clock
        self.wall_clock = wall_clock
        self.add_room = add_room
        self.metadata = metadata
        self.on_error = on_error
        #: Rooms whose recording failed and was reported (once each).
        self._failed: set[str] = set()
        self._opening: dict[str, asyncio.Task[None]] = {}
        #: The recorder of every recorded room, by room name.
        self.open: dict[str, RoomRecorder] = {}
        #: The one writer process every recorded room shares (started with the
        #: server, again for the next room after a crash of the previous one).
        self.host: RecorderHost | None = None
        self._host_lock = threading.Lock()
        self._retired_hosts: list[RecorderHost] = []
        #: Finished recordings, in the order they closed.
        self.paths: list[Path] = []

    async def start(self) -> None:
        """Recover leftover recordings; start the writer process (logged if it fails)."""
        from posecast.recorder import recover_leftovers

        directory = self.config.record_dir
        assert directory is not None
        directory.mkdir(parents=True, exist_ok=True)
        for report in await asyncio.to_thread(recover_leftovers, directory):
            log.warning("recovered leftover recording: %s", report.summary())
        if self.config.record_writer == "process":
            # Up front, so that no join waits for the writer's start-up.
            try:
                await asyncio.to_thread(self._ensure_host)
            except Exception:
                log.exception("cannot start the recorder process; each new room will retry")

    async def prepare(self, name: str, rooms: Container[str], tg: asyncio.TaskGroup) -> None:
        """Make sure room ``name`` exists (in ``rooms``), opening its recorder off the loop."""
        if self.config.record_dir is None or name in rooms:
            return
        pending = self._opening.get(name)
        if pending is None:
            pending = tg.create_task(self._open_room(name), name=f"opening:{name}")
            self._opening[name] = pending
        await asyncio.shield(pending)

    async def _open_room(self, name: str) -> None:
        from posecast.recorder import RecorderError, RecordOptions, SessionRecorder

        directory = self.config.record_dir
        assert directory is not None
        opener: Callable[..., RoomRecorder] = (
            SessionRecorder.open if self.config.record_writer == "thread" else self._open_on_host
        )
        try:
            options = RecordOptions(
                clock=self.clock,
                wall_clock=self.wall_clock,
                # A hand-off (one pipe write, one wake-up of the writer) at most
                # every 0.25 s: records reach the disk within 0.25 + 0.05 + 0.5 s.
                batch_size=1024,
                batch_delay=0.25,
                metadata=self.metadata(name),
            )
            rec: RoomRecorder | None = await asyncio.to_thread(opener, directory, name, options)
        except (OSError, RecorderError) as exc:  # disk full: one line, no traceback
            self.on_error()
            log.error("cannot record room %r (%s); it runs unrecorded", name, exc)
            rec = None
        except Exception:
            log.exception("cannot record room %r; it runs unrecorded", name)
            rec = None
        try:
            if self.add_room(name, rec is not None, self.clock()):
                if rec is not None:
                    self.open[name] = rec
                    log.info("recording room %r to %s", name, rec.path)
            elif rec is not None:
                await rec.aclose()
        finally:
            self._opening.pop(name, None)

    def _open_on_host(self, directory: Path, name: str, options: RecordOptions) -> RoomRecorder:
        """Open room ``name``'s recording on the shared writer process (a worker thread)."""
        return self._ensure_host().open_room(directory, name, options)

    def _ensure_host(self) -> RecorderHost:
        """The running writer process; a new one if there is none or it died (blocks)."""
        from posecast.recorder import RecorderHost

        with self._host_lock:
            host = self.host
            if host is None or not host.alive:
                if host is not None:
                    log.warning("the recorder process is gone; starting a new one")
                    self._retired_hosts.append(host)
                host = self.host = RecorderHost.start()
                log.info("recorder process started (pid %d)", host.pid)
            return host

    async def close_hosts(self) -> None:
        """Wait for the writer process(es) to end, once every room is closed."""
        hosts = [*self._retired_hosts, self.host]
        self.host, self._retired_hosts = None, []
        for host in hosts:
            if host is not None:
                code = await asyncio.to_thread(host.close)
                if code != 0:
                    log.warning("the recorder process exited with code %s", code)

    def carry_out(self, action: Action) -> None:
        """Write what the core says to write on a room's recording."""
        if type(action) is RecordPose:
            rec = self.open.get(action.room)
            if rec is not None:
                rec.record_pose_update(
                    action.user, action.now, action.update, action.codes, action.volume
                )
        elif isinstance(action, Record):
            rec = self.open.get(action.room)
            if rec is None:
                return
            if action.topic == "presence":
                rec.record_presence(action.record, action.now)
            elif action.topic == "event":
                rec.record_event(action.record, action.now)
            else:
                rec.record_drop(action.record, action.now)
        elif isinstance(action, PollRecording):
            rec = self.open.get(action.room)
            if rec is not None:
                rec.poll()
                if rec.failed and action.room not in self._failed:
                    self._report(action.room, rec)

    def _report(self, name: str, rec: RoomRecorder) -> None:
        """Room ``name``'s recording stopped writing: count it and say so, once."""
        self._failed.add(name)
        self.on_error()
        log.error(
            "recording of room %r stopped (%s); the room keeps serving unrecorded, %s is kept",
            name,
            rec.statistics().error or "the writer failed",
            rec.part_path,
        )

    def take(self, name: str) -> RoomRecorder | None:
        """Room ``name``'s recorder, no longer written to (its room is gone)."""
        return self.open.pop(name, None)

    async def finish(self, name: str, rec: RoomRecorder) -> None:
        """Close room ``name``'s recording (its room is gone)."""
        from posecast.recorder import RecorderError

        try:
            path = await rec.aclose(self.clock())
            self.paths.append(path)
            log.info("room %r recorded to %s", name, path)
        except RecorderError as exc:
            if name in self._failed:  # already reported when it stopped
                log.info("room %r closed; its recording had stopped: %s", name, exc)
            else:
                self._report(name, rec)
        except Exception:
            log.exception("recording of room %r did not finish cleanly", name)
        finally:
            self._failed.discard(name)
