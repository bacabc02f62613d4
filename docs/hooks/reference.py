"""mkdocs hook: the Reference pages, written from the code at every build.

Nothing here is copied by hand, so the pages cannot drift from the code:

- ``reference/cli.md``: every command and option of the ``posecast`` typer app
  (its click tree: names, types, defaults, environment variables, help);
- ``reference/settings.md``: every ``POSECAST_*`` environment variable: those the
  CLI's options read, plus the few read by ``os.environ`` (listed in
  :data:`OTHER_SETTINGS`; a ``POSECAST_*`` string in the code that is neither
  fails the build);
- ``reference/metrics.md``: every ``/metrics`` family: the relay's, read from
  ``metrics_text`` of a real ``RelayCore``, and the cluster node's, read from the
  rows of ``server/node.py``; a ``posecast_*`` metric name in ``server/`` that is
  in neither fails the build;
- ``reference/errors.md``: the error codes of ``protocol/errors.py`` (fatal and
  close code from ``ErrorCode`` itself, the "raised when" text from the table in
  the module's docstring).

``python docs/hooks/reference.py DIR`` writes the same pages into ``DIR`` (to read
them without building the site; the tests use the functions directly).
"""

from __future__ import annotations

import ast
import enum
import posixpath
import re
import sys
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path, PurePosixPath
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
#: The packages whose sources are scanned for settings and metric names.
SOURCES = ("posecast", "server", "client", "protocol", "interp", "recorder", "scenarios")

#: ``POSECAST_*`` variables read outside the CLI's options: name -> (default, meaning).
OTHER_SETTINGS: dict[str, tuple[str, str]] = {
    "POSECAST_TRACES": (
        "the bundled sets",
        "Folder holding the full trace sets `dev/` and `eval/` (`traces:dev`, "
        "`traces:eval`). Unset: the sets bundled in the package.",
    ),
    "POSECAST_PURE": (
        "unset (the compiled accelerator where it is built)",
        "`1`: run the compact codec's pure-Python twin instead of its C accelerator "
        "(same bytes, about twice the relay's CPU per pose), and the render frame's "
        "numpy kernels instead of the compiled ones (the same poses to float rounding, "
        "several times a bot's render CPU). `posecast --version` says which run; the "
        "`posecast_codec_info` metric, which codec.",
    ),
}


# -- the CLI ------------------------------------------------------------------------------


def _click_root() -> Any:
    import typer

    from posecast.cli import app

    return typer.main.get_command(app)


def walk_commands(cmd: Any | None = None, path: tuple[str, ...] = ("posecast",)) -> Iterator[Any]:
    """``(path, command)`` for the root and every subcommand, depth first, in name order."""
    cmd = _click_root() if cmd is None else cmd
    yield path, cmd
    subs = getattr(cmd, "commands", None) or {}
    for name in sorted(subs):
        if not subs[name].hidden:
            yield from walk_commands(subs[name], (*path, name))


def _cell(text: object) -> str:
    """Text fit for one cell of a Markdown table."""
    s = " ".join(str(text).split()).replace("``", "`")
    return s.replace("|", "\\|").replace("<", "&lt;").replace(">", "&gt;")


def _default(p: Any) -> str:
    if p.required:
        return "required"
    d = p.default
    if callable(d) or d is None or d == () or d == []:
        return ""
    if isinstance(d, bool):
        return "on" if d else "off"
    if isinstance(d, (list, tuple)):
        return ", ".join(str(x) for x in d)
    return str(d)


def _type(p: Any) -> str:
    if getattr(p, "is_flag", False):
        return "flag"
    ptype = getattr(p, "type", None)
    choices = getattr(ptype, "choices", None)
    if choices:
        return " | ".join(str(c) for c in choices)
    if ptype is not None:
        return str(getattr(ptype, "name", "") or "")
    ann = getattr(getattr(p, "type_descriptor", None), "annotation", None)
    if isinstance(ann, type) and issubclass(ann, enum.Enum):
        return " | ".join(str(m.value) for m in ann)
    args = [a for a in getattr(ann, "__args__", ()) if a is not type(None)]
    if getattr(ann, "__origin__", None) is list and args:
        ann = args[0]
    name = getattr(ann, "__name__", None) or str(ann or "")
    if getattr(p, "multiple", False):
        name += ", repeatable"
    return name.replace(" | None", "").replace("pathlib.", "").replace("Path", "path")


