"""The bundle shipped in ``tests/data/tiny-box`` (the core-install test's seat) loads, and is
what ``tests/data/make_tiny_bundle.py`` builds: after a bundle format change this fails,
and re-running the script mends it."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np

from hailstorm.runtime import load

DATA = Path(__file__).resolve().parents[1] / "data"


def _script():
    spec = importlib.util.spec_from_file_location("make_tiny_bundle", DATA / "make_tiny_bundle.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_shipped_tiny_bundle_is_small_and_is_what_its_script_builds(tmp_path):
    shipped = load(DATA / "tiny-box")  # verified: hashes, shapes, consistency
    size = sum(f.stat().st_size for f in (DATA / "tiny-box").iterdir())
    assert size < 1024**2, f"the shipped bundle is {size} bytes"
    rebuilt = load(_script().build(tmp_path / "tiny"))
    assert rebuilt.manifest["key"] == shipped.manifest["key"], "re-run python tests/data/make_tiny_bundle.py"
    # the same solve on another day: equal to the factorization's rounding (entries ~1e-5 m/N)
    np.testing.assert_allclose(rebuilt.D, shipped.D, rtol=1e-9, atol=1e-9 * np.abs(shipped.D).max())
    assert json.loads((DATA / "tiny-box" / "manifest.json").read_text())["format_version"] == \
        rebuilt.manifest["format_version"]
