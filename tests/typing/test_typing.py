"""The author API type-checks: mypy --strict accepts a fully typed model (tests/typing/typed_model.py) and the
typed modules of agents/."""
from __future__ import annotations

import inspect
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent.parent
TYPED = ["agents/__init__.py", "agents/model.py", "agents/runtime.py", "agents/testing.py", "agents/__main__.py",
         "agents/registry.py"]


def mypy_strict(*args: str) -> subprocess.CompletedProcess[str]:
    """mypy --strict on ``args`` (paths, or -c CODE) from the checkout's root."""
    pytest.importorskip("mypy")
    return subprocess.run([sys.executable, "-m", "mypy", "--strict", "--ignore-missing-imports",
                           "--follow-imports=silent", *args],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)


def test_typed_model_passes_mypy_strict():
    """A model written against the author API with full annotations is accepted by mypy --strict."""
    r = mypy_strict("tests/typing/typed_model.py")
    assert r.returncode == 0, r.stdout + r.stderr


def test_agents_package_passes_mypy_strict():
    """The author API, the runtime, the checker, the registry and the entry point are strictly typed."""
    r = mypy_strict(*TYPED)
    assert r.returncode == 0, r.stdout + r.stderr


def test_agents_ships_py_typed():
    """agents/ tells type checkers that it carries annotations."""
    assert (ROOT / "agents" / "py.typed").is_file()


def test_mypy_sees_a_wrong_declaration():
    """The annotations mean something: a parameter declared without Param is a type error."""
    r = mypy_strict("-c", "from agents import Model\n\nclass Bad(Model):\n    params = {'x': 1.0}\n")
    assert r.returncode == 1 and 'expected "str": "Param"' in r.stdout, r.stdout + r.stderr


def test_public_api_is_documented():
    """Every public class and function of agents/ (and every public method of those classes) has a docstring."""
    import agents
    import agents.model
    import agents.registry
    import agents.runtime
    import agents.testing

    missing = []
    for mod in (agents, agents.model, agents.runtime, agents.testing, agents.registry):
        for name in mod.__all__:
            obj = getattr(mod, name)
            if not (inspect.isclass(obj) or inspect.isfunction(obj)):
                continue  # type aliases and tables carry their doc in the module
            if not (obj.__doc__ or "").strip():
                missing.append(f"{mod.__name__}.{name}")
            for attr, member in vars(obj).items() if inspect.isclass(obj) else ():
                fn = getattr(member, "__func__", getattr(member, "fget", member))
                if not attr.startswith("_") and inspect.isfunction(fn) and not (fn.__doc__ or "").strip():
                    missing.append(f"{mod.__name__}.{name}.{attr}")
    assert not missing, missing
