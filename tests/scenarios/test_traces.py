"""Trace loading: the real vr-traces files and clear errors for bad ones."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from scenarios.traces import TraceError, device_class, find_traces, load_trace


def test_loads_real_dev_trace(dev_trace_path: Path) -> None:
    """A dev trace loads as (N,) times and (N, 3, 7) unit-quaternion poses."""
    tr = load_trace(dev_trace_path)
    assert tr.streams == ("head", "left", "right")
    assert tr.poses.shape == (tr.times.shape[0], 3, 7)
    assert np.all(np.diff(tr.times) > 0)
    np.testing.assert_allclose(np.linalg.norm(tr.poses[..., 3:], axis=-1), 1.0, atol=1e-12)
    assert 70 < tr.native_rate < 95


def test_find_traces_splits(trace_root: Path) -> None:
    """traces:dev and traces:eval resolve to the CSVs of each split."""
    dev = find_traces("traces:dev")
    ev = find_traces("traces:eval")
    assert len(dev) == 7 and len(ev) == 5
    assert all(p.parent.name == "dev" for p in dev)


def test_bad_trace_files_give_clear_errors(tmp_path: Path) -> None:
    """Missing, empty, wrong-header and non-monotonic files raise TraceError."""
    with pytest.raises(TraceError, match="no such trace"):
        load_trace(tmp_path / "nope.csv")
    empty = tmp_path / "empty.csv"
    empty.write_text("")
    with pytest.raises(TraceError, match="empty"):
        load_trace(empty)
    bad = tmp_path / "bad.csv"
    bad.write_text("t,a,b\n0,1,2\n")
    with pytest.raises(TraceError, match="unexpected columns"):
        load_trace(bad)
    header = "t," + ",".join(
        f"{d}_{c}"
        for d in ("head", "left", "right")
        for c in ("px", "py", "pz", "qw", "qx", "qy", "qz")
    )
    row = ",0,0,0,1,0,0,0" * 3
    back = tmp_path / "back.csv"
    back.write_text(f"{header}\n1{row}\n0.5{row}\n")
    with pytest.raises(TraceError, match="strictly increasing"):
        load_trace(back)


def test_device_classes() -> None:
    """head is head, left/right are hands, anything else is an object."""
    assert device_class("head") == "head"
    assert device_class("left") == device_class("right") == "hands"
    assert device_class("object:drill") == "objects"
