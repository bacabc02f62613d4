"""Guards on how our modules tie together, read from the source (ast, nothing imported).

No import cycles between modules, within a package or across ours. Every import
counts: at module level, under ``if TYPE_CHECKING:`` and inside a function -- a
deferred or type-only import hides a cycle from the interpreter, not from the
reader, who still cannot understand one module without the other.

The cycles that exist today are listed in :data:`ALLOWED_CYCLES`, each by its
modules. The list only shrinks: a new cycle, or a module joining a listed one,
fails; a listed cycle that got smaller or went away fails too, until its entry
is cut to what is left (so the list always says what remains to untie).

And the tests themselves: real sleeps stay within :data:`SLEEP_BUDGET`.
"""

from __future__ import annotations

import ast
import functools
import re
from collections.abc import Iterator, Mapping
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("posecast", "server", "client", "protocol", "interp", "recorder", "scenarios")

#: The cycles of issue 27 still to untie, each as the set of modules it binds: none
#: left (the relay core and its parts see it through server.ports; server.rates
#: takes its rooms, members and peers as Protocols).
ALLOWED_CYCLES: tuple[frozenset[str], ...] = ()


def module_files() -> dict[str, Path]:
    """Installed module name -> source file (``server/core.py`` is ``posecast.server.core``).
    A compiled module counts by its stub (``protocol/_speedups.pyi``): importing it from
    its package (``from posecast.protocol import _speedups``) is no import of the package."""
    out = {}
    for package in PACKAGES:
        stubs = [p for p in (ROOT / package).rglob("*.pyi") if not p.with_suffix(".py").exists()]
        for path in [*(ROOT / package).rglob("*.py"), *stubs]:
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            if parts[0] != "posecast":
                parts.insert(0, "posecast")
            out[".".join(parts)] = path
    return out


def imported(module: str, path: Path, modules: Mapping[str, Path]) -> Iterator[str]:
    """The modules of ours that ``module`` imports anywhere in its file.
    ``from a.b import c`` imports ``a.b.c`` when that is a module, else ``a.b``."""
    is_package = path.name == "__init__.py"
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            yield from (a.name for a in node.names if a.name in modules)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")[: None if is_package else -1]
                base = base[: len(base) - node.level + 1]
                source = ".".join([*base, *([node.module] if node.module else [])])
            else:
                source = node.module or ""
            for alias in node.names:
                name = f"{source}.{alias.name}"
                target = name if name in modules else source
                if target in modules and target != module:
                    yield target


@functools.cache
def import_graph() -> dict[str, set[str]]:
    """Module -> the modules of ours it imports; built once per process (three tests
    read it, none changes it)."""
    modules = module_files()
    return {m: set(imported(m, p, modules)) for m, p in modules.items()}


def cycles(graph: Mapping[str, set[str]]) -> list[frozenset[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[frozenset[str]] = []
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in index:
                    index[child] = low[child] = len(index)
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(graph.get(child, ())))))
                elif child in on_stack:
                    low[v] = min(low[v], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                component = set()
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.add(w)
                    if w == v:
                        break
                if len(component) > 1:
                    found.append(frozenset(component))
    return found


def test_no_new_import_cycle() -> None:
    """Every cycle among our modules is one of ALLOWED_CYCLES (or part of one)."""
    new = [sorted(c) for c in cycles(import_graph()) if not any(c <= a for a in ALLOWED_CYCLES)]
    assert not new, f"import cycles not in ALLOWED_CYCLES: {new}"


def test_allowed_cycles_only_shrink() -> None:
    """Each ALLOWED_CYCLES entry is exactly a cycle that still exists: when one is
    untied (fully or partly), its entry is cut to what remains or removed."""
    now = set(cycles(import_graph()))
    stale = [sorted(a) for a in ALLOWED_CYCLES if a not in now]
    assert not stale, f"ALLOWED_CYCLES entries that changed; now {[sorted(c) for c in now]}"


def test_the_cycle_finder_sees_cycles(tmp_path: Path) -> None:
    """Deferred, type-only and relative imports all count; a chain is no cycle."""
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert cycles(graph) == [frozenset({"a", "b", "c"})]
    assert cycles({"a": {"b"}, "b": set()}) == []
    pkg = tmp_path / "recorder"
    pkg.mkdir()
    f = pkg / "x.py"
    f.write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from .y import Y\n"
        "def g():\n    from posecast.recorder import z\n"
        "from posecast.recorder.w import W\n"
    )
    modules = {f"posecast.recorder.{n}": f for n in "xyzw"}
    found = set(imported("posecast.recorder.x", f, modules))
    assert found == {"posecast.recorder.y", "posecast.recorder.z", "posecast.recorder.w"}


