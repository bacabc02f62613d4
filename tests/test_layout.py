"""The layout of ../shared/DESIGN.md, checked on every module's imports (ast, no import).

Imports point one way: ``protocol`` and ``interp`` import nothing of ours;
``scenarios`` uses only those two; ``recorder`` uses those and ``scenarios``
(one way: scenarios never imports recorder); ``server`` and ``client`` use the
lower packages but never each other, ``posecast`` or experiment code, and
``server`` never imports ``scenarios`` (what the relay runs lives in it); only
``posecast`` composes, and nothing imports it.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("posecast", "server", "client", "protocol", "interp", "recorder", "scenarios")

#: Experiment code in scenarios/: composed only by posecast/.
EXPERIMENTS = (
    "scenarios.table1",
    "scenarios.live_agreement",
    "scenarios.bench_interp",
    "scenarios.velocity_sources",
    "scenarios.compare",
)

#: The client's sans-I/O core (client/): session, clock estimate, jitter buffers,
#: playout delay, render, reconnect policy. Experiments in scenarios/ that measure
#: the receiver (Table 1's running time, the interp bench) may use these modules and
#: no other part of client/ (client/ never imports experiments: no cycle).
CLIENT_CORE = (
    "client.buffers",
    "client.core",
    "client.playout",
    "client.reconnect",
    "client.render",
)

#: Which of our packages each package may import.
ALLOWED: dict[str, frozenset[str]] = {
    "protocol": frozenset(),
    "interp": frozenset(),
    "scenarios": frozenset({"protocol", "interp"}),
    "recorder": frozenset({"protocol", "interp", "scenarios"}),
    "server": frozenset({"protocol", "interp", "recorder"}),
    "client": frozenset({"protocol", "interp", "recorder", "scenarios"}),
    "posecast": frozenset(PACKAGES) - {"posecast"},
}


def folder_name(name: str) -> str:
    """A module name with the install prefix dropped: ``posecast.server.core`` is
    ``server.core`` (the folder it lives in); ``posecast.cli`` stays as it is."""
    head, _, rest = name.partition(".")
    if head == "posecast" and rest.split(".")[0] in PACKAGES[1:]:
        return rest
    return name


def imports_of(path: Path) -> list[str]:
    """Folder-relative module names a file imports (relative imports stay in their
    package); ``from posecast import interp`` imports ``interp``, not ``posecast``."""
    names: list[str] = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.extend(folder_name(alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            subs = [folder_name(f"{node.module}.{alias.name}") for alias in node.names]
            if node.module != "posecast" or any(s.startswith("posecast") for s in subs):
                names.append(folder_name(node.module))
            names.extend(subs)
    return names


@functools.cache
def edges() -> list[tuple[str, str, str]]:
    """(file, importing package, imported module) for every import of our packages;
    built once per process (two tests read it, neither changes it)."""
    out = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            for name in imports_of(path):
                if name.split(".")[0] in PACKAGES:
                    out.append((str(path.relative_to(ROOT)), package, name))
    return out


def test_imports_point_one_way() -> None:
    """No package imports one it may not (see ALLOWED)."""
    bad = [
        (f, src, name)
        for f, src, name in edges()
        if name.split(".")[0] != src
        and name.split(".")[0] not in ALLOWED[src]
        and not _experiment_uses_client_core(f, name)
    ]
    assert not bad, bad


def _experiment_uses_client_core(file: str, name: str) -> bool:
    """An experiment module of scenarios/ importing the client's sans-I/O core."""
    module = file.removesuffix(".py").removesuffix("/__init__").replace("/", ".")
    return module.startswith(EXPERIMENTS) and name.startswith(CLIENT_CORE)


def test_relay_and_bots_stay_out_of_experiments() -> None:
    """server/ and client/ never reach experiment code (only posecast/ composes it)."""
    bad = [
        (f, name)
        for f, src, name in edges()
        if src in ("server", "client") and name.startswith(EXPERIMENTS)
    ]
    assert not bad, bad


