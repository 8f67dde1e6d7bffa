"""The import direction of the architecture, checked on the source: lower layers never import upper ones."""

from __future__ import annotations

import ast
import gc
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
CORE_MODULES = {"geometry", "rotations", "kinematics", "scanfile", "progress", "orbits", "errorprofiles", "phantoms", "simulator"}

# package (or orbitct core) -> top-level packages it must never import
FORBIDDEN = {
    "calib": {"acquire", "devices", "recon", "orbitct_app.cli", "orbitct_app.service"},
    "recon": {"acquire", "devices", "calib", "orbitct_app.cli", "orbitct_app.service"},
    "devices": {"acquire", "calib", "recon", "orbitct_app.cli", "orbitct_app.service"},
    "acquire": {"orbitct_app.cli", "orbitct_app.service"},
    "orbitct-core": {"acquire", "devices", "calib", "recon", "orbitct_app.cli", "orbitct_app.service"},
}


def _imports(path: Path) -> set[str]:
    # Python 3.11.7 can fail in ast.parse when garbage collection runs Python code mid-parse
    # ("AST constructor recursion depth mismatch", fixed in 3.11.8): parse with the collector paused.
    source = path.read_text(encoding="utf-8")
    gc.collect()
    gc.disable()
    try:
        tree = ast.parse(source, filename=str(path))
    finally:
        gc.enable()
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


def _files(layer: str) -> list[Path]:
    if layer == "orbitct-core":
        out: list[Path] = []
        for name in CORE_MODULES:
            p = ROOT / "orbitct" / name
            out += sorted(p.rglob("*.py")) if p.is_dir() else ([p.with_suffix(".py")] if p.with_suffix(".py").exists() else [])
        return out
    return sorted((ROOT / layer).rglob("*.py"))


@pytest.mark.parametrize("layer", sorted(FORBIDDEN))
def test_layer_does_not_import_upward(layer: str) -> None:
    bad = []
    for f in _files(layer):
        for name in _imports(f):
            for forbidden in FORBIDDEN[layer]:
                if name == forbidden or name.startswith(forbidden + "."):
                    bad.append(f"{f.relative_to(ROOT)} imports {name}")
    assert not bad, "imports against the architecture:\n" + "\n".join(bad)
