"""``posecast vectors``: write the protocol's golden vectors (``protocol.golden_vectors``)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from posecast.cli.common import console


def vectors(
    out: Annotated[
        Path, typer.Option("--out", help="Folder to write the vector JSON files into.")
    ] = Path("protocol/vectors"),
) -> None:
    """Write the golden vectors of the wire protocol (docs/protocol.md), one JSON file each.

    Deterministic: running it again gives the same files. Stale vector files in
    the folder are removed; its README.md is kept.
    """
    from posecast.protocol.golden_vectors import write_vectors

    written = write_vectors(out)
    console.print(f"wrote {len(written)} files to {out}")
