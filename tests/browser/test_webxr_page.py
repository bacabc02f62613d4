"""The WebXR example page in headless Chromium with an emulated Meta Quest 3 (IWER),
joined to a real relay on loopback with real Python bots.

The page (``client/js/examples/web``, built on the JS SDK) is opened with
``?emulate=quest3``: IWER replaces the browser's WebXR runtime and the page enters
its immersive session at once. The test moves the emulated headset and controllers
through IWER and reads what the page shows back from its three.js objects.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest
from playwright.async_api import BrowserContext, Page
from scipy.spatial.transform import Rotation
from support import poll_until, running_server

from posecast.client.connection import ClientConnection
from posecast.interp import get as interpolator
from posecast.protocol import PeerLeft, PeerResumed, PeerStalled, PoseUpdate, Snapshot
from posecast.server.app import RelayServer, ServerConfig

#: One Chromium for the module: its tests share the module's event loop.
pytestmark = pytest.mark.asyncio(loop_scope="module")

STREAMS = ("head", "left", "right")
#: What each codec guarantees for a pose (docs/protocol.md), plus float32 rounding of
#: the emulator's own math (gl-matrix works in float32).
BOUNDS = {"raw": (2e-6, 0.005), "compact": (0.5e-3 + 2e-6, 0.04 + 0.005)}  # m, degrees


# -- the Python side: bots that publish a motion and record what they receive ------------


@dataclass
class Bot:
    """A real client in the room: publishes a slow circle at 30 Hz, records every keyframe
    and presence notice it receives."""

    conn: ClientConnection
    phase: float = 0.0
    keyframes: dict[tuple[int, int], list[tuple[float, np.ndarray]]] = field(default_factory=dict)
    notices: list[tuple[str, int]] = field(default_factory=list)

    @property
    def user(self) -> int:
        assert self.conn.welcome is not None
        return self.conn.welcome.user

    def pose(self, t: float) -> np.ndarray:
        a = 0.9 * t + self.phase
        head = [1.0 + 0.3 * math.sin(a), 1.6, -1.0 + 0.3 * math.cos(a)]
        q = [math.cos(a / 2), 0.0, math.sin(a / 2), 0.0]
        rows = [head + q]
        for side in (-1.0, 1.0):
            b = 2.3 * t + side
            qh = [math.cos(b / 2), math.sin(b / 2) * 0.6, 0.0, math.sin(b / 2) * 0.8]
            rows.append([head[0] + 0.25 * side, 1.15 + 0.1 * math.sin(b), head[2] - 0.3, *qh])
        return np.array(rows)

    async def publish(self, stop: asyncio.Event) -> None:
        assert self.conn.joined is not None
        ids = [self.conn.joined.streams[n] for n in STREAMS]
        seq = 0
        while not stop.is_set():
            seq += 1
            t = self.conn.clock()
            await self.conn.send(PoseUpdate.from_arrays(seq, ids, np.full(3, t), self.pose(t)))
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(1 / 30):
                    await stop.wait()

    async def receive(self) -> None:
        while True:
            event = (await self.conn.recv()).event
            if isinstance(event, Snapshot):
                for e in event.entries:
                    key = (int(e["user"]), int(e["stream"]))
                    capture = event.send_time + float(e["dt"])
                    self.keyframes.setdefault(key, []).append((capture, e["pose"].astype(float)))
            elif isinstance(event, PeerStalled | PeerResumed | PeerLeft):
                self.notices.append((event.TYPE, event.user))

    def latest(self, user: int, stream: int) -> np.ndarray | None:
        got = self.keyframes.get((user, stream))
        return None if not got else got[-1][1]


@contextlib.asynccontextmanager
async def bots_in(url: str, room: str, n: int, codec: str = "raw") -> AsyncIterator[list[Bot]]:
    """``n`` bots joined to ``room``, publishing and receiving while the block runs."""
    bots = [
        Bot(
            await ClientConnection.open(
                url, room=room, streams=STREAMS, rate=30, label=f"bot{i}", codec=codec
            ),
            phase=1.7 * i,
        )
        for i in range(n)
    ]
    stop = asyncio.Event()
    tasks = [asyncio.create_task(b.publish(stop)) for b in bots]
    tasks += [asyncio.create_task(b.receive()) for b in bots]
    try:
        yield bots
    finally:
        stop.set()
        for b in bots:
            await b.conn.close()
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)


@contextlib.asynccontextmanager
async def relay_and_bots(
    cfg: ServerConfig | None, room: str, n: int, codec: str = "raw"
) -> AsyncIterator[tuple[RelayServer, list[Bot]]]:
    """A real relay on loopback and ``n`` bots in ``room`` on it."""
    async with (
        running_server(cfg) as relay,
        bots_in(f"ws://127.0.0.1:{relay.port}", room, n, codec) as bots,
    ):
        yield relay, bots


# -- the page -------------------------------------------------------------------------------


async def open_page(
    browser: BrowserContext, web_port: int, relay: RelayServer, room: str, **query: str
) -> Page:
    """The example page joined to ``room`` in an emulated Quest 3 session, publishing."""
    host = query.pop("host", "127.0.0.1")
    page = await browser.new_page()
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.errors = errors  # type: ignore[attr-defined]
    args = "&".join(f"{k}={v}" for k, v in query.items())
    url = f"ws://127.0.0.1:{relay.port}"
    await page.goto(f"http://{host}:{web_port}/?url={url}&room={room}&emulate=quest3&{args}")
    return page


async def wait_publishing(page: Page) -> int:
    """Wait until the page has joined and published; its user id."""
    await page.wait_for_function(
        "() => { const s = window.posecastPage; return s && (s.error || "
        "(s.publisher && s.publisher.published > 3)); }",
        timeout=60_000,
    )
    error = await page.evaluate("() => window.posecastPage.error")
    assert error is None, error
    return int(await page.evaluate("() => window.posecastPage.client.user"))


async def until(condition: Any, limit: float = 30.0) -> None:
    """Poll ``condition()`` (sync or async) every 50 ms; ``limit`` is a hang guard."""
    await poll_until(condition, limit=limit, every=0.05)


def angle_deg(q1: np.ndarray, q2: np.ndarray) -> float:
    d = abs(float(np.dot(q1 / np.linalg.norm(q1), q2 / np.linalg.norm(q2))))
    return math.degrees(2 * math.acos(min(1.0, d)))


def grip_pose(pose: np.ndarray, offset: list[float]) -> np.ndarray:
    """The grip pose IWER reports for a controller set to ``pose``: the set transform
    times the profile's grip offset (a column-major 4x4 matrix)."""
    m = np.array(offset, dtype=float).reshape(4, 4).T
    rot = Rotation.from_quat([pose[4], pose[5], pose[6], pose[3]])
    position = pose[:3] + rot.apply(m[:3, 3])
    q = (rot * Rotation.from_matrix(m[:3, :3])).as_quat()  # x, y, z, w
    return np.array([*position, q[3], q[0], q[1], q[2]])


