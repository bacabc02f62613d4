"""The "where each rule lives" tables of ``docs/concepts/layout.md`` point at real code.

Issue 27's test for a newcomer: asked "where is the rule that X" (a skip, a refused
join, a resume window, a key slot, the playout delay, a reconnect), they find it in
one module on the first try. The tables are where they look; these tests check that
every name a table gives exists in the package it speaks of (a rename that forgets
the table fails here) and that the issue's six questions each have a row.
"""

from __future__ import annotations

import importlib
import re
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parent.parent
LAYOUT = ROOT / "docs" / "concepts" / "layout.md"

#: Table heading -> the package its names are relative to.
TABLES = {
    "## Where each rule of the relay lives": "posecast.server",
    "## Where each rule of the bot lives": "posecast.client",
}

#: Issue 27's questions, each as words its table row must hold.
QUESTIONS = {
    "a skip": ("relay", "skips a snapshot"),
    "a refused join": ("relay", "refuses a join"),
    "a resume window": ("relay", "the resume window"),
    "a key slot": ("relay", "key snapshot"),
    "the playout delay": ("bot", "the playout delay"),
    "a reconnect": ("bot", "reconnects"),
}

NAME = re.compile(r"`([A-Za-z_][\w.]*)`")


def table_rows(heading: str) -> list[tuple[str, str]]:
    """(rule, where) of each row of the table under ``heading``."""
    lines = LAYOUT.read_text().splitlines()
    start = lines.index(heading)
    rows: list[tuple[str, str]] = []
    for line in lines[start + 1 :]:
        if line.startswith("## "):
            break
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and len(cells) == 2 and not set(cells[1]) <= {"-"}:
            rows.append((cells[0], cells[1]))
    return rows[1:]  # the header row


def _module(package: str, name: str) -> ModuleType | None:
    try:
        return importlib.import_module(f"{package}.{name}")
    except ModuleNotFoundError:
        return None


def _attr(obj: object, dotted: list[str]) -> bool:
    for part in dotted:
        if not hasattr(obj, part):
            return False
        obj = getattr(obj, part)
    return True


def resolves(package: str, name: str, context: list[object]) -> bool:
    """Whether ``name`` is a module of ``package`` (with attributes after it), or an
    attribute of something an earlier name of the row resolved to."""
    first, *rest = name.split(".")
    module = _module(package, first)
    if module is not None and _attr(module, rest):
        context.append(module)
        if rest:
            context.append(getattr(module, rest[0]))
        return True
    return any(_attr(obj, name.split(".")) for obj in context)


def unresolved(heading: str, package: str) -> list[str]:
    missing = []
    for rule, where in table_rows(heading):
        context: list[object] = []
        names = NAME.findall(where)
        if not names:
            missing.append(f"{rule!r}: names no module")
        for name in names:
            if not resolves(package, name, context):
                missing.append(f"{rule!r}: `{name}`")
    return missing


@pytest.mark.parametrize("heading", sorted(TABLES))
def test_every_name_in_the_rule_table_exists(heading: str) -> None:
    missing = unresolved(heading, TABLES[heading])
    assert not missing, f"{heading}: names not found in {TABLES[heading]}:\n" + "\n".join(missing)


def test_each_question_of_the_issue_has_a_row() -> None:
    heads = {side: f"## Where each rule of the {side} lives" for side in ("relay", "bot")}
    absent = [
        question
        for question, (side, words) in QUESTIONS.items()
        if not any(words in rule for rule, _ in table_rows(heads[side]))
    ]
    assert not absent, f"no row answers: {absent}"


def test_a_renamed_rule_is_found_missing() -> None:
    """The resolver fails a name that is not there (so the test above can fail)."""
    assert resolves("posecast.server", "joins.Joins.admit", [])
    assert not resolves("posecast.server", "joins.Joins.no_such_rule", [])
    assert not resolves("posecast.client", "no_such_module.Thing", [])
