"""What ``protocol`` exports: each module's ``__all__`` names exactly its public definitions, every one of
them exists, and the package re-exports the same objects (in the spirit of httpx's
tests/test_exported_members.py)."""
from __future__ import annotations

import ast
import importlib
import pkgutil
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

import protocol

MODULES = sorted(m.name for m in pkgutil.iter_modules(protocol.__path__))


def _module(name: str) -> ModuleType:
    return importlib.import_module(f"protocol.{name}")


def _public_definitions(module: ModuleType) -> set[str]:
    """The names the module's own top-level statements define (classes, functions, assignments; not imports,
    nothing under ``if``), without a leading underscore."""
    assert module.__file__ is not None
    names: set[str] = set()
    for node in ast.parse(Path(module.__file__).read_text()).body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, ast.Assign):
            names.update(n.id for target in node.targets for n in ast.walk(target) if isinstance(n, ast.Name))
        elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
            names.add(node.target.id)
    return {n for n in names if not n.startswith("_")}


def test_the_modules_are_the_expected_ones() -> None:
    assert MODULES == ["codec", "config", "errors", "geometry", "joints", "keys", "messages", "robot", "ros2",
                       "security"]


@pytest.mark.parametrize("name", MODULES)
def test_every_exported_name_exists(name: str) -> None:
    module = _module(name)
    exported = module.__all__
    assert len(exported) == len(set(exported)), f"protocol.{name}.__all__ lists a name twice"
    missing = [n for n in exported if not hasattr(module, n)]
    assert not missing, f"protocol.{name}.__all__ lists names it does not define: {missing}"


@pytest.mark.parametrize("name", MODULES)
def test_every_public_definition_is_exported(name: str) -> None:
    module = _module(name)
    assert set(module.__all__) == _public_definitions(module)


def test_the_package_exports_its_modules_and_reexports_the_same_objects() -> None:
    exported = protocol.__all__
    assert len(exported) == len(set(exported))
    assert set(MODULES) <= set(exported)
    for n in exported:
        value = getattr(protocol, n)
        if n in MODULES:
            assert value is _module(n)
            continue
        homes = [m for m in MODULES if n in _module(m).__all__]
        assert len(homes) == 1, f"protocol.{n} is exported by {homes}"
        assert value is getattr(_module(homes[0]), n)


def test_star_import_gives_the_package_exports() -> None:
    namespace: dict[str, object] = {}
    exec("from protocol import *", namespace)
    assert set(namespace) - {"__builtins__"} == set(protocol.__all__)


def test_an_unknown_name_is_an_attribute_error() -> None:
    with pytest.raises(AttributeError, match="no_such_name"):
        protocol.no_such_name  # type: ignore[attr-defined]  # the point: it does not exist  # noqa: B018


def test_importing_keys_and_errors_stays_light() -> None:
    """The re-exports are loaded on first use: keys and errors need none of the heavy dependencies."""
    code = ("import sys, protocol, protocol.keys, protocol.errors\n"
            "print(sorted(m for m in ('numpy', 'msgpack', 'mcap', 'cryptography', 'zenoh') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=Path(__file__).resolve().parent.parent,
                         capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"
