"""Fast tests of studies.contact_study on tiny box meshes, and the mesh-dependence notebook."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hailstorm.precompute import box_mesh
from studies.contact_study import (
    StiffnessStudy,
    contact_stiffness,
    contact_stiffness_vs_mesh,
    degenerate_contacts,
    locate_points,
    StabilityMap,
    format_degenerate,
    format_locking,
    locking_vs_poisson,
    measure_dt_limit,
    plot_stability_map,
    plot_stiffness_vs_mesh,
    predicted_dt_limit,
    seat_contact_stiffness,
    separation_sweep,
    stability_map,
)
from hailstorm.runtime import load

ROOT = Path(__file__).resolve().parents[2]


def _box(h):
    return box_mesh((0.1, 0.1, 0.05), h)


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """Point vs patch stiffness on three box meshes (h = 25, 16.7, 12.5 mm), fixed patch a = 20 mm."""
    return contact_stiffness_vs_mesh(
        (0.025, 0.05 / 3, 0.0125), points={"centre": (0.047, 0.052), "corner": (0.02, 0.075)},
        patch_radius=0.02, control_radius=0.03, mesh=_box, young=1e6, poisson=0.3,
        cache_dir=tmp_path_factory.mktemp("cs"),
    )


def test_locate_points(box_bundle):
    gf = load(box_bundle)
    xy = np.array([[0.047, 0.052], [0.011, 0.093]])
    tri, bary = locate_points(gf, xy)
    x = np.einsum("ka,kad->kd", bary, gf.vertices[gf.triangles[tri]])
    np.testing.assert_allclose(x[:, :2], xy, atol=1e-12)
    np.testing.assert_allclose(x[:, 2], 0.05)
    with pytest.raises(ValueError, match="not above"):
        locate_points(gf, [[0.5, 0.5]])


def test_patch_converges_point_softens(study):
    assert isinstance(study, StiffnessStudy)
    assert study.k_point.shape == study.k_patch.shape == (3, 2)
    assert np.all(np.isfinite(study.k_point)) and np.all(study.k_point > 0)
    # spreading the load stiffens the contact
    assert np.all(study.k_patch > study.k_point)
    # the point contact softens under refinement; the patch changes less between refinements
    assert np.all(np.diff(study.k_point[:, 0]) < 0)
    # (the point stiffness also jumps with where the point falls relative to the vertices,
    # so a single refinement step can look converged by chance: compare the last step
    # and the mean over the steps)
    assert np.all(study.rel_change("patch")[-1] < study.rel_change("point")[-1])
    assert np.all(study.rel_change("patch").mean(axis=0) < study.rel_change("point").mean(axis=0))
    text = study.table()
    assert "centre" in text and "wide" in text and "last change" in text
    assert study.k_control.shape == (3, 2) and np.all(study.k_control > study.k_patch)


def test_contact_stiffness_modes(box_bundle):
    gf = load(box_bundle)
    tri, bary = locate_points(gf, [[0.047, 0.052]])
    kf = contact_stiffness(gf, tri, bary)
    ks = contact_stiffness(gf, tri, bary, mode="sticky")
    # n.K n with K = W^-1 (3x3) bounds 1/(n.W n) from above
    assert ks[0] >= kf[0] > 0
    rigid = np.flatnonzero(gf.fixed[gf.triangles].all(axis=1))[0]
    assert contact_stiffness(gf, [rigid], [[1 / 3] * 3])[0] == np.inf


@pytest.mark.parametrize("patch_radius", [None, 0.02])
def test_degenerate_contacts(box_bundle, patch_radius):
    gf = load(box_bundle)
    rows = {r["case"]: r for r in degenerate_contacts(gf, patch_radius=patch_radius)}
    one, pair = rows["single contact"], rows["coincident pair"]
    assert one["exact"] and np.isfinite(one["cond_W"]) and one["fn_total"] < 0
    # coincident: W singular -> pseudo-inverse, force split equally, total unchanged
    assert not pair["exact"] and pair["cond_W"] > 1e12
    np.testing.assert_allclose(pair["fn"][0], pair["fn"][1], rtol=1e-8)
    np.testing.assert_allclose(pair["fn_total"], one["fn_total"], rtol=1e-7)
    near = rows["pair 1e-09 apart (bary)"]
    assert not near["exact"] and np.isfinite(near["fn"]).all()
    np.testing.assert_allclose(near["fn_total"], one["fn_total"], rtol=1e-6)
    far = rows["pair 0.001 apart (bary)"]
    assert far["cond_W"] > one["cond_W"] and np.isfinite(far["fn"]).all()
    conf = rows["coincident, conflicting"]
    assert np.isfinite(conf["fn"]).all() and abs(conf["fn_total"]) < 1e-6 * abs(one["fn_total"])
    clamp = rows["on the clamp (+ a free one)"]
    assert clamp["rigid"] == [False, True] and clamp["fn"][1] == 0.0
    np.testing.assert_allclose(clamp["fn"][0], one["fn_total"], rtol=1e-10)
    # a point contact with all its weight on clamped vertices is rigid; a patch around the
    # same point reaches free vertices and is not
    assert rows["weight all on clamped vertices"]["rigid"] == [patch_radius is None]


def test_separation_sweep(box_bundle):
    """Two contacts closing in: W's condition number grows like 1/d^2; while the solve is exact
    the two prescriptions pin the surface's slope and the forces grow like 1/d with opposite
    signs (a dipole); past COND_LIMIT the pseudo-inverse splits the force equally."""
    gf = load(box_bundle)
    rows = separation_sweep(gf, (1e-1, 1e-3, 1e-6, 0.0))
    cond = [r["cond_W"] for r in rows]
    assert all(b > a for a, b in zip(cond, cond[1:]))
    assert [r["exact"] for r in rows] == [True, True, False, False]
    dip = [abs(r["split"] - 0.5) for r in rows[:2]]
    assert dip[1] > 30 * dip[0]
    for r in rows[2:]:
        assert r["split"] == pytest.approx(0.5, rel=1e-5)
        assert r["total_rel"] == pytest.approx(1.0, rel=1e-5)


def test_locking_vs_poisson():
    rows = locking_vs_poisson((0.3, 0.49), length=0.5, size=0.05)
    p1 = [r["p1_ratio"] for r in rows]
    p2 = [r["p2_ratio"] for r in rows]
    assert p1[0] < p2[0]  # P1 is stiffer already at nu = 0.3
    assert p1[1] < 0.8 * p1[0]  # and locks as nu -> 0.5
    assert p2[1] > 0.8 * p2[0]  # P2 much less
    assert 0.8 < p2[0] < 1.1


def test_plot(study, tmp_path):
    out = tmp_path / "fig.png"
    plot_stiffness_vs_mesh(study, out)
    assert out.stat().st_size < 150_000


# --------------------------------------------------------------------------
# stability of the contact integrators
# --------------------------------------------------------------------------
def test_predicted_dt_limit():
    assert predicted_dt_limit(1e4, 1e-2) == pytest.approx(2.0 / 1e3)
    np.testing.assert_allclose(predicted_dt_limit(np.array([1e4, 4e4]), 1e-2), [2e-3, 1e-3])


@pytest.fixture(scope="module")
def small_maps(box_bundle):
    """Stability maps on a small grid: real box-bundle stiffness and a bound, two stone sizes,
    time steps 0.3..30 x 2/omega (dense around 1)."""
    from hailstorm.runtime.storm.hail import stone_mass

    gf = load(box_bundle)
    k_box = seat_contact_stiffness(gf, {"centre": (0.047, 0.052)})["centre"]
    stiffness = [k_box, 1e5]
    masses = stone_mass(np.array([0.0025, 0.01]))
    rel = [0.3, 0.8, 0.93, 0.97, 1.03, 1.07, 1.2, 3.0, 30.0]
    return {integ: stability_map(stiffness, masses, rel, integ, relative=True, steps=200)
            for integ in ("symplectic", "implicit", "exact")}


def test_symplectic_boundary_matches_prediction(small_maps):
    sm = small_maps["symplectic"]
    assert isinstance(sm, StabilityMap) and sm.diverged.shape == (2, 2, 9)
    assert 1e3 < sm.stiffness[0] < 1e6  # a real contact stiffness
    lo, hi = sm.measured_bracket()
    pred = sm.predicted
    # the measured boundary lies within the grid's +-3 % bracket around 2/omega
    assert np.all(lo >= 0.9 * pred) and np.all(lo < pred)
    assert np.all(hi <= 1.1 * pred) and np.all(hi > pred)
    # and is sharp: every step below is bounded, every step above diverged
    below = sm.dt < pred[..., None]
    assert not sm.diverged[below].any() and sm.diverged[~below].all()
    assert np.all(sm.growth[below] < 2.0)
    assert "symplectic" in sm.table()


def test_implicit_and_exact_bounded_everywhere(small_maps):
    for name in ("implicit", "exact"):
        sm = small_maps[name]
        assert not sm.diverged.any(), name
        assert np.all(np.isfinite(sm.growth))
        lo, hi = sm.measured_bracket()
        assert np.all(np.isinf(hi))
    # backward Euler dissipates, the exact integrator conserves the energy
    assert np.all(small_maps["implicit"].growth[..., -1] < 0.5)
    np.testing.assert_allclose(small_maps["exact"].growth, 1.0, atol=1e-3)


def test_measure_dt_limit_bisection_and_damping():
    from hailstorm.runtime.storm.hail import stone_mass

    k, m = 2e4, float(stone_mass(0.005))
    pred = predicted_dt_limit(k, m)
    assert measure_dt_limit(k, m, "symplectic", rtol=1e-2, steps=200) == pytest.approx(pred, rel=0.02)
    assert measure_dt_limit(k, m, "implicit", steps=100) == np.inf
    assert measure_dt_limit(k, m, "exact", steps=100) == np.inf
    # the storm's (compression-only) dashpot lowers the explicit limit, but not below the two-way bound
    z = 0.597  # restitution 0.5
    damped = measure_dt_limit(k, m, "symplectic", restitution=0.5, rtol=1e-2, steps=200)
    assert (np.sqrt(1 + z * z) - z) * pred < damped < 0.9 * pred
    # stability_map with bisection stores the limit
    sm = stability_map([k], [m], [0.5, 2.0], "symplectic", relative=True, steps=100, bisect=True, rtol=1e-2)
    assert sm.limit.shape == (1, 1) and sm.limit[0, 0] == pytest.approx(pred, rel=0.02)
    with pytest.raises(ValueError):
        stability_map([k], [m], [0.0], "symplectic")


def test_plot_stability_map(small_maps, box_bundle, tmp_path):
    gf = load(box_bundle)
    deg = degenerate_contacts(gf)
    lock = [dict(poisson=0.3, w_p1=0.5, w_p2=0.97, w_beam=1.0, p1_ratio=0.5, p2_ratio=0.97),
            dict(poisson=0.49, w_p1=0.1, w_p2=0.95, w_beam=1.0, p1_ratio=0.1, p2_ratio=0.95)]
    assert "cond(BtDB)" in format_degenerate(deg) and "pinv" in format_degenerate(deg)
    assert "P2/P1" in format_locking(lock)
    out = tmp_path / "stab.png"
    plot_stability_map(list(small_maps.values()), out, degenerate=deg, locking=lock)
    assert 0 < out.stat().st_size < 150_000


# --------------------------------------------------------------------------
# the studies' committed figures and notebooks
# --------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["mesh_dependence.png", "stability.png"])
def test_committed_figure_is_small(name):
    fig = ROOT / "notebooks" / "figures" / name
    if not fig.exists():
        pytest.skip("figure not generated")
    assert fig.stat().st_size <= 150 * 1024


@pytest.mark.parametrize("name, interpretations", [("mesh_dependence.ipynb", 0), ("stability.ipynb", 4)])
def test_notebook_runs_small(run_notebook, name, interpretations):
    """The notebook runs on small settings (and the stability one interprets its four results)."""
    text = run_notebook(name)
    assert "SMALL = True" in text
    assert text.count("Interpretation:") >= interpretations
