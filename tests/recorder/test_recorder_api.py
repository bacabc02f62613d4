"""The recorder package surface: __all__ and docstrings everywhere, allowed imports only."""

from __future__ import annotations

import ast
import importlib
import pkgutil
import sys
from pathlib import Path

from support import import_root

from posecast import recorder

PACKAGE_DIR = Path(recorder.__file__).parent
MODULES = sorted(
    f"posecast.recorder.{info.name}" for info in pkgutil.iter_modules([str(PACKAGE_DIR)])
)
# recorder sits beside scenarios: it may use its QoE and traces (never the reverse).
ALLOWED_ROOTS = {"recorder", "protocol", "interp", "scenarios", "numpy", "mcap", "zstandard", "lz4"}
ALLOWED_ROOTS |= {"msgpack"}  # the writer process reads update frames
ALLOWED_ROOTS |= {"__future__"} | set(sys.stdlib_module_names)


def test_every_module_declares_all_and_a_docstring() -> None:
    """Every recorder module has a docstring and an __all__ whose names exist."""
    assert MODULES
    for name in ["posecast.recorder", *MODULES]:
        module = importlib.import_module(name)
        assert module.__doc__, name
        assert isinstance(module.__all__, list), name
        for exported in module.__all__:
            assert hasattr(module, exported), f"{name}.{exported}"


def test_package_reexports_exactly_all() -> None:
    """The package's public names are exactly its __all__, without duplicates."""
    public = {name for name in vars(recorder) if not name.startswith("_")}
    submodules = {name.rsplit(".", 1)[1] for name in MODULES}
    assert set(recorder.__all__) == public - submodules
    assert len(recorder.__all__) == len(set(recorder.__all__))


def test_imports_nothing_from_server_or_client() -> None:
    """recorder uses only the stdlib, numpy, mcap (zstd, lz4), protocol and interp."""
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
