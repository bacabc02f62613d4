"""Shared fixtures: paths to the real traces.

Tests read the bundled excerpt (``traces:sample``: the first 60 s of four real
``dev`` recordings), which keeps them quick. Tests that need the full sets ask for
``trace_root``: the sets bundled in the package (or ``POSECAST_TRACES``); it skips
them, with the reason, only when an install left them out.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import settings
from support import CliForker

from posecast.scenarios.traces import SAMPLE_DIR, default_trace_root, full_traces_available

# CI runs the same examples every time (no flaky reds from a lucky draw); local
# runs keep exploring.
settings.register_profile("ci", derandomize=True, database=None)
if os.environ.get("CI"):
    settings.load_profile("ci")


@pytest.fixture(scope="session")
def cli() -> Iterator[CliForker]:
    """``posecast ARGS`` in a child process each, forked from one process per worker that
    imported the CLI once (:class:`support.CliForker`): for the cases that check what a
    command prints and exits with, without an interpreter start each."""
    with CliForker({k: v for k, v in os.environ.items() if not k.startswith("POSECAST_")}) as f:
        yield f


@pytest.fixture(scope="session")
def trace_root() -> Path:
    """The full vr-traces folder (``dev/`` and ``eval/``); skips the test without it."""
    root = default_trace_root()
    if not (full_traces_available("dev") and full_traces_available("eval")):
        pytest.skip(f"needs the full vr-traces sets (not at {root}): set POSECAST_TRACES")
    return root


@pytest.fixture(scope="session")
def sample_dir() -> Path:
    """The bundled excerpt of the real traces (``traces:sample``)."""
    return SAMPLE_DIR


@pytest.fixture(scope="session")
def dev_trace_path(sample_dir: Path) -> Path:
    """S02 (Rift S, Expert+): the first 60 s of the dev recording, bit for bit."""
    return sample_dir / "S02_riftS_expertplus.csv.gz"


#: Fixtures of tests that build client/js (npm ci, esbuild into its folders) or run
#: Chromium: under pytest-xdist (``make test``) they share one worker, so no two
#: builds write the same node_modules and no two browsers compete for the CPU.
_ONE_WORKER = frozenset({"node", "web_port", "browser", "chromium_path", "page"})

#: The groups that take longest (minutes of real runs each): first in the queue, so
#: that the two workers start on them and the suite ends on short tests.
_FIRST = ("bench-hostile", "node-and-chromium")

_SHARED_SCOPES = frozenset({"module", "class", "package"})


def _group(item: pytest.Item) -> str | None:
    mark = item.get_closest_marker("xdist_group")
    return None if mark is None else str(mark.args[0] if mark.args else mark.kwargs["name"])


def _shares_a_fixture(item: pytest.Item) -> bool:
    """Whether ``item`` uses a module-, class- or package-scoped fixture (a real run, a
    relay, a built report shared by the module's tests)."""
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return False
    return any(d.scope in _SHARED_SCOPES for defs in info.name2fixturedefs.values() for d in defs)


# First: pytest-xdist reads the groups in its own hook of this name, which would
# otherwise run before this one and see no marks.
@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Groups for pytest-xdist's ``--dist loadgroup``: the JS/Chromium tests on one
    worker; the tests of a module that share a module-scoped fixture on one worker too
    (split over two, each would build the fixture: a 10 s real run twice); the longest
    groups first."""
    for item in items:
        if _group(item) is not None:
            continue
        if _ONE_WORKER & set(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.xdist_group("node-and-chromium"))
        elif _shares_a_fixture(item):
            item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::")[0]))
    rank = {name: i for i, name in enumerate(_FIRST)}
    items.sort(key=lambda item: rank.get(_group(item) or "", len(rank)))
