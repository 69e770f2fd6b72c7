"""The storm driver, the scene file and the output writers (synthetic plate, short runs)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from runtime.storm import Scene, SceneError, Storm, run_storm
from test_hail import plate_gf


@pytest.fixture(scope="module")
def gf():
    return plate_gf()


@pytest.fixture(scope="module")
def short_storm(gf):
    sc = Scene(duration=0.1, stones=12, seed=7, spawn_height=0.02, r_min=0.003, r_max=0.008, fps=100.0)
    return run_storm(gf, sc, progress=False)


def test_scene_default_and_round_trip(tmp_path):
    sc = Scene.default()
    assert sc.integrator == "implicit" and sc.mode == "frictionless"
    custom = Scene(duration=0.05, stones=3, seed=11, wind=(1.0, 0.0, 0.0), mode="sticky", integrator="symplectic")
    p = tmp_path / "scene.toml"
    custom.to_toml(p)
    assert Scene.from_toml(p) == custom
    # a partial file keeps the defaults for the rest
    p.write_text("[storm]\nduration = 1\n")
    s2 = Scene.from_toml(p)
    assert s2.duration == 1.0 and s2.rate == sc.rate and s2.stones is None


@pytest.mark.parametrize(
    "text, match",
    [
        ("[storm]\ndurration = 1.0\n", "unknown key 'durration' in \\[storm\\]"),
        ("[stormy]\nduration = 1.0\n", "unknown section \\[stormy\\]"),
        ("[time]\ndt = -1e-4\n", "dt must be a positive"),
        ("[contact]\nrestitution = 1.5\n", "restitution"),
        ("[time]\nintegrator = 'rk4'\n", "integrator"),
        ("[hail]\nr_min = 0.01\nr_max = 0.005\n", "r_max"),
        ("[storm]\nduration = \n", "not valid TOML"),
    ],
)
def test_scene_bad_values(tmp_path, text, match):
    p = tmp_path / "bad.toml"
    p.write_text(text)
    with pytest.raises(SceneError, match=match):
        Scene.from_toml(p)


def test_storm_no_nan_no_penetration(short_storm, gf):
    st = short_storm.stats
    assert st["hailstones"] == 12
    assert st["impacts"] >= 5
    for f in short_storm.frames:
        assert np.all(np.isfinite(f.displacement)) and np.all(np.isfinite(f.positions))
    # Stated tolerance: no stone overlaps the deformed surface by more than 5% of the
    # smallest radius. (The overlap is not zero: the contact point itself follows the
    # stone exactly, but the piecewise-linear dent around a point load tilts its
    # triangles into the sphere's cap; on this plate ~3% of r_min.)
    assert st["max_penetration_m"] < 0.05 * 0.003
    assert st["max_contact_force"] > 0 and np.isfinite(st["max_contact_force"])
    assert short_storm.frames[-1].t == pytest.approx(0.1)
    assert len(short_storm.frames) == 11


def test_storm_reproducible(gf, short_storm):
    again = run_storm(gf, short_storm.scene, progress=False)
    assert again.stats["impacts"] == short_storm.stats["impacts"]
    assert np.array_equal(again.frames[-1].positions, short_storm.frames[-1].positions)


def test_storm_sticky_symplectic_runs(gf):
    sc = Scene(duration=0.03, stones=4, seed=1, spawn_height=0.01, mode="sticky", integrator="symplectic", r_min=0.004)
    res = run_storm(gf, sc, progress=False)
    assert all(np.all(np.isfinite(f.displacement)) for f in res.frames)
    assert res.stats["max_penetration_m"] < 0.05 * 0.004


def test_clamped_triangle_is_a_hard_wall(gf):
    # a corner triangle of the plate has all its vertices clamped: the stone bounces off it
    sc = Scene(duration=0.05, stones=0, drag=False, restitution=0.5)
    st = Storm(gf, sc, spawn=False)
    t = int(np.flatnonzero(gf.fixed[gf.triangles].all(axis=1))[0])
    c = gf.vertices[gf.triangles[t]].mean(axis=0)
    st.add_stones(c + [0, 0, 0.005 + 1e-3], [0, 0, -1.0], 0.005)
    while st.t < 0.01:
        st.step()
    assert st.stats["wall_contacts"] >= 1
    assert st.vel[0, 2] > 0.3  # bounced with e = 0.5 (minus gravity)


def test_outputs(tmp_path, gf, short_storm):
    from runtime.output import write_animation, write_paraview, write_summary

    s = write_summary(short_storm, tmp_path / "summary.json")
    data = json.loads(s.read_text())
    for key in ("hailstones", "impacts", "max_contact_force", "sim_time_s", "wall_time_s", "max_indentation_m",
                "max_simultaneous_contacts", "steps", "real_time_factor", "seed", "dt"):
        assert key in data
    pvd = write_paraview(short_storm, gf, tmp_path / "pv")
    assert pvd.suffix == ".pvd" and pvd.is_file()
    import meshio

    m = meshio.read(next((tmp_path / "pv" / "frames").glob("surface_*.vtu")))
    assert "displacement" in m.point_data and "|u|" in m.point_data
    out = write_animation(short_storm, gf, tmp_path / "storm.mp4", max_frames=4, dpi=50)
    assert out.is_file() and out.stat().st_size > 0


def test_short_storm_on_the_seat(seat_bundle):
    """The real (coarse) seat bundle: a short storm stays finite and bounded."""
    from runtime.bundle import load

    gf = load(seat_bundle)
    sc = Scene(duration=0.04, stones=6, seed=3, spawn_height=0.01)
    res = run_storm(gf, sc, progress=False)
    st = res.stats
    assert st["impacts"] >= 1
    assert all(np.all(np.isfinite(f.displacement)) for f in res.frames)
    assert st["max_penetration_m"] < 0.25 * sc.r_min  # curved seat, coarse dents: looser than the plate
    assert np.isfinite(st["max_contact_force"]) and st["max_contact_force"] > 0
