"""The container files: compose parses and references what exists.

No Docker engine runs the tests: the compose file is checked as YAML against
what `docker compose up` needs (both services build the one image, the secret
comes from the environment, the bots' default motion is inside the image), and
the Dockerfile and pyproject.toml against what the image must contain.
"""

from __future__ import annotations

import fnmatch
import re
import tomllib
from pathlib import Path
from typing import Any

import typer.main
import yaml
from typer.testing import CliRunner

from posecast.cli import app
from scenarios.traces import SAMPLE_DIR, find_traces

ROOT = Path(__file__).resolve().parent.parent


def _commands() -> set[str]:
    out = CliRunner().invoke(app, ["--help"]).output
    return {c for c in ("serve", "bots", "demo", "token", "compare") if c in out}


def _compose() -> dict[str, Any]:
    data: dict[str, Any] = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    return data


def _default(value: str) -> str:
    """What compose substitutes for ``${NAME:-default}`` when NAME is unset."""
    return re.sub(r"\$\{[A-Z_]+:-([^}]*)\}", r"\1", value)


def test_compose_has_server_and_scalable_bots() -> None:
    """docker-compose.yml defines server and bots services built from our Dockerfile."""
    services = _compose()["services"]
    assert set(services) >= {"server", "bots"}
    assert (ROOT / "Dockerfile").is_file()
    assert services["bots"]["depends_on"]["server"]["condition"] == "service_healthy"
    assert "container_name" not in services["bots"]  # --scale bots=N needs distinct names


def test_both_services_build_the_one_image() -> None:
    """`docker compose up` builds what each service runs; nothing is pulled under our name."""
    services = _compose()["services"]
    for name in ("server", "bots"):
        svc = services[name]
        assert svc["build"] == ".", name
        assert svc.get("pull_policy") == "build", name
    assert services["bots"]["image"] == services["server"]["image"]


def test_compose_commands_are_real_cli_commands() -> None:
    """Each service's command starts with a posecast subcommand that exists."""
    known = _commands()
    for name, svc in _compose()["services"].items():
        cmd = svc["command"]
        assert cmd[0] in known, f"{name}: unknown posecast command {cmd[0]!r}"
    bots = _compose()["services"]["bots"]["command"]
    assert bots[bots.index("--url") + 1] == "ws://server:8765"


def test_the_secret_comes_from_the_environment_only() -> None:
    """No secret in the file: POSECAST_SECRET is passed through, and serve reads it."""
    lines = (ROOT / "docker-compose.yml").read_text().splitlines()
    text = "\n".join(line for line in lines if not line.lstrip().startswith("#"))
    assert "--secret" not in text
    assert not re.search(r"SECRET\s*[:=]", text), "a secret value in the compose file"
    services = _compose()["services"]
    for name in ("server", "bots"):
        env = services[name].get("environment", [])
        # The bare name: compose copies the host's value, or leaves it unset.
        assert "POSECAST_SECRET" in env, name
        for cmd_arg in services[name]["command"]:
            assert "secret" not in str(cmd_arg).lower(), name
    serve: Any = typer.main.get_command(app).commands["serve"]  # type: ignore[attr-defined]
    assert {p.name: p.envvar for p in serve.params}["secret"] == "POSECAST_SECRET"


def test_bots_default_to_the_bundled_sample() -> None:
    """Unset MOTION means traces:sample, which the package carries (no mount needed)."""
    bots = _compose()["services"]["bots"]
    cmd = bots["command"]
    motion = cmd[cmd.index("--motion") + 1]
    assert "${MOTION:-" in motion, "MOTION must stay overridable"
    assert _default(motion) == "traces:sample"
    assert find_traces("traces:sample")
    assert all(p.parent == SAMPLE_DIR for p in find_traces("traces:sample"))


def test_the_full_traces_mount_is_optional() -> None:
    """The traces volume falls back to a folder that exists, read-only, where the image looks."""
    (volume,) = _compose()["services"]["bots"]["volumes"]
    source, target, mode = _default(volume).split(":")
    assert "${POSECAST_TRACES:-" in volume
    assert (ROOT / source).resolve() == SAMPLE_DIR
    assert mode == "ro"
    assert f"ENV POSECAST_TRACES={target}" in (ROOT / "Dockerfile").read_text()


def test_dockerfile_copies_every_package() -> None:
    """The image installs every top-level package and runs the posecast CLI."""
    text = (ROOT / "Dockerfile").read_text()
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    packages = pyproject["tool"]["setuptools"]["packages"]
    for pkg in sorted({p.split(".")[0] for p in packages}):
        assert f"COPY {pkg} ./{pkg}" in text, pkg
    assert 'ENTRYPOINT ["posecast"]' in text
    assert "pip install ." in text


def test_dockerfile_copies_the_files_pyproject_names() -> None:
    """README (readme) and the license files must be in the build context of `pip install .`."""
    text = (ROOT / "Dockerfile").read_text()
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    copied = set()
    for line in text.splitlines():
        if line.startswith("COPY "):
            copied.update(line.split()[1:-1])
    needed = {project["readme"], *project.get("license-files", [])}
    assert needed <= copied, needed - copied
    for name in needed:
        assert (ROOT / name).is_file(), name


def _ignored(rel: str) -> bool:
    patterns = [
        line.strip()
        for line in (ROOT / ".dockerignore").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    ignored = False
    for pattern in patterns:
        negate = pattern.startswith("!")
        pat = pattern.lstrip("!").rstrip("/")
        parts = Path(rel).parts
        prefixes = ["/".join(parts[: i + 1]) for i in range(len(parts))]
        pats = (pat, pat.replace("**/", ""))
        if any(fnmatch.fnmatch(p, q) for p in prefixes for q in pats):
            ignored = not negate
    return ignored


def test_the_bundled_traces_reach_the_image_and_the_wheel() -> None:
    """scenarios/data/traces is neither docker-ignored nor left out of the package data."""
    files = sorted(SAMPLE_DIR.glob("*.csv.gz"))
    assert files
    globs = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"
    ]["scenarios"]
    for path in files:
        rel = path.relative_to(ROOT).as_posix()
        assert not _ignored(rel), f".dockerignore drops {rel}"
        in_package = path.relative_to(ROOT / "scenarios").as_posix()
        assert any(fnmatch.fnmatch(in_package, g) for g in globs), f"not package data: {rel}"
    assert _ignored("tests/test_deploy.py")  # the checker itself sees .dockerignore
