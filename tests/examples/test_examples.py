"""Every script in ``examples/`` runs, in its small mode (``--small``: tiny meshes, short storms).

Each runs as a user would run it (``python examples/NAME.py --small`` in a fresh
working directory, a subprocess) with the hailstorm cache in a temporary
directory shared by the examples (the small block's bundle is built once), and
the test checks what the example says it shows, not only its exit code.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    return tmp_path_factory.mktemp("hailstorm-cache")


def run_example(name: str, cwd: Path, cache: Path, *args: str, stderr: list[str] | None = None) -> str:
    """The example's stdout (its stderr appended to ``stderr`` if given)."""
    env = dict(os.environ, HAILSTORM_CACHE=str(cache), MPLBACKEND="Agg", OMP_NUM_THREADS="1")
    proc = subprocess.run([sys.executable, str(EXAMPLES / f"{name}.py"), *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=1800)
    assert proc.returncode == 0, f"{name} failed ({proc.returncode}):\n{proc.stdout}\n{proc.stderr}"
    if stderr is not None:
        stderr.append(proc.stderr)
    return proc.stdout


def test_every_example_is_tested():
    tested = {"api_walkthrough", "layered_materials", "user_geometry", "scene_file", "read_paraview",
              "speed_vs_accuracy", "compressed_bundle"}
    assert {p.stem for p in EXAMPLES.glob("*.py")} == tested


def test_api_walkthrough(tmp_path, cache):
    out = run_example("api_walkthrough", tmp_path, cache, "--small")
    for step in ("bundle:", "solve_contacts:", "capacitance:", "press_spheres:", "run_storm (frames in memory):",
                 "write_animation:", "StormOutput:", "convert_bundle: D float32"):
        assert step in out, out
    assert (tmp_path / "walkthrough-out" / "summary.json").is_file()
    assert (tmp_path / "walkthrough-out" / "storm.vtkhdf").is_file()


def test_layered_materials(tmp_path, cache):
    err: list[str] = []
    out = run_example("layered_materials", tmp_path, cache, "--small", stderr=err)
    assert "pad: E = 500000 Pa, nu = 0.3, shell: E = 2e+09 Pa, nu = 0.4" in out
    assert "on the stiff shell" in out  # the script itself fails if the shell did not make the dent shallower
    assert "thinner than one element" not in err[0], err[0]  # its mesh resolves its own layers (a lean house)


def test_compressed_bundle(tmp_path, cache):
    out = run_example("compressed_bundle", tmp_path, cache, "--small")
    assert "as an H-matrix" in out and "measured against 200 exact columns" in out  # `hailstorm info`
    line = next(x for x in out.splitlines() if x.startswith("D stored:"))
    stored, dense = (float(x.split(" MiB")[0].split()[-1]) for x in line.split(" against "))
    assert stored < 0.6 * dense  # the script itself fails if the forces differ by more than the tolerance


def test_user_geometry(tmp_path, cache):
    out = run_example("user_geometry", tmp_path, cache, "--small")
    assert "verified manifest hash" in out  # `hailstorm info`
    assert (tmp_path / "user-geometry-out" / "storm" / "summary.json").is_file()


def test_scene_file(tmp_path, cache):
    out = run_example("scene_file", tmp_path, cache, "--small")
    assert "[time] dt = 0.0005" in out
    assert "ran: integrator exact, dt 0.0005 s, 5 stones" in out
    assert (tmp_path / "scene-out" / "changed.toml").is_file()


def test_read_paraview(tmp_path, cache):
    """Both series read back, each with its own independent reader (h5py, meshio): the same frames."""
    one = run_example("read_paraview", tmp_path, cache, "--small")
    assert "frames of" in one and "the deepest dent" in one
    (tmp_path / "read-paraview-out").rename(tmp_path / "first")
    other = run_example("read_paraview", tmp_path, cache, "--small", "--series", "vtu")
    assert (tmp_path / "read-paraview-out" / "storm.pvd").is_file()
    assert [ln for ln in one.splitlines() if not ln.startswith("$")] == \
        [ln for ln in other.splitlines() if not ln.startswith("$")]


def test_read_paraview_needs_a_run(tmp_path, cache):
    env = dict(os.environ, HAILSTORM_CACHE=str(cache))
    proc = subprocess.run([sys.executable, str(EXAMPLES / "read_paraview.py")], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and "give a storm's output directory" in proc.stderr


def test_speed_vs_accuracy(tmp_path, cache):
    out = run_example("speed_vs_accuracy", tmp_path, cache, "--small", "--out", "plot.png")
    assert out.count("   P1 ") == 3 and out.count("   P2 ") == 3, out
    assert (tmp_path / "plot.png").stat().st_size > 1000


def test_the_examples_default_outputs_are_ignored_by_git():
    """Run from the repository's root, an example writes its default ``--out`` (and
    read_paraview.py its run) there: git ignores every one of them."""
    import re
    import shutil
    import subprocess

    root = Path(__file__).resolve().parents[2]
    if shutil.which("git") is None or not (root / ".git").exists():
        pytest.skip("not a git checkout")
    names = set()
    for script in (root / "examples").glob("*.py"):
        names |= set(re.findall(r'Path\("([^"/]+)"\)', script.read_text()))
    assert {"compressed-out", "speed_vs_accuracy.png", "read-paraview-out"} <= names
    paths = [n if "." in n else f"{n}/" for n in names]  # the folders as folders
    proc = subprocess.run(["git", "check-ignore", "--no-index", *paths], cwd=root, capture_output=True, text=True)
    ignored = {p.rstrip("/") for p in proc.stdout.split()}
    assert ignored == names, names - ignored
