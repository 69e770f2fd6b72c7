"""The package's import graph: no cycles, and the storm driver is a leaf that only the
CLI and the package faces import (its parts take explicit inputs, never the storm); arrows run down."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: import name -> folder (pyproject's package-dir mapping)
PACKAGES = {"hailstorm.runtime": ROOT / "runtime", "hailstorm.precompute": ROOT / "precompute",
            "studies": ROOT / "notebooks" / "studies"}


def _modules() -> dict[str, Path]:
    mods = {"hailstorm": ROOT / "__init__.py", "hailstorm.__main__": ROOT / "__main__.py", "hailstorm.cli": ROOT / "cli.py"}
    for pkg, folder in PACKAGES.items():
        for f in folder.rglob("*.py"):
            rel = f.relative_to(folder).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            mods[".".join([pkg, *parts])] = f
    return mods


def _is_type_checking(node: ast.If) -> bool:
    t = node.test
    return (isinstance(t, ast.Name) and t.id == "TYPE_CHECKING") or (
        isinstance(t, ast.Attribute) and t.attr == "TYPE_CHECKING")


def _imports(path: Path, mods: dict[str, Path], *, typing: bool = False) -> set[str]:
    """The package modules a module imports (at any depth of its code, type-checking blocks aside
    unless ``typing``)."""
    out: set[str] = set()
    todo: list[ast.AST] = [ast.parse(path.read_text())]
    while todo:
        node = todo.pop()
        if isinstance(node, ast.If) and _is_type_checking(node) and not typing:
            todo.extend(node.orelse)
            continue
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name in mods)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                if sub in mods:
                    out.add(sub)
                elif node.module in mods:
                    out.add(node.module)
        todo.extend(ast.iter_child_nodes(node))
    return out


def _graph(*, typing: bool = False) -> dict[str, set[str]]:
    mods = _modules()
    return {m: _imports(p, mods, typing=typing) - {m} for m, p in mods.items()}


@pytest.mark.parametrize("typing", [False, True], ids=["run-time", "with-type-checking-imports"])
def test_the_import_graph_has_no_cycles(typing):
    """No cycle, not even through an import made for type checking alone (a circle a reader of
    the imports still sees: issue 45, 0 circles)."""
    graph = _graph(typing=typing)
    assert "hailstorm.runtime.compiled.flight" in graph and graph["hailstorm.runtime.storm.driver"]  # the scan sees them
    state: dict[str, int] = {}  # 1: on the path, 2: done
    path: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        path.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                cycle = path[path.index(n):] + [n]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if n not in state:
                visit(n)
        path.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)


def test_only_the_cli_and_the_package_faces_import_the_storm_driver():
    """The driver (``Storm``) is imported only by the storm's run (``run_storm``) and the
    package faces; the run only by the faces and the command line."""
    graph = _graph()
    importers = {m for m, deps in graph.items() if "hailstorm.runtime.storm.driver" in deps}
    assert importers <= {"hailstorm", "hailstorm.runtime", "hailstorm.runtime.storm", "hailstorm.runtime.storm.run"}, importers
    run_importers = {m for m, deps in graph.items() if "hailstorm.runtime.storm.run" in deps}
    assert run_importers <= {"hailstorm", "hailstorm.runtime", "hailstorm.runtime.storm", "hailstorm.cli"}, run_importers
    assert "hailstorm.runtime" in importers and "hailstorm.runtime" in run_importers


def test_no_storm_part_takes_the_storm():
    """The parts' modules never name the Storm (no TYPE_CHECKING import of it, no 'st: Storm')."""
    parts = ["stones", "seat", "collide", "contact_set", "patches", "soft_contacts", "integrators", "recording"]
    for name in parts:
        text = (ROOT / "runtime" / "storm" / f"{name}.py").read_text()
        assert not re.search(r":\s*Storm\b|import\s+Storm\b|\bStorm\)|\bst\._", text), name


