"""Is a file a posecast recording? A check of its first bytes, for the CLI's clear errors."""

from __future__ import annotations

import os
import struct
from pathlib import Path

from posecast.recorder.format import PROFILE, FormatError
from posecast.recorder.scan import MAGIC

__all__ = ["EXPORT_LIBRARY_PREFIX", "check_recording"]

#: Bytes read by :func:`check_recording`: the magic and the header record, whose two
#: strings (profile, writer library) are short.
_HEAD_BYTES = 64 * 1024
_HEADER_OPCODE = 0x01
#: The writer library of ``posecast export --to foxglove`` files (their profile is empty).
EXPORT_LIBRARY_PREFIX = "posecast-export/"


def check_recording(path: str | os.PathLike[str]) -> None:
    """Raise :class:`FormatError` unless ``path`` starts as a posecast recording does.

    Only the MCAP magic and the header record are read, so a finished, an
    unfinished (``.part``) or a damaged recording passes (damage shows when it is
    read, and ``recover`` handles it). An empty file, a file that is not MCAP,
    one cut short inside its header, a Foxglove export and another program's
    MCAP file do not; the message says which, naming the file, in one line.
    ``OSError`` if the file cannot be opened.
    """
    p = Path(path)
    with p.open("rb") as fh:
        head = fh.read(_HEAD_BYTES)
    if not head:
        raise FormatError(f"{p} is empty, not a posecast recording")
    if head[: len(MAGIC)] != MAGIC:
        if MAGIC.startswith(head):
            raise FormatError(
                f"{p} is cut short inside its MCAP magic: there is no recording in it"
            )
        raise FormatError(f"{p} is not a posecast recording (not an MCAP file)")
    cut_short = FormatError(
        f"{p} is cut short inside its MCAP header ({len(head)} bytes): there is no recording in it"
    )
    pos = len(MAGIC)
    if len(head) < pos + 9:
        raise cut_short
    opcode, length = struct.unpack_from("<BQ", head, pos)
    if opcode != _HEADER_OPCODE:
        raise FormatError(f"{p} is damaged: its MCAP header record is missing; try recovering it")
    body = head[pos + 9 : pos + 9 + length]
    if len(body) < length:
        if len(head) < _HEAD_BYTES:
            raise cut_short
        raise FormatError(f"{p} is damaged: its MCAP header record is too long to be one")
    strings: list[str] = []
    at = 0
    try:
        for _ in range(2):
            (n,) = struct.unpack_from("<I", body, at)
            strings.append(body[at + 4 : at + 4 + n].decode("utf-8"))
            at += 4 + n
    except (struct.error, UnicodeDecodeError):
        raise FormatError(f"{p} is damaged: its MCAP header record is malformed") from None
    profile, library = strings
    if profile == PROFILE:
        return
    if library.startswith(EXPORT_LIBRARY_PREFIX):
        raise FormatError(
            f"{p} is a Foxglove export, not a posecast recording; replay the original "
            "recording (open this file in Foxglove)"
        )
    if not profile and "recovered by posecast" in library:
        return  # recovered from a file whose header was lost: judged by its channels
    raise FormatError(
        f"{p} is an MCAP file but not a posecast recording "
        f"(profile {profile!r}, written by {library!r})"
    )
