"""The command line, end to end, as a user runs it."""

import subprocess
import sys

import numpy as np
import pytest
from skfem import condense, solve

import hailstorm.runtime
from hailstorm.precompute import mesh_default_seat
from hailstorm.precompute.fem import clamp_dofs, elasticity_basis, stiffness_matrix, vertex_dofs


def run_cli(*args, check=True):
    return subprocess.run([sys.executable, "-m", "hailstorm", *map(str, args)],
                          capture_output=True, text=True, check=check, timeout=600)


def test_precompute_then_load_agrees_with_independent_fem(tmp_path):
    out = tmp_path / "gf"
    run = run_cli("precompute", "--mesh-size", 0.01, "--order", 1, "--load", "point", "--out", out, "-q")
    assert run.returncode == 0, run.stderr
    gf = hailstorm.runtime.load(out)
    # an independent solve: mesh again, assemble, scikit-fem's own condense/solve
    mesh = mesh_default_seat(0.01)
    assert np.array_equal(mesh.points, gf.volume_points)
    basis = elasticity_basis(mesh, 1)
    K = stiffness_matrix(basis, gf.young, gf.poisson)
    rng = np.random.default_rng(7)
    cols = rng.choice(gf.contact_vertices, size=3, replace=False)
    rows = np.arange(gf.n_vertices)
    block = gf.compliance(rows, cols)
    for k, j in enumerate(cols):
        f = np.zeros(K.shape[0])
        f[vertex_dofs(basis, [gf.surface_nodes[j]])[0, 1]] = 1.0
        u = solve(*condense(K, f, D=clamp_dofs(basis, mesh)))
        expected = u[vertex_dofs(basis, gf.surface_nodes).ravel()]
        assert np.linalg.norm(block[:, 3 * k + 1] - expected) <= 1e-6 * np.linalg.norm(expected)


def test_info_describes_a_bundle(box_bundle):
    run = run_cli("info", box_bundle)
    assert "contactable" in run.stdout and "D " in run.stdout


@pytest.mark.parametrize("args, message", [
    (["precompute", "--poisson", "0.5"], "Poisson"),
    (["precompute", "--young", "-3"], "Young"),
    (["precompute", "--geometry", "/no/such/seat.step"], "does not exist"),
    (["info", "/no/such/bundle"], "does not exist"),
])
def test_bad_input_gives_clear_error(tmp_path, args, message):
    if args[0] == "precompute":
        args = [*args, "--out", tmp_path / "b"]
    run = run_cli(*args, check=False)
    assert run.returncode != 0
    assert message in run.stderr
    assert "Traceback" not in run.stderr
    assert not (tmp_path / "b").exists()


def test_usage_errors_exit_2(tmp_path):
    run = run_cli("precompute", "--order", "3", "--out", tmp_path / "b", check=False)
    assert run.returncode == 2 and "invalid choice" in run.stderr
    run = run_cli("precompute", "--mesh-size", "-1", "--out", tmp_path / "b", check=False)
    assert run.returncode == 2 and "positive" in run.stderr


SUMMARY_KEYS = {"hailstones", "impacts", "max_contact_force", "sim_time_s", "wall_time_s",
                "max_indentation_m", "max_simultaneous_contacts", "steps", "real_time_factor"}


def test_storm_writes_animation_paraview_and_summary(seat_bundle, tmp_path):
    import json

    out = tmp_path / "run"
    run = run_cli("storm", "--duration", 0.06, "--stones", 8, "--seed", 3, "--gf", seat_bundle, "--out", out, "-q")
    assert run.returncode == 0, run.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert SUMMARY_KEYS <= set(summary)
    assert summary["hailstones"] == 8 and summary["sim_time_s"] == pytest.approx(0.06)
    assert (out / "storm.mp4").stat().st_size > 1000 or (out / "storm.gif").exists()
    assert (out / "storm.vtkhdf").is_file() and not (out / "frames").exists()  # the series in one file
    # reproducible from the seed
    again = tmp_path / "again"
    run_cli("storm", "--duration", 0.06, "--stones", 8, "--seed", 3, "--gf", seat_bundle, "--out", again,
              "-q", "--no-video")
    s2 = json.loads((again / "summary.json").read_text())
    for key in ("impacts", "max_contact_force", "max_indentation_m", "steps"):
        assert s2[key] == summary[key], key


def test_bare_hailstorm_runs_the_default_storm(tmp_path, monkeypatch):
    """`hailstorm` alone: builds and caches the default seat, runs the default storm."""
    import json
    import os

    env = {**os.environ, "HAILSTORM_CACHE": str(tmp_path / "cache"), "MPLBACKEND": "Agg"}
    run = subprocess.run([sys.executable, "-m", "hailstorm.cli", "--out", str(tmp_path / "out"), "--no-video"],
                         capture_output=True, text=True, env=env, cwd=tmp_path, timeout=900)
    assert run.returncode == 0, run.stderr[-2000:]
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert summary["hailstones"] > 0 and summary["impacts"] > 0
    bundles = [d for d in (tmp_path / "cache").iterdir() if (d / "manifest.json").is_file()]
    assert len(bundles) == 1  # one cached bundle (beside it: verified/, the load's verification stamps)
    assert "real_time_factor" in run.stdout


def test_bad_scene_file_gives_clear_error(tmp_path):
    scene = tmp_path / "scene.toml"
    scene.write_text("[storm]\nduraton = 1.0\n")
    run = run_cli("storm", "--scene", scene, "--out", tmp_path / "o", check=False)
    assert run.returncode == 3 and "duraton" in run.stderr and "Traceback" not in run.stderr