def _private_imports(path: Path) -> list[str]:
    """``from hailstorm... import _name`` and imports of ``hailstorm...._module`` in a file."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 and node.module.startswith("hailstorm"):
            if any(p.startswith("_") and not p.startswith("__") for p in node.module.split(".")):
                out.append(node.module)
            out.extend(f"{node.module}.{a.name}" for a in node.names
                       if a.name.startswith("_") and not a.name.startswith("__"))
        elif isinstance(node, ast.Import):
            out.extend(a.name for a in node.names if a.name.startswith("hailstorm")
                       and any(p.startswith("_") and not p.startswith("__") for p in a.name.split(".")))
    return out


def test_no_module_imports_another_modules_private_names():
    found = {m: bad for m, p in _modules().items() if (bad := _private_imports(p))}
    assert not found, f"private names imported across modules: {found}"


def test_the_private_import_check_sees_one(tmp_path):
    f = tmp_path / "m.py"
    f.write_text("from hailstorm.runtime.compiled.grid import _hidden, public\nimport hailstorm.runtime._secret\n")
    assert _private_imports(f) == ["hailstorm.runtime.compiled.grid._hidden", "hailstorm.runtime._secret"]


def test_the_runtime_never_imports_the_offline_stage_or_the_cli():
    """Arrows run down: no module of hailstorm.runtime imports hailstorm.precompute or hailstorm.cli,
    and the scene sits with the storm it configures (runtime/storm/scene.py)."""
    graph = _graph()
    up = {m: sorted(d for d in deps if d.startswith(("hailstorm.precompute", "hailstorm.cli")))
          for m, deps in graph.items() if m.startswith("hailstorm.runtime")}
    assert not {m: d for m, d in up.items() if d}
    assert "hailstorm.runtime.storm.scene" in graph


def test_the_settings_records_import_nothing_of_the_storm():
    """The settings' ground (``runtime/sections.py``, its ``SceneError`` too) and the default seat's
    record (``runtime/seat_settings.py``) import nothing of ``hailstorm.runtime.storm``: the storm's
    scene builds on them, so an import the other way would run back up (issue: a lean house)."""
    graph = _graph()
    for m in ("hailstorm.runtime.sections", "hailstorm.runtime.seat_settings"):
        assert m in graph
        assert not sorted(d for d in graph[m] if d.startswith("hailstorm.runtime.storm")), m
    from hailstorm.runtime.sections import SceneError
    from hailstorm.runtime.storm.errors import SceneError as reexported, StormTooLarge

    assert reexported is SceneError and issubclass(StormTooLarge, SceneError)


def test_the_old_scene_path_is_gone():
    """``hailstorm.runtime.scene`` (a deprecated shim since the scene moved to the storm's folder)
    is removed (issue: a lean house); the scene is ``hailstorm.runtime.Scene``."""
    import importlib
    import sys

    sys.modules.pop("hailstorm.runtime.scene", None)
    assert not (ROOT / "runtime" / "scene.py").exists()
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module("hailstorm.runtime.scene")
    from hailstorm.runtime import Scene
    from hailstorm.runtime.storm.scene import Scene as where

    assert Scene is where


def _module_level_imports(path: Path) -> set[str]:
    """Top-level names of the packages a module imports when it is imported (function bodies aside)."""
    out: set[str] = set()
    todo: list[ast.AST] = list(ast.parse(path.read_text()).body)
    while todo:
        node = todo.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            continue
        if isinstance(node, ast.If) and _is_type_checking(node):
            todo.extend(node.orelse)
            continue
        if isinstance(node, ast.Import):
            out.update(a.name.split(".")[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module.split(".")[0])
        todo.extend(ast.iter_child_nodes(node))
    return out


def test_no_module_imports_an_optional_extra_when_it_is_imported():
    """The core install imports every module (the CLI reads the offline stage's defaults): the
    extras' packages are imported inside the functions that need them (require_extra)."""
    from hailstorm.runtime.resources import EXTRAS

    extras = {m for modules in EXTRAS.values() for m in modules}
    found = {m: sorted(_module_level_imports(p) & extras) for m, p in _modules().items()
             if m.startswith("hailstorm")}
    assert not {m: d for m, d in found.items() if d}
    assert _module_level_imports(ROOT / "tests" / "cli" / "test_cli.py") & extras  # the scan sees one


def test_the_package_never_imports_the_studies():
    """The studies are not in the wheel (they run from the repository, ``notebooks/studies``)."""
    found = {m: sorted(d) for m, deps in _graph().items() if m.startswith("hailstorm")
             and (d := {n for n in deps if n.split(".")[0] == "studies"})}
    assert not found
