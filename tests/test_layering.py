"""The architecture, checked on the source: a ground, walls and a roof, no import cycles, modules of a readable size.

Every import counts, also one inside a function (it runs when the function does); only imports
under ``if TYPE_CHECKING:`` are left out (they never run).
"""

from __future__ import annotations

import ast
import gc
from functools import cache, lru_cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# The rules, as data. Each top-level package of the project and the packages it may import.
MAY_IMPORT: dict[str, set[str]] = {
    "orbitct": set(),  # the ground: geometry, scan files, orbits, phantoms, simulator, progress
    "devices": {"orbitct"},  # walls
    "acquire": {"orbitct", "devices"},
    "calib": {"orbitct"},
    "recon": {"orbitct"},
    "orbitct_app": {"orbitct", "devices", "acquire", "calib", "recon"},  # the roof: CLI, REST service, console
    "orbitct_bluesky": {"orbitct", "devices", "acquire", "calib"},  # the adapter for bluesky stacks: nothing imports it
}
ROOF = "orbitct_app"  # nothing imports it
# Modules that may not import a part of their own package: drivers never see their twins.
# (module prefix, forbidden prefix, exceptions: modules of the prefix that may)
MODULE_RULES: list[tuple[str, str, set[str]]] = [
    ("devices", "devices.twins", {"devices.sim", "devices.twins"}),
]


def _parse(path: Path) -> ast.Module:
    # Python 3.11.7 can fail in ast.parse when garbage collection runs Python code mid-parse
    # ("AST constructor recursion depth mismatch", fixed in 3.11.8): parse with the collector paused.
    source = path.read_text(encoding="utf-8")
    gc.disable()  # (no gc.collect() first: in a test process with a large heap that took minutes over the tree)
    try:
        return ast.parse(source, filename=str(path))
    finally:
        gc.enable()


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


@lru_cache(maxsize=1)
def _modules() -> dict[str, Path]:
    out: dict[str, Path] = {}
    for package in MAY_IMPORT:
        for path in sorted((ROOT / package).rglob("*.py")):
            out[_module_name(path)] = path
    return out


def _type_checking_nodes(tree: ast.Module) -> set[int]:
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for stmt in node.body for n in ast.walk(stmt))
    return skip


@cache
def imports_of(module: str, *, for_types: bool = False) -> frozenset[str]:
    """Project modules that ``module`` imports (a package import means its ``__init__``); with ``for_types`` also
    those imported only for type checking (a design dependency, though it never runs)."""
    path = _modules()[module]
    tree = _parse(path)
    skip = set() if for_types else _type_checking_nodes(tree)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    known = _modules()
    found: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(
                    package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else [])
                )
            names = [base] + [f"{base}.{a.name}" for a in node.names]
        else:
            continue
        for name in names:
            if name in known:
                found.add(name)
    found.discard(module)
    return frozenset(found)


def _top(module: str) -> str:
    return module.split(".")[0]


def test_every_package_imports_only_what_its_layer_allows() -> None:
    bad = []
    for module in _modules():
        for target in imports_of(module):
            top, other = _top(module), _top(target)
            if other != top and other not in MAY_IMPORT[top]:
                bad.append(
                    f"{module} imports {target} ({top} may import {sorted(MAY_IMPORT[top]) or 'nothing of ours'})"
                )
    assert not bad, "imports against the layers:\n" + "\n".join(bad)


def test_nothing_imports_the_roof() -> None:
    bad = [f"{m} imports {t}" for m in _modules() if _top(m) != ROOF for t in imports_of(m) if _top(t) == ROOF]
    for script in sorted((ROOT / "benchmarks").glob("*.py")):
        bad += [f"benchmarks/{script.name} imports {n}" for n in _raw_imports(script) if _top(n) == ROOF]
    assert not bad, "the roof is imported by:\n" + "\n".join(bad)


def _raw_imports(path: Path) -> set[str]:
    names: set[str] = set()
    for node in ast.walk(_parse(path)):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            names.add(node.module)
    return names


@pytest.mark.parametrize("prefix, forbidden, allowed", MODULE_RULES)
def test_module_rules(prefix: str, forbidden: str, allowed: set[str]) -> None:
    def under(name: str, root: str) -> bool:
        return name == root or name.startswith(root + ".")

    bad = [
        f"{m} imports {t}"
        for m in _modules()
        if under(m, prefix) and not any(under(m, a) for a in allowed)
        for t in imports_of(m)
        if under(t, forbidden)
    ]
    assert not bad, f"modules of {prefix} importing {forbidden}:\n" + "\n".join(bad)


def _cycles(graph: dict[str, frozenset[str]]) -> list[list[str]]:
    state: dict[str, int] = {}  # 1 on the current path, 2 done
    cycles: list[list[str]] = []

    def visit(node: str, path: list[str]) -> None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph[node]):
            if state.get(nxt) == 1:
                cycles.append(path[path.index(nxt) :] + [nxt])
            elif nxt not in state:
                visit(nxt, path)
        path.pop()
        state[node] = 2

    for module in sorted(graph):
        if module not in state:
            visit(module, [])
    return cycles


def test_the_module_import_graph_has_no_cycles() -> None:
    cycles = _cycles({m: imports_of(m) for m in _modules()})
    assert not cycles, "import cycles:\n" + "\n".join(" -> ".join(c) for c in cycles[:20])


def _package_of(module: str) -> str:
    return module if _modules()[module].name == "__init__.py" else module.rpartition(".")[0]


def test_no_cycles_inside_a_package_even_through_type_hints() -> None:
    """Inside one package the modules form a hierarchy: no two import each other, not even for their type hints
    (a package's ``__init__``, which gathers its public names, is left out: it imports its modules by design)."""
    inner = {m for m in _modules() if _modules()[m].name != "__init__.py"}
    graph = {
        m: frozenset(t for t in imports_of(m, for_types=True) if t in inner and _package_of(t) == _package_of(m))
        for m in inner
    }
    cycles = _cycles(graph)
    assert not cycles, "import cycles inside a package:\n" + "\n".join(" -> ".join(c) for c in cycles[:20])


#: the most lines a module may have (as formatted by ruff); a module that grows past it has more than one job
MAX_MODULE_LINES = 900


def test_no_module_is_over_the_size_limit() -> None:
    sizes = {m: len(p.read_text(encoding="utf-8").splitlines()) for m, p in _modules().items()}
    big = sorted((n, m) for m, n in sizes.items() if n > MAX_MODULE_LINES)
    assert not big, f"modules over {MAX_MODULE_LINES} lines: " + ", ".join(f"{m} ({n})" for n, m in big[::-1])


def test_the_rules_cover_every_package() -> None:
    packages = {p.name for p in ROOT.iterdir() if (p / "__init__.py").is_file()} - {"tests"}
    assert packages == set(MAY_IMPORT), f"packages without a layer rule: {sorted(packages - set(MAY_IMPORT))}"
