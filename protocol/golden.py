"""What ``docs/protocol.md`` shows from the code: the error table and the worked examples.

Both are generated here and pasted between markers in the doc
(``<!-- NAME:begin -->`` ... ``<!-- NAME:end -->``); ``tests/protocol/test_protocol_doc.py``
checks the doc holds exactly what these functions give, so neither can drift.
``python -m posecast.protocol.golden docs/protocol.md`` rewrites them. The golden
vectors themselves are built by ``protocol.golden_vectors``.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import numpy as np

from posecast.protocol import errors
from posecast.protocol._compact import relative
from posecast.protocol.codec import DEFAULT_VOLUME, encode_update_codes, quantise
from posecast.protocol.codec_relay import encode_group
from posecast.protocol.errors import ErrorCode
from posecast.protocol.golden_walk import field_table, walk_snapshot, walk_update

__all__ = [
    "EXAMPLE_POSES",
    "doc_sections",
    "error_rows",
    "error_table",
    "example_snapshot",
    "example_update",
    "rewrite",
]

#: Three poses (head, left and right hand) of the worked examples: metres, w-first.
EXAMPLE_POSES = (
    (0.1, 1.6, -0.2, 0.9238795, 0.0, 0.3826834, 0.0),
    (-0.25, 1.2, -0.4, 0.7071068, 0.7071068, 0.0, 0.0),
    (0.25, 1.2, -0.4, 0.0, 0.0, 0.0, 1.0),
)


def error_rows() -> list[tuple[str, str]]:
    """(code, when it is raised) of each row of ``protocol.errors``' docstring table."""
    doc = errors.__doc__ or ""
    lines = doc.splitlines()
    rules = [i for i, line in enumerate(lines) if line.startswith("=====")]
    # The table: rule, header, rule, rows..., rule; columns start where the rule's runs do.
    starts = [m.start() for m in re.finditer(r"=+", lines[rules[0]])]
    rows: list[tuple[str, str]] = []
    for line in lines[rules[1] + 1 : rules[2]]:
        if not line.strip():
            continue
        code = line[: starts[1]].strip()
        text = line[starts[3] :].strip()
        if code:
            rows.append((code, text))
        else:
            rows[-1] = (rows[-1][0], f"{rows[-1][1]} {text}")
    return rows


def error_table() -> str:
    """The markdown error table: every ``ErrorCode`` with its fatality and close code."""
    when = dict(error_rows())
    lines = [
        "| code | fatal | close code | raised when |",
        "|---|---|---|---|",
    ]
    for code in ErrorCode:
        close = code.close_code
        text = when[str(code)].replace("``", "`").replace("|", "\\|")
        lines.append(f"| `{code}` | {'yes' if code.fatal else 'no'} | {close or '-'} | {text} |")
    return "\n".join(lines)


def _example_codes() -> list[list[int]]:
    codes: list[list[int]] = quantise(np.array(EXAMPLE_POSES), DEFAULT_VOLUME).tolist()
    return codes


def example_update() -> tuple[bytes, bytes, dict[int, list[int]]]:
    """(first update frame, second update frame, the baselines of the second).

    The first is a key update of the three poses, seq 7, base time 100 s; the
    second, seq 8 at 100.033 s, moves every position 1 mm along +x and turns the
    left hand so that its largest component changes (w to x): a delta update with a
    relative header and a rotation-index change.
    """
    volume = DEFAULT_VOLUME
    codes = quantise(np.array(EXAMPLE_POSES), volume)
    first = encode_update_codes(7, 100.0, [0, 1, 2], [100.0, 99.99, 99.98], codes, volume)
    baselines: dict[int, np.typing.NDArray[np.int64]] = {}
    first.frame.remember(baselines)
    moved = np.array(EXAMPLE_POSES)
    moved[:, 0] += 0.001
    moved[1, 3:] = (0.7, 0.71414284, 0.0, 0.0)
    codes2 = quantise(moved, volume)
    times = [100.033, 100.033, 100.03]
    second = encode_update_codes(8, 100.033, [0, 1, 2], times, codes2, volume, baselines)
    data, _ = relative(second.data, (7, 100_000_000))
    return first.data, data, {k: v.tolist() for k, v in baselines.items()}


def example_snapshot() -> tuple[bytes, dict[tuple[int, int], list[int]]]:
    """A version-2 snapshot with a key and two delta entries, and its baselines."""
    volume = DEFAULT_VOLUME
    c = _example_codes()
    moved = [list(row) for row in c]
    moved[0][4] += 2  # the head 2 steps (0.98 mm) along +x
    moved[1][0] = 1  # the left hand's largest component: x instead of w (same rotation)
    entries = [
        (1, 0, 100.02, moved[0], c[0]),
        (1, 1, 100.01, moved[1], c[1]),
        (2, 5, 99.95, c[2], None),
    ]
    group = encode_group(13, 100.033, entries, volume)
    data, _ = group.frame(None)
    return data, {(1, 0): c[0], (1, 1): c[1]}


def _volume() -> tuple[tuple[float, ...], tuple[float, ...]]:
    return DEFAULT_VOLUME.lo, DEFAULT_VOLUME.hi


def doc_sections() -> dict[str, str]:
    """Marker name -> the generated text the doc holds between its markers."""
    key, delta, baselines = example_update()
    walked_key = walk_update(key, _volume(), {}, None)
    walked_delta = walk_update(delta, _volume(), baselines, (7, 100_000_000))
    snap, snap_baselines = example_snapshot()
    walked_snap = walk_snapshot(snap, _volume(), snap_baselines)
    return {
        "errors": error_table(),
        "example-update-key": f"```\n{key.hex(' ')}\n```\n\n{field_table(key, walked_key.fields)}",
        "example-update-delta": (
            f"```\n{delta.hex(' ')}\n```\n\n{field_table(delta, walked_delta.fields)}"
        ),
        "example-snapshot": f"```\n{snap.hex(' ')}\n```\n\n{field_table(snap, walked_snap.fields)}",
    }


def rewrite(text: str, sections: dict[str, str]) -> str:
    """``text`` with each marked section replaced by its generated content."""
    for name, body in sections.items():
        begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
        if begin not in text or end not in text:
            raise ValueError(f"the doc lacks the markers of {name!r}")
        head, rest = text.split(begin, 1)
        _, tail = rest.split(end, 1)
        text = f"{head}{begin}\n{body}\n{end}{tail}"
    return text


if __name__ == "__main__":
    path = Path(sys.argv[1] if len(sys.argv) > 1 else "docs/protocol.md")
    path.write_text(rewrite(path.read_text(), doc_sections()))
