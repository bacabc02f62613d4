"""Field checks shared by the message dataclasses.

Each check either returns the value in its canonical Python type (an int sent
for a float field becomes a float, a list becomes a tuple) or raises
``LocalProtocolError("bad-message", ...)``. Decoders turn that into a remote
error, the way h11 re-raises a local error as a remote one.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

from posecast.protocol.errors import ErrorCode, LocalProtocolError
from posecast.protocol.limits import MAX_PAYLOAD_DEPTH, MAX_TEXT_LENGTH

__all__ = [
    "U16_MAX",
    "U63_MAX",
    "bad",
    "check_bool",
    "check_float",
    "check_int",
    "check_optional_float",
    "check_optional_int",
    "check_optional_text",
    "check_payload",
    "check_stream_map",
    "check_text",
]

U16_MAX = (1 << 16) - 1
# Sequence and tick numbers: anything msgpack packs as a non-negative int64.
U63_MAX = (1 << 63) - 1


def bad(where: str, what: str) -> LocalProtocolError:
    """Build the bad-message error for field ``where``."""
    return LocalProtocolError(ErrorCode.BAD_MESSAGE, f"{where} {what}")


def check_int(where: str, value: object, lo: int, hi: int) -> int:
    """An int (not a bool) in [lo, hi]."""
    # bool is a subclass of int, and True must not pass as user id 1.
    if type(value) is not int or not lo <= value <= hi:
        raise bad(where, f"must be an int in [{lo}, {hi}]")
    return value


def check_optional_int(where: str, value: object, lo: int, hi: int) -> int | None:
    """None, or an int in [lo, hi]."""
    return None if value is None else check_int(where, value, lo, hi)


def check_float(where: str, value: object) -> float:
    """A finite number; ints are accepted because msgpack packs 20.0 and 20 alike in JS."""
    if type(value) is float:
        if math.isfinite(value):
            return value
    elif type(value) is int and -(1 << 53) <= value <= 1 << 53:
        return float(value)
    raise bad(where, "must be a finite number")


def check_optional_float(where: str, value: object) -> float | None:
    """None, or a finite number."""
    return None if value is None else check_float(where, value)


def check_bool(where: str, value: object) -> bool:
    """A bool."""
    if type(value) is not bool:
        raise bad(where, "must be a bool")
    return value


def check_text(
    where: str, value: object, *, max_length: int = MAX_TEXT_LENGTH, empty: bool = True
) -> str:
    """A str of at most ``max_length`` characters, non-empty unless ``empty``."""
    if type(value) is not str or len(value) > max_length or (not empty and not value):
        size = f"1-{max_length}" if not empty else f"at most {max_length}"
        raise bad(where, f"must be a string of {size} characters")
    return value


def check_optional_text(where: str, value: object) -> str | None:
    """None, or a str of at most ``MAX_TEXT_LENGTH`` characters."""
    return None if value is None else check_text(where, value)


def check_stream_map(where: str, value: object) -> dict[str, int]:
    """A map of stream name -> u16 stream id, ids distinct (names are checked by sessions)."""
    if not isinstance(value, Mapping):
        raise bad(where, "must be a map of name to stream id")
    result: dict[str, int] = {}
    for name, stream in value.items():
        check_text(f"{where} name", name, empty=False)
        result[name] = check_int(f"{where} id", stream, 0, U16_MAX)
    if len(set(result.values())) != len(result):
        raise bad(where, "has duplicate stream ids")
    return result


def check_payload(where: str, value: object) -> dict[str, object]:
    """A map with str keys of msgpack scalars, arrays and maps, not too deep; arrays as tuples."""
    if not isinstance(value, Mapping):
        raise bad(where, "must be a map")
    # Iterative walk: a hostile payload nested 1000 deep must not hit the
    # interpreter's recursion limit.
    todo: list[tuple[object, int]] = [(value, 1)]
    while todo:
        item, depth = todo.pop()
        if isinstance(item, Mapping):
            children = list(item.values())
            if not all(type(key) is str for key in item):
                raise bad(where, "keys must be strings")
        elif isinstance(item, list | tuple):
            children = list(item)
        elif type(item) is int:
            # msgpack has no integers outside int64/uint64.
            if not -(1 << 63) <= item < 1 << 64:
                raise bad(where, "holds an int msgpack cannot carry")
            continue
        elif item is None or type(item) in (bool, float, str, bytes):
            continue
        else:
            raise bad(where, f"cannot hold {type(item).__name__}")
        if depth > MAX_PAYLOAD_DEPTH:
            raise bad(where, f"is nested deeper than {MAX_PAYLOAD_DEPTH}")
        todo.extend((child, depth + 1) for child in children)
    frozen = _freeze(value)
    assert isinstance(frozen, dict)
    return frozen


def _freeze(item: object) -> object:
    # Arrays become tuples, as msgpack decodes them (use_list=False), so that a
    # payload compares equal before and after a round trip. Recursion is safe:
    # the depth was bounded above.
    if isinstance(item, Mapping):
        return {key: _freeze(child) for key, child in item.items()}
    if isinstance(item, list | tuple):
        return tuple(_freeze(child) for child in item)
    return item
