"""docs/architecture.md against the code: the paths it names exist, every folder has its row,
the import arrows it draws are the code's, and the objects it says resolve each choice exist."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import pytest

from contract.test_import_graph import _graph  # (tests/ is on the import path)

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "architecture.md"


def _text() -> str:
    return PAGE.read_text()


def _folder(module: str) -> str:
    """The drawing's name of a module's folder."""
    parts = module.split(".")
    if parts[0] == "studies":
        return "studies"
    if module in ("hailstorm", "hailstorm.__main__"):
        return module
    if module == "hailstorm.cli":
        return "cli.py"
    if parts[1] == "precompute":
        return "precompute"
    if len(parts) == 2:
        return "face"
    return parts[2]


def test_the_page_is_in_the_docs_table_of_contents():
    assert "\narchitecture\n" in (ROOT / "docs" / "index.md").read_text()


def test_every_path_it_names_exists():
    names = set(re.findall(r"`([\w./-]+\.(?:py|geo|toml|md)|[\w/-]+/)`", _text()))
    files = {p.name for d in ("runtime", "precompute", "meshes", "notebooks", "tests") for p in (ROOT / d).rglob("*")}
    missing = [n for n in sorted(names) if not (ROOT / n).exists() and not (ROOT / "docs" / n).exists()
               and not ("/" not in n.rstrip("/") and n.rstrip("/") in files)]
    assert not missing, missing


def test_every_folder_has_its_row():
    folders = {f"runtime/{p.name}/" for p in (ROOT / "runtime").iterdir() if (p / "__init__.py").is_file()}
    folders |= {"precompute/", "meshes/"}
    rows = set(re.findall(r"^\| `([\w/]+/)` \|", _text(), re.M))
    assert folders <= rows, folders - rows


def test_the_arrows_it_draws_are_the_codes():
    """Each ``X -> a, b`` line of the drawing lists exactly the folders X's modules import
    (the package face and the studies aside)."""
    drawn = {}
    for src, dsts in re.findall(r"^ (\S+?)/?\s+-> (.+?)(?:\s{2,}\(.*\))?$", _text(), re.M):
        names = []
        for part in re.split(r",\s*(?![^{]*\})", dsts):
            part = part.strip().removeprefix("runtime/")
            m = re.fullmatch(r"\{(.+)\}", part)
            names += [x.strip() for x in m.group(1).split(",")] if m else [part]
        drawn[src] = set(names)
    assert {"cli.py", "storm", "precompute", "contact", "bundle"} <= set(drawn), drawn
    code: dict[str, set[str]] = {}
    for m, deps in _graph().items():
        a = _folder(m)
        for d in deps:
            b = _folder(d)
            if a != b and b != "face":
                code.setdefault(a, set()).add(b)
    for src, dsts in drawn.items():
        assert code.get(src, set()) == dsts, (src, sorted(code.get(src, set())), sorted(dsts))


@pytest.mark.parametrize("module, names", [
    ("hailstorm.runtime.contact.validate", ["ContactMode"]),
    ("hailstorm.runtime.storm.hail", ["Integrator", "INTEGRATORS"]),
    ("hailstorm.runtime.storm.scene_sections", ["TimeSettings.min_substep", "ContactSettings.contact_mode"]),
    ("hailstorm.runtime.bundle.read", ["load", "EXPAND_UP_TO"]),
    ("hailstorm.runtime.bundle.compliance", ["reader", "DenseReader.compressed"]),
    ("hailstorm.runtime.bundle.hreader", ["HMatrixReader.compressed"]),
    ("hailstorm.precompute.settings", ["BuildSettings", "RunSettings"]),
    ("hailstorm.precompute.greens", ["SolverSpec", "SOLVER_SPECS", "solver_spec"]),
    ("hailstorm.runtime.resources", ["EXTRAS", "require_extra"]),
    ("hailstorm.runtime.contact.near_field", ["NEAR_FIELDS"]),
    ("hailstorm.runtime.output.storm_output", ["SERIES_FORMATS"]),
])
def test_where_each_choice_is_made_is_where_the_page_says(module, names):
    text = _text()
    path = module.removeprefix("hailstorm.").replace(".", "/") + ".py"
    assert f"`{path}`" in text, path
    mod = importlib.import_module(module)
    for name in names:
        obj = mod
        for part in name.split("."):
            obj = getattr(obj, part)
        assert f"`{name.split('.')[0]}" in text or f"`{name}`" in text, name
