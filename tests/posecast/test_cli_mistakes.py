"""Every user mistake ends in one line on stderr and exit code 2 (usage) or 1 (run time).

Each case runs ``posecast`` in a process of its own, so what is checked is what
a user sees: the exit code, one or two lines on stderr (the last one ``error:
...`` naming the problem), and never a traceback. The processes are forked from
one that imported the CLI once (``support.CliForker``: an interpreter start and
the CLI's imports were most of each case's CPU); the relay the bots' cases talk
to is the real executable.
"""

from __future__ import annotations

import atexit
import json
import os
import selectors
import shutil
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest
from support import CliForker

from posecast.client.connection import JoinRefused
from posecast.protocol import PosecastError, ProtocolViolation
from posecast.recorder import FormatError, RecorderError, RecoveryError
from posecast.scenarios.network import TierError
from posecast.server.auth import TokenError, verify_token

_EXE = Path(sys.executable).with_name("posecast")
_COMMAND = [str(_EXE)] if _EXE.exists() else [sys.executable, "-m", "posecast.cli"]
_ROOT = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class Run:
    code: int
    stdout: str
    stderr: str

    @property
    def lines(self) -> list[str]:
        return [line for line in self.stderr.splitlines() if line.strip()]


def _env(**extra: str) -> dict[str, str]:
    """The test's environment without any POSECAST_* setting of the caller, plus ``extra``."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("POSECAST_")}
    env.update(extra)
    return env


@pytest.fixture(scope="module", autouse=True)
def _forker(cli: CliForker) -> Iterator[None]:
    """The worker's CLI forker (conftest ``cli``), for :func:`posecast`."""
    global _FORKER
    _FORKER = cli
    yield
    _FORKER = None


_FORKER: CliForker | None = None


def posecast(*args: str | Path, cwd: Path | None = None, **env: str) -> Run:
    """Run ``posecast ARGS`` in a child process of its own; the limit is a hang guard.
    Another module importing this (test_export_cli) has no ``_forker`` fixture: its
    first call starts a forker of its own, closed when the process exits."""
    global _FORKER
    if _FORKER is None:
        _FORKER = CliForker(_env())
        atexit.register(_FORKER.close)
    return Run(*_FORKER.run([*map(str, args)], _env(**env), cwd, limit=120))


def assert_one_line(res: Run, code: int, *words: str) -> str:
    """Exit ``code``, 1-2 lines on stderr, the last ``error: ...`` with ``words``; no traceback."""
    assert "Traceback" not in res.stderr + res.stdout, res.stderr
    assert res.code == code, (res.code, res.stderr)
    assert 1 <= len(res.lines) <= 2, res.stderr
    line = res.lines[-1]
    assert line.startswith("error: "), res.stderr
    for word in words:
        assert word in line, (word, line)
    return line


# -- the exception root -------------------------------------------------------------


@pytest.mark.parametrize(
    ("family", "other"),
    [
        (ProtocolViolation, Exception),
        (TokenError, ValueError),
        (JoinRefused, RuntimeError),
        (RecoveryError, RuntimeError),
        (RecorderError, RuntimeError),
        (FormatError, ValueError),
        (TierError, ValueError),
    ],
)
def test_error_families_share_one_root(family: type[Exception], other: type[Exception]) -> None:
    """Every user-facing family is a PosecastError and keeps the base it had."""
    assert issubclass(family, PosecastError)
    assert issubclass(family, other)


# -- serve ---------------------------------------------------------------------------


