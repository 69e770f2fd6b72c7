"""The supernodal solve of D's columns against independent solves and its own factor.

Checked against SciPy's ``spsolve`` and dense inverses, the factor against
K itself (L Lᵀ = P K Pᵀ), the pruning against the nonzero pattern of the
solution it skips, and the operation count against a count done here.
"""

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.linalg import spsolve

from hailstorm.precompute.fem import clamp_dofs, elasticity_basis, stiffness_matrix, vertex_dofs
from hailstorm.precompute.geometry import box_mesh
from hailstorm.precompute.greens import column_problem, compliance_matrix, factorize
from hailstorm.precompute.pipeline import extract_surface
from hailstorm.precompute.supernodal import SupernodalSolver, supernodal_factor
from hailstorm.precompute.supernodal_kernels import GEMM_FROM


@pytest.fixture(scope="module")
def elastic():
    """The clamped P2 stiffness of a small box, its surface (read) and top (load) dofs among the free ones."""
    mesh = box_mesh((0.1, 0.1, 0.05), 0.025)
    basis = elasticity_basis(mesh, 2)
    K = stiffness_matrix(basis, 1e6, 0.3)
    fixed = clamp_dofs(basis, mesh)
    surf = extract_surface(mesh)
    problem = column_problem(K, fixed, vertex_dofs(basis, surf.nodes[surf.contactable]).ravel(),
                             vertex_dofs(basis, surf.nodes).ravel())
    return problem


def _dense_L(f):
    """L (dense) from the supernodal panels."""
    L = np.zeros((f.n, f.n))
    for s in range(f.start.size - 1):
        c0, c1 = f.start[s], f.start[s + 1]
        nc = c1 - c0
        rows = f.rows[f.roff[s]:f.roff[s + 1]]
        diag_inv = f.dinv[f.doff[s]:f.doff[s] + nc * nc].reshape(nc, nc, order="F")
        assert np.all(np.triu(diag_inv, 1) == 0)  # stored lower triangular
        L[c0:c1, c0:c1] = np.tril(np.linalg.inv(diag_inv))
        L[rows, c0:c1] = f.below[f.boff[s]:f.boff[s] + rows.size * nc].reshape(rows.size, nc, order="F")
    return L