def test_the_checker_sees_a_forbidden_edge(tmp_path: Path) -> None:
    """The parser finds every form of import (so a clean result means something)."""
    f = tmp_path / "m.py"
    f.write_text(
        "import posecast.server.core\nfrom posecast.client import bot\n"
        "from posecast.cli import app\nfrom posecast import interp\n"
        "from . import sibling\nimport numpy\n"
    )
    found = imports_of(f)
    assert {"server.core", "client", "client.bot", "posecast.cli", "interp"} <= set(found)
    assert "numpy" in found and not any(n.startswith("sibling") for n in found)


def test_server_holds_only_the_relay() -> None:
    """server/ is the relay: its core (config, actions, peers, limits), rooms, auth,
    adapter, HTTP."""
    modules = {p.name for p in (ROOT / "server").glob("*.py")}
    relay = {
        "__init__.py",
        "capacity.py",
        "guard.py",
        "core.py",
        "config.py",
        "resume.py",
        "objects.py",
        "tokens.py",
        "cluster.py",
        "forward.py",
        "actions.py",
        "peer.py",
        "handshakes.py",
        "intake.py",
        "stopping.py",
        "joins.py",
        "connection.py",
        "member.py",
        "parked.py",
        "parking.py",
        "ports.py",
        "presence.py",
        "silence.py",
        "limits.py",
        "stamps.py",
        "link.py",
        "rates.py",
        "view_rates.py",
        "histogram.py",
        "room.py",
        "rooms.py",
        "shared.py",
        "recordings.py",
        "auth.py",
        "logs.py",
        "app.py",
        "http.py",
        "transport.py",
        "wsframe.py",
        "node.py",
    }
    assert modules == relay


def _sources() -> list[Path]:
    return [p for package in PACKAGES for p in sorted((ROOT / package).rglob("*.py"))]


def test_no_module_over_800_lines() -> None:
    """Every module of the packages stays readable in one sitting."""
    long = {
        str(p.relative_to(ROOT)): n for p in _sources() if (n := p.read_text().count("\n")) > 800
    }
    assert not long, long


def test_no_function_over_80_lines() -> None:
    """A function longer than 80 lines (def to last line) is split into named steps."""
    long = []
    for path in _sources():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                size = (node.end_lineno or node.lineno) - node.lineno + 1
                if size > 80:
                    long.append((str(path.relative_to(ROOT)), node.name, size))
    assert not long, long


# -- the relay's parts (server/) ---------------------------------------------------------

#: The relay core and its parts: sans I/O (the adapter is app, connection, intake,
#: transport, http, recordings, and the cluster side: node, cluster, forward).
RELAY_CORE = (
    "actions",
    "auth",
    "capacity",
    "config",
    "core",
    "guard",
    "handshakes",
    "histogram",
    "joins",
    "limits",
    "link",
    "logs",
    "member",
    "objects",
    "parked",
    "parking",
    "peer",
    "ports",
    "presence",
    "rates",
    "resume",
    "room",
    "rooms",
    "shared",
    "silence",
    "stamps",
    "tokens",
    "view_rates",
)

#: What touches a clock, a file, a socket or a thread: never imported (at run time)
#: by the relay core (nor ``logging``: RELAY_CORE_FORBIDS).
IO_MODULES = frozenset(
    {"asyncio", "io", "mmap", "nats", "os", "pathlib", "resource", "select", "selectors",
     "shutil", "socket", "ssl", "subprocess", "tempfile", "threading", "time",
     "websockets", "recorder"}
)  # fmt: skip


#: The relay core logs nothing itself: a log line is an action it returns (``Log``),
#: which the adapter writes on the ``posecast.server`` logger.
RELAY_CORE_FORBIDS = IO_MODULES | {"logging"}


