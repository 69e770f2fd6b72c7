"""The speed-vs-accuracy study: its functions on a tiny box, and the notebook.

The box is 0.1 x 0.1 x 0.05 m clamped at z = 0; two 20 mm pressure discs on
its upper face; the reference is P2 at 10 mm (about 15k dofs, a few seconds).
"""

import math
from pathlib import Path

import numpy as np
import pytest

from hailstorm.precompute import box_mesh
from studies import study as S

SIZE = (0.1, 0.1, 0.05)
ROOT = Path(__file__).resolve().parents[2]


def mesher(h):
    return box_mesh(SIZE, h)


@pytest.fixture(scope="module")
def scenario():
    return S.box_scenario(SIZE)


@pytest.fixture(scope="module")
def ref(scenario, tmp_path_factory):
    return S.reference(scenario, mesher=mesher, mesh_size=0.01, order=2,
                       cache_dir=tmp_path_factory.mktemp("ref"))


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("study")


@pytest.fixture(scope="module")
def base(work):
    return S.build_config(work, mesher=mesher, mesh_size=0.025, order=1, name="base")


# ---------------------------------------------------------------- pieces
def test_pareto_front_hand_made():
    pts = [(1.0, 0.5), (2.0, 0.1), (2.0, 0.3), (0.5, 0.9), (3.0, 0.1), (4.0, 0.01), (5.0, math.nan), (0.4, 0.9)]
    assert S.pareto_front(pts) == [7, 0, 1, 5]
    # dominated by (0.4, 0.9): same error, lower cost; ties in cost keep the lower error only
    assert S.pareto_front([(1, 1), (1, 2), (2, 1)]) == [0]
    assert S.pareto_front([]) == []
    sp = [S.StudyPoint("k", "a", 1.0, 9.0, 0.2), S.StudyPoint("k", "b", 2.0, 1.0, 0.1)]
    assert S.pareto_front(sp) == [0, 1]
    assert S.pareto_front(sp, cost="memory_mb") == [1]


def test_nodal_loads_sum_to_the_disc_force():
    mesh = mesher(0.025)
    from hailstorm.precompute.geometry import boundary_triangles

    tris = boundary_triangles(mesh.tets)
    load = S.LoadCase((0.05, 0.05), 0.02, 1000.0)
    f = S.nodal_loads(mesh.points, tris, tris, mesh.points.shape[0], load)
    total = f.sum(axis=0)
    # flat upper face, disc inside it: all of it pushes down, p * pi R^2
    assert abs(total[2] + 1000.0 * math.pi * 0.02**2) < 2e-3 * 1000.0 * math.pi * 0.02**2
    assert np.allclose(total[:2], 0, atol=1e-12)


def test_trace_shape_reproduces_quadratics():
    rng = np.random.default_rng(0)
    lam = rng.dirichlet(np.ones(3), size=20)
    corners = np.array([[0.0, 0.0], [1.0, 0.2], [0.3, 1.1]])
    mids = (corners + corners[[1, 2, 0]]) / 2
    g = lambda x: 1 + 2 * x[..., 0] - x[..., 1] + 3 * x[..., 0] * x[..., 1] - x[..., 1] ** 2  # noqa: E731
    x = lam @ corners
    assert np.allclose(S.trace_shape(lam, 2) @ g(np.vstack([corners, mids])), g(x))
    lin = lambda x: 1 + 2 * x[..., 0] - x[..., 1]  # noqa: E731
    assert np.allclose(S.trace_shape(lam, 1) @ lin(corners), lin(x))


def test_locate_probes_rejects_a_probe_off_the_seat(scenario):
    mesh = mesher(0.025)
    from hailstorm.precompute.geometry import boundary_triangles

    tris = boundary_triangles(mesh.tets)
    loc = S.locate_probes(mesh.points, tris, np.array(scenario.probes))
    assert np.allclose(loc.lam.sum(axis=1), 1)
    assert np.allclose((mesh.points[tris[loc.triangle]][:, :, 2]), SIZE[2])
    with pytest.raises(ValueError, match="not above"):
        S.locate_probes(mesh.points, tris, np.array([[0.5, 0.5]]))


def test_reference_is_cached_and_keyed_on_the_scenario(scenario, ref, tmp_path):
    S.reference(scenario, mesher=mesher, mesh_size=0.025, order=1, cache_dir=tmp_path)
    cached = list(tmp_path.glob("reference-*.npz"))
    assert len(cached) == 1
    stamp = cached[0].stat().st_mtime_ns
    again = S.reference(scenario, mesher=mesher, mesh_size=0.025, order=1, cache_dir=tmp_path)
    assert cached[0].stat().st_mtime_ns == stamp  # read back, not recomputed
    other = S.Scenario(scenario.loads[:1], scenario.probes)
    S.reference(other, mesher=mesher, mesh_size=0.025, order=1, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("reference-*.npz"))) == 2
    direct = S.direct_qoi(mesher(0.025), 1, scenario)
    assert np.allclose(again.qoi.u, direct.qoi.u, rtol=1e-12, atol=0)


# ---------------------------------------------------------------- discretization
def test_p1_bundle_equals_direct_p1_and_converges(scenario, ref, work):
    sizes = (0.025, 0.0167, 0.0125)
    pts = S.study_discretization(sizes, (1,), scenario, ref, work, mesher=mesher, with_steps=False)
    bundle = [p for p in pts if p.knob == "P1 mesh"]
    direct = [p for p in pts if p.knob == "direct FEM/step"]
    assert len(bundle) == len(direct) == 3
    for b, d in zip(bundle, direct):
        # P1: lumping the pressure to corners *is* the consistent load
        assert b.error == pytest.approx(d.error, rel=1e-8)
        assert b.precompute_s > 0 and b.memory_mb > 0 and d.step_s > 0
    err = np.array([p.error for p in bundle])
    assert np.all(np.diff(err) < 0)
    rate = np.polyfit(np.log(sizes), np.log(err), 1)[0]
    assert rate > 0.9, f"P1 convergence rate {rate:.2f}"


