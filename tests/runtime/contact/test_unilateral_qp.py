"""The frictionless unilateral solve as a convex QP: projected Newton
(:func:`nonnegative_qp`) converges where block pivoting cycles, meets the KKT conditions on
1000 contacts, and gives today's answers where block pivoting settles."""

from __future__ import annotations

import numpy as np
import pytest

from hailstorm.runtime.contact import active_set, capacitance, solve_contacts, triangle_normals
from hailstorm.runtime.contact.active_set import ACTIVE_SET_TOL, nonnegative_qp


def block_pivoting(W, q, limit):
    """The old iteration on ``x >= 0, W x + q >= 0`` (a plain statement, for the
    measurement in the report): the set of positive components from the last solve's
    signs; a repeated set -> one flip per round (the last violated index); returns the
    rounds or None (no settling)."""
    n = q.size
    act = np.ones(n, bool)
    seen, single = set(), False
    for it in range(1, limit + 1):
        x = np.zeros(n)
        if act.any():
            x[act] = np.linalg.solve(W[np.ix_(act, act)], -q[act])
        g = W @ x + q
        scale = max(np.abs(q).max(), np.abs(W @ x).max())
        viol = np.flatnonzero((act & (x < -ACTIVE_SET_TOL * max(np.abs(x).max(), 1e-300)))
                              | (~act & (g < -ACTIVE_SET_TOL * scale)))
        if viol.size == 0:
            return it
        key = act.tobytes()
        single = single or key in seen
        seen.add(key)
        if single:
            viol = viol[-1:]
        act = act.copy()
        act[viol] = ~act[viol]
    return None


def kkt(W, q, x):
    """Largest violation of x >= 0, g >= 0, x g = 0, relative to the problem's scale."""
    g = W @ x + q
    gs = max(np.abs(q).max(), np.abs(W @ x).max())
    xs = max(np.abs(x).max(), 1e-300)
    return max(-x.min() / xs, -g.min() / gs, np.abs(x * g).max() / (xs * gs))


