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


@pytest.fixture(scope="module")
def exact_storm(gf):
    sc = Scene(duration=0.1, stones=12, seed=7, spawn_height=0.02, r_min=0.003, r_max=0.008, fps=100.0,
               integrator="exact", dt=5e-4)
    return run_storm(gf, sc, progress=False)


def test_exact_storm_no_nan_bounded_penetration_reproducible(gf, exact_storm):
    st = exact_storm.stats
    assert st["hailstones"] == 12 and st["impacts"] >= 5
    for f in exact_storm.frames:
        assert np.all(np.isfinite(f.displacement)) and np.all(np.isfinite(f.positions))
    assert st["max_penetration_m"] < 0.05 * 0.003  # same tolerance as the implicit storm
    assert st["substeps"] < 2 * st["steps"]  # no omega-dt sub-steps: only time-of-impact splits
    again = run_storm(gf, exact_storm.scene, progress=False)
    assert np.array_equal(again.frames[-1].positions, exact_storm.frames[-1].positions)
    assert np.array_equal(again.frames[-1].displacement, exact_storm.frames[-1].displacement)


def test_frame_displacement_is_the_full_surface_response(gf, exact_storm):
    """Only candidate vertices are deformed in the loop; the recorded frame is the
    full-surface response D[:, V] B f of the contact forces at that instant."""
    sc = exact_storm.scene
    st = Storm(gf, sc)
    while st.t < 0.1 - 1e-12:
        st.step()
        ids, f = st.contact_forces()
        if ids.size:
            break
    assert ids.size
    cc = st.cache
    keep = st.ctri[cc.stones] >= 0
    u_ref = np.zeros((st.n, 3))
    for k in np.flatnonzero(keep):  # superpose the point-force responses
        fk = f[np.flatnonzero(ids == cc.stones[k])[0]]  # force on the seat
        u_ref += gf.displacement(gf.triangles[cc.tris[k]], np.outer(cc.bary[k], fk))
    assert np.allclose(st.frame().displacement, u_ref, rtol=1e-4, atol=1e-9)
    # and a local evaluation agrees with the full one
    v = np.arange(0, st.n, 7)
    assert np.allclose(st._u_at(v), st.u[v])


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


def test_closest_point_and_index_match_brute_force(gf):
    """Narrow phase: the vectorised closest point (against dense sampling of each
    triangle) and the sampled k-d index query (against all triangles), including the
    ball-query fallback and a local displacement callback."""
    from runtime.collide import SurfaceIndex, closest_point_on_triangles

    rng = np.random.default_rng(0)
    A, B, C, P = (rng.normal(size=(300, 3)) for _ in range(4))
    cp, bc = closest_point_on_triangles(P, A, B, C)
    assert np.all(bc >= 0) and np.allclose(bc.sum(axis=1), 1.0)
    uv = rng.random((4000, 2))
    uv = np.where(uv.sum(axis=1, keepdims=True) > 1, 1 - uv, uv)
    for i in range(300):
        S = A[i] + uv[:, :1] * (B[i] - A[i]) + uv[:, 1:] * (C[i] - A[i])
        assert np.linalg.norm(cp[i] - P[i]) <= np.linalg.norm(S - P[i], axis=1).min() + 1e-12
    # a lifted, bumpy copy of the plate (a non-flat surface) and brute force over all triangles
    V = gf.vertices.copy()
    V[:, 2] = 0.01 * np.sin(40 * V[:, 0]) * np.cos(30 * V[:, 1])
    T = np.asarray(gf.triangles)
    u = np.zeros_like(V)
    u[:, 2] = -0.002 * np.exp(-((V[:, 0] - 0.06) ** 2 + V[:, 1] ** 2) / 2e-4)
    Q = rng.uniform(V.min(axis=0) - 0.01, V.max(axis=0) + 0.01, (200, 3))
    reach = rng.uniform(0.001, 0.03, 200)
    for knn in (48, 3):  # 3: every query takes the ball-query fallback
        idx = SurfaceIndex(V, T)
        idx.KNN = knn
        for disp in (None, lambda v: u[v]):
            q = idx.query(Q, reach, displacement=disp, max_displacement=0.002 if disp else 0.0)
            X = V + (u if disp else 0.0)
            assert np.isfinite(q.distance).sum() > 30  # the test sees hits and misses
            for i in range(200):
                cpi, _ = closest_point_on_triangles(np.repeat(Q[i:i + 1], len(T), 0), X[T[:, 0]], X[T[:, 1]], X[T[:, 2]])
                d = np.linalg.norm(cpi - Q[i], axis=1).min()
                if d <= reach[i]:
                    assert q.distance[i] == pytest.approx(d, rel=1e-9, abs=1e-12)
                else:
                    assert q.triangle[i] == -1 and np.isinf(q.distance[i])
