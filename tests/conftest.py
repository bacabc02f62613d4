"""Shared fixtures: paths to the real traces."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from hypothesis import settings

from scenarios.traces import default_trace_root

# CI runs the same examples every time (no flaky reds from a lucky draw); local
# runs keep exploring.
settings.register_profile("ci", derandomize=True, database=None)
if os.environ.get("CI"):
    settings.load_profile("ci")


@pytest.fixture(scope="session")
def trace_root() -> Path:
    root = default_trace_root()
    if not (root / "dev").is_dir():
        pytest.fail(f"vr-traces not found at {root}; set POSECAST_TRACES")
    return root


@pytest.fixture(scope="session")
def dev_trace_path(trace_root: Path) -> Path:
    return trace_root / "dev" / "S02_riftS_expertplus.csv"
