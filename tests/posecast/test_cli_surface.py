"""The CLI's surface (commands, their parameters and flags) is what cli_surface.json says.

The JSON was recorded from the CLI before it moved into ``posecast/``; a command
or flag added, renamed or removed fails here until the JSON is updated on
purpose (regenerate it with ``python tests/posecast/test_cli_surface.py``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import typer

SURFACE = Path(__file__).with_name("cli_surface.json")


def _walk(cmd: Any, path: list[str], out: dict[str, list[dict[str, Any]]]) -> None:
    out[" ".join(path)] = [
        {
            "name": p.name,
            "opts": list(p.opts),
            "secondary_opts": list(getattr(p, "secondary_opts", [])),
        }
        for p in cmd.params
    ]
    for name in sorted(getattr(cmd, "commands", None) or {}):
        _walk(cmd.commands[name], [*path, name], out)


def cli_surface() -> dict[str, list[dict[str, Any]]]:
    """``{"posecast bench relay": [{"name", "opts", "secondary_opts"}, ...], ...}``."""
    from posecast.cli import app

    out: dict[str, list[dict[str, Any]]] = {}
    _walk(typer.main.get_command(app), ["posecast"], out)
    return out


def test_cli_surface_matches_the_recorded_one() -> None:
    assert cli_surface() == json.loads(SURFACE.read_text())


if __name__ == "__main__":
    SURFACE.write_text(json.dumps(cli_surface(), indent=1, sort_keys=True) + "\n")
