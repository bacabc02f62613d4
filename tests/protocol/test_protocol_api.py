"""The package surface: re-exports, __all__ everywhere, and no imports of other posecast code."""

from __future__ import annotations

import ast
import importlib
import pkgutil
import sys
from pathlib import Path

from support import import_root

from posecast import protocol

PACKAGE_DIR = Path(protocol.__file__).parent
MODULES = sorted(
    f"posecast.protocol.{info.name}" for info in pkgutil.iter_modules([str(PACKAGE_DIR)])
)
ALLOWED_ROOTS = {"protocol", "numpy", "msgpack", "__future__"} | set(sys.stdlib_module_names)


def test_every_module_declares_all() -> None:
    """Every protocol module declares __all__ and every listed name exists."""
    for name in MODULES:
        module = importlib.import_module(name)
        assert isinstance(module.__all__, list), name
        for exported in module.__all__:
            assert hasattr(module, exported), f"{name}.{exported}"


def test_package_reexports_exactly_all() -> None:
    """The package's public names are exactly its __all__, with no duplicates."""
    public = {name for name in vars(protocol) if not name.startswith("_")}
    submodules = {name.rsplit(".", 1)[1] for name in MODULES}
    assert set(protocol.__all__) == public - submodules
    assert len(protocol.__all__) == len(set(protocol.__all__))


def test_public_modules_reexported() -> None:
    """Everything the public modules export is also reachable from the package."""
    for name in ("errors", "events", "limits", "messages", "poses", "session", "wire"):
        module = importlib.import_module(f"posecast.protocol.{name}")
        missing = set(module.__all__) - set(protocol.__all__)
        assert not missing, f"protocol.{name}: {missing}"


def test_imports_only_stdlib_numpy_msgpack() -> None:
    """protocol imports nothing of ours and no I/O framework: stdlib, numpy, msgpack only."""
    for path in PACKAGE_DIR.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level:
                roots = {PACKAGE_DIR.name}  # a relative import stays in the package
            elif isinstance(node, ast.Import):
                roots = {import_root(alias.name) for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module == "posecast":
                roots = {import_root(f"posecast.{alias.name}") for alias in node.names}
            elif isinstance(node, ast.ImportFrom):
                roots = {import_root(node.module or "")}
            else:
                continue
            assert roots <= ALLOWED_ROOTS, f"{path.name} imports {roots - ALLOWED_ROOTS}"
            assert not roots & {"asyncio", "socket", "time", "selectors"}, path.name


def test_every_module_has_a_docstring() -> None:
    """Every protocol module says what it owns in its docstring."""
    for name in MODULES:
        assert importlib.import_module(name).__doc__, name
