"""The docs site's Reference pages are generated from the code and list all of it.

``docs/hooks/reference.py`` writes them at every ``mkdocs build``; these tests call
its functions directly (no mkdocs needed), so a command, a setting, a metric or an
error code the pages would miss fails here.
"""

from __future__ import annotations

import functools
import importlib.util
import re
from pathlib import Path
from types import ModuleType

import typer

ROOT = Path(__file__).resolve().parent.parent


@functools.cache
def _hook() -> ModuleType:
    path = ROOT / "docs" / "hooks" / "reference.py"
    spec = importlib.util.spec_from_file_location("docs_reference", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _commands() -> dict[str, object]:
    from posecast.cli import app

    out: dict[str, object] = {}

    def walk(cmd: object, path: str) -> None:
        out[path] = cmd
        for name, sub in (getattr(cmd, "commands", None) or {}).items():
            walk(sub, f"{path} {name}")

    walk(typer.main.get_command(app), "posecast")
    return out


def test_cli_page_lists_every_command_and_option() -> None:
    """Every command has a heading and every option of it a row in reference/cli.md."""
    page = _hook().cli_page()
    for path, cmd in _commands().items():
        assert f"`{path}`" in page, path
        section = page.split(f"# `{path}`\n", 1)[1].split("\n#", 1)[0]
        for p in getattr(cmd, "params", []):
            if p.name in ("help", "install_completion"):
                continue
            flag = p.opts[0] if p.opts[0].startswith("-") else p.name.upper()
            assert f"`{flag}`" in section, (path, flag)


def test_settings_page_lists_every_posecast_variable() -> None:
    """Every POSECAST_* name the code reads has a row in reference/settings.md."""
    hook = _hook()
    page = hook.settings_page()
    names = hook.settings_in_code()
    assert "POSECAST_PORT" in names and "POSECAST_TRACES" in names
    for name in names:
        assert f"| `{name}` |" in page, name


def test_metrics_page_lists_what_a_relay_serves() -> None:
    """Every family of a real relay's /metrics, and the cluster's, is in reference/metrics.md."""
    from posecast.server.core import RelayCore
    from posecast.server.http import metrics_text

    hook = _hook()
    page = hook.metrics_page()
    served = re.findall(r"^# TYPE (\S+) ", metrics_text(RelayCore(), now=0.0), re.M)
    assert "posecast_tick_lag_seconds" in served
    for name in [*served, "posecast_cluster_nats_up", "posecast_cluster_rooms_owned"]:
        assert f"| `{name}` |" in page, name


def test_errors_page_lists_every_code_with_its_close_code() -> None:
    """Every ErrorCode is a row with its fatal flag, close code and a description."""
    from posecast.protocol.errors import ErrorCode

    page = _hook().errors_page()
    for code in ErrorCode:
        row = next(line for line in page.splitlines() if line.startswith(f"| `{code.value}` |"))
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert cells[1] == ("yes" if code.fatal else "no")
        assert cells[2] == ("" if code.close_code is None else str(code.close_code))
        assert cells[3], code


def test_links_to_moved_pages_and_repository_files_resolve() -> None:
    """A link to a page that moved follows it; one out of docs/ becomes the repository path."""
    fix = _hook().fix_links
    uris = {"protocol.md", "guides/shared-objects.md", "guides/viewer.md", "viewer-live.png"}
    assert fix("[so](shared-objects.md#rules)", "protocol.md", uris) == (
        "[so](guides/shared-objects.md#rules)"
    )
    assert fix("[v](viewer.md)", "guides/security.md", uris) == "[v](viewer.md)"
    assert fix("[`protocol/vectors/`](../protocol/vectors/README.md)", "protocol.md", uris) == (
        "`protocol/vectors/`"
    )
    assert fix("[the vectors](../protocol/vectors/README.md)", "protocol.md", uris) == (
        "the vectors (`protocol/vectors/README.md`)"
    )
    assert fix("![p](../viewer-live.png)", "guides/viewer.md", uris) == "![p](../viewer-live.png)"
    assert fix("[x](https://a.b/c.md)", "protocol.md", uris) == "[x](https://a.b/c.md)"
