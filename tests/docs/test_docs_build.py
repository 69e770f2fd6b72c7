"""The documentation builds with warnings as errors, and its reference tables match the code.

The build is the one the docs describe, ``sphinx-build -W --keep-going -b html
docs OUT``, run in a subprocess (autodoc imports the package; the command-line
pages run ``hailstorm ... --help``). Skipped, saying why, when Sphinx or
myst-parser is not installed (``pip install -e ".[test]"`` installs both).
"""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOCS = ROOT / "docs"

PAGES = ["index", "getting-started", "cli", "scenes", "outputs", "examples", "api", "how-it-works",
         "architecture", "bundle-format", "verification", "validity", "choosing-settings", "performance", "scale"]

needs_sphinx = pytest.mark.skipif(
    importlib.util.find_spec("sphinx") is None or importlib.util.find_spec("myst_parser") is None,
    reason="the docs build needs sphinx and myst-parser: pip install -e '.[docs]' (or '.[test]')")


@needs_sphinx
def test_docs_build_without_warnings(tmp_path):
    out = tmp_path / "html"
    proc = subprocess.run([sys.executable, "-m", "sphinx", "-W", "--keep-going", "-b", "html", "-q", str(DOCS),
                           str(out)], capture_output=True, text=True, timeout=1800)
    assert proc.returncode == 0, f"sphinx-build failed:\n{proc.stdout}\n{proc.stderr}"
    for page in PAGES:
        assert (out / f"{page}.html").is_file(), page
    api = (out / "api.html").read_text()
    for name in ("hailstorm.runtime.load", "hailstorm.runtime.solve_contacts", "hailstorm.runtime.run_storm",
                 "hailstorm.precompute.build_bundle"):
        assert f'id="{name}"' in api, name
    cli = (out / "cli.html").read_text()
    assert "--mesh-size" in cli and "--scene" in cli  # the parsers' own help, inserted at build time


def documented_summary_keys() -> set[str]:
    text = (DOCS / "outputs.md").read_text()
    table = text[text.index("(summary-keys)="):]
    keys: set[str] = set()
    for line in table.splitlines():
        if line.startswith("| `"):
            keys.update(re.findall(r"`([A-Za-z_]+)`", line.split("|")[1]))
    return keys


def test_summary_table_lists_exactly_the_keys_a_storm_writes():
    from helpers import plate_gf

    from hailstorm.runtime import Scene, run_storm
    from hailstorm.runtime.output.files import summary

    gf = plate_gf()
    result = run_storm(gf, Scene.from_flat(duration=0.01, stones=2), progress=False)
    keys = set(summary(result)) | {"bundle"}  # "bundle" is written only with a bundle on disk
    assert documented_summary_keys() == keys


def test_every_page_is_in_the_toctree():
    index = (DOCS / "index.md").read_text()
    pages = {p.stem for p in DOCS.glob("*.md")} - {"index"}
    assert pages == set(PAGES) - {"index"}
    for page in pages:
        assert re.search(rf"^{re.escape(page)}$", index, flags=re.M), page


def test_module_table_matches_the_tree():
    """Every module of the package is named in "How it works"'s module table, and every path it names exists."""
    text = (DOCS / "how-it-works.md").read_text()
    table = text[text.index("## Modules"):]
    named = set(re.findall(r"`((?:runtime|precompute|meshes|notebooks)/[\w/.]*)`", table))
    for path in named:
        assert (ROOT / path).exists(), path
    short = set(re.findall(r"`(\w+\.py)`", table))
    for folder in ("precompute", "runtime/bundle", "runtime/contact", "runtime/inertia", "runtime/storm", "runtime/output"):
        for module in (ROOT / folder).glob("*.py"):
            if module.name != "__init__.py":
                rel = f"{folder}/{module.name}"
                assert rel in named or module.name in short, f"{rel} is missing from the module table"
    for module in (ROOT / "runtime" / "compiled").glob("*.py"):
        if module.name != "__init__.py":
            assert f"`{module.stem}`" in table, f"runtime/compiled/{module.name} is missing from the module table"


def test_citation_file_is_cff_1_2_and_names_this_version():
    yaml = pytest.importorskip("yaml", reason="reading CITATION.cff needs PyYAML")
    import hailstorm

    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff["cff-version"] == "1.2.0"
    assert cff["version"] == hailstorm.__version__
    for key in ("message", "title", "authors"):
        assert cff[key]


def test_changelog_has_this_version():
    import hailstorm

    text = (ROOT / "CHANGELOG.md").read_text()
    assert "## [Unreleased]" in text
    assert f"## [{hailstorm.__version__}]" in text


def test_api_page_documents_every_public_name():
    import hailstorm.precompute
    import hailstorm.runtime

    text = (DOCS / "api.md").read_text()
    for module in (hailstorm.runtime, hailstorm.precompute):
        for name in module.__all__:
            assert re.search(rf"^\.\. auto\w+:: {re.escape(module.__name__)}\.{name}$", text, flags=re.M), \
                f"{module.__name__}.{name} is public but not in docs/api.md"


def test_front_page_picture_script_renders_a_frame(tmp_path, box_bundle):
    """``docs/storm_frame.py`` (the README's picture) runs; here on a small box and a short storm."""
    import os

    out = tmp_path / "frame.png"
    env = dict(os.environ, MPLBACKEND="Agg", OMP_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, str(DOCS / "storm_frame.py"), "--gf", str(box_bundle), "--duration",
                           "0.03", "--size", "640", "360", "--out", str(out)], capture_output=True, text=True,
                          env=env, timeout=900)
    assert proc.returncode == 0, proc.stderr
    assert "stone(s) in contact" in proc.stdout
    from matplotlib.image import imread

    assert imread(out).shape[:2] == (360, 640)
