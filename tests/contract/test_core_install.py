"""The core install: ``pip install hailstorm`` without extras loads a bundle, solves
contacts and runs a storm, with none of the offline stage's or the video's packages.

A fresh virtual environment gets the project alone (pip's cache is reused); the
storm runs on the bundle shipped in ``tests/data/tiny-box`` (built by
``tests/data/make_tiny_bundle.py``). The test prints the core's site-packages size
beside this (full, ``[test]``) environment's. ``.ci/run`` runs it after the README's
test command (it is slow: an install and a first compile of the storm's kernels).

Run it alone with ``python -m pytest tests/contract/test_core_install.py -m slow -s``.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
TINY = ROOT / "tests" / "data" / "tiny-box"
#: import names of the extras' packages that must not come with the core
NOT_IN_CORE = ("gmsh", "skfem", "meshio", "pyamg", "cholespy", "matplotlib", "imageio", "imageio_ffmpeg",
               "distributed", "h5py")

#: a contact on the tiny box, solved in both installs (printed as JSON by the core's interpreter)
CONTACT = """
import json, sys
import numpy as np
from hailstorm.runtime import load, solve_contacts
gf = load(sys.argv[1])
tri = int(np.flatnonzero(gf.contactable[gf.triangles].all(axis=1))[0])
sol = solve_contacts(gf, [tri], [[1 / 3, 1 / 3, 1 / 3]], [[0.0, 0.0, -1e-4]])
print(json.dumps({"triangle": tri, "forces": sol.forces.tolist()}))
"""


def _site_packages_bytes(python: Path | str) -> int:
    purelib = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             check=True, capture_output=True, text=True).stdout.strip()
    return sum(f.stat().st_size for f in Path(purelib).rglob("*") if f.is_file() and not f.is_symlink())


def _env(tmp_path: Path) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env.update(HAILSTORM_CACHE=str(tmp_path / "cache"), NUMBA_CACHE_DIR=str(tmp_path / "numba"), CI="true")
    return env


@pytest.fixture(scope="module")
def core_venv(tmp_path_factory) -> Path:
    """A fresh venv holding hailstorm's core install (``pip install <repo>``, no extras).

    pip installs a copy of the repository (no ``.git``, no earlier ``build/``): a
    non-editable install builds in the source tree, and a stale ``build/lib`` would
    put modules deleted since into the wheel.
    """
    base = tmp_path_factory.mktemp("core")
    src = base / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".git", "build", "*.egg-info", "__pycache__", "dist",
                                                             ".pytest_cache", "_build"))
    venv = base / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    python = venv / "bin" / "python"
    done = subprocess.run([str(python), "-m", "pip", "install", "--quiet", "--disable-pip-version-check", str(src)],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    return venv


@pytest.mark.slow
def test_the_core_install_has_no_extra_and_runs_a_storm(core_venv, tmp_path):
    python, env = core_venv / "bin" / "python", _env(tmp_path)
    found = subprocess.run([str(python), "-c", "import importlib.util as u, sys; "
                            f"print(' '.join(m for m in {NOT_IN_CORE!r} if u.find_spec(m)))"],
                           check=True, capture_output=True, text=True, cwd=tmp_path, env=env).stdout.split()
    assert found == [], f"the core install brought {found}"
    studies = subprocess.run([str(python), "-c", "import hailstorm.studies"], capture_output=True, text=True,
                             cwd=tmp_path, env=env)
    assert studies.returncode != 0, "the studies are in the wheel"

    out = tmp_path / "storm"
    run = subprocess.run([str(core_venv / "bin" / "hailstorm"), "storm", "--gf", str(TINY), "--duration", "0.05",
                          "--stones", "20", "--seed", "3", "--out", str(out)],
                         capture_output=True, text=True, cwd=tmp_path, env=env)
    assert run.returncode == 0, run.stderr[-3000:]
    # no video extra: one note naming it, and every other output
    notes = [line for line in run.stderr.splitlines() if "hailstorm[video]" in line]
    assert len(notes) == 1 and notes[0].startswith("note: no animation"), run.stderr[-2000:]
    # no series extra: the per-frame .vtu files, said in one note
    notes = [line for line in run.stderr.splitlines() if "hailstorm[series]" in line]
    assert len(notes) == 1 and notes[0].startswith("note: the ParaView series as .vtu"), run.stderr[-2000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["hailstones"] == 20 and summary["impacts"] > 0
    assert (out / "impacts.csv").read_text().count("\n") == summary["impacts"] + 1  # a header and a row per impact
    assert not (out / "storm.mp4").exists() and not (out / "storm.gif").exists()
    # the frames, read back by this environment's meshio (an independent reader of the format)
    meshio = pytest.importorskip("meshio")
    frames = sorted((out / "frames").glob("surface_*.vtu"))
    assert len(frames) == summary["frames"] > 0
    seat = meshio.read(frames[-1])
    assert seat.points.shape == (len(np.load(TINY / "vertices.npy")), 3)
    assert np.isfinite(seat.point_data["displacement"]).all()

    # the API: a contact solved in the core install is the one this (full) install solves
    core = json.loads(subprocess.run([str(python), "-c", CONTACT, str(TINY)], check=True, capture_output=True,
                                     text=True, cwd=tmp_path, env=env).stdout)
    full = json.loads(subprocess.run([sys.executable, "-c", CONTACT, str(TINY)], check=True, capture_output=True,
                                     text=True, cwd=tmp_path, env=env).stdout)
    assert core["triangle"] == full["triangle"]
    # the same code and bundle, maybe other numpy/BLAS builds: equal to rounding of a 3 x 3 solve
    np.testing.assert_allclose(core["forces"], full["forces"], rtol=1e-9)
    assert core["forces"][0][2] < 0  # the force on the seat that presses it down by 0.1 mm

    core_mb = _site_packages_bytes(python) / 2**20
    full_mb = _site_packages_bytes(sys.executable) / 2**20
    print(f"\nsite-packages: core install {core_mb:.0f} MiB, this environment ({sysconfig.get_paths()['purelib']}) "
          f"{full_mb:.0f} MiB")


@pytest.mark.slow
def test_the_core_install_names_the_extra_an_offline_command_needs(core_venv, tmp_path):
    env = _env(tmp_path)
    hailstorm = str(core_venv / "bin" / "hailstorm")
    for argv, extra in ((["precompute", "--out", str(tmp_path / "gf")], "precompute"),
                        (["--out", str(tmp_path / "storm")], "precompute")):  # the default storm meshes the seat
        run = subprocess.run([hailstorm, *argv], capture_output=True, text=True, cwd=tmp_path, env=env)
        assert run.returncode == 3, run.stderr[-2000:]
        lines = run.stderr.strip().splitlines()
        assert len(lines) == 1 and f"pip install 'hailstorm[{extra}]'" in lines[0], run.stderr
    assert not (tmp_path / "gf").exists() and not (tmp_path / "storm").exists()
