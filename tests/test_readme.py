"""The README stays a short front page whose links and promised commands work."""

from __future__ import annotations

import re
from pathlib import Path

import typer

ROOT = Path(__file__).resolve().parent.parent
README = (ROOT / "README.md").read_text(encoding="utf-8")


def test_readme_is_short() -> None:
    """Under 200 lines: what it is, two commands, the demo's table, links into the docs,
    and the whole WebXR app of "Connect your app" (about 45 lines, issue 26)."""
    assert README.count("\n") < 200


def test_readme_links_resolve() -> None:
    """Every relative link and image of the README names a file of the repository."""
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", README)
    assert targets
    for target in targets:
        if "://" not in target:
            assert (ROOT / target).exists(), target


def test_readme_commands_exist() -> None:
    """Every `posecast X --flag` the README shows is a command and option of the CLI."""
    from posecast.cli import app

    root = typer.main.get_command(app)
    shown = re.findall(r"^ {4}posecast ([a-z0-9-]+)([^\n#]*)", README, re.M)
    assert shown
    for name, rest in shown:
        cmd = root.commands[name]  # type: ignore[attr-defined]
        opts = {o for p in cmd.params for o in (*p.opts, *getattr(p, "secondary_opts", []))}
        for flag in re.findall(r"(--[a-z0-9-]+)", rest):
            assert flag in opts, f"posecast {name} {flag}"


def test_readme_make_targets_exist() -> None:
    """Every `make X` of the README is a target of the Makefile."""
    makefile = (ROOT / "Makefile").read_text(encoding="utf-8")
    for target in set(re.findall(r"make ([a-z]+)", README)):
        assert re.search(rf"^{target}:", makefile, re.M), target