def test_p2_more_accurate_than_p1_at_equal_mesh(scenario, ref):
    for h in (0.025, 0.0167):
        e1 = S.relative_error(S.direct_qoi(mesher(h), 1, scenario).qoi, ref.qoi)
        e2 = S.relative_error(S.direct_qoi(mesher(h), 2, scenario).qoi, ref.qoi)
        assert e2 < 0.5 * e1


def test_hat_columns_make_p2_bundles_better_than_corner_forces(scenario, ref, work):
    corner = S.study_discretization((0.0167,), (2,), scenario, ref, work, mesher=mesher,
                                    with_steps=False, with_direct=False)[0]
    hat = S.study_hat_columns((0.0167,), (2,), scenario, ref, mesher=mesher)[0]
    assert hat.memory_mb == pytest.approx(corner.memory_mb)
    assert hat.error < 0.7 * corner.error


# ---------------------------------------------------------------- other knobs
def test_amg_error_decreases_with_tolerance(scenario, ref, work):
    # 12.5 mm: 1215 dofs, more than pyamg's coarsest level (below it AMG is a direct solve)
    pts = S.study_solver(0.0125, 1, (1e-4, 1e-6, 1e-8), scenario, ref, work, mesher=mesher)
    assert pts[0].knob == "CHOLMOD"
    amg = pts[1:]
    own = [p.extra["error_vs_parent"] for p in amg]
    d_err = [p.extra["d_error"] for p in amg]
    assert own[0] > own[1] > own[2] and d_err[0] > d_err[1] > d_err[2]
    assert d_err[0] < 1e-2 and d_err[2] < 1e-6
    # the solver's own error is far below the discretization error
    assert all(abs(p.error - pts[0].error) < 1e-2 * pts[0].error for p in amg)


def test_float32_costs_half_and_errs_about_1e_7(scenario, ref, base):
    (p,) = S.study_precision(base, scenario, ref)
    assert p.memory_mb == pytest.approx(base.memory_mb / 2)
    assert 1e-9 < p.extra["d_error"] < 1e-6
    assert 1e-10 < p.extra["error_vs_parent"] < 1e-6


def test_low_rank_error_decreases_with_rank_and_vanishes_at_full_rank(scenario, ref, base):
    full = min(base.gf.D.shape)
    pts = S.study_low_rank(base, (5, 20, 60, full), scenario, ref)
    d_err = [p.extra["d_error"] for p in pts]
    assert all(a > b for a, b in zip(d_err, d_err[1:]))
    assert d_err[-1] < 1e-10 and pts[-1].extra["error_vs_parent"] < 1e-10
    assert pts[-1].error == pytest.approx(S.relative_error(S.bundle_qoi(base.gf, scenario), ref.qoi), rel=1e-8)
    mem = [p.memory_mb for p in pts]
    assert all(a < b for a, b in zip(mem, mem[1:]))


def test_randomized_low_rank_matches_svd():
    rng = np.random.default_rng(1)
    A = rng.standard_normal((60, 8)) @ rng.standard_normal((8, 40))
    L, R = S.low_rank(A, 8, method="randomized")
    assert np.allclose(L @ R, A)
    L, R = S.low_rank(A, 4, method="svd")
    Lr, Rr = S.low_rank(A, 4, method="randomized", power=3)
    assert np.linalg.norm(A - Lr @ Rr) < 1.05 * np.linalg.norm(A - L @ R)
    with pytest.raises(ValueError, match="low-rank method"):
        S.low_rank(A, 4, method="wavelet")


def test_region_cuts_columns_and_only_errs_when_it_misses_the_load(scenario, ref, work):
    pts = S.study_region(0.025, 1, (0.005, 0.04, 1.0), scenario, ref, work, mesher=mesher)
    tiny, enough, everything = pts
    assert tiny.extra["dropped_vertices"] > 0 and tiny.error > 1.2 * everything.error
    assert enough.extra["dropped_vertices"] == 0
    assert enough.error == pytest.approx(everything.error, rel=1e-10)
    assert enough.memory_mb < 0.7 * everything.memory_mb


def test_plot_writes_a_small_png(scenario, tmp_path):
    pts = [S.StudyPoint("P1 mesh", "h=10 mm", 1.0, 3.0, 0.3, 1e-3), S.StudyPoint("P2 mesh", "h=10 mm", 5.0, 3.0, 0.1),
           S.StudyPoint("direct FEM/step", "h=10 mm", math.nan, math.nan, 0.3, 1e-1)]
    out = tmp_path / "fig.png"
    S.plot_speed_vs_accuracy(pts, out, reference_error=0.01)
    assert out.stat().st_size < 200_000
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ---------------------------------------------------------------- notebook
def test_notebook_executes_on_small_settings(run_notebook):
    png = ROOT / "notebooks" / "figures" / "speed_vs_accuracy.png"
    before = png.stat().st_mtime_ns if png.exists() else None
    text = run_notebook("speed_vs_accuracy.ipynb")
    assert "P1 mesh" in text and "SMALL = True" in text
    # the small run must not overwrite the committed figure
    assert (png.stat().st_mtime_ns if png.exists() else None) == before