def test_serve_on_a_taken_port_fails_in_one_line() -> None:
    """A port another socket listens on: exit 1, naming the address, no traceback."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        res = posecast("serve", "--host", "127.0.0.1", "--port", str(port))
    assert_one_line(res, 1, f"127.0.0.1:{port}", "in use", "--port")


def test_serve_refuses_a_port_out_of_range() -> None:
    """--port 99999 is refused (not wrapped to another port), and so is POSECAST_PORT."""
    assert_one_line(posecast("serve", "--port", "99999"), 2, "0..65535", "99999")
    assert_one_line(posecast("serve", POSECAST_PORT="70000"), 2, "0..65535", "70000")


def test_serve_refuses_a_malformed_allow_origin() -> None:
    """--allow-origin (or POSECAST_ALLOW_ORIGIN) with a bare host name says how to write one."""
    for res in (
        posecast("serve", "--port", "0", "--allow-origin", "app.example.com"),
        posecast("serve", "--port", "0", POSECAST_ALLOW_ORIGIN="https://a.example,junk"),
    ):
        assert_one_line(res, 2, "--allow-origin", "scheme://host[:port]")
    assert_one_line(posecast("serve", "--stall-after", "-1"), 2, "--stall-after", "negative")


def test_serve_refuses_a_file_as_the_recording_folder(tmp_path: Path) -> None:
    """--record FILE where FILE is a regular file: exit 2 before anything starts."""
    target = tmp_path / "notes.txt"
    target.write_text("keep me\n")
    assert_one_line(posecast("serve", "--port", "0", "--record", target), 2, str(target), "folder")
    assert target.read_text() == "keep me\n"


def test_serve_names_the_log_levels() -> None:
    """An unknown --log-level (or POSECAST_LOG_LEVEL) lists the allowed ones."""
    for res in (
        posecast("serve", "--port", "0", "--log-level", "loud"),
        posecast("serve", "--port", "0", POSECAST_LOG_LEVEL="loud"),
    ):
        assert_one_line(res, 2, "loud", "debug", "info", "warning", "error")


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("this is not toml [", "not valid TOML"),
        ("[tier.fast]\nbandwidth_kbps = 'lots'\n", "must be a number"),
        ("[tier.good]\nspeed = 3\n", "unknown field"),
        ("[tier.new]\nbandwidth_kbps = 100\n", "new tier needs"),
    ],
)
def test_serve_names_the_malformed_tiers_file(tmp_path: Path, text: str, problem: str) -> None:
    """A malformed --tiers file: one line naming the file and the problem, even without --link."""
    tiers = tmp_path / "tiers.toml"
    tiers.write_text(text)
    assert_one_line(posecast("serve", "--port", "0", "--tiers", tiers), 2, str(tiers), problem)


def test_serve_takes_the_secret_once(tmp_path: Path) -> None:
    """--secret with --secret-file is a usage mistake; so is an empty or missing secret file."""
    secret_file = tmp_path / "secret"
    secret_file.write_text("s3cret\n")
    res = posecast("serve", "--port", "0", "--secret", "x", "--secret-file", secret_file)
    assert_one_line(res, 2, "--secret", "--secret-file", "not both")
    empty = tmp_path / "empty"
    empty.write_text("\n")
    assert_one_line(posecast("serve", "--port", "0", "--secret-file", empty), 2, str(empty))
    missing = tmp_path / "missing"
    assert_one_line(posecast("serve", "--port", "0", "--secret-file", missing), 2, str(missing))


# -- token ---------------------------------------------------------------------------


def test_token_reads_the_secret_from_a_file_or_the_environment(tmp_path: Path) -> None:
    """posecast token takes --secret-file or POSECAST_SECRET; the token verifies."""
    import time

    secret_file = tmp_path / "secret"
    secret_file.write_text("  s3cret  \nignored second line\n")
    for res in (
        posecast("token", "--room", "lab", "--user", "ann", "--secret-file", secret_file),
        posecast("token", "--room", "lab", "--user", "ann", POSECAST_SECRET="s3cret"),
    ):
        assert res.code == 0, res.stderr
        claims = verify_token("s3cret", res.stdout.strip(), "lab", time.time())
        assert claims.user == "ann"
    # An option on the command line wins over the other one's environment variable.
    res = posecast(
        "token", "--room", "lab", "--user", "ann", "--secret-file", secret_file, POSECAST_SECRET="x"
    )
    assert res.code == 0, res.stderr
    verify_token("s3cret", res.stdout.strip(), "lab", time.time())
    assert_one_line(posecast("token", "--room", "lab", "--user", "ann"), 2, "--secret-file")
    res = posecast(
        "token", "--room", "l", "--user", "u", "--secret", "a", "--secret-file", secret_file
    )
    assert_one_line(res, 2, "not both")


# -- rates: bots against a server, and the demo --------------------------------------


@pytest.fixture(scope="module")
def relay(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """A real ``posecast serve`` configured from the environment (port 0, rates 5-30 Hz,
    the secret from a file); yields its URL."""
    secret_file = tmp_path_factory.mktemp("relay") / "secret"
    secret_file.write_text("s3cret\n")
    proc = subprocess.Popen(
        [*_COMMAND, "serve"],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
        env=_env(
            POSECAST_PORT="0",
            POSECAST_MIN_RATE="5",
            POSECAST_MAX_RATE="30",
            POSECAST_SECRET_FILE=str(secret_file),
        ),
    )
    assert proc.stdout is not None
    try:
        with selectors.DefaultSelector() as sel:
            sel.register(proc.stdout, selectors.EVENT_READ)
            assert sel.select(timeout=60), "posecast serve did not start"  # hang guard
        line = proc.stdout.readline()
        assert "posecast listening on ws://" in line and "token required" in line, line
        yield line.split()[3]
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        proc.stdout.close()


@pytest.mark.parametrize("rate", ["500", "3"])
def test_bots_say_the_servers_rate_range(relay: str, rate: str) -> None:
    """A bad-rate refusal becomes one line with the server's 5-30 Hz range, exit 2."""
    res = posecast(
        "bots",
        "--url",
        relay,
        "--n",
        "2",
        "--rate",
        rate,
        "--duration",
        "1",
        "--motion",
        "synthetic",
        "--secret",
        "s3cret",
    )
    assert_one_line(res, 2, "bad-rate", f"{rate} Hz", "5-30 Hz")


