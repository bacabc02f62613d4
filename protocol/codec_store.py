"""A relay stream's coded versions, packed so that the accelerator reads them in place.

A compact subscriber's delta is coded against the codes it holds of each stream:
those of the newest version at or before its last snapshot. The relay keeps a
stream's last few coded versions for that (``server.room``). :class:`CodeHistory`
keeps them in one ``bytearray``, oldest first, so that the group encode in C
(``_speedups.encode_stored``) finds a baseline and remembers a new version with
no Python object per version; this module is its pure-Python twin and the
reference of the layout. Codes are rows of 7 or 13 int64.

Layout (native byte order, as C reads it)::

    int64  count     versions held (0..capacity)
    int64  capacity
    capacity x 120 bytes, the first count used, oldest first:
        int64  version
        int64  width (7 or 13)
        int64  codes[13] (the first width used, the rest 0)
"""

from __future__ import annotations

import struct
from collections.abc import Iterable

__all__ = ["CodeHistory", "baseline_of"]

_HEAD = struct.Struct("=qq")
_ENTRY = struct.Struct("=qq13q")
_WIDTHS = (7, 13)
#: One int64: the count, or an entry's version (its first field).
_Q = struct.Struct("=q")


class CodeHistory(bytearray):
    """The last ``capacity`` coded versions of a stream, oldest first (see the module)."""

    __slots__ = ()

    def __init__(self, capacity: int) -> None:
        if capacity < 1:
            raise ValueError("a code history holds at least one version")
        super().__init__(_HEAD.size + capacity * _ENTRY.size)
        _HEAD.pack_into(self, 0, 0, capacity)

    def held(self) -> int:
        """How many versions it holds."""
        return int(_Q.unpack_from(self)[0])

    def _entry(self, i: int) -> tuple[int, list[int]]:
        fields = _ENTRY.unpack_from(self, _HEAD.size + i * _ENTRY.size)
        return fields[0], list(fields[2 : 2 + fields[1]])

    def last_version(self) -> int | None:
        """The newest version held (None: none)."""
        n = self.held()
        if n == 0:
            return None
        return int(_Q.unpack_from(self, _HEAD.size + (n - 1) * _ENTRY.size)[0])

    def append(self, item: tuple[int, list[int]]) -> None:  # type: ignore[override]
        """Remember ``item``, (version, codes), as the newest, dropping the oldest if
        full (as a ``deque`` of ``maxlen`` capacity)."""
        version, codes = item
        width = len(codes)
        if width not in _WIDTHS:
            raise ValueError("codes are rows of 7 or 13")
        n, capacity = _HEAD.unpack_from(self)
        start = _HEAD.size
        if n == capacity:
            self[start : start + (n - 1) * _ENTRY.size] = self[start + _ENTRY.size :]
            n -= 1
        padded = list(codes) + [0] * (13 - width)
        _ENTRY.pack_into(self, start + n * _ENTRY.size, version, width, *padded)
        _HEAD.pack_into(self, 0, n + 1, capacity)

    def baseline(self, since: int) -> list[int] | None:
        """The codes of the newest version at or before ``since`` (None: none held)."""
        unpack, size = _Q.unpack_from, _ENTRY.size
        for i in range(self.held() - 1, -1, -1):
            if unpack(self, _HEAD.size + i * size)[0] <= since:
                return self._entry(i)[1]
        return None

    def items(self) -> list[tuple[int, list[int]]]:
        """(version, codes) of every version held, oldest first."""
        return [self._entry(i) for i in range(self.held())]


def baseline_of(
    history: CodeHistory | Iterable[tuple[int, list[int]]], since: int
) -> list[int] | None:
    """The codes of the newest version at or before ``since`` in ``history`` (a
    :class:`CodeHistory` or (version, codes) pairs oldest first); None: none."""
    if isinstance(history, CodeHistory):
        return history.baseline(since)
    for version, codes in reversed(list(history)):
        if version <= since:
            return codes
    return None