def _flags(p: Any) -> str:
    if _is_argument(p):
        return f"`{(p.name or '').upper()}` (argument)"
    opts = [*p.opts, *getattr(p, "secondary_opts", [])]
    return " / ".join(f"`{o}`" for o in opts)


def _is_argument(p: Any) -> bool:
    return any(c.__name__.endswith("Argument") for c in type(p).__mro__)


def _envvars(p: Any) -> list[str]:
    env = getattr(p, "envvar", None)
    if not env:
        return []
    return [env] if isinstance(env, str) else list(env)


def _first_paragraph(text: str | None) -> str:
    if not text:
        return ""
    return text.strip().split("\n\n")[0]


def cli_page() -> str:
    """Markdown of every command with every parameter."""
    out = [
        "# Command line",
        "",
        "Generated from the `posecast` command's own definition at build time: every",
        "command and option below is what `posecast COMMAND --help` accepts.",
        "Options marked with a variable can also be set in the environment",
        "([settings](settings.md)).",
        "",
    ]
    for path, cmd in walk_commands():
        name = " ".join(path)
        depth = "##" if len(path) <= 2 else "###"
        out += [f"{depth} `{name}`", ""]
        if cmd.help:
            out += [cmd.help.strip().replace("\b\n", ""), ""]
        params = [p for p in cmd.params if not getattr(p, "hidden", False)]
        params = [p for p in params if p.name not in ("help", "install_completion")]
        if params:
            out += ["| option | type | default | environment | meaning |", "|---|---|---|---|---|"]
            for p in params:
                env = ", ".join(f"`{e}`" for e in _envvars(p))
                out.append(
                    f"| {_flags(p)} | {_cell(_type(p))} | {_cell(_default(p))} | {env} | "
                    f"{_cell(getattr(p, 'help', '') or '')} |"
                )
            out.append("")
        subs = getattr(cmd, "commands", None) or {}
        if subs:
            out += ["Commands: " + ", ".join(f"`{name} {s}`" for s in sorted(subs)), ""]
    return "\n".join(out)


# -- settings -----------------------------------------------------------------------------


def _source_files() -> Iterator[Path]:
    for pkg in SOURCES:
        yield from sorted((ROOT / pkg).rglob("*.py"))


def cli_settings() -> dict[str, list[tuple[str, Any]]]:
    """``POSECAST_X -> [(command, parameter), ...]`` for every option with a variable."""
    found: dict[str, list[tuple[str, Any]]] = {}
    for path, cmd in walk_commands():
        for p in cmd.params:
            for env in _envvars(p):
                found.setdefault(env, []).append((" ".join(path), p))
    return found


def settings_in_code() -> set[str]:
    """Every ``POSECAST_*`` name written as a whole string literal in the sources."""
    return _literals(_source_files(), r"POSECAST_[A-Z0-9_]+")


def _literals(files: Iterable[Path], pattern: str) -> set[str]:
    """Every string literal in ``files`` that matches ``pattern`` whole."""
    names: set[str] = set()
    for f in files:
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if (
                isinstance(node, ast.Constant)
                and isinstance(node.value, str)
                and re.fullmatch(pattern, node.value)
            ):
                names.add(node.value)
    return names


def settings_page() -> str:
    """Markdown of every ``POSECAST_*`` variable."""
    cli = cli_settings()
    missing = settings_in_code() - set(cli) - set(OTHER_SETTINGS)
    if missing:
        raise RuntimeError(
            f"POSECAST_* variables read in the code but not documented: {sorted(missing)}; "
            "add them to OTHER_SETTINGS in docs/hooks/reference.py"
        )
    out = [
        "# Settings",
        "",
        "Generated from the code at build time. Every option of `posecast serve` (and",
        "a few of other commands) can be set by an environment variable instead; an",
        "option given on the command line wins. The same names work in",
        "`docker-compose.yml` and a systemd unit's `Environment=`.",
        "",
        "| variable | option | default | meaning |",
        "|---|---|---|---|",
    ]
    for env in sorted(set(cli) | set(OTHER_SETTINGS)):
        if env in cli:
            uses = cli[env]
            _, p = uses[0]
            opts = ", ".join(sorted({f"`{c} {q.opts[0]}`" for c, q in uses}))
            out.append(
                f"| `{env}` | {opts} | {_cell(_default(p))} | {_cell(getattr(p, 'help', ''))} |"
            )
        else:
            default, meaning = OTHER_SETTINGS[env]
            out.append(f"| `{env}` | | {_cell(default)} | {_cell(meaning)} |")
    out.append("")
    return "\n".join(out)


