"""Import directions (DESIGN.md, Architecture): every import points down the layers, none in a
circle.

Every module under ``app/`` is parsed (``ast``) and each ``import``/``from ... import``
of ``app.*`` is checked, wherever it stands: at the top, inside a function, or under
``TYPE_CHECKING`` (a type-only import is still a dependency the design forbids).
"""

from __future__ import annotations

import ast
import graphlib
from pathlib import Path

import pytest

APP = Path(__file__).resolve().parents[2] / "app"

#: layer of each top-level part of ``app``, bottom first; a module may import its own
#: package and any lower layer (and the parts in ``ACROSS``). ``capture`` (capture-set I/O) sits
#: under ``calib``: the calibration fit reads capture sets. ``app/__init__.py`` holds only the
#: version and imports nothing, so every layer may read it. ``batch`` (reprocessing on Dask) sits
#: beside ``api``: it reuses the service's calibration carry-over rule.
LAYERS: dict[str, int] = {
    "__init__": -1,
    "core": 0, "atomic": 0,
    "recon": 1, "capture": 1,
    "calib": 2,
    "analysis": 3, "devices": 3,
    "config": 4,
    "service": 5,
    "api": 6, "outputs": 6, "batch": 6,
    "main": 7,
    "cli": 8,
    "__main__": 9,
}

#: imports allowed between two parts of one layer: ``outputs`` (viewer, OpenIGTLink, image
#: encoders) sits beside ``api`` and reads the result slot; the API serves the encoders' images,
#: while an output never imports the API (checked below, and a cycle would fail anyway).
#: ``atomic`` (file writes and JSON reads) refuses hostile JSON with ``core.jsonlimits``.
ACROSS: frozenset[tuple[str, str]] = frozenset({("api", "outputs"), ("atomic", "core")})


def _module_name(path: Path) -> str:
    parts = path.relative_to(APP.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _part(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "__init__"


def _imports(path: Path, source: str | None = None) -> list[tuple[str, int]]:
    """(imported ``app.*`` module, line) for every import in the file (or in ``source``, as if it
    were there)."""
    module = _module_name(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out: list[tuple[str, int]] = []
    text = path.read_text(encoding="utf-8") if source is None else source
    for node in ast.walk(ast.parse(text, str(path))):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            out.append((target, node.lineno))
    return [(t, line) for t, line in out if t == "app" or t.startswith("app.")]


def _all_imports() -> list[tuple[str, str, int]]:
    return [(_module_name(p), target, line)
            for p in sorted(APP.rglob("*.py")) for target, line in _imports(p)]


def test_every_part_has_a_layer():
    parts = {_part(_module_name(p)) for p in APP.rglob("*.py")}
    assert parts <= LAYERS.keys(), f"parts of app without a layer: {sorted(parts - LAYERS.keys())}"


def test_no_import_runs_up_the_layers():
    bad = []
    for module, target, line in _all_imports():
        src, dst = _part(module), _part(target)
        if src == dst or (src, dst) in ACROSS:
            continue
        if LAYERS[dst] >= LAYERS[src]:
            bad.append(f"{module}:{line} imports {target} "
                       f"({src} layer {LAYERS[src]} → {dst} layer {LAYERS[dst]})")
    assert not bad, "imports up or across the layers:\n" + "\n".join(bad)


def test_no_cycle_between_packages():
    graph: dict[str, set[str]] = {}
    for module, target, _ in _all_imports():
        src, dst = _part(module), _part(target)
        if src != dst:
            graph.setdefault(src, set()).add(dst)
    try:
        tuple(graphlib.TopologicalSorter(graph).static_order())
    except graphlib.CycleError as exc:
        pytest.fail(f"import cycle between packages: {' → '.join(exc.args[1])}")


def test_outputs_sit_beside_the_api_and_never_import_it():
    """The outputs read the service (and below); the API may use their encoders, not the reverse."""
    assert LAYERS["outputs"] == LAYERS["api"] < LAYERS["main"]
    assert ("outputs", "api") not in ACROSS
    up = [f"{m}:{line} imports {t}" for m, t, line in _all_imports()
          if _part(m) == "outputs" and _part(t) in {"api", "main", "cli", "__main__"}]
    assert not up, "outputs importing the API or above:\n" + "\n".join(up)
    assert (APP / "outputs" / "igtl.py").is_file() and not (APP / "viewer").exists()


def test_checker_sees_relative_and_nested_imports(tmp_path):
    """The parser resolves relative imports and finds imports inside functions and TYPE_CHECKING."""
    src = ("from typing import TYPE_CHECKING\nfrom . import fast\nif TYPE_CHECKING:\n"
           "    from app.calib import x\ndef f():\n    import app.service.instrument\n")
    found = {t for t, _ in _imports(APP / "recon" / "probe.py", src)}
    assert found == {"app.recon", "app.calib", "app.service.instrument"}
    assert _part("app.calib") == "calib"
    assert LAYERS[_part("app.service.instrument")] > LAYERS["calib"]


def _module_edges() -> dict[str, set[str]]:
    """Module → the ``app`` modules it imports, file by file.

    ``from app.pkg import name`` counts as an import of ``app.pkg.name`` when that is a module
    (a submodule named in the import), else of ``app.pkg`` (a name its ``__init__`` holds).
    """
    modules = {_module_name(p) for p in APP.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for path in sorted(APP.rglob("*.py")):
        module = _module_name(path)
        package = module if path.name == "__init__.py" else module.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                    base_name = ".".join(base + ([node.module] if node.module else []))
                else:
                    base_name = node.module or ""
                targets = [f"{base_name}.{a.name}" if f"{base_name}.{a.name}" in modules
                           else base_name for a in node.names]
            for target in targets:
                if target in modules and target != module:
                    graph.setdefault(module, set()).add(target)
    return graph


def test_no_cycle_between_modules():
    """No two files import each other, directly or round a longer loop (a package's own too)."""
    try:
        tuple(graphlib.TopologicalSorter(_module_edges()).static_order())
    except graphlib.CycleError as exc:
        pytest.fail(f"import cycle between modules: {' → '.join(exc.args[1])}")
