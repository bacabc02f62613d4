"""The ``posecast`` command line: one entry point for every job.

Subcommands import their machinery lazily so ``posecast --help`` stays fast.
"""

from __future__ import annotations

import sys

from posecast.cli import benchmarks, demo_cmd, experiments, recordings, session, vectors
from posecast.cli import view as view_cli
from posecast.cli import web as web_cli
from posecast.cli.common import app, bench_app

__all__ = ["app", "main"]

# The command table, in the order ``posecast --help`` lists the commands.
app.command()(experiments.compare)
app.command()(session.serve)
app.command()(session.token)
app.command()(session.bots)
app.command()(demo_cmd.demo)
bench_app.command("interp")(benchmarks.bench_interp)
bench_app.command("relay")(benchmarks.bench_relay)
app.command()(experiments.table1)
app.command()(recordings.info)
app.command()(recordings.recover)
app.command()(recordings.replay)
app.command()(view_cli.view)
app.command()(web_cli.web)
app.command()(recordings.export)
app.command()(recordings.analyze)
app.command("interpolators")(experiments.list_interpolators)
app.command("velocity-sources")(experiments.velocity_sources)
app.command()(vectors.vectors)


def _tune_allocator() -> None:
    """Keep freed large buffers in the process (glibc only).

    Interpolating a batch allocates a few hundred kB of numpy temporaries per
    call. By default glibc serves those with mmap and returns them to the OS
    on free, so every call page-faults its memory in again; measured on
    `posecast bench interp`, that doubles the time of an interpolator at batch
    10k. Raising the mmap and trim thresholds keeps them in the heap.
    """
    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        m_trim_threshold, m_mmap_threshold = -1, -3
        libc.mallopt(m_mmap_threshold, 64 << 20)
        libc.mallopt(m_trim_threshold, 256 << 20)
    except (OSError, AttributeError):
        pass  # not glibc: nothing to tune


def main() -> None:
    """Entry point of the ``posecast`` console script."""
    _tune_allocator()
    try:
        app()
    except KeyboardInterrupt:
        sys.exit(130)


if __name__ == "__main__":
    main()