SET_POSE_JS = """([head, left, right]) => {
  const d = window.posecastPage.device;
  const put = (o, p) => {
    o.position.set(p[0], p[1], p[2]);
    o.quaternion.set(p[4], p[5], p[6], p[3]);
  };
  put(d, head); put(d.controllers.left, left); put(d.controllers.right, right);
  const layout = window.posecastPage.iwer.metaQuest3.controllerConfig.layout;
  return [layout.left.gripOffsetMatrix, layout.right.gripOffsetMatrix];
}"""


def scripted_motion(k: int) -> list[np.ndarray]:
    """Step ``k`` of the page's scripted motion: head and both controllers (w-first)."""
    rng = np.random.default_rng(100 + k)
    out = []
    for y in (1.6, 1.1, 1.1):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        out.append(
            np.array(
                [
                    *rng.uniform(-1.5, 1.5, 1),
                    y + rng.uniform(-0.2, 0.2),
                    *rng.uniform(-1.5, 1.5, 1),
                    *q,
                ]
            )
        )
    return out


# -- the tests ------------------------------------------------------------------------------


@pytest.mark.parametrize("codec", ["raw", "compact"])
async def test_bots_receive_the_headset_and_controllers_as_scripted(
    browser: BrowserContext, web_port: int, codec: str
) -> None:
    """The emulated headset and controllers, moved step by step, reach a Python bot equal
    to the set poses (controllers: their grip poses) within the codec's bound."""
    async with relay_and_bots(None, "xr", 1, codec) as (relay, (bot,)):
        page = await open_page(browser, web_port, relay, "xr", codec=codec)
        user = await wait_publishing(page)
        streams = await page.evaluate("() => window.posecastPage.client.streams")
        pos_bound, rot_bound = BOUNDS[codec]
        for k in range(4):
            head, left, right = scripted_motion(k)
            offsets = await page.evaluate(SET_POSE_JS, [p.tolist() for p in (head, left, right)])
            want = {
                "head": head,
                "left": grip_pose(left, offsets[0]),
                "right": grip_pose(right, offsets[1]),
            }

            def arrived(want: dict[str, np.ndarray] = want) -> bool:
                for name, pose in want.items():
                    got = bot.latest(user, streams[name])
                    if got is None or np.abs(got[:3] - pose[:3]).max() > pos_bound:
                        return False
                    if angle_deg(got[3:], pose[3:]) > rot_bound:
                        return False
                return True

            await until(arrived)
        assert page.errors == []  # type: ignore[attr-defined]


