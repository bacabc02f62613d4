"""The interpolator registry: names, lookup, registration and entry-point plug-ins."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from numpy.typing import ArrayLike, NDArray

from posecast import interp
from posecast.interp import registry

F64 = NDArray[np.float64]
#: The paper's three pair interpolators (more built-ins may follow them).
PAPER_METHODS = ["soa", "dq-slerp", "motor-lerp"]


def hold_first(a: ArrayLike, b: ArrayLike, s: ArrayLike) -> F64:
    """A toy plug-in interpolator: always shows ``a``."""
    return np.array(a, dtype=np.float64)


@dataclass
class FakeEntryPoint:
    """Stands in for ``importlib.metadata.EntryPoint``: name, value and ``load()``."""

    name: str
    value: str
    obj: Any
    loads: int = 0

    def load(self) -> Any:
        """Return the plug-in object, counting calls."""
        self.loads += 1
        return self.obj


@pytest.fixture
def isolated_registry(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[str]]:
    """A private copy of the registry, entry points not yet loaded; yields the built-ins."""
    monkeypatch.setattr(registry, "_REGISTRY", dict(registry._REGISTRY))
    monkeypatch.setattr(registry, "_entry_points_loaded", False)
    yield list(registry._REGISTRY)


@pytest.fixture
def install_entry_points(
    monkeypatch: pytest.MonkeyPatch, isolated_registry: list[str]
) -> Callable[[list[FakeEntryPoint]], list[str]]:
    """Make ``importlib.metadata.entry_points`` (as seen by the registry) return fakes.

    Returns a function installing the fakes; it gives back the groups asked for.
    """
    groups: list[str] = []

    def install(eps: list[FakeEntryPoint]) -> list[str]:
        def entry_points(*, group: str) -> list[FakeEntryPoint]:
            groups.append(group)
            return eps if group == interp.ENTRY_POINT_GROUP else []

        monkeypatch.setattr(registry, "metadata", SimpleNamespace(entry_points=entry_points))
        return groups

    return install


def test_names_lists_the_built_ins_first() -> None:
    """names() starts with soa, dq-slerp, motor-lerp."""
    assert interp.names()[:3] == PAPER_METHODS


def test_get_returns_the_built_in_functions() -> None:
    """get(name) is the matching function of interp.methods."""
    assert interp.get("soa") is interp.soa
    assert interp.get("dq-slerp") is interp.dq_slerp
    assert interp.get("motor-lerp") is interp.motor_lerp


def test_info_describes_the_built_ins() -> None:
    """info() gives a description and the frame-invariance flag of each built-in."""
    flags = {name: interp.info(name).frame_invariant for name in PAPER_METHODS}
    assert flags == {"soa": False, "dq-slerp": True, "motor-lerp": True}
    for name in PAPER_METHODS:
        assert interp.info(name).name == name
        assert interp.info(name).description


def test_get_unknown_name_raises_key_error_listing_names() -> None:
    """get('slerp') raises KeyError naming the request and every known interpolator."""
    with pytest.raises(KeyError) as excinfo:
        interp.get("slerp")
    message = str(excinfo.value)
    assert "unknown interpolator 'slerp'" in message
    for name in PAPER_METHODS:
        assert name in message


@pytest.mark.usefixtures("isolated_registry")
def test_register_refuses_duplicates() -> None:
    """Registering an existing name raises ValueError; the old entry stays."""
    with pytest.raises(ValueError, match="interpolator 'soa' is already registered"):
        interp.register("soa", hold_first)
    assert interp.get("soa") is interp.soa


def test_register_adds_and_replaces_on_request(isolated_registry: list[str]) -> None:
    """A new name is listed after the built-ins; replace=True swaps an entry."""
    interp.register("hold", hold_first, description="shows a", frame_invariant=True)
    assert interp.names() == [*isolated_registry, "hold"]
    assert interp.get("hold") is hold_first
    assert interp.info("hold").frame_invariant
    interp.register("hold", interp.soa, replace=True)
    assert interp.get("hold") is interp.soa


@pytest.mark.usefixtures("isolated_registry")
@pytest.mark.parametrize("name", ["", "with space", "dot.ted", "semi;colon"])
def test_register_refuses_invalid_names(name: str) -> None:
    """Empty names and names with characters other than letters, digits, - and _ are refused."""
    with pytest.raises(ValueError, match="invalid interpolator name"):
        interp.register(name, hold_first)


def test_entry_points_group_is_honoured(
    install_entry_points: Callable[[list[FakeEntryPoint]], list[str]],
    isolated_registry: list[str],
) -> None:
    """A plug-in of group posecast.interpolators is listed after the built-ins and usable."""
    ep = FakeEntryPoint("hold-first", "posecast_plugin:hold_first", hold_first)
    groups = install_entry_points([ep])
    assert interp.names() == [*isolated_registry, "hold-first"]
    assert groups == ["posecast.interpolators"]
    f = interp.get("hold-first")
    a = np.array([1.0, 2.0, 3.0, 1.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(f(a, a * 0, 0.5), a)
    assert "posecast_plugin:hold_first" in interp.info("hold-first").description


def test_entry_points_are_loaded_once_and_lazily(
    install_entry_points: Callable[[list[FakeEntryPoint]], list[str]],
) -> None:
    """Entry points are read on the first lookup only, not at install time or later calls."""
    ep = FakeEntryPoint("hold-first", "posecast_plugin:hold_first", hold_first)
    groups = install_entry_points([ep])
    assert groups == [] and ep.loads == 0
    interp.get("soa")
    interp.names()
    interp.info("hold-first")
    assert groups == ["posecast.interpolators"]
    assert ep.loads == 1


def test_entry_points_cannot_replace_built_ins(
    install_entry_points: Callable[[list[FakeEntryPoint]], list[str]],
    isolated_registry: list[str],
) -> None:
    """A plug-in named like a built-in is ignored; the built-in stays."""
    ep = FakeEntryPoint("soa", "evil:soa", hold_first)
    install_entry_points([ep])
    assert interp.names() == isolated_registry
    assert interp.get("soa") is interp.soa
    assert ep.loads == 0


def test_entry_point_kind_attribute_is_honoured(
    install_entry_points: Callable[[list[FakeEntryPoint]], list[str]],
) -> None:
    """A plug-in's ``posecast_kind`` attribute sets its kind; without one it is a pair method."""

    def windowed(keys: ArrayLike, times: ArrayLike, t: ArrayLike) -> F64:
        return np.asarray(keys, dtype=np.float64)[..., 1, :]

    windowed.posecast_kind = "window"  # type: ignore[attr-defined]
    install_entry_points(
        [
            FakeEntryPoint("windowed", "plugin:windowed", windowed),
            FakeEntryPoint("hold-first", "plugin:hold_first", hold_first),
        ]
    )
    assert interp.info("windowed").kind == "window"
    assert interp.info("hold-first").kind == "pair"


def test_entry_point_that_is_not_callable_raises_type_error(
    install_entry_points: Callable[[list[FakeEntryPoint]], list[str]],
) -> None:
    """A plug-in whose object is not callable raises TypeError naming it."""
    install_entry_points([FakeEntryPoint("broken", "plugin:CONSTANT", 42)])
    message = r"entry point 'broken' \(plugin:CONSTANT\) is not callable"
    with pytest.raises(TypeError, match=message):
        interp.names()


def test_real_entry_points_lookup_uses_the_group(
    monkeypatch: pytest.MonkeyPatch, isolated_registry: list[str]
) -> None:
    """Patching importlib.metadata.entry_points itself reaches the registry too."""
    import importlib.metadata

    seen: list[str] = []

    def entry_points(*, group: str) -> list[FakeEntryPoint]:
        seen.append(group)
        return [FakeEntryPoint("hold-first", "plugin:hold_first", hold_first)]

    monkeypatch.setattr(importlib.metadata, "entry_points", entry_points)
    assert "hold-first" in interp.names()
    assert seen == [interp.ENTRY_POINT_GROUP]