def test_storm_integrator_and_dt_from_the_command_line(seat_bundle, tmp_path):
    import json

    out = tmp_path / "run"
    run = run_cli("storm", "--duration", 0.02, "--stones", 3, "--integrator", "exact", "--dt", 5e-4,
                    "--gf", seat_bundle, "--out", out, "-q", "--no-video")
    assert run.returncode == 0, run.stderr
    s = json.loads((out / "summary.json").read_text())
    assert s["integrator"] == "exact" and s["dt"] == 5e-4 and s["steps"] == 40
    assert s["scene"]["time"]["integrator"] == "exact"
    run = run_cli("storm", "--integrator", "verlet", "--out", tmp_path / "o", check=False)
    assert run.returncode == 2 and "invalid choice" in run.stderr


def test_unknown_command_is_a_usage_error(tmp_path):
    run = run_cli("bogus", "--out", tmp_path / "o", check=False)
    assert run.returncode == 2 and "unknown command 'bogus'" in run.stderr and "storm" in run.stderr
    assert not (tmp_path / "o").exists()


def test_backend_option_is_gone(tmp_path):
    """The storm always runs its compiled kernels: no --backend, and a scene's old
    [compute] section is refused in one line that says what to do."""
    run = run_cli("storm", "--backend", "numpy", "--out", tmp_path / "o", check=False)
    assert run.returncode == 2 and "--backend" in run.stderr
    scene = tmp_path / "old.toml"
    scene.write_text('[compute]\nbackend = "numpy"\n')
    run = run_cli("storm", "--scene", scene, "--out", tmp_path / "o", check=False)
    assert run.returncode == 3 and "Traceback" not in run.stderr
    assert "[compute]" in run.stderr and "remove" in run.stderr and len(run.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "o").exists()


def test_precompute_tol_stores_d_compressed_and_info_prints_its_error(tmp_path):
    out = tmp_path / "gf"
    run = run_cli("precompute", "--mesh-size", 0.015, "--order", 1, "--load", "point", "--tol", 1e-3,
                  "--out", out, "-q")
    assert run.returncode == 0, run.stderr
    gf = hailstorm.runtime.load(out)
    assert gf.manifest["format_version"] == 3 and gf.manifest["compliance"]["tol"] == 1e-3
    info = run_cli("info", out).stdout
    err = gf.manifest["compliance"]["error"]
    assert "as an H-matrix" in info
    assert f"tol 0.001: measured against {err['columns']} exact columns" in info
    assert f"max {err['max']:.2e}" in info
    # small: the contact API reads its expansion (float32 from tol 1e-5 up: 4 bytes an entry)
    assert gf.dtype == np.float32 and not gf.reads_hmatrix
    mib = np.prod(gf.manifest["compliance"]["shape"]) * 4 / 2**20
    assert f"read it from D expanded once into the cache (the float32 expansion: {mib:.1f} MiB" in info


@pytest.mark.parametrize("tol", ["0.5", "0", "-1e-3", "nan"])
def test_precompute_tol_out_of_range_is_one_line_exit_3(tmp_path, tol):
    run = run_cli("precompute", "--mesh-size", 0.015, "--order", 1, f"--tol={tol}", "--out", tmp_path / "b",
                  check=False)
    assert run.returncode == 3, run.stderr
    assert run.stderr.count("\n") == 1 and "compression tolerance" in run.stderr and "[1e-12, 0.1]" in run.stderr
    assert not (tmp_path / "b").exists()


def test_precompute_stream_without_tol_is_one_line_exit_3(tmp_path):
    run = run_cli("precompute", "--mesh-size", 0.015, "--order", 1, "--stream", "--out", tmp_path / "b", check=False)
    assert run.returncode == 3, run.stderr
    assert run.stderr.count("\n") == 1 and "--stream needs --tol" in run.stderr
    assert not (tmp_path / "b").exists()


def test_scene_seat_coarsening_reaches_the_default_seat_build(tmp_path, monkeypatch):
    """`[seat] coarsening` is the default seat's precompute setting: passed to build_bundle as read."""
    from hailstorm import cli
    from hailstorm.precompute import pipeline

    seen = {}

    class Stop(Exception):
        pass

    def fake_build(*args, **kw):
        seen.update(kw)
        raise Stop

    monkeypatch.setattr(pipeline, "build_bundle", fake_build)
    scene = tmp_path / "scene.toml"
    scene.write_text("[seat]\ncoarsening = 5.0\n")
    with pytest.raises(Stop):
        cli.main(["-q", "storm", "--scene", str(scene), "--out", str(tmp_path / "o"), "--no-video"])
    assert seen["coarsening"] == 5.0 and seen["mesh_size"] == 0.006
    scene.write_text("[seat]\nmesh_size = 0.004\n")  # left out: the packaged default
    with pytest.raises(Stop):
        cli.main(["-q", "storm", "--scene", str(scene), "--out", str(tmp_path / "o"), "--no-video"])
    assert seen["coarsening"] == 2.5 and seen["mesh_size"] == 0.004


@pytest.mark.parametrize("value", ["0.5", "'wide'", "nan"])
def test_scene_seat_bad_coarsening_is_one_line_exit_3(tmp_path, value):
    scene = tmp_path / "scene.toml"
    scene.write_text(f"[seat]\ncoarsening = {value}\n")
    run = run_cli("storm", "--scene", scene, "--out", tmp_path / "o", check=False)
    assert run.returncode == 3 and "coarsening" in run.stderr and "Traceback" not in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1 and not (tmp_path / "o").exists()