RENDERED_JS = """() => {
  const s = window.posecastPage;
  const f = s.lastFrame;
  const out = [];
  for (const p of f.poses) {
    if (p.stalled || p.user === 65535) continue;
    const o = s.avatars.part(p.user, p.name);
    out.push({ user: p.user, stream: p.stream, time: p.time,
      shown: [o.position.x, o.position.y, o.position.z,
              o.quaternion.w, o.quaternion.x, o.quaternion.y, o.quaternion.z],
      keyframes: s.keyframes.get(`${p.user}/${p.stream}`) || [] });
  }
  return out;
}"""


async def test_the_page_shows_each_bot_interpolated_between_its_keyframes(
    browser: BrowserContext, web_port: int
) -> None:
    """Each bot's head and hands, as the page's three.js objects show them, equal the
    method's interpolation between the two keyframes the page received around the
    playout time (1e-5), for soa, dq-slerp and motor-lerp."""
    async with running_server() as relay, bots_in(f"ws://127.0.0.1:{relay.port}", "show", 2):
        page = await open_page(browser, web_port, relay, "show")
        await wait_publishing(page)
        for method in ("soa", "dq-slerp", "motor-lerp"):
            await page.evaluate(f"() => {{ window.posecastPage.method = '{method}'; }}")
            await page.wait_for_function(
                "() => { const f = window.posecastPage.lastFrame; "
                "return f && f.poses.filter(p => !p.stalled).length >= 6; }",
                timeout=30_000,
            )
            # Every frame read is checked; under load a frame may have fewer than six
            # streams between two keyframes (a bot late: stalled or held), so frames
            # are read until one has six.
            f, best = interpolator(method), 0
            for _ in range(FRAMES_TO_TRY):
                await page.evaluate("() => new Promise(r => requestAnimationFrame(() => r()))")
                best = max(best, check_rendered(await page.evaluate(RENDERED_JS), f, method))
                if best >= 6:
                    break
            assert best >= 6, (method, best)


#: How many animation frames a check reads at most for one with six bracketed streams.
FRAMES_TO_TRY = 30


