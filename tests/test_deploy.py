"""The container files: compose parses and references what exists.

No Docker engine runs the tests: the compose file is checked as YAML against
what `docker compose up` needs (both services build the one image, the secret
comes from the environment, the bots' default motion is inside the image), and
the Dockerfile and pyproject.toml against what the image must contain. The
cluster (profile ``cluster``: NATS, scalable relays, bots that list them) is
checked the same way, and plain `docker compose up` must start exactly the
single server and its bots, as before.
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
from posecast.client.connection import relay_urls
from posecast.scenarios.traces import SAMPLE_DIR, find_traces

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


def _ours() -> dict[str, dict[str, Any]]:
    """The services that run our image (the others, like nats, run someone else's)."""
    services: dict[str, dict[str, Any]] = _compose()["services"]
    return {name: svc for name, svc in services.items() if svc.get("build") == "."}


def test_compose_commands_are_real_cli_commands() -> None:
    """Each of our services' command starts with a posecast subcommand that exists."""
    known = _commands()
    for name, svc in _ours().items():
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
    assert set(_ours()) == {"server", "bots", "relay", "cluster-bots"}
    for name in _ours():
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
    folders = pyproject["tool"]["setuptools"]["package-dir"].values()
    for pkg in sorted({"posecast", *folders}):
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
    """scenarios/data/traces (the sample, dev/ and eval/) is neither docker-ignored nor left
    out of the package data."""
    files = sorted(SAMPLE_DIR.rglob("*.csv.gz"))
    assert len(files) == 4 + 7 + 5
    globs = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
        "package-data"
    ]
    for path in files:
        rel = path.relative_to(ROOT).as_posix()
        assert not _ignored(rel), f".dockerignore drops {rel}"
        package = ".".join(("posecast", *path.parent.relative_to(ROOT).parts))
        assert any(fnmatch.fnmatch(path.name, g) for g in globs.get(package, [])), rel
    assert _ignored("tests/test_deploy.py")  # the checker itself sees .dockerignore


# -- the cluster -----------------------------------------------------------------------


def _option(cmd: list[str], flag: str) -> str:
    return cmd[cmd.index(flag) + 1]


def test_plain_up_starts_exactly_the_single_server_and_its_bots() -> None:
    """Only server and bots have no profile; the cluster's services are all in `cluster`."""
    services = _compose()["services"]
    plain = {name for name, svc in services.items() if not svc.get("profiles")}
    assert plain == {"server", "bots"}
    assert {name for name in services if name not in plain} == {"nats", "relay", "cluster-bots"}
    for name in ("nats", "relay", "cluster-bots"):
        assert services[name]["profiles"] == ["cluster"], name


def test_every_flag_in_a_command_is_an_option_of_it() -> None:
    """The compose commands use flags the CLI has (serve --cluster included), no typos."""
    commands: Any = typer.main.get_command(app).commands  # type: ignore[attr-defined]
    for name, svc in _ours().items():
        cmd = svc["command"]
        options = {opt for p in commands[cmd[0]].params for opt in p.opts}
        for arg in cmd[1:]:
            if str(arg).startswith("--"):
                assert arg in options, f"{name}: {cmd[0]} has no {arg}"


def test_nats_runs_jetstream_of_2_11_or_newer() -> None:
    """The cluster's directory needs JetStream KV with per-message TTL: NATS >= 2.11, -js."""
    nats = _compose()["services"]["nats"]
    image, _, tag = nats["image"].partition(":")
    assert image == "nats"
    found = re.match(r"(\d+)\.(\d+)", tag)
    assert found, tag
    assert (int(found.group(1)), int(found.group(2))) >= (2, 11), tag
    assert "-js" in nats["command"]
    assert nats["healthcheck"]["test"][0] == "CMD"


def test_relays_form_a_cluster_and_scale() -> None:
    """relay serves on 8765 in the cluster of the nats service, with nothing that would
    stop --scale relay=3: no container name, no fixed host port."""
    services = _compose()["services"]
    relay, server = services["relay"], services["server"]
    cmd = relay["command"]
    assert cmd[0] == "serve"
    assert (_option(cmd, "--host"), _option(cmd, "--port")) == ("0.0.0.0", "8765")
    cluster = _option(cmd, "--cluster")
    assert cluster == "nats://nats:4222"  # the nats service, its client port
    assert "--node" not in cmd  # each replica is named after its host name
    assert "container_name" not in relay
    for port in relay.get("ports", []):
        assert ":" not in str(port), f"a fixed host port stops --scale: {port}"
    assert relay["depends_on"]["nats"]["condition"] == "service_healthy"
    assert relay["healthcheck"] == server["healthcheck"]
    assert relay["image"] == server["image"] and relay["pull_policy"] == "build"
    assert relay["deploy"]["replicas"] >= 2


def test_cluster_bots_list_the_relays_by_replica_name() -> None:
    """cluster-bots' --url (unless RELAYS is set) is a list the CLI accepts, of the
    replicas' container names (project name, service, index) on the relays' port."""
    compose = _compose()
    services = compose["services"]
    bots = services["cluster-bots"]
    cmd = bots["command"]
    assert cmd[0] == "bots"
    url = _option(cmd, "--url")
    assert url.startswith("${RELAYS:-")
    urls = relay_urls(_default(url))
    port = _option(services["relay"]["command"], "--port")
    assert urls == tuple(
        f"ws://{compose['name']}-relay-{k}:{port}" for k in range(1, len(urls) + 1)
    )
    assert len(urls) >= services["relay"]["deploy"]["replicas"]
    assert bots["depends_on"]["relay"]["condition"] == "service_healthy"
    assert "container_name" not in bots
    assert _default(_option(cmd, "--motion")) == "traces:sample"
    assert bots["volumes"] == services["bots"]["volumes"]
