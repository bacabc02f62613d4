"""docs/protocol.md says what the code does: generated parts, message tables, token recipe.

The error table and the worked examples are generated (``protocol/golden.py``) and
must be in the doc verbatim (regenerate them with
``python -m posecast.protocol.golden docs/protocol.md``); every message's field
table must list the dataclass's fields in order, with the right required and
omitted-at-default marks; the Python token recipe, taken from the doc, must mint a
token a real relay with a secret accepts.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import time
from dataclasses import MISSING, fields
from pathlib import Path
from typing import Any

import pytest
from support import poll_until, running_server
from websockets.asyncio.client import connect
from websockets.exceptions import ConnectionClosed

from posecast.protocol import (
    ClientSession,
    ErrorCode,
    ErrorMessage,
    Hello,
    Join,
    Joined,
    Welcome,
)
from posecast.protocol.golden import doc_sections, error_rows, rewrite
from posecast.protocol.messages import ControlMessage
from posecast.protocol.objects import OBJECT_MESSAGE_TYPES
from posecast.protocol.wire import _CONTROL
from posecast.server.app import ServerConfig

DOC = Path(__file__).resolve().parents[2] / "docs" / "protocol.md"


def _doc() -> str:
    return DOC.read_text(encoding="utf-8")


def test_generated_sections_match_the_code() -> None:
    """The error table and the worked examples are what protocol/golden.py generates."""
    text = _doc()
    assert rewrite(text, doc_sections()) == text, (
        "docs/protocol.md is stale: run python -m posecast.protocol.golden docs/protocol.md"
    )


def test_error_table_lists_every_code() -> None:
    """Every ErrorCode has a row in errors.py's docstring table, so none is left undocumented."""
    from posecast.protocol import ErrorCode

    assert [code for code, _ in error_rows()] == [str(c) for c in ErrorCode]


def _field_tables(text: str) -> list[list[list[str]]]:
    """Every markdown table whose header is ``| field | type | default | meaning |``."""
    tables: list[list[list[str]]] = []
    rows: list[list[str]] | None = None
    for line in text.splitlines():
        if line.startswith("| field | type | default | meaning |"):
            rows = []
            tables.append(rows)
        elif rows is not None and line.startswith("|"):
            if not line.startswith("|---"):
                rows.append([cell.strip() for cell in line.strip()[1:-1].split("|")])
        else:
            rows = None
    return tables


def _spec_of(cls: type[ControlMessage]) -> list[tuple[str, bool, bool]]:
    """(name, required, omitted at default) of each field, in wire order."""
    out = []
    for f in fields(cls):  # type: ignore[arg-type]
        required = f.default is MISSING and f.default_factory is MISSING
        out.append((f.name, required, f.name in cls._OMIT))
    return out


@pytest.mark.parametrize(
    "cls", sorted(_CONTROL.values(), key=lambda c: c.TYPE), ids=lambda c: c.TYPE
)
def test_message_table_matches_the_dataclass(cls: type[ControlMessage]) -> None:
    """Each control message has a doc table listing its fields in order, with the
    required ones (no default) and the omitted-at-default ones marked."""
    want = _spec_of(cls)
    names = [name for name, _, _ in want]
    tables = [t for t in _field_tables(_doc()) if [r[0].strip("`") for r in t] == names]
    assert tables, f"no field table for {cls.TYPE!r} with fields {names}"
    for row, (name, required, omitted) in zip(tables[0], want, strict=True):
        default = row[2]
        assert (default == "") == required, f"{cls.TYPE}.{name}: default column {default!r}"
        assert ("*omitted*" in default) == omitted, f"{cls.TYPE}.{name}: omitted mark"


def test_every_message_type_has_a_heading() -> None:
    """The doc names every message type the wire knows."""
    text = _doc()
    types = set(_CONTROL) | {"update", "snapshot"}
    assert all(f"`{t}`" in text for t in types)
    assert {c.TYPE for c in OBJECT_MESSAGE_TYPES} <= types


def _token_recipe() -> Any:
    """The doc's Python token recipe, run as written; its ``mint_token``."""
    blocks = re.findall(r"```python\n(.*?)```", _doc(), flags=re.S)
    (source,) = [b for b in blocks if "def mint_token" in b]
    scope: dict[str, Any] = {}
    exec(compile(source, "docs/protocol.md", "exec"), scope)  # the doc's own code
    return scope["mint_token"]


def test_token_recipe_matches_the_server() -> None:
    """The recipe's token verifies with the server's own checker, for its room only."""
    from posecast.server.auth import TokenError, verify_token

    token = _token_recipe()("s3cret", "lab", "alice", 60.0)
    claims = verify_token("s3cret", token, "lab", time.time())
    assert (claims.room, claims.user) == ("lab", "alice")
    with pytest.raises(TokenError, match="room"):
        verify_token("s3cret", token, "other", time.time())


def _js_recipes() -> list[str]:
    """The doc's JavaScript token recipes (node:crypto, then WebCrypto)."""
    blocks = re.findall(r"```js\n(.*?)```", _doc(), flags=re.S)
    return [b for b in blocks if "mintToken" in b]


@pytest.mark.skipif(shutil.which("node") is None, reason="needs Node.js")
@pytest.mark.parametrize("which", [0, 1], ids=["node-crypto", "webcrypto"])
def test_js_token_recipes_match_the_server(which: int, tmp_path: Path) -> None:
    """The doc's JavaScript recipes, run by Node, mint tokens the server's checker accepts."""
    from posecast.server.auth import verify_token

    recipes = _js_recipes()
    assert len(recipes) == 2
    script = tmp_path / "mint.mjs"
    script.write_text(
        recipes[which] + '\nconsole.log(await mintToken("s3cret", "lab", "alice", 60));\n',
        encoding="utf-8",
    )
    token = subprocess.run(
        ["node", str(script)], capture_output=True, text=True, check=True, timeout=60
    ).stdout.strip()
    claims = verify_token("s3cret", token, "lab", time.time())
    assert (claims.room, claims.user) == ("lab", "alice")


