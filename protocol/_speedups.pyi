# Types of the compiled accelerator (protocol/_speedups.c); see protocol/_accel.py.
from collections.abc import Sequence
from typing import Any

__all__ = [
    "decode_update",
    "decode_update_rows",
    "delta_blocks",
    "eg_pack",
    "encode_group",
    "splice",
    "splice_packed",
    "update_records",
]

SOURCE_HASH: str
CONSTANTS: dict[str, int]

def eg_pack(values: Sequence[int], orders: Sequence[int], /) -> tuple[int, int] | None: ...
def decode_update_rows(
    data: bytes,
    pos: int,
    flags: int,
    geometry: tuple[int, ...],
    baselines: dict[int, list[int]],
    /,
) -> tuple[list[int], list[int], list[list[int]]] | None: ...
def decode_update(
    data: bytes,
    previous: tuple[int, int] | None,
    geometry: tuple[int, ...],
    baselines: dict[int, list[int]],
    lo: tuple[float, float, float],
    step: tuple[float, float, float],
    /,
) -> tuple[int, int, bytes, dict[int, list[int]]] | None: ...
def update_records(
    base_us: int,
    streams: list[int],
    offsets: list[int],
    rows: list[list[int]],
    lo: tuple[float, float, float],
    step: tuple[float, float, float],
    /,
) -> bytes: ...
def delta_blocks(
    entries: list[Any], base: float, velocity: bool, /
) -> tuple[list[tuple[int, int, int, int, int]], list[int]] | None: ...
def encode_group(
    entries: list[Any], base_us: int, velocity: bool, bits: tuple[int, int, int], /
) -> tuple[bytes, list[int], list[int]] | None: ...
def splice_packed(
    head: bytes,
    packed: bytes,
    key_nibbles: list[int],
    delta_nibbles: list[int],
    exclude: int,
    /,
) -> tuple[bytes, int]: ...
def splice(
    head: bytes,
    key_blocks: list[Any],
    delta_blocks: list[Any],
    key_nibbles: list[int],
    delta_nibbles: list[int],
    exclude: int,
    /,
) -> tuple[bytes, int]: ...