def test_the_factor_is_a_cholesky_factor_of_the_permuted_matrix(elastic):
    K = elastic.Kff.toarray()
    f = supernodal_factor(elastic.Kff)
    assert np.array_equal(np.sort(f.perm), np.arange(f.n))
    L = _dense_L(f)
    inv = np.argsort(f.perm)  # L's position p holds dof inv[p]
    Kp = K[inv][:, inv]
    assert np.abs(L @ L.T - Kp).max() <= 1e-12 * np.abs(K).max()
    # L's entries (the diagonal blocks come back through two inversions: roundoff where zeros are)
    entries = np.count_nonzero(np.abs(L) > 1e-12 * np.abs(L).max())
    assert entries <= f.nnz_L <= entries * 1.01  # SuperLU may keep a few exact zeros
    assert np.all((f.parent > np.arange(f.parent.size)) | (f.parent < 0))  # parents follow their children
    # postordered and relaxed: most supernodes are wider than one vertex's three dofs, and their
    # panels hold L's entries plus a few explicit zeros
    assert np.mean(np.diff(f.start)) > 3
    stored = np.sum(np.diff(f.start) * (np.diff(f.start) + 1) // 2 + np.diff(f.start) * np.diff(f.roff))
    assert f.nnz_L <= stored <= 1.3 * f.nnz_L
    # both code paths of the kernels are exercised here: BLAS products and loops
    nc, mb = np.diff(f.start), np.diff(f.roff)
    work = 64 * nc * np.maximum(nc, mb)
    assert (work >= GEMM_FROM).any() and (work < GEMM_FROM).any()


def test_unit_columns_equal_a_direct_solve_at_the_rows_read(elastic, rng):
    K = elastic.Kff.tocsc()
    solver = SupernodalSolver(K, threads=1)
    load = rng.choice(elastic.load_pos, size=70, replace=False)  # more than one batch of 64
    read = elastic.read_pos
    B = sp.csc_matrix((np.ones(load.size), (load, np.arange(load.size))), shape=(K.shape[0], load.size))
    got = solver.solve_columns(B, read)
    X = spsolve(K, B.toarray())
    expected = np.where(read[:, None] >= 0, X[np.maximum(read, 0)], 0.0)
    assert np.abs(got - expected).max() <= 1e-12 * np.abs(expected).max()
    assert np.all(got[read < 0] == 0.0)


def test_sparse_and_dense_right_hand_sides(elastic, rng):
    K = elastic.Kff.tocsc()
    solver = factorize(K, "supernodal")
    n = K.shape[0]
    B = sp.random(n, 9, density=0.002, random_state=1, format="csc") + sp.eye(n, 9, format="csc")
    ref = spsolve(K, B.toarray())
    assert np.abs(solver.solve(B.toarray()) - ref).max() <= 1e-12 * np.abs(ref).max()
    b = rng.normal(size=n)
    x = solver.solve(b)
    assert x.shape == (n,)
    assert np.linalg.norm(K @ x - b) <= 1e-10 * np.linalg.norm(b)
    some = rng.choice(n, size=40, replace=False)
    assert np.abs(solver.solve_columns(B, some) - ref[some]).max() <= 1e-12 * np.abs(ref).max()
    assert solver.solve_columns(B[:, :0], some).shape == (40, 0)


def test_pruned_sweeps_cover_the_solution_and_count_their_operations(elastic):
    K = elastic.Kff.tocsc()
    solver = SupernodalSolver(K, threads=1)
    f = solver.factor
    L = _dense_L(f)
    j = int(elastic.load_pos[0])
    e = np.zeros(f.n)
    e[f.perm[j]] = 1.0
    y = np.linalg.solve(L, e)  # the forward solve's result, dense: its nonzeros must lie in the visited set
    forward = f.closure(np.array([f.perm[j]]))
    visited = np.zeros(f.n, dtype=bool)
    for s in forward:
        visited[f.start[s]:f.start[s + 1]] = True
    assert np.all(visited[np.abs(y) > 0])
    assert not visited.all()  # something was skipped
    read = elastic.read_pos
    back = f.closure(f.perm[read[read >= 0]])
    B = sp.csc_matrix(([1.0], ([j], [0])), shape=(f.n, 1))
    solver.solve_columns(B, read)
    assert solver.flops == f.flops(forward) + f.flops(back)
    full = f.flops(np.arange(f.start.size - 1))
    # one full sweep: about 2 nnz(L), and at least that (the relaxed panels' explicit zeros add some)
    assert 2 * f.nnz_L - f.n <= full <= 1.3 * 2 * f.nnz_L
    assert solver.flops < 2 * full


def test_threads_and_batches_give_identical_columns(elastic):
    K = elastic.Kff
    load = elastic.load_pos[:150]
    B = sp.csc_matrix((np.ones(load.size), (load, np.arange(load.size))), shape=(K.shape[0], load.size))
    # batches of 32: four sweeps of the same columns on one thread or two
    one = SupernodalSolver(K, batch=32, threads=1).solve_columns(B, elastic.read_pos)
    two = SupernodalSolver(K, batch=32, threads=2).solve_columns(B, elastic.read_pos)
    assert np.array_equal(one, two)
    for batch, threads in ((1, 1), (128, 1), (128, 2)):  # other batches: the same to rounding
        other = SupernodalSolver(K, batch=batch, threads=threads).solve_columns(B, elastic.read_pos)
        assert np.abs(other - one).max() <= 1e-13 * np.abs(one).max()


def test_compliance_agrees_with_cholmod_and_splu(box_system):
    K, fixed, load, read = box_system.K, box_system.fixed, box_system.load, box_system.read
    D = compliance_matrix(K, fixed, load, read)
    scale = np.abs(D).max()
    for other in ("cholmod", "splu"):
        assert np.abs(compliance_matrix(K, fixed, load, read, solver=other) - D).max() <= 1e-12 * scale
    # reciprocity on the loaded rows
    row_of = {int(d): i for i, d in enumerate(read)}
    rows = np.array([row_of[int(d)] for d in load])
    assert np.abs(D[rows] - D[rows].T).max() <= 1e-12 * scale


def test_a_matrix_that_is_not_positive_definite_is_refused():
    A = sp.diags([2.0, -1.0, 3.0], format="csc")
    with pytest.raises(np.linalg.LinAlgError, match="positive definite"):
        supernodal_factor(A)


def test_tiny_systems():
    A = sp.csc_matrix(np.array([[4.0]]))
    s = SupernodalSolver(A, threads=2)
    assert s.solve(np.array([2.0])) == pytest.approx([0.5], rel=1e-15)
    T = sp.diags([-np.ones(4), 2.5 * np.ones(5), -np.ones(4)], [-1, 0, 1], format="csc")
    s = SupernodalSolver(T)
    np.testing.assert_allclose(s.solve(np.eye(5)), np.linalg.inv(T.toarray()), rtol=0, atol=1e-14)


def test_the_manifest_records_the_factor_and_the_operations(tmp_path, small_box, box_system):
    from hailstorm.precompute import build_bundle
    from hailstorm.precompute.greens import cholesky_nnz
    from hailstorm.runtime import load

    problem = column_problem(box_system.K, box_system.fixed, box_system.load, box_system.read)
    ours = load(build_bundle(tmp_path / "s", mesh=small_box, young=1e6, poisson=0.3)).manifest["solve_stats"]
    factor = supernodal_factor(problem.Kff)
    ncols = problem.shape[1]
    assert ours["solver"] == "supernodal" and ours["nnz_L"] == factor.nnz_L
    assert ours["full_solve_flops"] == 4 * factor.nnz_L * ncols
    back = factor.closure(factor.perm[problem.read_pos[problem.read_pos >= 0]])
    # pruned: more than the backward sweeps alone, at most both sweeps over every panel
    assert factor.flops(back) * ncols < ours["solve_flops"] <= 2 * factor.flops(np.arange(factor.start.size - 1)) * ncols
    theirs = load(build_bundle(tmp_path / "c", mesh=small_box, young=1e6, poisson=0.3,
                               solver="cholmod")).manifest["solve_stats"]
    assert theirs["nnz_L"] == cholesky_nnz(problem.Kff) and theirs["solve_flops"] == theirs["full_solve_flops"]


def test_entries_cancelled_to_zero_do_not_break_the_pruning():
    """Poisson's ratio 0 decouples the directions: SuperLU's L then leaves out entries that cancel
    exactly, so its pattern is no Cholesky pattern (a column's rows are not all in its parent's) and
    parent pointers would miss rows a solve reaches. The factor restores the full pattern."""
    from hailstorm.precompute.supernodal import _superlu
    from hailstorm.precompute.supernodal_kernels import pattern_is_closed

    mesh = box_mesh((0.1, 0.02, 0.02), 0.01, clamp="x0")
    basis = elasticity_basis(mesh, 1)
    surf = extract_surface(mesh)
    problem = column_problem(stiffness_matrix(basis, 5e6, 0.0), clamp_dofs(basis, mesh),
                             vertex_dofs(basis, surf.nodes[surf.contactable]).ravel(),
                             vertex_dofs(basis, surf.nodes).ravel())
    K = problem.Kff.tocsc()
    raw = _superlu(K).L.tocsc()
    raw.sort_indices()
    assert not pattern_is_closed(raw.indptr.astype(np.int64), raw.indices.astype(np.int64), np.full(K.shape[0], -1))
    load = problem.load_pos
    B = sp.csc_matrix((np.ones(load.size), (load, np.arange(load.size))), shape=K.shape)
    got = SupernodalSolver(K).solve_columns(B, problem.read_pos)
    X = spsolve(K, B.toarray())
    expected = np.where(problem.read_pos[:, None] >= 0, X[np.maximum(problem.read_pos, 0)], 0.0)
    assert np.abs(got - expected).max() <= 1e-12 * np.abs(expected).max()