# -- /metrics -----------------------------------------------------------------------------


def relay_metrics() -> list[tuple[str, str, str]]:
    """``(name, type, help)`` of every family a relay's ``/metrics`` serves, in order."""
    from posecast.server.core import RelayCore
    from posecast.server.http import metrics_text

    text = metrics_text(RelayCore(), now=0.0)
    helps = dict(re.findall(r"^# HELP (\S+) (.*)$", text, re.M))
    types = re.findall(r"^# TYPE (\S+) (\S+)$", text, re.M)
    return [(name, kind, helps.get(name, "")) for name, kind in types]


def cluster_metrics() -> list[tuple[str, str, str]]:
    """``(name, type, help)`` of the rows a cluster node adds (``server/node.py``)."""
    tree = ast.parse((ROOT / "server" / "node.py").read_text(encoding="utf-8"))
    rows = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Tuple) and len(node.elts) >= 3:
            first = node.elts[:3]
            if all(isinstance(e, ast.Constant) and isinstance(e.value, str) for e in first):
                name, kind, help_ = (e.value for e in first)  # type: ignore[attr-defined]
                if name.startswith("posecast_"):
                    rows.append((name, kind, help_))
    return rows


def metric_names_in_server() -> set[str]:
    """Every whole ``posecast_*`` metric name written as a literal in ``server/``."""
    return _literals(sorted((ROOT / "server").rglob("*.py")), r"posecast_[a-z0-9_]+")


def metrics_page() -> str:
    """Markdown of every ``/metrics`` family."""
    relay, cluster = relay_metrics(), cluster_metrics()
    missing = metric_names_in_server() - {n for n, _, _ in relay + cluster}
    if missing:
        raise RuntimeError(f"metric names in server/ that the reference cannot find: {missing}")
    out = [
        "# Metrics",
        "",
        "Generated from the relay's code at build time. `GET /metrics` on the relay's",
        "websocket port answers in the Prometheus text format; `GET /healthz` answers",
        "`ok`. Per-room families carry a `room` label; `posecast_updates_refused_total`",
        "a `reason` label (`stale-capture`, `future-capture`, `out-of-bounds`).",
        "",
        "## Every relay",
        "",
        *_metric_table(relay),
        "",
        "## A cluster node (`posecast serve --cluster`)",
        "",
        *_metric_table(cluster),
        "",
    ]
    return "\n".join(out)


def _metric_table(rows: list[tuple[str, str, str]]) -> list[str]:
    lines = ["| name | type | meaning |", "|---|---|---|"]
    lines += [f"| `{n}` | {k} | {_cell(h)} |" for n, k, h in rows]
    return lines


# -- errors -------------------------------------------------------------------------------


def error_descriptions() -> dict[str, str]:
    """``code -> raised when`` from the table in ``protocol/errors.py``'s docstring."""
    from posecast.protocol import errors

    doc = errors.__doc__ or ""
    desc: dict[str, str] = {}
    current = None
    for line in doc.splitlines():
        if line.startswith("=") or not line.strip():
            continue
        m = re.match(r"^([a-z][a-z-]+)\s+(yes|no)\s+(\d+|--)\s+(.*)$", line)
        if m:
            current = m.group(1)
            desc[current] = m.group(4).strip()
        elif current and line.startswith(" " * 20):
            desc[current] += " " + line.strip()
        else:
            current = None
    return desc