def _bots(relay: str, *args: str | Path, secret: str | None = None) -> Run:
    """Two short synthetic bots against ``relay``; ``secret``: their POSECAST_SECRET."""
    common = ("--url", relay, "--n", "2", "--duration", "2", "--motion", "synthetic")
    if secret is None:
        return posecast("bots", *common, *args)
    return posecast("bots", *common, *args, POSECAST_SECRET=secret)


def test_bots_take_the_secret_from_the_environment(relay: str, tmp_path: Path) -> None:
    """POSECAST_SECRET (kept out of ps) lets the bots mint tokens the secret relay admits."""
    report = tmp_path / "bots.json"
    res = _bots(relay, "--json", report, secret="s3cret")
    assert res.code == 0, res.stderr
    assert "Traceback" not in res.stderr + res.stdout, res.stderr
    data = json.loads(report.read_text())
    assert len(data["bots"]) == 2
    assert data["ending"]["complete"], data["ending"]
    assert all(b["frames_rendered"] > 0 for b in data["bots"]), data["bots"]
    # The same relay refuses the bots a wrong secret from the environment.
    assert_one_line(_bots(relay, secret="wrong"), 1, "join refused", "unauthorized")


def test_bots_take_the_secret_once(relay: str, tmp_path: Path) -> None:
    """--secret with --secret-file is a usage mistake; an explicit --token beats the env."""
    secret_file = tmp_path / "secret"
    secret_file.write_text("s3cret\n")
    res = _bots(relay, "--secret", "s3cret", "--secret-file", secret_file)
    assert_one_line(res, 2, "--secret", "--secret-file", "not both")
    # The bad --token given on the command line is used, not POSECAST_SECRET: refused.
    res = _bots(relay, "--token", "not-a-token", "--n", "1", secret="s3cret")
    assert_one_line(res, 1, "join refused", "malformed access token")
    # One token is one user, and a user has one connection per room.
    res = _bots(relay, "--token", "not-a-token", secret="s3cret")
    assert_one_line(res, 2, "--token names one user", "--secret")


def test_demo_checks_the_rate_before_starting(tmp_path: Path) -> None:
    """demo --rate 500: refused with its server's range before any server or bot starts."""
    res = posecast("demo", "--rate", "500", "--duration", "1", "--bots", "1", cwd=tmp_path)
    assert_one_line(res, 2, "--rate 500", "5-30 Hz")
    assert not any(tmp_path.iterdir())  # no recordings folder