def check_rendered(rendered: list[dict[str, Any]], f: Any, method: str) -> int:
    """Assert each shown pose with a bracketing keyframe pair equals ``f`` between the
    pair at the playout time (1e-5); how many were checked."""
    checked = 0
    for r in rendered:
        times = np.array([k[0] for k in r["keyframes"]])
        i = int(np.searchsorted(times, r["time"], side="right"))
        if i == 0 or i == len(times):
            continue  # no bracketing pair (held)
        a = np.array(r["keyframes"][i - 1][1:])
        b = np.array(r["keyframes"][i][1:])
        s = (r["time"] - times[i - 1]) / (times[i] - times[i - 1])
        want = np.asarray(f(a, b, np.float64(s)))
        shown = np.array(r["shown"])
        assert np.abs(shown[:3] - want[:3]).max() < 1e-5, (method, r["user"])
        sign = 1.0 if float(np.dot(shown[3:], want[3:])) >= 0 else -1.0
        assert np.abs(shown[3:] - sign * want[3:]).max() < 1e-5, (method, r["user"])
        checked += 1
    return checked


async def test_the_page_resumes_after_its_socket_is_cut(
    browser: BrowserContext, web_port: int
) -> None:
    """The relay's side of the page's TCP connection is aborted: the SDK resumes with its
    token; the bot sees peer_stalled then peer_resumed (never peer_left), the same user
    publishing again. (Silence is not announced here: on a loaded machine a starved
    page could be announced stalled for it, which is the next test's subject.)"""
    cfg = ServerConfig(host="127.0.0.1", port=0, stall_after=0.0)
    async with relay_and_bots(cfg, "cut", 1) as (relay, (bot,)):
        page = await open_page(browser, web_port, relay, "cut")
        user = await wait_publishing(page)
        relay.connection_of(user).abort()

        async def page_resumed() -> bool:
            notices = await page.evaluate("() => window.posecastPage.notices")
            return ["resumed", user] in notices

        await until(page_resumed)
        await until(lambda: ("peer_resumed", user) in bot.notices)
        assert [n for n in bot.notices if n[1] == user] == [
            ("peer_stalled", user),
            ("peer_resumed", user),
        ]
        head = int(await page.evaluate("() => window.posecastPage.client.streams.head"))
        before = len(bot.keyframes.get((user, head), []))
        await until(lambda: len(bot.keyframes.get((user, head), [])) > before + 3)


async def test_a_frozen_page_is_reported_stalled_to_the_bots(
    browser: BrowserContext, web_port: int
) -> None:
    """The page's JavaScript blocks for 2 s (a frozen tab: the browser still answers
    pings): the bot hears peer_stalled, then peer_resumed once the page runs again."""
    cfg = ServerConfig(host="127.0.0.1", port=0, stall_after=0.5)
    async with relay_and_bots(cfg, "frozen", 1) as (relay, (bot,)):
        page = await open_page(browser, web_port, relay, "frozen")
        user = await wait_publishing(page)
        before = len(bot.notices)
        await page.evaluate(
            "() => { setTimeout(() => { const end = performance.now() + 2000; "
            "while (performance.now() < end) {} }, 0); }"
        )
        await until(lambda: ("peer_resumed", user) in bot.notices[before:])
        # (A page starved by a loaded machine may be announced again after.)
        assert [n for n in bot.notices[before:] if n[1] == user][:2] == [
            ("peer_stalled", user),
            ("peer_resumed", user),
        ]
        assert ("peer_left", user) not in bot.notices
        assert relay.core.silence.stalls >= 1


async def test_a_page_from_a_refused_origin_is_closed(
    browser: BrowserContext, web_port: int
) -> None:
    """With --allow-origin naming the page's 127.0.0.1 origin, the same page opened as
    localhost (another origin) cannot join: its socket is refused (403), and it says so."""
    allowed = f"http://127.0.0.1:{web_port}"
    cfg = ServerConfig(host="127.0.0.1", port=0, allow_origins=(allowed,))
    async with running_server(cfg) as relay:
        page = await open_page(browser, web_port, relay, "origin", host="localhost")
        await page.wait_for_function("() => window.posecastPage && window.posecastPage.error")
        assert relay.origins.refused >= 1
        assert not relay.rooms
        ok = await open_page(browser, web_port, relay, "origin")
        await wait_publishing(ok)
        assert "origin" in relay.rooms