def random_contacts(n, seed):
    """A dense SPD compliance far from an M-matrix (long-range positive and negative
    coupling, as a curved seat's), and loads that press some contacts, pull others."""
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n)) / np.sqrt(n)
    W = A @ A.T + 0.05 * np.eye(n)
    return W, rng.normal(size=n)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_projected_newton_solves_1000_contacts_to_kkt(seed):
    W, q = random_contacts(1000, seed)
    x, iterations = nonnegative_qp(W, q)
    assert kkt(W, q, x) < 1e-9
    assert iterations < 60  # measured: 5-14
    # independent check: the same x from the KKT system of the set it found
    a = x > 0
    ref = np.zeros_like(x)
    ref[a] = np.linalg.solve(W[np.ix_(a, a)], -q[a])
    assert np.abs(x - ref).max() <= 1e-8 * np.abs(ref).max()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_projected_newton_converges_from_any_start_on_low_rank_couplings(seed):
    """Nearly singular W (rank n/10 plus a small diagonal): every start, the sign
    pattern's worst one included, reaches the same KKT point."""
    rng = np.random.default_rng(seed)
    n = 300
    A = rng.normal(size=(n, n // 10))
    W = A @ A.T / n + 1e-3 * np.eye(n)
    q = rng.normal(size=n)
    x1, _ = nonnegative_qp(W, q)
    x2, _ = nonnegative_qp(W, q, x0=np.where(q < 0, 0.0, 10.0))
    assert kkt(W, q, x1) < 1e-9 and kkt(W, q, x2) < 1e-9
    assert np.abs(x1 - x2).max() <= 1e-6 * np.abs(x1).max()  # unique minimiser (W SPD), cond ~1e4


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    import hailstorm.precompute
    from hailstorm.runtime.bundle.read import load

    mesh = hailstorm.precompute.box_mesh(size=(0.1, 0.1, 0.05), mesh_size=0.02)
    path = hailstorm.precompute.build_bundle(tmp_path_factory.mktemp("bundle") / "box", mesh=mesh,
                                             young=1.0e6, poisson=0.3, solver="splu")
    gf = load(path)
    return gf, np.flatnonzero(gf.contactable[gf.triangles].all(axis=1))


@pytest.mark.parametrize("seed", range(6))
def test_qp_path_gives_todays_answers_on_small_cases(box, monkeypatch, seed):
    """Forced onto the QP at once (BLOCK_PIVOT_ROUNDS = 1), a small frictionless set gets
    block pivoting's forces and active set (to the conditioning's rounding)."""
    gf, unclamped = box
    rng = np.random.default_rng(seed)
    s = 15
    tri = rng.choice(unclamped, s, replace=False)
    bary = rng.dirichlet([1.0, 1.0, 1.0], s)
    n = triangle_normals(gf.vertices, gf.triangles[tri])
    ubar = rng.normal(0.0, 1e-4, (s, 3))
    before = solve_contacts(gf, tri, bary, ubar, mode="frictionless", unilateral=True, normals=n, rows=None)
    monkeypatch.setattr(active_set, "BLOCK_PIVOT_ROUNDS", 1)
    after = solve_contacts(gf, tri, bary, ubar, mode="frictionless", unilateral=True, normals=n, rows=None)
    np.testing.assert_array_equal(after.active, before.active)
    scale = np.abs(before.forces).max()
    assert np.abs(after.forces - before.forces).max() <= 1e-9 * scale


@pytest.mark.parametrize("bad", [-1, 0, 2.5, True])
def test_max_iter_must_be_a_positive_integer(box, bad):
    gf, unclamped = box
    cap = capacitance(gf, unclamped[:3], np.full((3, 3), 1 / 3), mode="frictionless")
    with pytest.raises(ValueError, match="max_iter must be a positive integer"):
        cap.solve(np.zeros((3, 3)), unilateral=True, max_iter=bad)
    with pytest.raises(ValueError, match="max_iter must be a positive integer"):
        nonnegative_qp(np.eye(2), np.ones(2), max_iter=bad)


@pytest.mark.parametrize("unilateral", [False, True])
def test_complex_displacements_are_refused_not_made_real(box, unilateral):
    """numpy would drop the imaginary part (a ComplexWarning at most): refused instead."""
    gf, unclamped = box
    tri, bary = unclamped[:3], np.full((3, 3), 1 / 3)
    ubar = np.zeros((3, 3), complex)
    ubar[:, 2] = -1e-4 + 1e-5j
    with pytest.raises(ValueError, match="displacements must be real numbers"):
        solve_contacts(gf, tri, bary, ubar, mode="frictionless", unilateral=unilateral)
    cap = capacitance(gf, tri, bary, mode="frictionless")
    with pytest.raises(ValueError, match="displacements must be real numbers"):
        cap.solve(ubar, unilateral=unilateral)
    with pytest.raises(ValueError, match="displacements must be real numbers"):
        cap.forces(ubar)  # the same check (was: the imaginary part dropped, a ComplexWarning at most)


@pytest.mark.parametrize("seed", [0])
def test_1000_random_unilateral_contacts_on_the_seat_settle(seat_bundle, seed):
    """The case the bad-input round measured: 1000 random frictionless unilateral contacts
    through ``solve_contacts`` on a seat of 225 contactable vertices (W singular: more
    contacts than the seat's vertices can tell apart) settle (before: "active set did not
    settle in 2010 iterations"). Checked against SciPy's NNLS (Lawson-Hanson, finite
    termination) on the same QP: the normal displacements ``W x`` are unique at every
    minimiser of the convex QP even where the forces are not."""
    from scipy.linalg import cholesky, solve_triangular
    from scipy.optimize import nnls

    from hailstorm.runtime.bundle.read import load

    gf = load(seat_bundle)
    rng = np.random.default_rng(seed)
    tris = np.flatnonzero(gf.contactable[gf.triangles].all(axis=1) & ~gf.fixed[gf.triangles].all(axis=1))
    s = 1000
    tri = rng.choice(tris, size=s)
    bary = rng.dirichlet([1.0, 1.0, 1.0], size=s)
    n = triangle_normals(gf.vertices, gf.triangles[tri])
    ubar = -1e-3 * n + rng.normal(scale=2e-4, size=(s, 3))
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):  # a threaded BLAS on a shared machine is 10x slower at this size
        sol = solve_contacts(gf, tri, bary, ubar, mode="frictionless", unilateral=True, normals=n, rows=None)
    fn = np.einsum("ki,ki->k", sol.forces, n)
    assert (fn <= 1e-9 * np.abs(fn).max()).all()  # contacts only push
    assert 0 < sol.active.sum() < s and (fn[~sol.active] == 0).all()
    # the same QP (x = -lambda >= 0: min 1/2 x^T W x + c^T x) by NNLS on W's Cholesky factor
    cap = capacitance(gf, tri, bary, mode="frictionless", normals=n)
    W, c = cap.W, np.einsum("ki,ki->k", ubar, n)
    R = cholesky(W + 1e-10 * np.diag(W).mean() * np.eye(s))  # W + eps I = R^T R (W is singular)
    x, _ = nnls(R, -solve_triangular(R, c, trans="T"), maxiter=20 * s)
    un_ref = W @ x
    un = W @ -fn  # x = -lambda, lambda the signed normal forces
    # the two differ by the shifts (1e-8 and 1e-10 of the mean compliance) and rounding in a
    # singular W: a relative 1e-6 of the displacements is far above both, far below a changed set
    assert np.abs(un - un_ref).max() <= 1e-6 * np.abs(c).max()