# -- recording commands given something that is not a recording -------------------------


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small real recording (2 users, 1 s)."""
    from posecast.recorder.replay import synthesize_recording

    return synthesize_recording(tmp_path_factory.mktemp("rec"), users=2, rate=30.0, duration=1.0)


@pytest.fixture(scope="module")
def foxglove(recording: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``posecast export REC --to foxglove`` of the recording."""
    out = tmp_path_factory.mktemp("fox") / "session-foxglove.mcap"
    res = posecast("export", recording, "--to", "foxglove", "--out", out)
    assert res.code == 0, res.stderr
    return out


_COMMANDS = {
    "info": ("info",),
    "recover": ("recover",),
    "replay": ("replay", "--offline", "--interp", "soa"),
    "export": ("export", "--to", "csv"),
    "analyze": ("analyze", "--interp", "soa"),
}

_BAD_FILES = {
    "readme": ("README.md", "not a posecast recording"),
    "empty": ("empty.mcap", "is empty"),
    "truncated": ("cut.mcap", "cut short"),
    "directory": ("folder.mcap", "directory"),
    "missing": ("missing.mcap", "no such"),
}


def _bad_file(kind: str, folder: Path, recording: Path) -> Path:
    name = _BAD_FILES[kind][0]
    path = folder / name
    if kind == "readme":
        shutil.copy(_ROOT / "README.md", path)
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "truncated":
        path.write_bytes(recording.read_bytes()[:12])  # the magic and part of the header
    elif kind == "directory":
        path.mkdir()
    return path


@pytest.mark.parametrize("command", list(_COMMANDS))
@pytest.mark.parametrize("kind", list(_BAD_FILES))
def test_recording_commands_refuse_what_is_not_a_recording(
    tmp_path: Path, recording: Path, command: str, kind: str
) -> None:
    """README, empty, truncated, a directory, a missing path: one line, exit 2, no output."""
    path = _bad_file(kind, tmp_path, recording)
    before = sorted(tmp_path.iterdir())
    res = posecast(*_COMMANDS[command], path, cwd=tmp_path)
    problem = _BAD_FILES[kind][1]
    assert_one_line(res, 2, path.name, problem)
    assert sorted(tmp_path.iterdir()) == before  # recover (or export) wrote nothing


@pytest.mark.parametrize("command", ["info", "replay", "recover", "export", "analyze"])
def test_a_foxglove_export_is_recognised(foxglove: Path, command: str) -> None:
    """A Foxglove export given back is named as such, with what to do instead."""
    before = sorted(foxglove.parent.iterdir())
    res = posecast(*_COMMANDS[command], foxglove)
    assert_one_line(
        res, 2, f"{foxglove} is a Foxglove export, not a posecast recording", "original recording"
    )
    assert sorted(foxglove.parent.iterdir()) == before


def test_a_real_recording_still_passes(recording: Path) -> None:
    """The check lets real recordings through, finished or unfinished (.part)."""
    assert posecast("info", recording).code == 0
    part = recording.with_name("cut.mcap.part")
    part.write_bytes(recording.read_bytes()[: recording.stat().st_size // 2])
    res = posecast("info", part)
    assert res.code == 0 and "UNFINISHED" in res.stdout, res.stderr


def test_an_empty_room_name_is_bad_room(relay: str) -> None:
    """--room '' reaches the server, which refuses it with bad-room (not bad-message)."""
    res = _bots(relay, "--room", "", "--secret", "s3cret")
    assert_one_line(res, 2, "join refused (bad-room)", "room name is empty")


# -- what the parser finds: one line, a "did you mean", never a usage box ----------------


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (("demo", "--bogus"), ("posecast demo has no option --bogus", "did you mean --bots?")),
        (("demo", "--rat", "5"), ("posecast demo has no option --rat", "did you mean --rate")),
        (("demoo",), ("posecast has no command 'demoo'", "did you mean demo?")),
        (("bench", "relai"), ("posecast bench has no command 'relai'", "did you mean relay?")),
        (("frobnicate",), ("no command 'frobnicate'", "commands: analyze", "demo")),
        (("demo", "--rate", "abc"), ("posecast demo", "'--rate'", "number", "--help")),
        (("demo", "--codec", "foo"), ("'--codec'", "'foo' is not one of 'compact', 'raw'")),
        (("bots",), ("posecast bots: missing option '--url'", "posecast bots --help")),
        (("info",), ("posecast info: missing argument 'file'",)),
    ],
)
def test_parser_mistakes_are_one_line(args: tuple[str, ...], words: tuple[str, ...]) -> None:
    """Unknown commands and options, bad and missing values: one line, exit 2, no box."""
    res = posecast(*args)
    assert_one_line(res, 2, *words)
    assert "Usage:" not in res.stderr and "╭" not in res.stderr, res.stderr