def test_the_graph_covers_every_package() -> None:
    """The graph holds every package's modules and their imports of each other."""
    graph = import_graph()
    assert {m.split(".")[1] for m in graph if m.count(".")} >= set(PACKAGES[1:])
    assert "posecast.protocol" in graph["posecast.server.core"] or any(
        t.startswith("posecast.protocol.") for t in graph["posecast.server.core"]
    )


# -- real sleeps in the tests ----------------------------------------------------------------

#: At most this many real sleeps in the suite (issue 27). A real sleep is a call to
#: ``asyncio.sleep`` or ``time.sleep`` whose argument is not a literal 0 (a bare yield
#: to the loop); each place in the source counts once, also inside a child process's
#: script held in a string. A test that needs "later" waits for an observable
#: condition through support.poll_until / wait_until, or paces a source with
#: support.Pacer, or takes an injected clock.
SLEEP_BUDGET = 10
#: No literal sleep longer than this (seconds).
LONGEST_SLEEP = 0.5
#: Stand-alone tools kept beside the tests they feed, which pytest never runs (their
#: use is in docs/guides/viewer.md): not part of the suite's budget.
TOOLS = frozenset({"make_screenshots.py", "measure_view.py"})
SLEEP = re.compile(r"\b(?:asyncio|time)\.sleep\(")


def real_sleeps(text: str) -> list[tuple[int, str]]:
    """(line, argument) of each real sleep in ``text``; comment lines do not count."""
    found = []
    for n, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith("#"):
            continue
        for m in SLEEP.finditer(line):
            depth, end = 1, m.end()
            while end < len(line) and depth:
                depth += {"(": 1, ")": -1}.get(line[end], 0)
                end += 1
            arg = line[m.end() : end - 1].strip()
            if not re.fullmatch(r"0(?:\.0*)?", arg):
                found.append((n, arg))
    return found


def suite_sleeps() -> list[tuple[str, int, str]]:
    here = Path(__file__).resolve().parent
    return [
        (str(path.relative_to(here)), n, arg)
        for path in sorted(here.rglob("*.py"))
        if path.name not in TOOLS
        for n, arg in real_sleeps(path.read_text())
    ]


def test_real_sleeps_within_budget() -> None:
    """The suite sleeps for real in at most SLEEP_BUDGET places, none over LONGEST_SLEEP."""
    sleeps = suite_sleeps()
    where = "\n".join(f"{p}:{n}: sleep({a})" for p, n, a in sleeps)
    assert len(sleeps) <= SLEEP_BUDGET, f"{len(sleeps)} real sleeps:\n{where}"
    long = [s for s in sleeps if re.fullmatch(r"[\d.]+", s[2]) and float(s[2]) > LONGEST_SLEEP]
    assert not long, f"sleeps over {LONGEST_SLEEP} s: {long}"


def test_the_sleep_counter_sees_sleeps() -> None:
    """Literal, computed and in-string sleeps count; sleep(0) and comments do not."""
    lines = [
        "await asyncio.nap(0)",
        "await asyncio.nap(0.0)",
        "await asyncio.nap(0.25)",
        "time.nap(max(0.0, due - clock()))",
        "# time.nap(3)",
        'SCRIPT = "time.nap(0.01)"',
        "await asyncio.nap(every)",
    ]
    text = "\n".join(lines).replace(".nap(", ".sleep(")  # not counted in this file
    assert real_sleeps(text) == [
        (3, "0.25"),
        (4, "max(0.0, due - clock())"),
        (6, "0.01"),
        (7, "every"),
    ]


def test_test_file_names_are_unique() -> None:
    """No two test files share a name: tests import their siblings by module name
    (``from test_core import connect``), so a second ``test_core.py`` elsewhere
    breaks the collection of every file that imports the first."""
    names: dict[str, list[str]] = {}
    for path in sorted(Path(__file__).parent.rglob("test_*.py")):
        names.setdefault(path.name, []).append(str(path))
    assert not {n: p for n, p in names.items() if len(p) > 1}
