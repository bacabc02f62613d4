"""The container files: compose parses and references what exists."""

from __future__ import annotations

from pathlib import Path

import yaml
from typer.testing import CliRunner

from server.cli import app

ROOT = Path(__file__).resolve().parent.parent


def _commands() -> set[str]:
    out = CliRunner().invoke(app, ["--help"]).output
    return {c for c in ("serve", "bots", "demo", "token", "compare") if c in out}


def test_compose_has_server_and_scalable_bots() -> None:
    """docker-compose.yml defines server and bots services built from our Dockerfile."""
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    services = compose["services"]
    assert set(services) >= {"server", "bots"}
    assert services["server"]["build"] == "."
    assert (ROOT / "Dockerfile").is_file()
    assert services["bots"]["image"] == services["server"]["image"]
    assert services["bots"]["depends_on"]["server"]["condition"] == "service_healthy"


def test_compose_commands_are_real_cli_commands() -> None:
    """Each service's command starts with a posecast subcommand that exists."""
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    known = _commands()
    for name, svc in compose["services"].items():
        cmd = svc["command"]
        assert cmd[0] in known, f"{name}: unknown posecast command {cmd[0]!r}"
    bots = compose["services"]["bots"]["command"]
    assert bots[bots.index("--url") + 1] == "ws://server:8765"


def test_dockerfile_copies_every_package() -> None:
    """The image installs every top-level package and runs the posecast CLI."""
    text = (ROOT / "Dockerfile").read_text()
    for pkg in ("protocol", "interp", "recorder", "scenarios", "client", "server"):
        assert f"COPY {pkg} ./{pkg}" in text
    assert 'ENTRYPOINT ["posecast"]' in text
