"""Tests of hailstorm.runtime.contact: point contacts through the precomputed compliance.

The reference is an independent direct FEM solve (scikit-fem stiffness, the
contact constraints imposed by Lagrange multipliers in a saddle-point system),
which never touches the bundle's compliance D.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla

import hailstorm.runtime
from hailstorm.runtime.bundle.read import load
from hailstorm.runtime.contact import (
    Capacitance,
    ContactSolution,
    barycentric_matrix,
    capacitance,
    contact_points,
    hertz_radius,
    patch_matrix,
    patch_weights,
    solve_contacts,
    triangle_normals,
)

precompute = pytest.importorskip("hailstorm.precompute")
from hailstorm.precompute import fem  # noqa: E402

YOUNG, POISSON = 1.0e6, 0.3


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    """A small clamped box (0.1 x 0.1 x 0.05 m, h = 0.02), its bundle and its FEM."""
    mesh = hailstorm.precompute.box_mesh(size=(0.1, 0.1, 0.05), mesh_size=0.02)
    path = hailstorm.precompute.build_bundle(
        tmp_path_factory.mktemp("bundle") / "box", mesh=mesh, young=YOUNG, poisson=POISSON, solver="splu"
    )
    gf = load(path)
    basis = fem.elasticity_basis(mesh, 1)
    K = fem.stiffness_matrix(basis, YOUNG, POISSON)
    clamp = fem.clamp_dofs(basis, mesh)
    free = fem.free_dofs(K.shape[0], clamp)
    Kff = K[free][:, free]
    surf_dofs = fem.vertex_dofs(basis, gf.surface_nodes)  # (n, 3)
    tv = gf.triangles
    allowed = (gf.contactable | gf.fixed)[tv].all(axis=1)
    rigid_tris = np.flatnonzero(gf.fixed[tv].all(axis=1))
    touchable = np.flatnonzero(allowed & ~gf.fixed[tv].all(axis=1))
    nfix = gf.fixed[tv].sum(axis=1)
    partly = np.flatnonzero(allowed & (nfix == 1))  # one clamped vertex
    single = np.flatnonzero(allowed & (nfix == 2))  # a single free vertex
    unclamped = np.flatnonzero(allowed & (nfix == 0))
    return dict(gf=gf, basis=basis, Kff=Kff, free=free, ndof=K.shape[0], surf_dofs=surf_dofs,
                touchable=touchable, rigid_tris=rigid_tris, partly=partly, single=single,
                unclamped=unclamped)


def direct_fem(box, tri, bary, ubar, mode="sticky", normals=None, *, verts=None, weights=None):
    """Forces on the seat and surface displacement from the saddle-point FEM solve.

    [[K, C^T], [C, 0]] [u; mu] = [0; ubar_c], clamp dofs eliminated. The
    multipliers are minus the nodal forces applied to the body: K u = -C^T mu,
    so the force on the seat at contact k is -mu_k (times n_k if frictionless).
    Constraint row (k, d) is ``sum_a w_ka u_d(v_ka)`` with ``v_k`` the
    contacted triangle's vertices and ``w_k`` its barycentric coordinates, or
    the given patch ``verts`` / ``weights`` (s, P) (patch contacts).
    """
    gf, basis = box["gf"], box["basis"]
    s = len(tri)
    if normals is None:
        normals = triangle_normals(gf.vertices, gf.triangles[tri])
    if verts is None:
        verts, weights = gf.triangles[tri], bary
    nodes = gf.surface_nodes[np.asarray(verts)]
    rows, cols, vals, rhs = [], [], [], []
    r = 0
    for k in range(s):
        dofs = fem.vertex_dofs(basis, nodes[k])  # (P vertices, 3 components)
        if mode == "sticky":
            for d in range(3):
                for a in range(dofs.shape[0]):
                    rows.append(r), cols.append(dofs[a, d]), vals.append(weights[k, a])
                rhs.append(ubar[k, d])
                r += 1
        else:
            for d in range(3):
                for a in range(dofs.shape[0]):
                    rows.append(r), cols.append(dofs[a, d]), vals.append(weights[k, a] * normals[k, d])
            rhs.append(ubar[k] @ normals[k])
            r += 1
    C = sp.coo_matrix((vals, (rows, cols)), shape=(r, box["ndof"])).tocsr()[:, box["free"]]
    A = sp.bmat([[box["Kff"], C.T], [C, None]]).tocsc()
    nf = box["free"].size
    sol = spla.spsolve(A, np.concatenate([np.zeros(nf), rhs]))
    u = np.zeros(box["ndof"])
    u[box["free"]] = sol[:nf]
    mu = sol[nf:]
    f = -mu.reshape(s, 3) if mode == "sticky" else -mu[:, None] * normals
    return f, u[box["surf_dofs"]]


def random_contacts(box, s, rng, *, same_triangle=True):
    """s random contacts; W stays regular (no two contacts on a lone free vertex)."""
    tri = rng.choice(box["unclamped"], s, replace=False)
    if same_triangle and s >= 2:
        tri[1] = tri[0]  # two contacts on one triangle
    if s >= 7:
        tri[2] = box["partly"][0]  # a triangle touching the clamp
    bary = rng.dirichlet([1.0, 1.0, 1.0], s)
    return tri, bary


def one_pulled_out(box, s, pulled, *, seed):
    """s random contacts on distinct triangles (:func:`random_contacts`) pressed 1 mm in along
    their normals, all but contact ``pulled``, which is pulled 2 mm outward: tri, bary, normals, ubar."""
    gf = box["gf"]
    rng = np.random.default_rng(seed)
    tri, bary = random_contacts(box, s, rng, same_triangle=False)
    n = triangle_normals(gf.vertices, gf.triangles[tri])
    ubar = -1e-3 * n  # everyone presses in...
    ubar[pulled] = +2e-3 * n[pulled]  # ...but one is pulled outward
    return tri, bary, n, ubar


def rel(a, b):
    return np.abs(a - b).max() / max(np.abs(b).max(), 1e-300)


# ---------------------------------------------------------------------------
# B
# ---------------------------------------------------------------------------
def test_barycentric_matrix_blocks():
    triangles = np.array([[0, 1, 2], [2, 1, 3], [4, 4, 5]])
    bary = np.array([[0.2, 0.3, 0.5], [0.1, 0.6, 0.3], [0.25, 0.25, 0.5]])
    V, B = barycentric_matrix(triangles, np.array([0, 1, 1, 2]), np.vstack([bary, [0.25, 0.25, 0.5]])[[0, 1, 1, 2]])
    assert V.tolist() == [0, 1, 2, 3, 4, 5]
    assert B.shape == (18, 12)
    I3 = np.eye(3)
    np.testing.assert_array_equal(B[3:6, 0:3], 0.3 * I3)  # vertex 1 in contact 0
    np.testing.assert_array_equal(B[6:9, 3:6], 0.1 * I3)  # vertex 2 in contact 1
    np.testing.assert_array_equal(B[3:6, 6:9], 0.6 * I3)  # shared triangle, contact 2
    np.testing.assert_array_equal(B[12:15, 9:12], 0.5 * I3)  # repeated vertex accumulates
    np.testing.assert_array_equal(B[15:18, 9:12], 0.5 * I3)
    np.testing.assert_array_equal(B[0:3, 3:12], 0.0)  # vertex 0 only in contact 0


def test_barycentric_matrix_columns_sum_to_identity():
    rng = np.random.default_rng(1)
    triangles = rng.integers(0, 20, size=(30, 3))
    tri = rng.integers(0, 30, size=9)
    bary = rng.dirichlet([1, 1, 1], 9)
    V, B = barycentric_matrix(triangles, tri, bary)
    np.testing.assert_array_equal(V, np.unique(triangles[tri]))
    # sum over vertices of block (i, k) is sum_i beta_ki I3 = I3
    np.testing.assert_allclose(B.reshape(V.size, 3, 9, 3).sum(axis=0), np.tile(np.eye(3)[:, None, :], (1, 9, 1)))


# ---------------------------------------------------------------------------
# against the direct FEM saddle point
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("mode", ["sticky", "frictionless"])
@pytest.mark.parametrize("s", [1, 2, 7, 30])
def test_matches_direct_fem(box, mode, s):
    rng = np.random.default_rng(100 + s + (mode == "frictionless"))
    gf = box["gf"]
    tri, bary = random_contacts(box, s, rng)
    if s >= 7:  # contacts sharing vertices are part of the test
        verts = gf.triangles[tri]
        assert np.unique(verts).size < verts.size
    ubar = rng.normal(scale=1e-3, size=(s, 3))
    sol = solve_contacts(gf, tri, bary, ubar, mode=mode)
    f_ref, u_ref = direct_fem(box, tri, bary, ubar, mode)
    assert isinstance(sol, ContactSolution)
    assert sol.forces.shape == (s, 3) and sol.surface_displacement.shape == (gf.n_vertices, 3)
    assert rel(sol.forces, f_ref) < 1e-8
    assert rel(sol.surface_displacement, u_ref) < 1e-8
    # the contact points move as prescribed (normal component only if frictionless)
    nrm = triangle_normals(gf.vertices, gf.triangles[tri])
    if mode == "sticky":
        np.testing.assert_allclose(sol.contact_displacement, ubar, atol=1e-10 * np.abs(ubar).max())
    else:
        np.testing.assert_allclose(np.einsum("ki,ki->k", sol.contact_displacement, nrm),
                                   np.einsum("ki,ki->k", ubar, nrm), atol=1e-10 * np.abs(ubar).max())
        # frictionless forces are normal
        tang = sol.forces - np.einsum("ki,ki->k", sol.forces, nrm)[:, None] * nrm
        assert np.abs(tang).max() < 1e-12 * np.abs(sol.forces).max()
    # contact displacement is B^T u_V of the returned surface field
    u_c = np.einsum("ka,kad->kd", bary, sol.surface_displacement[gf.triangles[tri]])
    np.testing.assert_allclose(sol.contact_displacement, u_c, atol=1e-12 * np.abs(u_c).max())
    assert sol.active.all() and not sol.rigid.any()


def test_custom_normals_match_direct_fem(box):
    rng = np.random.default_rng(7)
    tri, bary = random_contacts(box, 7, rng)
    normals = rng.normal(size=(7, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    ubar = rng.normal(scale=1e-3, size=(7, 3))
    sol = solve_contacts(box["gf"], tri, bary, ubar, mode="frictionless", normals=3.0 * normals)
    f_ref, u_ref = direct_fem(box, tri, bary, ubar, "frictionless", normals)
    assert rel(sol.forces, f_ref) < 1e-8
    assert rel(sol.surface_displacement, u_ref) < 1e-8


def test_pushing_contact_pushes_inward(box):
    """Sign convention: pressing in (ubar.n < 0) gives a force on the seat with f.n < 0."""
    gf = box["gf"]
    tri = box["touchable"][:1]
    n = triangle_normals(gf.vertices, gf.triangles[tri])
    sol = solve_contacts(gf, tri, [[1 / 3, 1 / 3, 1 / 3]], -1e-3 * n, mode="frictionless")
    assert float(sol.forces[0] @ n[0]) < 0
    assert float(sol.contact_displacement[0] @ n[0]) == pytest.approx(-1e-3, rel=1e-10)


def test_rows_subset_and_none(box):
    gf = box["gf"]
    rng = np.random.default_rng(3)
    tri, bary = random_contacts(box, 7, rng)
    ubar = rng.normal(scale=1e-3, size=(7, 3))
    full = solve_contacts(gf, tri, bary, ubar)
    rows = np.array([0, 5, 17, gf.n_vertices - 1])
    sub = solve_contacts(gf, tri, bary, ubar, rows=rows)
    # (with numba, rows "all" and None take the one-call fast path and a subset the general one)
    np.testing.assert_allclose(sub.surface_displacement, full.surface_displacement[rows], rtol=0,
                               atol=1e-12 * np.abs(full.surface_displacement).max())
    none = solve_contacts(gf, tri, bary, ubar, rows=None)
    assert none.surface_displacement is None
    np.testing.assert_array_equal(none.forces, full.forces)


@pytest.mark.parametrize("s", [1, 7, 30])
def test_memory_layouts_agree(box, s):
    """Memory-mapped, in-memory C-order and Fortran-order D give the same results (the
    kernels read a C-order D through a column-major copy, the row gathers take other paths)."""
    import dataclasses

    gf = box["gf"]
    rng = np.random.default_rng(60 + s)
    tri, bary = random_contacts(box, s, rng)
    ubar = rng.normal(scale=1e-3, size=(s, 3))
    ref = solve_contacts(gf, tri, bary, ubar)
    rows = np.arange(0, gf.n_vertices, 2)
    ref_sub = solve_contacts(gf, tri, bary, ubar, rows=rows)  # the general path (not the one-call kernel)
    assert rel(ref_sub.surface_displacement, ref.surface_displacement[rows]) < 1e-9
    for D in (np.array(gf.D), np.asfortranarray(gf.D)):
        other = dataclasses.replace(gf, D=D)
        sol = solve_contacts(other, tri, bary, ubar)
        assert rel(sol.forces, ref.forces) < 1e-12
        assert rel(sol.surface_displacement, ref.surface_displacement) < 1e-12
        sub = solve_contacts(other, tri, bary, ubar, rows=rows)
        assert rel(sub.surface_displacement, ref_sub.surface_displacement) < 1e-12


def test_no_contacts(box):
    sol = solve_contacts(box["gf"], np.zeros(0, int), np.zeros((0, 3)), np.zeros((0, 3)))
    assert sol.forces.shape == (0, 3)
    assert not sol.surface_displacement.any()


def test_exported_from_runtime():
    assert hailstorm.runtime.solve_contacts is solve_contacts
    assert hailstorm.runtime.capacitance is capacitance


# ---------------------------------------------------------------------------
# unilateral contact
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("mode", ["sticky", "frictionless"])
def test_unilateral_releases_pulling_contact(box, mode):
    gf = box["gf"]
    tri, bary, n, ubar = one_pulled_out(box, 7, 4, seed=11)
    bil = solve_contacts(gf, tri, bary, ubar, mode=mode)
    assert bil.forces[4] @ n[4] > 0  # a bilateral contact would pull
    uni = solve_contacts(gf, tri, bary, ubar, mode=mode, unilateral=True)
    keep = np.arange(7) != 4
    assert uni.active.tolist() == keep.tolist()
    np.testing.assert_array_equal(uni.forces[4], 0.0)
    ref = solve_contacts(gf, tri[keep], bary[keep], ubar[keep], mode=mode)
    assert rel(uni.forces[keep], ref.forces) < 1e-10
    assert rel(uni.surface_displacement, ref.surface_displacement) < 1e-10
    # consistency: active contacts push, the released one is not penetrated
    assert np.all(np.einsum("ki,ki->k", uni.forces[keep], n[keep]) <= 0)
    assert (uni.contact_displacement[4] - ubar[4]) @ n[4] <= 0


@pytest.mark.parametrize("mode", ["sticky", "frictionless"])
def test_unilateral_all_pushing_equals_bilateral(box, mode):
    gf = box["gf"]
    for seed in range(50):  # a configuration in which the bilateral solution pushes everywhere
        rng = np.random.default_rng(seed)
        tri, bary = random_contacts(box, 4, rng, same_triangle=False)
        n = triangle_normals(gf.vertices, gf.triangles[tri])
        ubar = -1e-3 * n
        a = solve_contacts(gf, tri, bary, ubar, mode=mode)
        if np.all(np.einsum("ki,ki->k", a.forces, n) < 0):
            break
    else:
        pytest.fail("no all-pushing configuration found")
    b = solve_contacts(gf, tri, bary, ubar, mode=mode, unilateral=True)
    assert b.active.all() and b.iterations == 1
    assert rel(b.forces, a.forces) < 1e-12


def test_unilateral_complementarity_random(box):
    """Random prescriptions: the active set satisfies the contact conditions."""
    gf = box["gf"]
    rng = np.random.default_rng(13)
    tri, bary = random_contacts(box, 30, rng, same_triangle=False)
    n = triangle_normals(gf.vertices, gf.triangles[tri])
    ubar = rng.normal(scale=1e-3, size=30)[:, None] * n
    sol = solve_contacts(gf, tri, bary, ubar, mode="frictionless", unilateral=True)
    fn = np.einsum("ki,ki->k", sol.forces, n)
    gap = np.einsum("ki,ki->k", sol.contact_displacement - ubar, n)
    scale_f, scale_u = np.abs(fn).max(), np.abs(ubar).max()
    assert 0 < sol.active.sum() < 30
    assert np.all(fn <= 1e-9 * scale_f)
    assert np.all(gap <= 1e-9 * scale_u)
    assert np.all(np.abs(gap[sol.active]) <= 1e-9 * scale_u)
    assert np.all(fn[~sol.active] == 0)


# ---------------------------------------------------------------------------
# rigid and coincident contacts
# ---------------------------------------------------------------------------
def test_rigid_contact_on_clamped_triangle(box):
    gf = box["gf"]
    rng = np.random.default_rng(21)
    assert box["rigid_tris"].size
    tri, bary = random_contacts(box, 5, rng, same_triangle=False)
    tri = np.append(tri, box["rigid_tris"][0])
    bary = np.vstack([bary, [0.2, 0.3, 0.5]])
    ubar = rng.normal(scale=1e-3, size=(6, 3))
    for mode in ("sticky", "frictionless"):
        sol = solve_contacts(gf, tri, bary, ubar, mode=mode)
        assert sol.rigid.tolist() == [False] * 5 + [True]
        assert not sol.active[5]
        np.testing.assert_array_equal(sol.forces[5], 0.0)
        np.testing.assert_array_equal(sol.contact_displacement[5], 0.0)
        assert np.all(np.isfinite(sol.forces))
        ref = solve_contacts(gf, tri[:5], bary[:5], ubar[:5], mode=mode)
        assert rel(sol.forces[:5], ref.forces) < 1e-12
        assert rel(sol.surface_displacement, ref.surface_displacement) < 1e-12
    cap = capacitance(gf, tri, bary)
    assert not cap.W[15:].any() and not cap.W[:, 15:].any() and cap.K.shape == (15, 15)
    only = solve_contacts(gf, tri[5:], bary[5:], ubar[5:], unilateral=True)
    assert only.rigid.all() and not only.forces.any() and not only.surface_displacement.any()


def test_contact_on_clamped_vertex_is_rigid(box):
    gf = box["gf"]
    t = box["partly"][0]
    v = gf.triangles[t]
    bary = gf.fixed[v].astype(float)
    bary /= bary.sum()
    sol = solve_contacts(gf, [t], [bary], [[0.0, 0.0, -1e-3]])
    assert sol.rigid[0] and not sol.forces.any()


@pytest.mark.parametrize("mode", ["sticky", "frictionless"])
def test_coincident_contacts_split_equally(box, mode):
    gf = box["gf"]
    t = int(box["touchable"][3])
    b = np.array([0.2, 0.5, 0.3])
    u = np.array([1e-4, -2e-4, -1e-3])
    one = solve_contacts(gf, [t], [b], [u], mode=mode)
    two = solve_contacts(gf, [t, t], [b, b], [u, u], mode=mode)
    assert np.all(np.isfinite(two.forces))
    np.testing.assert_allclose(two.forces[0], two.forces[1], rtol=1e-8, atol=1e-12 * np.abs(one.forces).max())
    np.testing.assert_allclose(two.forces.sum(axis=0), one.forces[0], rtol=1e-7)
    np.testing.assert_allclose(two.surface_displacement, one.surface_displacement, rtol=1e-7,
                               atol=1e-9 * np.abs(one.surface_displacement).max())
    # conflicting prescriptions on one point: still finite (least-squares compromise)
    conf = solve_contacts(gf, [t, t], [b, b], [u, -u], mode=mode)
    assert np.all(np.isfinite(conf.forces))
    assert np.abs(conf.forces).max() <= 10 * np.abs(one.forces).max()
    # nearly coincident (1e-14 apart): finite as well
    b2 = b + np.array([1e-14, -1e-14, 0.0])
    near = solve_contacts(gf, [t, t], [b, b2], [u, u], mode=mode)
    assert np.all(np.isfinite(near.forces))
    np.testing.assert_allclose(near.forces.sum(axis=0), one.forces[0], rtol=1e-6)


def test_rank_deficient_contacts_stay_finite(box):
    """Two frictionless contacts on a triangle with one free vertex: W is singular."""
    gf = box["gf"]
    t = int(box["single"][0])
    bary = np.array([[0.2, 0.3, 0.5], [0.5, 0.3, 0.2]])
    n = triangle_normals(gf.vertices, gf.triangles[[t, t]])
    cap = capacitance(gf, [t, t], bary, mode="frictionless")
    assert not cap.exact
    sol = solve_contacts(gf, [t, t], bary, -1e-4 * n, mode="frictionless")
    assert np.all(np.isfinite(sol.forces)) and np.all(np.isfinite(sol.surface_displacement))
    assert np.all(np.einsum("ki,ki->k", sol.forces, n) < 0)


def test_coincident_with_others_matches_merged_contact(box):
    """A duplicated contact among others behaves like a single one with its force split."""
    gf = box["gf"]
    rng = np.random.default_rng(31)
    tri, bary = random_contacts(box, 7, rng, same_triangle=False)
    ubar = rng.normal(scale=1e-3, size=(7, 3))
    dup = solve_contacts(gf, np.append(tri, tri[2]), np.vstack([bary, bary[2]]), np.vstack([ubar, ubar[2]]))
    ref = solve_contacts(gf, tri, bary, ubar)
    np.testing.assert_allclose(dup.forces[2], dup.forces[7], rtol=1e-7)
    assert rel(np.vstack([dup.forces[:2], dup.forces[2:3] + dup.forces[7:], dup.forces[3:7]]), ref.forces) < 1e-7


# ---------------------------------------------------------------------------
# capacitance object and low-rank updates
# ---------------------------------------------------------------------------
def _assert_same_capacitance(a: Capacitance, b: Capacitance):
    np.testing.assert_array_equal(a.V, b.V)
    np.testing.assert_array_equal(a.rigid, b.rigid)
    assert rel(a.B, b.B) == 0
    assert rel(a.D_VV, b.D_VV) == 0
    assert rel(a.W, b.W) < 1e-12
    assert rel(a.K, b.K) < 1e-10


@pytest.mark.parametrize("mode", ["sticky", "frictionless"])
def test_add_remove_equal_fresh_build(box, mode):
    gf = box["gf"]
    rng = np.random.default_rng(41)
    tri, bary = random_contacts(box, 12, rng)
    tri[9] = box["rigid_tris"][1]  # one rigid contact in the mix
    cap = capacitance(gf, tri[:5], bary[:5], mode=mode)
    for k in range(5, 12):
        idx = cap.add(int(tri[k]), bary[k])
        assert idx == k
        _assert_same_capacitance(cap, capacitance(gf, tri[: k + 1], bary[: k + 1], mode=mode))
    assert cap.exact
    keep = list(range(12))
    for k in (3, 0, 7, 1):  # positions in the current list
        cap.remove(k)
        del keep[k]
        _assert_same_capacitance(cap, capacitance(gf, tri[keep], bary[keep], mode=mode))
    ubar = rng.normal(scale=1e-3, size=(len(keep), 3))
    fresh = solve_contacts(gf, tri[keep], bary[keep], ubar, mode=mode)
    assert rel(cap.forces(ubar), fresh.forces) < 1e-10
    assert rel(cap.surface_displacement(cap.forces(ubar)), fresh.surface_displacement) < 1e-10


@pytest.mark.parametrize("mode", ["sticky", "frictionless"])
def test_add_equals_fresh_build_on_a_hat_load_bundle(tmp_path, mode):
    """On a hat-load bundle D is not symmetric (docs/verification.md, "reciprocity") and W is its
    symmetric part: a contact added by the bordered update gives the W and K of a fresh build (its
    coupling column the mean of both products; the plain G_old^T D G_new missed by 1e-3 of K)."""
    mesh = hailstorm.precompute.box_mesh(size=(0.1, 0.1, 0.05), mesh_size=0.02)
    gf = load(hailstorm.precompute.build_bundle(tmp_path / "hat", mesh=mesh, young=YOUNG, poisson=POISSON, load="hat"))
    cv = gf.contact_vertices
    Dcc = gf.compliance(cv, cv)
    assert np.linalg.norm(Dcc - Dcc.T) > 0.01 * np.linalg.norm(Dcc)  # the case this test is for
    T = np.asarray(gf.triangles)
    tri = np.flatnonzero(gf.contactable[T].all(axis=1))[[0, 3, 7, 12, 20, 28]]
    bary = np.random.default_rng(5).dirichlet(np.ones(3), tri.size)
    cap = capacitance(gf, tri[:2], bary[:2], mode=mode)
    for k in range(2, tri.size):
        cap.add(int(tri[k]), bary[k])
        fresh = capacitance(gf, tri[: k + 1], bary[: k + 1], mode=mode)
        assert rel(cap.W, fresh.W) < 1e-12 and np.allclose(cap.W, cap.W.T, rtol=0, atol=1e-15 * np.abs(cap.W).max())
        assert rel(cap.K, fresh.K) < 1e-10


@pytest.mark.parametrize("pos", [[0, 1, 2, 6, 7, 8], [3, 4, 5, 9, 10, 11, 12, 13, 14], [1, 2, 3], [0, 2, 4, 6]])
def test_embed_block_copies(pos, monkeypatch):
    import hailstorm.runtime.contact.capacitance_update as rc
    from hailstorm.runtime.contact.capacitance_update import embed

    monkeypatch.setattr(rc, "EMBED_BLOCKS_FROM", 0)
    pos = np.array(pos)
    M = np.random.default_rng(0).normal(size=(pos.size, pos.size))
    out = embed(M, pos, int(pos.max()) + 2)
    np.testing.assert_array_equal(out[np.ix_(pos, pos)], M)


def test_add_remove_block_copy_path(box, monkeypatch):
    """Same as a fresh build when D_VV is grown by block copies."""
    import hailstorm.runtime.contact.capacitance_update as rc

    monkeypatch.setattr(rc, "EMBED_BLOCKS_FROM", 0)
    gf = box["gf"]
    rng = np.random.default_rng(42)
    tri, bary = random_contacts(box, 9, rng)
    for mode in ("sticky", "frictionless"):
        cap = capacitance(gf, tri[:4], bary[:4], mode=mode)
        for k in range(4, 9):
            cap.add(int(tri[k]), bary[k])
        _assert_same_capacitance(cap, capacitance(gf, tri, bary, mode=mode))
        cap.remove(2)
        keep = np.arange(9) != 2
        _assert_same_capacitance(cap, capacitance(gf, tri[keep], bary[keep], mode=mode))


def test_add_coincident_falls_back_to_pseudo_inverse(box):
    gf = box["gf"]
    t = box["touchable"][:3]
    bary = np.full((3, 3), 1 / 3)
    cap = capacitance(gf, t, bary)
    cap.add(int(t[1]), bary[1])
    assert not cap.exact
    fresh = capacitance(gf, np.append(t, t[1]), np.vstack([bary, bary[1]]))
    assert not fresh.exact
    assert rel(cap.K, fresh.K) < 1e-8
    cap.remove(3)
    _assert_same_capacitance(cap, capacitance(gf, t, bary))
    assert cap.exact


def test_capacitance_methods(box):
    gf = box["gf"]
    rng = np.random.default_rng(51)
    tri, bary = random_contacts(box, 7, rng)
    cap = capacitance(gf, tri, bary)
    ubar = rng.normal(scale=1e-3, size=(7, 3))
    f = cap.forces(ubar)
    np.testing.assert_allclose(cap.contact_displacement(f), ubar, atol=1e-12 * np.abs(ubar).max())
    np.testing.assert_allclose(cap.K @ cap.W, np.eye(21), atol=1e-9)
    rows = np.arange(0, gf.n_vertices, 3)
    np.testing.assert_allclose(cap.surface_displacement(f, rows), cap.surface_displacement(f)[rows], rtol=1e-12)
    # response matrix D[rows, V] G (what the storm multiplies multipliers with)
    R = cap.surface_response()
    np.testing.assert_allclose(R, gf.compliance(np.arange(gf.n_vertices), cap.V) @ cap.G, rtol=1e-12, atol=1e-20)
    np.testing.assert_allclose((R @ f.ravel()).reshape(-1, 3), cap.surface_displacement(f), rtol=1e-12, atol=1e-20)
    np.testing.assert_allclose(cap.surface_response(rows), R.reshape(-1, 3, 21)[rows].reshape(-1, 21), rtol=1e-12)
    fr = capacitance(gf, tri, bary, mode="frictionless")
    np.testing.assert_allclose(fr.surface_response(rows), gf.compliance(rows, fr.V) @ fr.G, rtol=1e-12, atol=1e-20)
    # surface displacement equals the bundle's own superposition of vertex forces
    np.testing.assert_allclose(cap.surface_displacement(f), gf.displacement(cap.V, cap.vertex_forces(f)), rtol=1e-12,
                               atol=1e-20)


# ---------------------------------------------------------------------------
# validation
# ---------------------------------------------------------------------------
@pytest.mark.parametrize(
    "kwargs, exc, match",
    [
        (dict(triangles=[[0, 1]]), ValueError, "shape"),
        (dict(triangles=[0.5]), ValueError, "integer"),
        (dict(triangles=[10**6]), IndexError, "outside"),
        (dict(triangles=[-1]), IndexError, "outside"),
        (dict(barycentric=[[0.2, 0.3, 0.5], [0.2, 0.3, 0.5]]), ValueError, "shape"),
        (dict(barycentric=[[0.2, 0.3, 0.6]]), ValueError, "sum"),
        (dict(barycentric=[[-0.1, 0.6, 0.5]]), ValueError, "negative"),
        (dict(barycentric=[[np.nan, 0.5, 0.5]]), ValueError, "NaN"),
        (dict(displacements=[[0.0, 0.0]]), ValueError, "shape"),
        (dict(displacements=[[0.0, np.nan, 0.0]]), ValueError, "NaN"),
        (dict(mode="slippery"), ValueError, "mode"),
        (dict(normals=[[0.0, 0.0, 0.0]]), ValueError, "zero"),
        (dict(normals=[[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]), ValueError, "shape"),
        (dict(rows="some"), ValueError, "rows"),
        (dict(rows=[10**6]), IndexError, "rows"),
    ],
)
def test_validation(box, kwargs, exc, match):
    args = dict(triangles=[int(box["touchable"][0])], barycentric=[[0.2, 0.3, 0.5]], displacements=[[0.0, 0.0, -1e-3]])
    opts = {}
    for k, v in kwargs.items():
        (args if k in args else opts)[k] = v
    with pytest.raises(exc, match=match):
        solve_contacts(box["gf"], args["triangles"], args["barycentric"], args["displacements"], **opts)


def test_validation_barycentric_tolerances(box):
    t = [int(box["touchable"][0])]
    solve_contacts(box["gf"], t, [[0.5 + 5e-7, 0.5, 0.0]], [[0, 0, -1e-3]])  # within 1e-6
    solve_contacts(box["gf"], t, [[1.0 + 5e-10, 0.0, -5e-10]], [[0, 0, -1e-3]])  # within -1e-9


def test_validation_non_contactable_triangle(box):
    """A triangle with a vertex that owns no column of D (neither contactable nor clamped)."""
    import dataclasses

    gf = box["gf"]
    t = int(box["touchable"][0])
    contactable = gf.contactable.copy()
    contactable[gf.triangles[t][~gf.fixed[gf.triangles[t]]][0]] = False
    crippled = dataclasses.replace(gf, contactable=contactable)
    with pytest.raises(ValueError, match="contactable"):
        solve_contacts(crippled, [t], [[1 / 3, 1 / 3, 1 / 3]], [[0, 0, 0]])


def test_add_remove_validation(box):
    cap = capacitance(box["gf"], box["touchable"][:2], np.full((2, 3), 1 / 3))
    with pytest.raises(IndexError):
        cap.remove(2)
    with pytest.raises(IndexError, match="out of range"):  # like a triangle index: -1 is refused
        cap.remove(-1)
    with pytest.raises(TypeError, match="integer"):
        cap.remove(0.5)
    assert cap.s == 2  # nothing was removed
    with pytest.raises(ValueError, match="sum"):
        cap.add(int(box["touchable"][3]), [0.5, 0.5, 0.5])
    with pytest.raises(ValueError, match="shape"):
        cap.forces(np.zeros((3, 3)))


# ---------------------------------------------------------------------------
# patch contacts
# ---------------------------------------------------------------------------
def _top_contacts(box, s, rng):
    """s random contacts on the upper face z = 0.05 (flat, away from the clamp)."""
    gf = box["gf"]
    z = gf.vertices[gf.triangles[box["unclamped"]], 2]
    top = box["unclamped"][np.all(np.isclose(z, 0.05), axis=1)]
    tri = rng.choice(top, s, replace=False)
    return tri, rng.dirichlet([1.0, 1.0, 1.0], s)


@pytest.mark.parametrize("mode", ["sticky", "frictionless"])
@pytest.mark.parametrize("s, radius", [(1, 0.03), (3, 0.025), (7, "mixed")])
def test_patch_matches_direct_fem(box, mode, s, radius):
    """Patch contacts = the FEM saddle point with the patch weights as constraint rows."""
    gf = box["gf"]
    rng = np.random.default_rng(200 + s + (mode == "frictionless"))
    tri, bary = random_contacts(box, s, rng, same_triangle=False)
    if radius == "mixed":  # point contacts, patches of several sizes, one reaching the clamp
        radius = np.array([0.0, 0.015, 0.03, 0.045, 0.0, 0.02, 0.06])
    ubar = rng.normal(scale=1e-3, size=(s, 3))
    sol = solve_contacts(gf, tri, bary, ubar, mode=mode, patch_radius=radius)
    cap = capacitance(gf, tri, bary, mode=mode, patch_radius=radius)
    verts, w = patch_weights(gf, tri, bary, radius)
    assert verts.shape[1] > 3  # the patches really cover more than a triangle
    np.testing.assert_array_equal(cap.V[cap.loc], verts)
    np.testing.assert_array_equal(cap.weights, w)
    f_ref, u_ref = direct_fem(box, tri, bary, ubar, mode, verts=verts, weights=w)
    assert rel(sol.forces, f_ref) < 1e-8
    assert rel(sol.surface_displacement, u_ref) < 1e-8
    # the patch-mean displacement is the prescription (normal part if frictionless)
    nrm = triangle_normals(gf.vertices, gf.triangles[tri])
    u_patch = np.einsum("kp,kpd->kd", w, sol.surface_displacement[verts])
    np.testing.assert_allclose(sol.contact_displacement, u_patch, atol=1e-12 * np.abs(ubar).max())
    if mode == "sticky":
        np.testing.assert_allclose(u_patch, ubar, atol=1e-10 * np.abs(ubar).max())
    else:
        np.testing.assert_allclose(np.einsum("ki,ki->k", u_patch, nrm), np.einsum("ki,ki->k", ubar, nrm),
                                   atol=1e-10 * np.abs(ubar).max())
    # B of the capacitance is the patch matrix
    V, B = patch_matrix(gf, tri, bary, radius)
    np.testing.assert_array_equal(V, cap.V)
    np.testing.assert_array_equal(B, cap.B)


@pytest.mark.parametrize("mode", ["sticky", "frictionless"])
def test_patch_unilateral_matches_direct_fem(box, mode):
    gf = box["gf"]
    tri, bary, n, ubar = one_pulled_out(box, 5, 2, seed=17)  # contact 2 released
    sol = solve_contacts(gf, tri, bary, ubar, mode=mode, unilateral=True, patch_radius=0.02)
    assert not sol.active[2] and sol.active.sum() == 4
    keep = np.arange(5) != 2
    verts, w = patch_weights(gf, tri[keep], bary[keep], 0.02)
    f_ref, u_ref = direct_fem(box, tri[keep], bary[keep], ubar[keep], mode, verts=verts, weights=w)
    assert rel(sol.forces[keep], f_ref) < 1e-8
    assert rel(sol.surface_displacement, u_ref) < 1e-8


def test_patch_radius_zero_is_point_contact(box):
    gf = box["gf"]
    rng = np.random.default_rng(5)
    tri, bary = random_contacts(box, 7, rng)
    ubar = rng.normal(scale=1e-3, size=(7, 3))
    # the general path (explicit normals: not the one-call point-contact kernel), which a
    # patch radius of 0 takes too
    ref = solve_contacts(gf, tri, bary, ubar, normals=triangle_normals(gf.vertices, gf.triangles[tri]))
    for radius in (0.0, np.zeros(7)):
        sol = solve_contacts(gf, tri, bary, ubar, patch_radius=radius)
        np.testing.assert_array_equal(sol.forces, ref.forces)
        np.testing.assert_array_equal(sol.surface_displacement, ref.surface_displacement)
    # a patch much smaller than a triangle: the weights tend to beta (continuity at a -> 0)
    tri1, bary1 = _top_contacts(box, 4, rng)
    bary1 = 0.8 * bary1 + 0.2 / 3  # keep the tiny disc inside the triangle
    verts, w = patch_weights(gf, tri1, bary1, 1e-6)
    dense = np.zeros((4, gf.n_vertices))
    np.add.at(dense, (np.repeat(np.arange(4), verts.shape[1]), verts.ravel()), w.ravel())
    point = np.zeros((4, gf.n_vertices))
    np.add.at(point, (np.repeat(np.arange(4), 3), gf.triangles[tri1].ravel()), bary1.ravel())
    np.testing.assert_allclose(dense, point, atol=1e-9)
    small = solve_contacts(gf, tri1, bary1, ubar[:4], patch_radius=1e-6)
    assert rel(small.forces, solve_contacts(gf, tri1, bary1, ubar[:4]).forces) < 1e-7


def test_patch_weights_properties(box):
    gf = box["gf"]
    rng = np.random.default_rng(8)
    tri, bary = _top_contacts(box, 6, rng)
    x = contact_points(gf.vertices, gf.triangles, tri, bary)
    a = 0.012
    verts, w = patch_weights(gf, tri, bary, a)
    assert np.all(w >= 0)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, rtol=1e-13)
    # only vertices of triangles the disc touches (h = 0.02: within a + h)
    dist = np.linalg.norm(gf.vertices[verts] - x[:, None, :], axis=2)
    assert np.all(dist[w > 0] <= a + 0.02 * np.sqrt(2) + 1e-12)
    # linear reproduction on the flat top: the weights' first moment is the centre
    # (exact for discs inside the top face, truncated ones are pulled inward)
    inside = np.all((x[:, :2] > a) & (x[:, :2] < 0.1 - a), axis=1)
    mom = np.einsum("kp,kpd->kd", w, gf.vertices[verts])
    np.testing.assert_allclose(mom[inside], x[inside], atol=2e-3 * a)
    # continuity: a small move of the centre changes the weights a little
    b2 = bary + 1e-4 * np.array([1.0, -1.0, 0.0])
    b2 = np.clip(b2, 0, None) / np.clip(b2, 0, None).sum(axis=1, keepdims=True)
    v2, w2 = patch_weights(gf, tri, b2, a)
    d1 = np.zeros((6, gf.n_vertices))
    d2 = np.zeros((6, gf.n_vertices))
    np.add.at(d1, (np.repeat(np.arange(6), verts.shape[1]), verts.ravel()), w.ravel())
    np.add.at(d2, (np.repeat(np.arange(6), v2.shape[1]), v2.ravel()), w2.ravel())
    assert np.abs(d1 - d2).max() < 0.02
    # uniform profile: also normalised, flatter than Hertz (less weight on the nearest vertex)
    vu, wu = patch_weights(gf, tri, bary, a, profile="uniform")
    np.testing.assert_allclose(wu.sum(axis=1), 1.0, rtol=1e-13)


def test_patch_on_clamp_is_rigid(box):
    gf = box["gf"]
    t = int(box["rigid_tris"][0])
    sol = solve_contacts(gf, [t], [[1 / 3] * 3], [[0.0, 0.0, 1e-3]], patch_radius=0.02)
    assert sol.rigid[0] and not sol.forces.any() and not sol.surface_displacement.any()


@pytest.mark.parametrize("mode", ["sticky", "frictionless"])
def test_patch_add_remove_equal_fresh_build(box, mode):
    gf = box["gf"]
    rng = np.random.default_rng(43)
    tri, bary = random_contacts(box, 9, rng)
    radii = np.array([0.02, 0.0, 0.03, 0.02, 0.05, 0.0, 0.01, 0.02, 0.04])
    cap = capacitance(gf, tri[:3], bary[:3], mode=mode, patch_radius=radii[:3])
    for k in range(3, 9):
        cap.add(int(tri[k]), bary[k], patch_radius=radii[k])
        fresh = capacitance(gf, tri[: k + 1], bary[: k + 1], mode=mode, patch_radius=radii[: k + 1])
        _assert_same_capacitance(cap, fresh)
        np.testing.assert_array_equal(cap.patch_radius, radii[: k + 1])
    keep = list(range(9))
    for k in (4, 0, 2):
        cap.remove(k)
        del keep[k]
        _assert_same_capacitance(cap, capacitance(gf, tri[keep], bary[keep], mode=mode, patch_radius=radii[keep]))
    # a scalar radius at build is the default of add
    cap2 = capacitance(gf, tri[:2], bary[:2], mode=mode, patch_radius=0.02)
    cap2.add(int(tri[2]), bary[2])
    _assert_same_capacitance(cap2, capacitance(gf, tri[:3], bary[:3], mode=mode, patch_radius=0.02))
    ubar = rng.normal(scale=1e-3, size=(len(keep), 3))
    fresh = solve_contacts(gf, tri[keep], bary[keep], ubar, mode=mode, patch_radius=radii[keep])
    assert rel(cap.forces(ubar), fresh.forces) < 1e-10
    assert rel(cap.surface_displacement(cap.forces(ubar)), fresh.surface_displacement) < 1e-10
    R = cap.surface_response()
    np.testing.assert_allclose(R, gf.compliance(np.arange(gf.n_vertices), cap.V) @ cap.G, rtol=1e-12, atol=1e-20)


@pytest.mark.parametrize("mode", ["sticky", "frictionless"])
@pytest.mark.parametrize("patch", [False, True])
def test_kept_response_follows_add_and_remove(box, mode, patch):
    """keep_response: surface_displacement is R @ f, and R follows add / remove (with a
    rigid contact and patches in the mix): equal to the column gather and to direct FEM."""
    gf = box["gf"]
    rng = np.random.default_rng(44)
    tri, bary = random_contacts(box, 8, rng)
    tri[6] = box["rigid_tris"][0]
    radii = np.array([0.02, 0.0, 0.03, 0.02, 0.0, 0.01, 0.02, 0.04]) if patch else np.zeros(8)
    cap = capacitance(gf, tri[:3], bary[:3], mode=mode, patch_radius=radii[:3])
    R = cap.keep_response()
    assert R.shape == (3 * gf.n_vertices, 9) and cap.keep_response() is R  # formed once
    keep = [0, 1, 2]
    for op in [("add", 3), ("add", 4), ("remove", 1), ("add", 5), ("add", 6), ("remove", 0), ("add", 7)]:
        if op[0] == "add":
            cap.add(int(tri[op[1]]), bary[op[1]], patch_radius=radii[op[1]])
            keep.append(op[1])
        else:
            cap.remove(op[1])
            del keep[op[1]]
        # arbitrary forces (tangential parts too): R @ f is D[:, V] B f whatever the mode
        f = rng.normal(size=(len(keep), 3))
        kept = cap.surface_displacement(f)
        gathered = gf.displacement(cap.V, cap.vertex_forces(f))
        assert rel(kept, gathered) < 1e-12
    assert cap._R.shape[1] == 3 * len(keep)
    ubar = -1e-3 * triangle_normals(gf.vertices, gf.triangles[tri[keep]]) + rng.normal(scale=1e-4, size=(len(keep), 3))
    f = cap.forces(ubar)
    live = ~cap.rigid  # the rigid contact carries no force; FEM constrains the others
    assert cap.rigid.sum() == 1 and not f[~live].any()
    verts = weights = None
    if patch:
        verts, weights = cap.V[cap.loc][live], cap.weights[live]
    kl = np.asarray(keep)[live]
    f_fem, u_fem = direct_fem(box, tri[kl], bary[kl], ubar[live], mode, cap.normals[live], verts=verts,
                              weights=weights)
    assert rel(f[live], f_fem) < 1e-8
    assert rel(cap.surface_displacement(f), u_fem) < 1e-8
    with pytest.raises(ValueError, match="shape"):
        cap.surface_displacement(np.zeros((len(keep) + 1, 3)))


def test_patch_is_stiffer_than_point(box):
    """Spreading the force over a patch raises the contact stiffness (W shrinks)."""
    gf = box["gf"]
    rng = np.random.default_rng(9)
    tri, bary = _top_contacts(box, 3, rng)
    k = [capacitance(gf, tri, bary, mode="frictionless", patch_radius=a).K.diagonal() for a in (0.0, 0.01, 0.03)]
    assert np.all(k[0] < k[1]) and np.all(k[1] < k[2])


def test_hertz_radius():
    E, nu, R, F = 2e6, 0.35, 0.01, 5.0
    a = hertz_radius(F, R, E, nu)
    assert a == pytest.approx((3 * F * R * (1 - nu**2) / (4 * E)) ** (1 / 3), rel=1e-14)
    np.testing.assert_allclose(hertz_radius([F, -8 * F], R, E, nu), [a, 2 * a], rtol=1e-14)  # a ~ F^(1/3)
    assert hertz_radius(0.0, R, E, nu, a_min=1e-3) == 1e-3
    assert hertz_radius(1e6, R, E, nu, a_max=R) == R
    with pytest.raises(ValueError):
        hertz_radius(F, R, E, 0.5)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(patch_radius=-0.01), "non-negative"),
        (dict(patch_radius=[0.01, 0.02]), "shape"),
        (dict(patch_radius=np.nan), "finite"),
        (dict(patch_radius=0.01, patch_profile="gaussian"), "profile"),
    ],
)
def test_patch_validation(box, kwargs, match):
    with pytest.raises(ValueError, match=match):
        solve_contacts(box["gf"], [int(box["touchable"][0])], [[0.2, 0.3, 0.5]], [[0.0, 0.0, -1e-3]], **kwargs)
    with pytest.raises(ValueError, match=match):
        capacitance(box["gf"], [int(box["touchable"][0])], [[0.2, 0.3, 0.5]], **kwargs)


# ---------------------------------------------------------------------------
# the contact core as one package: public active set, protocol, one policy
# ---------------------------------------------------------------------------
@pytest.mark.parametrize("mode", ["sticky", "frictionless"])
def test_capacitance_solve_is_the_active_set(box, mode):
    """Capacitance.solve (public) is what solve_contacts runs: the same forces, active set
    and iterations for unilateral contacts that partly pull; the bilateral solve is forces()."""
    gf = box["gf"]
    rng = np.random.default_rng(77)
    tri, bary = random_contacts(box, 12, rng)
    n = triangle_normals(gf.vertices, gf.triangles[tri])
    ubar = -1e-3 * n * rng.choice([-1.0, 1.0], size=(12, 1))  # some press, some pull
    ref = solve_contacts(gf, tri, bary, ubar, mode=mode, unilateral=True)
    cap = capacitance(gf, tri, bary, mode=mode)
    got = cap.solve(ubar, unilateral=True)
    assert 0 < got.active.sum() < 12 and got.iterations == ref.iterations
    np.testing.assert_array_equal(got.active, ref.active)
    assert rel(got.forces, ref.forces) < 1e-12
    np.testing.assert_array_equal(cap.solve(ubar).forces, cap.forces(ubar))
    with pytest.raises(ValueError, match="shape"):
        cap.solve(ubar[:3])


def test_compliance_source_protocol(box):
    """Any object with the ComplianceSource attributes serves the contact core (here a plain
    namespace holding a C-ordered copy of D): the same solution as the bundle."""
    import types

    from hailstorm.runtime.contact import ComplianceSource

    gf = box["gf"]
    src = types.SimpleNamespace(D=np.ascontiguousarray(gf.D), column_of=gf.column_of, contactable=gf.contactable,
                                fixed=gf.fixed, vertices=gf.vertices, triangles=gf.triangles)
    attrs = {name for name in dir(ComplianceSource) if not name.startswith("_")}
    assert attrs == {"D", "column_of", "contactable", "fixed", "vertices", "triangles"}
    rng = np.random.default_rng(3)
    tri, bary = random_contacts(box, 9, rng)
    ubar = rng.normal(scale=1e-3, size=(9, 3))
    for kw in ({}, {"unilateral": True, "mode": "frictionless"}, {"patch_radius": 0.02}):
        a = solve_contacts(gf, tri, bary, ubar, **kw)
        b = solve_contacts(src, tri, bary, ubar, **kw)
        assert rel(b.forces, a.forces) < 1e-12
        assert rel(b.surface_displacement, a.surface_displacement) < 1e-12


@pytest.mark.parametrize("fast", [True, False])
def test_rigid_threshold_is_the_policy_constant(box, monkeypatch, fast):
    """Both paths (the one-call point-contact kernel and the general one) read the rigid
    threshold from hailstorm.runtime.contact.policy: a contact with 1e-13 of its weight on
    its one free vertex is a hard wall at the default 1e-12 and a soft contact below it."""
    from hailstorm.runtime.contact import policy

    gf = box["gf"]
    t = int(box["single"][0])
    free = ~gf.fixed[gf.triangles[t]]
    b = np.where(free, 1e-13, 0.0)
    b[np.flatnonzero(~free)[0]] = 1.0 - 1e-13
    kw = {} if fast else {"normals": triangle_normals(gf.vertices, gf.triangles[[t]])}
    sol = solve_contacts(gf, [t], [b], [[0.0, 0.0, -1e-6]], **kw)
    assert sol.rigid.all() and not sol.forces.any()
    monkeypatch.setattr(policy, "RIGID_WEIGHT", 1e-14)
    sol = solve_contacts(gf, [t], [b], [[0.0, 0.0, -1e-6]], **kw)
    assert not sol.rigid.any() and sol.active.all() and np.abs(sol.forces).max() > 0


def test_contact_api_has_no_backend_switch(box):
    """One implementation: the contact API takes no backend=, and the kernels'
    package has no backend switch left to resolve."""
    import inspect

    from hailstorm.runtime import compiled, press_spheres

    for fn in (solve_contacts, capacitance, patch_weights, patch_matrix, press_spheres):
        assert "backend" not in inspect.signature(fn).parameters, fn.__name__
    with pytest.raises(TypeError):
        solve_contacts(box["gf"], [int(box["touchable"][0])], [[0.2, 0.3, 0.5]], [[0, 0, -1e-3]], backend="numpy")
    for name in ("resolve_backend", "HAVE_NUMBA"):
        assert not hasattr(compiled, name) and name not in compiled.__all__, name


def test_contact_core_imports_no_private_names():
    """No module of the contact core (nor the bundle or press_spheres) imports an underscore
    name from another module (the patch kernel they share is
    :func:`hailstorm.runtime.compiled.patches.disc_patch`)."""
    import ast
    from pathlib import Path

    root = Path(hailstorm.runtime.__file__).parent
    files = sorted((root / "contact").glob("*.py")) + sorted((root / "bundle").glob("*.py"))
    allowed: set[tuple[str, str]] = set()
    found = []
    for f in files:
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("hailstorm"):
                found += [(f.name, node.module, a.name) for a in node.names
                          if a.name.startswith("_") and (node.module, a.name) not in allowed]
    assert not found
    assert len(files) >= 8