def _runtime_imports(tree: ast.Module) -> list[str]:
    """Top-level names a module imports when it runs (``if TYPE_CHECKING:`` left out)."""
    typing_only = {
        id(sub)
        for node in ast.walk(tree)
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)
        for sub in ast.walk(node)
    }
    names: list[str] = []
    for node in ast.walk(tree):
        if id(node) in typing_only:
            continue
        if isinstance(node, ast.Import):
            names.extend(folder_name(alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.append(folder_name(node.module))
    return names


def test_the_relay_core_is_every_module_but_the_adapter() -> None:
    """Each module of server/ is either the core (RELAY_CORE, checked below) or the
    adapter: a new module is put on one side on purpose."""
    adapter = {"app", "cluster", "connection", "forward", "http", "intake", "node",
               "recordings", "stopping", "transport", "wsframe"}  # fmt: skip
    modules = {p.stem for p in (ROOT / "server").glob("*.py")} - {"__init__"}
    assert modules - adapter == set(RELAY_CORE)


def test_the_relay_core_touches_no_clock_file_or_socket() -> None:
    """The relay core's modules import nothing that reads a clock or does I/O, nor
    ``logging``: the adapter carries out what they decide, log lines included."""
    bad = [
        (module, name)
        for module in RELAY_CORE
        for name in _runtime_imports(ast.parse((ROOT / "server" / f"{module}.py").read_text()))
        if name.split(".")[0] in RELAY_CORE_FORBIDS
    ]
    assert not bad, bad


def test_the_core_s_parts_see_it_through_its_port() -> None:
    """No module of the relay core but ``core`` itself names ``server.core`` (not even
    for a type): the parts act on it through ``server.ports.Relay``, so it can import
    them without a cycle (the adapter's modules may import it)."""
    bad = [
        (module, name)
        for module in RELAY_CORE
        if module != "core"
        for name in imports_of(ROOT / "server" / f"{module}.py")
        if name == "server.core" or name.startswith("server.core.")
    ]
    assert not bad, bad


def _body_names(cls: ast.ClassDef) -> set[str]:
    """Names a class body defines: methods, annotated fields, assigned fields."""
    out: set[str] = set()
    for item in cls.body:
        if isinstance(item, ast.FunctionDef | ast.AsyncFunctionDef):
            out.add(item.name)
        elif isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
            out.add(item.target.id)
        elif isinstance(item, ast.Assign):
            out.update(t.id for t in item.targets if isinstance(t, ast.Name))
    return out


def _attributes(tree: ast.Module) -> set[str]:
    """Attribute names a module's classes define: methods, class fields, ``x.name = ...``."""
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ClassDef):
            out |= _body_names(node)
        elif isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store):
            out.add(node.attr)
    return out


def private_reaches(folder: Path) -> list[tuple[str, int, str]]:
    """Every ``x._name`` (``x`` not ``self`` or ``cls``) in a module of ``folder`` whose
    ``_name`` is no attribute of that module's own classes: one part reading another
    part's private state (a module's classes may share their private names)."""
    out = []
    for path in sorted(folder.glob("*.py")):
        tree = ast.parse(path.read_text())
        own = _attributes(tree)
        for node in ast.walk(tree):
            if not isinstance(node, ast.Attribute):
                continue
            attr = node.attr
            if not attr.startswith("_") or attr.startswith("__") or attr in own:
                continue
            if isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"):
                continue
            out.append((path.name, node.lineno, ast.unparse(node)))
    return out


def _class_attributes(cls: ast.ClassDef) -> set[str]:
    """Attribute names one class defines: methods, class fields, ``self.name = ...``."""
    out = _body_names(cls)
    for node in ast.walk(cls):
        if (
            isinstance(node, ast.Attribute)
            and isinstance(node.ctx, ast.Store)
            and isinstance(node.value, ast.Name)
            and node.value.id == "self"
        ):
            out.add(node.attr)
    return out


def private_reaches_by_class(folder: Path) -> list[tuple[str, int, str]]:
    """Every ``x._name`` in a module of ``folder`` where ``x`` is not ``self`` or ``cls``
    and ``_name`` is no attribute of the class the access is written in (another
    instance of the same class may be read, e.g. in ``__eq__`` or a classmethod). Two
    classes of one module share nothing private: a connection reads its server's
    state through the server's public methods even when both sat in one file."""
    out: list[tuple[str, int, str]] = []
    for path in sorted(folder.glob("*.py")):
        stack: list[tuple[ast.AST, frozenset[str]]] = [(ast.parse(path.read_text()), frozenset())]
        while stack:
            node, own = stack.pop()
            if isinstance(node, ast.ClassDef):
                own = frozenset(_class_attributes(node))
            if isinstance(node, ast.Attribute):
                attr, value = node.attr, node.value
                if (
                    attr.startswith("_")
                    and not attr.startswith("__")
                    and attr not in own
                    and not (isinstance(value, ast.Name) and value.id in ("self", "cls"))
                ):
                    out.append((path.name, node.lineno, ast.unparse(node)))
            stack.extend((child, own) for child in ast.iter_child_nodes(node))
    return sorted(out)


