"""The tree keeps its shape: the conductor's core stays a short story, no class outgrows 600 lines, no function
in conductor/, agents/ or protocol/ is above cyclomatic complexity 30, there is no import circle among the
project's modules, and the packages import only downwards (protocol <- agents; protocol <- conductor; the
tools recordings/ and bench/ on top; nothing installed imports tests/)."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("protocol", "agents", "conductor", "recordings", "bench")
# what each package may import of the others (besides itself)
ALLOWED = {
    "protocol": set(),
    "agents": {"protocol"},
    "conductor": {"protocol", "recordings", "bench"},  # only the command line registers the tools' commands
    "recordings": {"protocol", "agents", "conductor"},
    "bench": {"protocol", "agents", "conductor", "recordings"},
}


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts = parts[:-1]
            out[".".join(parts)] = path
    return out


def _imports(name: str, path: Path, known: set[str]) -> set[str]:
    """Project modules that ``name`` imports, at any depth of the file (lazy imports count too)."""
    is_pkg = path.name == "__init__.py"
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            mod = node.module or ""
            if node.level:
                mod = ".".join(base[: len(base) - node.level + 1] + ([mod] if mod else []))
            targets = [mod] + [f"{mod}.{a.name}" for a in node.names]
        for t in targets:
            while t and t not in known:
                t = t.rpartition(".")[0]
            if t and t != name:
                found.add(t)
    return found


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    known = set(mods)
    return {name: _imports(name, path, known) for name, path in mods.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return out


def _package_of(module: str) -> str:
    return module.split(".")[0]


def _is_submodule(child: str, parent: str) -> bool:
    return child.startswith(parent + ".")


def test_no_import_circles():
    graph = _graph()
    # a package's __init__ re-exporting its own modules is not a circle worth the name
    pruned = {m: {d for d in deps if not _is_submodule(d, m)} for m, deps in graph.items()}
    assert _cycles(pruned) == []


def test_packages_import_only_downwards_and_never_the_tests():
    bad = []
    for path in (p for pkg in PACKAGES for p in (ROOT / pkg).rglob("*.py")):
        text = path.read_text()
        if "import tests" in text or "from tests" in text:
            bad.append(f"{path.relative_to(ROOT)} imports tests")
    for mod, deps in _graph().items():
        pkg = _package_of(mod)
        for d in deps:
            if _package_of(d) != pkg and _package_of(d) not in ALLOWED[pkg]:
                bad.append(f"{mod} imports {d}")
    cli_only = [f"{m} imports {d}" for m, deps in _graph().items() if _package_of(m) == "conductor"
                and not m.startswith("conductor.cli") for d in deps if _package_of(d) in ("recordings", "bench")]
    assert bad + cli_only == []


def test_the_core_stays_small_and_no_class_outgrows_600_lines():
    core = (ROOT / "conductor" / "core.py").read_text().count("\n")
    assert core < 500, f"conductor/core.py has {core} lines"
    big = []
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > 600:
                    big.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.name}")
    assert big == []


def test_no_function_above_cyclomatic_complexity_30():
    radon = pytest.importorskip("radon.complexity")
    over = []
    for pkg in ("conductor", "agents", "protocol"):
        for path in (ROOT / pkg).rglob("*.py"):
            for block in radon.cc_visit(path.read_text()):
                if block.complexity > 30:
                    over.append(f"{path.relative_to(ROOT)}:{block.lineno} {block.name} ({block.complexity})")
    assert over == []
