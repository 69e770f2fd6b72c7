"""The front page: its Python example runs as printed, and the page stays a front page.

The snippet is taken from ``README.md`` itself (the one ``python`` block, under
"Python API") and run in a fresh interpreter from the repository's root, as the
README says, with the hailstorm cache in a temporary directory.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"


def python_blocks(text: str) -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", text, flags=re.S | re.M)


def test_readme_python_example_runs(tmp_path):
    blocks = python_blocks(README.read_text())
    assert len(blocks) == 1, "the README has one Python example (more go to examples/)"
    env = dict(os.environ, HAILSTORM_CACHE=str(tmp_path / "cache"), MPLBACKEND="Agg", OMP_NUM_THREADS="1")
    before = set(os.listdir(ROOT))
    proc = subprocess.run([sys.executable, "-c", blocks[0]], cwd=ROOT, env=env, capture_output=True, text=True,
                          timeout=1800)
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    impacts, frames = map(int, lines[-1].split())
    assert frames > 0 and impacts >= 0
    assert "[[" in proc.stdout  # the forces array
    assert set(os.listdir(ROOT)) == before, "the example wrote into the repository"


def test_readme_is_a_front_page():
    text = README.read_text()
    assert len(text.splitlines()) < 150
    for needed in ('pip install -e ".[all]" && hailstorm', 'pip install -e ".[test]" && pytest', "CITATION.cff",
                   "docs/images/storm-frame.png", "## License"):
        assert needed in text
    assert (ROOT / "docs" / "images" / "storm-frame.png").stat().st_size < 300 * 1024
    # no history on the front page: it lives in CHANGELOG.md
    assert not re.search(r"issue #?\d+|this stop|this session", text, flags=re.I)


def test_readme_links_exist():
    text = README.read_text()
    for target in re.findall(r"\]\(([^)#]+)\)", text):
        if "://" not in target:
            assert (ROOT / target).exists(), target
