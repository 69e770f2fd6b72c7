"""The storm driver, the scene file and the output writers (synthetic plate, short runs)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from hailstorm.runtime.storm.scene import Scene, SceneError
from hailstorm.runtime.storm.driver import Storm
from hailstorm.runtime.storm.run import run_storm
from helpers import drop_on_seat_top


@pytest.fixture(scope="module")
def short_storm(gf):
    sc = Scene.from_flat(duration=0.1, stones=12, seed=7, spawn_height=0.02, r_min=0.003, r_max=0.008, fps=100.0)
    return run_storm(gf, sc, progress=False)


def test_scene_default_and_round_trip(tmp_path):
    sc = Scene.default()
    assert sc.time.integrator == "exact" and sc.contact.mode == "frictionless"
    # patch contact is the default for hail, in the packaged scene and the dataclass alike
    assert sc.contact.patch == Scene().contact.patch == "hertz"
    assert sc.contact.patch_min_radius == Scene().contact.patch_min_radius == 1e-3
    assert sc.contact.patch_tolerance == Scene().contact.patch_tolerance == 0.2
    pt = Scene.from_flat(patch="none", patch_min_radius=5e-4, patch_tolerance=0.5)
    pp = tmp_path / "point.toml"
    pt.to_toml(pp)
    assert Scene.from_toml(pp) == pt
    custom = Scene.from_flat(duration=0.05, stones=3, seed=11, wind=(1.0, 0.0, 0.0), mode="sticky", integrator="symplectic")
    p = tmp_path / "scene.toml"
    custom.to_toml(p)
    assert Scene.from_toml(p) == custom
    # a partial file keeps the defaults for the rest
    p.write_text("[storm]\nduration = 1\n")
    s2 = Scene.from_toml(p)
    assert s2.storm.duration == 1.0 and s2.storm.rate == sc.storm.rate and s2.storm.stones is None


@pytest.mark.parametrize(
    "text, match",
    [
        ("[storm]\ndurration = 1.0\n", "unknown key 'durration' in \\[storm\\]"),
        ("[stormy]\nduration = 1.0\n", "unknown section \\[stormy\\]"),
        ("[time]\ndt = -1e-4\n", "dt must be a positive"),
        ("[time]\ndt = 1.0\n", "dt .* must not exceed duration"),
        ("[contact]\nrestitution = 1.5\n", "restitution"),
        ("[time]\nintegrator = 'rk4'\n", "integrator"),
        ("[hail]\nr_min = 0.01\nr_max = 0.005\n", "r_max"),
        ("[storm]\nduration = \n", "not valid TOML"),
        ("[contact]\npatch = 'point'\n", "patch must be 'hertz' or 'none'"),
        ("[contact]\npatch_min_radius = -0.001\n", "patch_min_radius"),
        ("[contact]\npatch_tolerance = -0.1\n", "patch_tolerance"),
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
    sc = Scene.from_flat(duration=0.1, stones=12, seed=7, spawn_height=0.02, r_min=0.003, r_max=0.008, fps=100.0,
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


@pytest.mark.parametrize("patch", ["hertz", "none"])
def test_frame_displacement_is_the_full_surface_response(gf, exact_storm, patch):
    """Only candidate vertices are deformed in the loop; the recorded frame is the
    full-surface response D[:, V] B f of the contact forces at that instant
    (B: the patch weights, or the barycentric ones of a point contact)."""
    sc = exact_storm.scene.with_(patch=patch)
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
    for k in np.flatnonzero(keep):  # superpose the vertex-force responses
        fk = f[np.flatnonzero(ids == cc.stones[k])[0]]  # force on the seat
        if patch == "none":
            assert cc.patch_radius[k] == 0.0
            u_ref += gf.displacement(gf.triangles[cc.tris[k]], np.outer(cc.bary[k], fk))
        else:
            assert cc.patch_radius[k] >= sc.contact.patch_min_radius
            w = cc.weights[k]
            assert w.sum() == pytest.approx(1.0) and (w > 0).sum() > 3  # a real patch on this plate
            u_ref += gf.displacement(cc.verts[k][w > 0], np.outer(w[w > 0], fk))
    assert np.allclose(st.frame().displacement, u_ref, rtol=1e-4, atol=1e-9)
    # and a local evaluation agrees with the full one
    v = np.arange(0, st.n, 7)
    assert np.allclose(st.seat.u_at(v), st.u[v])


@pytest.mark.parametrize("patch,mode", [("hertz", "frictionless"), ("none", "frictionless"), ("none", "sticky")])
def test_storm_contact_set_is_the_api_capacitance(gf, exact_storm, patch, mode):
    """The storm's contact set is a layer over the contact API's Capacitance: its W is
    G^T D G from the dense D (G = B or B N with the set's weights), its K inverts its W,
    and a point-contact set's K is the API's capacitance of the same contacts."""
    from hailstorm.runtime.contact import Capacitance, capacitance

    sc = exact_storm.scene.with_(patch=patch, mode=mode)
    st = Storm(gf, sc)
    while st.t < 0.1 - 1e-12 and st.cache is None:
        st.step()
    cc = st.cache
    assert cc is not None and isinstance(cc.capacitance, Capacitance)
    s = cc.stones.size
    n3 = 3 * st.n
    B = np.zeros((n3, 3 * s))  # dense force distribution over the whole surface
    for k in range(s):
        for v, w in zip(cc.verts[k], cc.weights[k]):
            B[3 * v:3 * v + 3, 3 * k:3 * k + 3] += w * np.eye(3)
    G = B if mode == "sticky" else np.einsum("rkj,kj->rk", B.reshape(n3, s, 3), cc.normals)
    Dfull = np.zeros((n3, n3))
    col = np.asarray(gf.column_of)
    for v in np.flatnonzero(col >= 0):
        Dfull[:, 3 * v:3 * v + 3] = gf.D[:, 3 * col[v]:3 * col[v] + 3]
    W = G.T @ Dfull @ G
    np.testing.assert_allclose(cc.capacitance.W, W, rtol=1e-10, atol=1e-14 * np.abs(W).max())
    np.testing.assert_allclose(cc.K @ cc.W, np.eye(W.shape[0]), atol=1e-8)
    np.testing.assert_allclose(cc.DVV, (Dfull @ G)[np.repeat(3 * np.unique(cc.verts), 3)
                                                   + np.tile(np.arange(3), np.unique(cc.verts).size)], rtol=1e-10,
                               atol=1e-14 * np.abs(Dfull).max())
    if patch == "none":  # no secant scaling: the API's capacitance of the same contacts
        api = capacitance(gf, cc.tris, cc.bary, normals=cc.normals, mode=mode)
        np.testing.assert_allclose(cc.K, api.K, rtol=1e-12)


def test_storm_sticky_symplectic_runs(gf):
    sc = Scene.from_flat(duration=0.03, stones=4, seed=1, spawn_height=0.01, mode="sticky", integrator="symplectic", r_min=0.004)
    res = run_storm(gf, sc, progress=False)
    assert all(np.all(np.isfinite(f.displacement)) for f in res.frames)
    assert res.stats["max_penetration_m"] < 0.05 * 0.004


def test_clamped_triangle_is_a_hard_wall(gf):
    # a corner triangle of the plate has all its vertices clamped: the stone bounces off it
    sc = Scene.from_flat(duration=0.05, stones=0, drag=False, restitution=0.5)
    st = Storm(gf, sc, spawn=False)
    t = int(np.flatnonzero(gf.fixed[gf.triangles].all(axis=1))[0])
    c = gf.vertices[gf.triangles[t]].mean(axis=0)
    st.add_stones(c + [0, 0, 0.005 + 1e-3], [0, 0, -1.0], 0.005)
    while st.t < 0.01:
        st.step()
    assert st.stats["wall_contacts"] >= 1
    assert st.vel[0, 2] > 0.3  # bounced with e = 0.5 (minus gravity)


@pytest.mark.parametrize("mode, patch", [("sticky", "none"), ("frictionless", "hertz")])
def test_contact_on_a_clamped_edge_of_a_soft_triangle_is_a_hard_wall(gf, mode, patch):
    """A stone that lands exactly on the clamped edge of a soft triangle (its barycentric
    weight all on clamped vertices: nothing there can move) bounces as off a wall
    instead of asking the capacitance for a rigid contact."""
    sc = Scene.from_flat(duration=0.05, stones=0, drag=False, restitution=0.5, mode=mode, patch=patch)
    st = Storm(gf, sc, spawn=False)
    T = np.asarray(gf.triangles)
    t = int(np.flatnonzero(st.soft & (gf.fixed[T].sum(axis=1) == 2))[0])
    edge = T[t][gf.fixed[T[t]]]
    c = gf.vertices[edge].mean(axis=0)
    st.add_stones(c + [0, 0, 0.005 + 1e-3], [0, 0, -1.0], 0.005)
    while st.t < 0.01:
        st.step()
    assert st.stats["wall_contacts"] >= 1
    assert st.vel[0, 2] > 0.3  # bounced with e = 0.5 (minus gravity)


def test_outputs(tmp_path, gf, short_storm):
    from hailstorm.runtime.output.files import write_animation, write_paraview, write_summary

    s = write_summary(short_storm, tmp_path / "summary.json")
    data = json.loads(s.read_text())
    for key in ("hailstones", "impacts", "max_contact_force", "sim_time_s", "wall_time_s", "max_indentation_m",
                "max_simultaneous_contacts", "steps", "real_time_factor", "seed", "dt"):
        assert key in data
    pvd = write_paraview(short_storm, gf, tmp_path / "pv")
    assert pvd.suffix == ".pvd" and pvd.is_file()
    import meshio

    files = sorted((tmp_path / "pv" / "frames").glob("surface_*.vtu"))
    assert len(files) == len(short_storm.frames)
    for f, fr in zip(files, short_storm.frames):
        m = meshio.read(f)
        assert "displacement" in m.point_data and "|u|" in m.point_data and "peak_displacement" in m.point_data
        assert np.allclose(m.point_data["peak_displacement"], fr.peak_displacement)
        # the peak covers the instant itself
        assert np.all(np.linalg.norm(m.point_data["peak_displacement"], axis=1)
                      >= np.linalg.norm(m.point_data["displacement"], axis=1) - 1e-9)
    import matplotlib
    import matplotlib.pyplot as plt

    before = matplotlib.get_backend()
    plt.switch_backend("pdf")  # a caller's own backend (not Agg) ...
    try:
        out = write_animation(short_storm, gf, tmp_path / "storm.mp4", max_frames=4, dpi=50)
        assert matplotlib.get_backend() == "pdf"  # ... is left alone by the renderer
    finally:
        plt.switch_backend(before)
    assert out.is_file() and out.stat().st_size > 0


def test_short_storm_on_the_seat(seat_bundle):
    """The real (coarse) seat bundle: a short storm stays finite and bounded."""
    from hailstorm.runtime.bundle.read import load

    gf = load(seat_bundle)
    sc = Scene.from_flat(duration=0.04, stones=6, seed=3, spawn_height=0.01)
    res = run_storm(gf, sc, progress=False)
    st = res.stats
    assert st["impacts"] >= 1
    assert all(np.all(np.isfinite(f.displacement)) for f in res.frames)
    assert st["max_penetration_m"] < 0.25 * sc.hail.r_min  # curved seat, coarse dents: looser than the plate
    assert np.isfinite(st["max_contact_force"]) and st["max_contact_force"] > 0


# --------------------------------------------------------------------------
# patch contacts (the default for hail) vs point contacts
# --------------------------------------------------------------------------
def _drop(gf, patch, r=0.005, v0=9.0, integrator="exact", dt=5e-4, at_vertex=True):
    """One stone (no drag) onto the seat's top: (storm, restitution)."""
    sc = Scene.from_flat(duration=0.05, stones=0, drag=False, dt=dt, integrator=integrator, restitution=0.5, patch=patch)
    # an impact inside one step's sub-steps (a stiff seat) counts: gravity over one step changes
    # the speeds by g dt, < 0.1 % of them
    st, v_in, v_out, _ = drop_on_seat_top(gf, sc, int(0.03 / dt), r=r, v0=v0, at_vertex=at_vertex)
    assert v_in is not None and v_out is not None, "the stone did not bounce"
    return st, v_out / v_in


@pytest.mark.parametrize("integrator, dt, tol", [("exact", 5e-4, 0.01), ("implicit", 2e-4, 0.02)])
def test_patch_drop_on_the_seat_restitution_and_one_weighting(seat_bundle, integrator, dt, tol):
    """A single impact with patch contact: restitution on target, the disc is sized once
    (expected peak force) and kept for the whole impact (one capacitance, <= 2 weightings)."""
    from hailstorm.runtime.bundle.read import load

    gf = load(seat_bundle)
    st, e = _drop(gf, "hertz", integrator=integrator, dt=dt)
    assert e == pytest.approx(0.5, abs=tol)
    S = st.stats
    assert S["capacitance_rebuilds"] == 1 and S["patch_resizes"] == 0
    assert 1 <= S["patch_weights_computed"] <= 2
    # Hertz radius of the impact's peak force: between the floor and the stone radius
    assert 1e-3 < S["max_patch_radius_m"] < 0.005
    pt, e_pt = _drop(gf, "none", integrator=integrator, dt=dt)
    assert e_pt == pytest.approx(0.5, abs=tol)
    # the in-contact overlap with the deformed surface (stated tolerance: 1% of r) and no worse than a point's
    assert S["max_penetration_contact_m"] < 0.01 * 0.005
    assert S["max_penetration_contact_m"] <= pt.stats["max_penetration_contact_m"] + 1e-6
    assert np.isfinite(st.pos).all() and np.isfinite(st.u).all()


def test_patch_weights_are_cached_per_contact(gf):
    """On the plate the patch disc covers several vertices (weights summing to one, a
    stiffness of its own); the same contact again reuses the cached weights."""
    sc = Scene.from_flat(duration=0.05, stones=0, drag=False, dt=5e-4, integrator="exact")
    st = Storm(gf, sc, spawn=False)
    t = np.flatnonzero(st.soft)[len(np.flatnonzero(st.soft)) // 2]
    st.add_stones(gf.vertices[gf.triangles[t]].mean(axis=0) + [0, 0, 0.01], [0, 0, -5.0], 0.006)
    st.ctri[0], st.cbary[0], st.stones.cnormal[0] = t, 1.0 / 3.0, st.index.normals[t]
    args = (np.array([0]), np.array([t]), st.cbary[[0]], np.array([0.004]), st.index.normals[[t]], st.stats)
    verts, w = st.patches.weights(*args)
    assert (w > 0).sum() > 3 and w.sum() == pytest.approx(1.0)
    k_patch = st.patches.stiffness(verts, w, st.index.normals[[t]])[0]
    assert np.isfinite(k_patch) and k_patch > 0
    # cached: the same contact again costs nothing
    n0 = st.stats["patch_weights_computed"]
    st.patches.weights(*args)
    assert st.stats["patch_weights_computed"] == n0 and st.stats["patch_weights_reused"] >= 1


def test_resting_stone_reuses_its_patch(gf):
    """A stone that comes to rest keeps its contact: its weights are computed a few times
    (impact, then one shrink to the resting force) and kept for every later sub-step."""
    sc = Scene.from_flat(duration=0.2, stones=0, drag=False, dt=5e-4, integrator="exact", restitution=0.0)
    st = Storm(gf, sc, spawn=False)
    c = gf.vertices[~gf.fixed].mean(axis=0)
    c[2] = gf.vertices[:, 2].max()
    st.add_stones(c + [0, 0, 0.006], [0, 0, -2.0], 0.005)
    for _ in range(300):
        st.step()
    assert st.ctri[0] >= 0  # resting
    S = st.stats
    assert S["patch_weights_computed"] <= 4  # 300 steps in contact: the weights are not recomputed
    assert S["capacitance_rebuilds"] <= 4  # nor the capacitance (the key does not change)
    # at rest the radius is the impact patch of the stone's weight (floored): the sphere's radius there
    from hailstorm.runtime.contact.sphere_patch import impact_radius

    a_rest = float(impact_radius(st.mass[0] * 9.81, 0.005, gf.young, gf.poisson, a_min=sc.contact.patch_min_radius))
    assert st.crad[0] == pytest.approx(a_rest, rel=sc.contact.patch_tolerance + 0.01)


def test_patch_and_point_storms_on_the_seat(seat_bundle):
    """The real (coarse) seat: patch and point storms both run, stay finite and bounded; the
    patch storm is reproducible, and its in-contact overlap is within a stated tolerance."""
    from hailstorm.runtime.bundle.read import load

    gf = load(seat_bundle)
    out = {}
    for patch in ("hertz", "none"):
        sc = Scene.from_flat(duration=0.1, stones=30, seed=5, spawn_height=0.01, integrator="exact", dt=5e-4, patch=patch)
        res = run_storm(gf, sc, progress=False)
        st = res.stats
        assert st["patch"] == patch
        assert st["impacts"] >= 5
        assert all(np.all(np.isfinite(f.displacement)) and np.all(np.isfinite(f.positions)) for f in res.frames)
        assert np.isfinite(st["max_contact_force"]) and st["max_contact_force"] > 0
        out[patch] = res
    ph, pn = out["hertz"].stats, out["none"].stats
    assert ph["patch_weights_computed"] > 0 and pn["patch_weights_computed"] == 0
    # stated tolerance: in contact, no stone overlaps the deformed surface by more than 1% of its radius
    assert ph["max_penetration_contact_rel"] < 0.01
    # a patch prescribes Hertz's secant law: its weighted mean surface lies up to a^2 / (5 R) = 0.2 delta
    # short of the stone's lowest point (runtime/storm/contact_set.py), so the stone may overlap the
    # interpolated surface at its contact point by that much more than a point contact, not more
    assert ph["max_penetration_contact_m"] <= pn["max_penetration_contact_m"] + 0.2 * ph["max_indentation_m"]
    assert pn["max_penetration_contact_m"] > 0.0  # (a point load's spike of a dent tilts into the sphere)
    again = run_storm(gf, out["hertz"].scene, progress=False)
    assert np.array_equal(again.frames[-1].positions, out["hertz"].frames[-1].positions)
    assert np.array_equal(again.frames[-1].displacement, out["hertz"].frames[-1].displacement)


def test_frame_peak_displacement_keeps_the_dent_of_a_finished_impact(gf):
    """An impact (~1 ms) ends between two frames: the frame's displacement is back to
    zero, but its peak_displacement holds the dent, equal per vertex to the largest
    full-surface response sampled at every step (finer than the frame interval)."""
    sc = Scene.from_flat(duration=0.05, stones=0, drag=False, dt=5e-5, integrator="implicit", restitution=0.5)
    st = Storm(gf, sc, spawn=False)
    top = int(np.argmax(gf.vertices[:, 2] - 1e3 * np.abs(gf.vertices[:, :2] - gf.vertices[:, :2].mean(0)).sum(1)))
    st.add_stones(gf.vertices[top] + [0.0, 0.0, 0.006], [0.0, 0.0, -5.0], 0.005)
    st.frame()  # starts the interval
    u_max = np.zeros(st.n)
    touched = False
    for _ in range(400):
        st.step()
        u_max = np.maximum(u_max, np.linalg.norm(st.u, axis=1))
        touched |= st.ctri[0] >= 0
        if touched and st.ctri[0] < 0:
            break
    assert touched and st.ctri[0] < 0, "the stone did not bounce off"
    fr = st.frame()
    assert np.abs(fr.displacement).max() == 0.0  # nothing pressed now
    peak = np.linalg.norm(fr.peak_displacement.astype(np.float64), axis=1)
    assert u_max.max() > 0
    # at least what every step saw, and no more than the sub-step peak between two steps
    assert np.all(peak >= u_max * (1 - 1e-5) - 1e-12)
    assert peak.max() <= 1.02 * u_max.max()
    assert np.allclose(peak, u_max, rtol=0.0, atol=0.02 * u_max.max())
    # the next interval starts empty
    st.step()
    assert np.abs(st.frame().peak_displacement).max() == 0.0


@pytest.mark.parametrize("stones", [0, 12])
def test_summary_has_no_internal_counters(gf, short_storm, stones):
    res = short_storm if stones else run_storm(gf, Scene.from_flat(duration=0.01, stones=0), progress=False)
    assert not [k for k in res.stats if k.startswith("_")]
    assert res.stats["mean_penetration_contact_m"] >= 0.0


def test_scene_to_toml_replaces_atomically(tmp_path):
    p = tmp_path / "scene.toml"
    p.write_text("old")
    Scene.from_flat(duration=0.07).to_toml(p)
    assert Scene.from_toml(p).storm.duration == 0.07
    assert sorted(x.name for x in tmp_path.iterdir()) == ["scene.toml"]  # no temporary left behind
    with pytest.raises(OSError):
        Scene().to_toml(tmp_path / "missing-dir" / "scene.toml")
    assert sorted(x.name for x in tmp_path.iterdir()) == ["scene.toml"]