def test_a_bad_environment_value_is_one_line() -> None:
    """POSECAST_PORT=zz is refused like --port zz, naming the variable."""
    assert_one_line(posecast("serve", POSECAST_PORT="zz"), 2, "'--port'", "POSECAST_PORT")


def test_no_arguments_still_print_the_help() -> None:
    """`posecast` alone prints the help (exit 2 as before), not an error line."""
    res = posecast()
    assert res.code == 2 and "Usage: posecast" in res.stdout + res.stderr
    assert "error:" not in res.stderr


def test_version_names_package_protocol_and_codec_path() -> None:
    """--version: the installed package version, PROTOCOL_VERSION and the codec path."""
    from importlib.metadata import version

    from posecast.protocol import PROTOCOL_VERSION, _accel

    res = posecast("--version")
    assert res.code == 0, res.stderr
    lines = res.stdout.splitlines()
    assert lines[0] == f"posecast {version('posecast')}"
    assert lines[1] == f"protocol version {PROTOCOL_VERSION}"
    # The child's environment may set POSECAST_PURE: compiled only where built and not off.
    assert lines[2] in (
        f"codec: {_accel.COMPILED}",
        "codec: pure Python (accelerator not built)",
        "codec: pure Python (POSECAST_PURE=1)",
    )
    assert (lines[2] == f"codec: {_accel.COMPILED}") == (
        _accel.compiled() is not None and not os.environ.get(_accel.PURE_ENV)
    )


# -- issue 30's list -----------------------------------------------------------------


def test_view_names_a_junk_file_once(tmp_path: Path) -> None:
    """view junk.mcap: the path once and the real reason (not an MCAP file)."""
    junk = tmp_path / "junk.mcap"
    junk.write_text("junk\n")
    line = assert_one_line(posecast("view", junk), 2, "is not a posecast recording")
    assert line.count("junk.mcap") == 1, line


def test_offline_replay_at_or_above_the_recorded_rate_says_why(recording: Path) -> None:
    """--rate 100 (or 30) on a 30 Hz recording would print zeros: refused, saying why."""
    for rate in ("100", "30"):
        res = posecast("replay", "--offline", "--rate", rate, "--interp", "soa", recording)
        assert_one_line(res, 2, f"--rate {rate} Hz", "own 30 Hz", "every error 0", "lower --rate")
    assert posecast("replay", "--offline", "--rate", "10", "--interp", "soa", recording).code == 0


def test_wss_against_a_plain_server_gives_the_reason(relay: str) -> None:
    """wss:// to a ws:// relay: the TLS handshake failed, and the ws:// URL to try."""
    tls_url = relay.replace("ws://", "wss://")
    res = posecast("bots", "--url", tls_url, "--n", "1", "--duration", "1",
                   "--motion", "synthetic", "--insecure")  # fmt: skip
    line = assert_one_line(res, 2, f"cannot connect to {tls_url}", "TLS handshake failed")
    assert line.endswith(f"Try {relay}"), line


def test_a_lone_bot_demo_prints_no_nan_and_no_open_server_warning(tmp_path: Path) -> None:
    """demo --bots 1: no 'nan bytes per remote pose', no '--secret' warning (demo has none)."""
    res = posecast("demo", "--bots", "1", "--duration", "2", "--motion", "synthetic",
                   "--no-record", cwd=tmp_path)  # fmt: skip
    assert res.code == 0, res.stderr
    assert "nan" not in res.stdout, res.stdout
    assert "no remote poses received, so no bytes per pose" in res.stdout
    assert "a lone bot has nobody to watch (run 2 or more bots)" in res.stdout
    assert "verdict: none" in res.stdout and "a lone bot sees nobody" in res.stdout
    assert "--secret" not in res.stderr + res.stdout, res.stderr