async def _join(port: int, token: str) -> tuple[list[object], int | None]:
    """Hello and join with ``token``: the messages received, and the close code if closed."""
    session = ClientSession()
    got: list[object] = []
    async with connect(f"ws://127.0.0.1:{port}") as ws:
        await ws.send(session.send(Hello(agent="doc")))
        got += session.receive_data(await ws.recv())
        await ws.send(session.send(Join(room="lab", streams=("head",), rate=10.0, token=token)))
        try:
            while not any(isinstance(m, Joined | ErrorMessage) for m in got):
                got += session.receive_data(await ws.recv())
            if any(isinstance(m, ErrorMessage) for m in got):
                await ws.recv()  # the close follows the fatal error
        except ConnectionClosed as exc:
            return got, exc.rcvd.code if exc.rcvd else None
    return got, None


async def test_token_recipe_admits_a_join_on_a_real_relay() -> None:
    """A relay with a secret admits the doc recipe's token and refuses a forged one (1008)."""
    mint = _token_recipe()
    config = ServerConfig(host="127.0.0.1", port=0, secret="s3cret")
    async with running_server(config) as srv:
        assert srv.port is not None
        got, code = await _join(srv.port, mint("s3cret", "lab", "alice", 60.0))
        assert isinstance(got[0], Welcome) and isinstance(got[-1], Joined)
        assert code is None
        got, code = await _join(srv.port, mint("not the secret", "lab", "bob", 60.0))
        errors = [m for m in got if isinstance(m, ErrorMessage)]
        assert [(e.code, e.fatal) for e in errors] == [("unauthorized", True)]
        assert errors[0].message == "invalid access token signature"
        assert code == 1008


async def _hello(
    port: int, hello: Hello, join: Join | None = None, last: ErrorMessage | None = None
) -> list[object]:
    """One connection: ``hello`` (and ``join``), the messages up to welcome (joined); then
    the TCP connection is cut without a close frame, as a dropped connection is, or
    (``last``) that error is sent and the socket closed as the SDK does after one."""
    session = ClientSession()
    got: list[object] = []
    async with connect(f"ws://127.0.0.1:{port}") as ws:
        await ws.send(session.send(hello))
        got += session.receive_data(await ws.recv())
        if join is not None:
            await ws.send(session.send(join))
            while not any(isinstance(m, Joined) for m in got):
                got += session.receive_data(await ws.recv())
        if last is None:
            ws.transport.abort()
        else:
            await ws.send(session.send(last))
            await ws.close(1002, last.message)
    return got


async def test_resume_tokens_behave_as_the_doc_says() -> None:
    """Section 9: a dropped resumable member resumes with the same user and stream ids and
    a fresh token; a bad resume token gets a new user id, no resumed, a new token."""
    join = Join(room="lab", streams=("head", "left"), rate=10.0)
    async with running_server() as srv:
        assert srv.port is not None
        first = await _hello(srv.port, Hello(agent="a", resumable=True), join)
        welcome, joined = first[0], first[-1]
        assert isinstance(welcome, Welcome) and isinstance(joined, Joined)
        assert welcome.resume is not None and not welcome.resumed
        token = welcome.resume
        await poll_until(lambda: srv.core.parking.has(token))
        back = await _hello(srv.port, Hello(agent="a", resumable=True, resume=welcome.resume), join)
        again, rejoined = back[0], back[-1]
        assert isinstance(again, Welcome) and isinstance(rejoined, Joined)
        assert (again.user, again.resumed) == (welcome.user, True)
        assert again.resume not in (None, welcome.resume)
        assert rejoined.streams == joined.streams
        bogus = await _hello(srv.port, Hello(agent="b", resumable=True, resume="not-a-token"))
        fresh = bogus[0]
        assert isinstance(fresh, Welcome) and not fresh.resumed
        assert fresh.user != welcome.user and fresh.resume is not None


def test_contents_links_reach_headings() -> None:
    """Every in-page link of the doc names a heading (as mkdocs slugs it)."""
    text = _doc()
    slugs = set()
    for heading in re.findall(r"^#{2,4} (.+)$", text, flags=re.M):
        slug = re.sub(r"[^\w\s-]", "", heading.lower()).strip()
        slugs.add(re.sub(r"[\s]+", "-", slug))
    links = re.findall(r"\]\(#([^)]+)\)", text)
    assert links and set(links) <= slugs, set(links) - slugs


async def test_a_session_ended_on_an_error_is_not_resumed() -> None:
    """Section 11.3: a client that ends its session with a fatal error (bad-baseline) has
    left; its resume token then gets a new user id (section 9.3), not its old place."""
    join = Join(room="lab", streams=("head",), rate=10.0)
    error = ErrorMessage.from_code(ErrorCode.BAD_BASELINE, "check differs", in_reply_to="snapshot")
    async with running_server() as srv:
        assert srv.port is not None
        first = await _hello(srv.port, Hello(agent="a", resumable=True), join, last=error)
        welcome = first[0]
        assert isinstance(welcome, Welcome) and welcome.resume is not None
        await poll_until(lambda: not srv.rooms)  # it left: the room is gone
        back = await _hello(srv.port, Hello(agent="a", resumable=True, resume=welcome.resume))
        again = back[0]
        assert isinstance(again, Welcome) and not again.resumed