def test_no_part_of_the_relay_reads_another_parts_private_names() -> None:
    """server/'s modules and classes talk through public methods and fields only (issue
    27: 59 private cross-object reaches once; 20 left before the adapter was split)."""
    assert private_reaches(ROOT / "server") == []
    assert private_reaches_by_class(ROOT / "server") == []


def test_the_by_class_check_finds_a_neighbour_class_s_private(tmp_path: Path) -> None:
    """Per class: a neighbour class's private name fails, the class's own passes
    (on ``self``, on another instance, in a classmethod), and so does a module's
    private function read off the module."""
    (tmp_path / "m.py").write_text(
        "import other\n"
        "class Server:\n    def __init__(self):\n        self._conns = {}\n"
        "    def same(self, twin):\n        return twin._conns\n"
        "    @classmethod\n    def make(cls):\n        s = cls()\n        return s._conns\n"
        "class Conn:\n    def __init__(self, server):\n        self._s = server._conns\n"
        "def f():\n    return other._helper()\n"
    )
    assert private_reaches_by_class(tmp_path) == [
        ("m.py", 13, "server._conns"),
        ("m.py", 15, "other._helper"),
    ]


def test_the_private_reach_check_finds_one(tmp_path: Path) -> None:
    """The checker sees a private name of another module, and lets a module's own pass."""
    (tmp_path / "a.py").write_text("class A:\n    def __init__(self):\n        self._x = 1\n")
    (tmp_path / "b.py").write_text(
        "def _x():\n    pass\n"
        "class B:\n    def __init__(self, a):\n        self._own = a._x\n"
        "    def f(self, other):\n        return other._own\n"
    )
    assert private_reaches(tmp_path) == [("b.py", 5, "a._x")]


# -- the client's parts (client/) --------------------------------------------------------


#: What the client core may not import: the relay core's list, less ``threading``
#: (the render keeps per-thread scratch rows, as ``interp`` does: no I/O), plus the
#: client's own adapters.
CLIENT_CORE_FORBIDS = IO_MODULES - {"threading"}
CLIENT_ADAPTERS = ("client.connection", "client.bot", "client.receiver", "client.swarm")


def test_the_client_core_touches_no_clock_file_or_socket() -> None:
    """The client core's modules import nothing that reads a clock or does I/O: the
    bot, the viewer's spectator and the replay bots carry out what they decide."""
    bad = [
        (module, name)
        for module in CLIENT_CORE
        for name in _runtime_imports(
            ast.parse((ROOT / "client" / f"{module.split('.')[1]}.py").read_text())
        )
        if name.split(".")[0] in CLIENT_CORE_FORBIDS or name.startswith(CLIENT_ADAPTERS)
    ]
    assert not bad, bad


def private_imports(paths: list[Path], package: str) -> list[tuple[str, int, str]]:
    """Every ``from <package>.x import _name`` in ``paths``: a private class or
    function of a module used (or subclassed) by another."""
    out = []
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text())):
            if not (isinstance(node, ast.ImportFrom) and node.level == 0 and node.module):
                continue
            if not folder_name(node.module).startswith(package):
                continue
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    out.append((path.name, node.lineno, alias.name))
    return out


def test_no_part_of_the_client_reads_another_parts_private_names() -> None:
    """client/'s modules, and what composes them (posecast/), use each other's public
    names only: no ``x._name`` of another module, no private class imported or
    subclassed (the viewer's spectator is an adapter over the core, not a ``_Bot``)."""
    assert private_reaches(ROOT / "client") == []
    users = sorted((ROOT / "client").glob("*.py")) + sorted((ROOT / "posecast").rglob("*.py"))
    assert private_imports(users, "client") == []


def test_the_private_import_check_finds_one(tmp_path: Path) -> None:
    """The checker sees a private name imported from the client package."""
    probe = tmp_path / "probe.py"
    probe.write_text("from posecast.client.bot import _Bot, Bot\nfrom os import _exit\n")
    assert private_imports([probe], "client") == [("probe.py", 1, "_Bot")]