def errors_page() -> str:
    """Markdown of every error code: fatal, close code, when."""
    from posecast.protocol.errors import ErrorCode

    desc = error_descriptions()
    out = [
        "# Errors",
        "",
        "Generated from `protocol/errors.py` at build time. Anything a peer sends wrong",
        "becomes an `error` message with one of these codes. A fatal error ends the",
        "session: the server closes the websocket with the close code and the message as",
        "its reason. A non-fatal one drops the offending message and the session goes on.",
        "\"(server decision)\" codes come from the relay's rules, not the protocol's.",
        "",
        "| code | fatal | close code | raised when |",
        "|---|---|---|---|",
    ]
    for code in ErrorCode:
        close = code.close_code
        out.append(
            f"| `{code.value}` | {'yes' if code.fatal else 'no'} | "
            f"{close if close is not None else ''} | {_cell(desc.get(code.value, ''))} |"
        )
    out.append("")
    return "\n".join(out)


PAGES: dict[str, Callable[[], str]] = {
    "reference/cli.md": cli_page,
    "reference/settings.md": settings_page,
    "reference/metrics.md": metrics_page,
    "reference/errors.md": errors_page,
}


def changelog_page() -> str:
    """``CHANGELOG.md`` of the repository, its links to ``docs/`` made relative to the page."""
    return (ROOT / "CHANGELOG.md").read_text(encoding="utf-8").replace("](docs/", "](../")


PAGES["reference/changelog.md"] = changelog_page


def _drop_missing(nav: list[Any], docs_dir: Path) -> list[Any]:
    """The nav without entries of pages that are neither in docs/ nor generated."""
    kept: list[Any] = []
    for item in nav:
        title, target = next(iter(item.items())) if isinstance(item, dict) else (None, item)
        if isinstance(target, list):
            target = _drop_missing(target, docs_dir)
        elif target not in PAGES and not (docs_dir / target).is_file():
            continue
        kept.append({title: target} if title is not None else target)
    return kept


def on_config(config: Any) -> Any:
    """mkdocs event: a page still being written (no file yet) is left out of the nav."""
    config["nav"] = _drop_missing(config["nav"], Path(config["docs_dir"]))
    return config


_LINK = re.compile(r"(?<!!)\[([^\]]*)\]\(([^)\s#]+)(#[^)\s]*)?\)")


def fix_links(markdown: str, page_uri: str, doc_uris: set[str]) -> str:
    """Links of a page that would not resolve, made to (the site has no other way):

    - a link to a page that moved (no such file, one page of the same name
      elsewhere in docs/) points at where it is now;
    - a link out of docs/ (``../protocol/vectors/README.md``: a file of the
      repository) becomes its text, followed by the path in the repository as code
      unless the text already names it.
    """
    base = PurePosixPath(page_uri).parent

    def fix(m: re.Match[str]) -> str:
        text, target, anchor = m.group(1), m.group(2), m.group(3) or ""
        if "://" in target or target.startswith(("mailto:", "/")):
            return m.group(0)
        resolved = posixpath.normpath((base / target).as_posix())
        if resolved in doc_uris:
            return m.group(0)
        if not resolved.startswith(".."):
            same = [u for u in doc_uris if PurePosixPath(u).name == PurePosixPath(target).name]
            if len(same) == 1:
                rel = posixpath.relpath(same[0], base.as_posix() or ".")
                return f"[{text}]({rel}{anchor})"
            return m.group(0)
        in_repo = posixpath.normpath(("docs" / PurePosixPath(resolved)).as_posix())
        return text if text.strip("`").rstrip("/") in in_repo else f"{text} (`{in_repo}`)"

    return _LINK.sub(fix, markdown)


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    """mkdocs event: links to moved pages and to the repository's files resolve."""
    uris = {f.src_uri for f in files}
    return fix_links(markdown, page.file.src_uri, uris)


def on_files(files: Any, config: Any) -> Any:
    """mkdocs event: add the generated pages to the site's files."""
    from mkdocs.structure.files import File

    for uri, make in PAGES.items():
        files.append(File.generated(config, uri, content=make()))
    return files


if __name__ == "__main__":
    target = Path(sys.argv[1] if len(sys.argv) > 1 else "build/reference")
    for uri, make in PAGES.items():
        path = target / Path(uri).name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(make(), encoding="utf-8")
        print(path)
