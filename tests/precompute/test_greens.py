"""The compliance D against independent direct solves, reciprocity, equilibrium."""

import numpy as np
import pytest
from skfem import condense, solve

import hailstorm.runtime
from hailstorm.precompute.fem import clamp_dofs, elasticity_basis, stiffness_matrix, vertex_dofs
from hailstorm.precompute.geometry import box_mesh
from hailstorm.precompute.greens import area_matrix, compliance_matrix, traction_greens_function
from hailstorm.precompute.fem import rigid_modes_on_dofs
from hailstorm.precompute.pipeline import build_bundle


def _direct_column(mesh, order, E, nu, node, direction):
    """Displacement (all dofs) under a unit nodal force, by scikit-fem's own solve."""
    basis = elasticity_basis(mesh, order)
    K = stiffness_matrix(basis, E, nu)
    f = np.zeros(K.shape[0])
    f[vertex_dofs(basis, [node])[0, direction]] = 1.0
    u = solve(*condense(K, f, D=clamp_dofs(basis, mesh)))
    return basis, K, f, u


@pytest.mark.parametrize("order", [1, 2])
def test_columns_equal_direct_fem(tmp_path, small_box, rng, order):
    gf = hailstorm.runtime.load(build_bundle(tmp_path / "b", mesh=small_box, order=order, young=1e6, poisson=0.3))
    cv = gf.contact_vertices
    rows = np.arange(gf.n_vertices)
    for j in rng.choice(cv, size=4, replace=False):
        d = int(rng.integers(3))
        basis, K, f, u = _direct_column(small_box, order, 1e6, 0.3, gf.surface_nodes[j], d)
        expected = u[vertex_dofs(basis, gf.surface_nodes[rows]).ravel()]
        got = gf.compliance(rows, [j])[:, d]
        assert np.linalg.norm(got - expected) <= 1e-10 * np.linalg.norm(expected)


def test_reciprocity_contactable_block_is_symmetric(seat_bundle):
    gf = hailstorm.runtime.load(seat_bundle)
    cv = gf.contact_vertices
    Dcc = gf.compliance(cv, cv)
    assert np.abs(Dcc - Dcc.T).max() <= 1e-10 * np.abs(Dcc).max()
    # and positive definite: a compliance stores energy
    assert np.linalg.eigvalsh(0.5 * (Dcc + Dcc.T)).min() > 0


def _surface_mass(vertices, triangles):
    """The P1 consistent mass matrix of a triangulated surface, (n, n) dense: area / 12 (2 on the diagonal)."""
    p = vertices[triangles]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    M = np.zeros((vertices.shape[0],) * 2)
    for a in range(3):
        for b in range(3):
            np.add.at(M, (triangles[:, a], triangles[:, b]), area * (2.0 if a == b else 1.0) / 12.0)
    return M


def test_hat_load_block_is_reciprocal_in_hat_weighted_displacements(tmp_path, small_box):
    """load="hat" (P1): the rows are nodal displacements and the columns hat loads, so the contactable
    block is not symmetric (here by several per cent); reciprocity holds for the displacement that is
    the hat load's work-conjugate, the hat-weighted mean A^-1 M u (M the surface's consistent mass matrix,
    A its lumped areas, M's row sums): A^-1 M^T D is symmetric to round-off. (The contact solves use the
    symmetric part of the nodal block: docs/verification.md.)"""
    gf = hailstorm.runtime.load(build_bundle(tmp_path / "hat", mesh=small_box, order=1, young=1e6, poisson=0.3,
                                             load="hat"))
    cv = gf.contact_vertices
    D = gf.compliance(np.arange(gf.n_vertices), cv)  # (3n, 3c): every surface row
    M = _surface_mass(np.asarray(gf.vertices), np.asarray(gf.triangles))
    np.testing.assert_allclose(M.sum(axis=1), gf.areas, rtol=1e-12)  # the lumped areas are M's row sums
    S = np.kron(M[:, cv].T / gf.areas[cv][:, None], np.eye(3)) @ D  # hat-weighted rows of the contactable vertices
    assert np.abs(S - S.T).max() <= 1e-10 * np.abs(S).max()
    Dcc = D.reshape(gf.n_vertices, 3, -1)[cv].reshape(3 * cv.size, -1)
    assert np.linalg.norm(Dcc - Dcc.T) > 0.01 * np.linalg.norm(Dcc)


def test_traction_greens_function_is_D_times_A(box_bundle, rng):
    gf = hailstorm.runtime.load(box_bundle)
    cv = gf.contact_vertices
    rows = np.arange(gf.n_vertices)
    p = rng.normal(size=3 * cv.size)  # tractions [Pa] at the contactable vertices
    Xi = gf.traction_greens(rows, cv)
    D = gf.compliance(rows, cv)
    A = area_matrix(gf.areas[cv])
    assert np.allclose(Xi @ p, D @ (A @ p), rtol=1e-12, atol=0)
    assert np.allclose(traction_greens_function(D, gf.areas[cv]), Xi, rtol=1e-14, atol=0)


def test_lumped_areas_sum_to_surface_area(box_bundle):
    gf = hailstorm.runtime.load(box_bundle)
    total = 2 * (0.1 * 0.1 + 0.1 * 0.05 + 0.1 * 0.05)
    assert gf.areas.sum() == pytest.approx(total, rel=1e-12)


def test_clamp_reactions_balance_applied_force(small_box):
    node = np.flatnonzero(np.isclose(small_box.points[:, 2], 0.05))[5]
    basis, K, f, u = _direct_column(small_box, 1, 1e6, 0.3, node, 2)
    reaction = K @ u - f  # nonzero only on the clamp
    fixed = clamp_dofs(basis, small_box)
    free = np.setdiff1d(np.arange(K.shape[0]), fixed)
    assert np.abs(reaction[free]).max() <= 1e-9
    per_node = reaction[vertex_dofs(basis, np.arange(small_box.points.shape[0]))]  # (N, 3)
    assert np.allclose(per_node.sum(axis=0), [0.0, 0.0, -1.0], atol=1e-9)  # the clamp pushes back with -f
    # moments balance too: sum x × r + x_load × e_z = 0
    moment = np.cross(small_box.points, per_node).sum(axis=0) + np.cross(small_box.points[node], [0, 0, 1.0])
    assert np.allclose(moment, 0.0, atol=1e-9)


def test_amg_path_matches_direct(box_system):
    basis, K, fixed, read = box_system.basis, box_system.K, box_system.fixed, box_system.read
    load = box_system.load[:30]  # ten vertices
    D_direct = compliance_matrix(K, fixed, load, read, solver="cholmod")
    D_splu = compliance_matrix(K, fixed, load, read, solver="splu")
    D_amg = compliance_matrix(K, fixed, load, read, solver="amg", near_null=rigid_modes_on_dofs(basis), tol=1e-10)
    scale = np.linalg.norm(D_direct)
    assert np.linalg.norm(D_splu - D_direct) <= 1e-12 * scale
    assert np.linalg.norm(D_amg - D_direct) <= 1e-7 * scale


def test_blocked_solves_match_one_block(box_system):
    K, fixed, load, read = box_system.K, box_system.fixed, box_system.load, box_system.read
    big = compliance_matrix(K, fixed, load, read)
    tiny = compliance_matrix(K, fixed, load, read, block_bytes=1)  # one column per block
    assert np.array_equal(big.shape, tiny.shape)
    assert np.abs(big - tiny).max() <= 1e-14 * np.abs(big).max()


def test_clamped_columns_are_zero_and_unknown_columns_refused(box_bundle):
    gf = hailstorm.runtime.load(box_bundle)
    fixed = np.flatnonzero(gf.fixed)[:3]
    block = gf.compliance(np.arange(5), fixed)
    assert block.shape == (15, 9) and not block.any()
    mesh = box_mesh((0.1, 0.1, 0.05), 0.02)
    assert mesh.points.shape[0] == gf.volume_points.shape[0]


def test_parallel_workers_give_identical_columns(box_system):
    K, fixed, load, read = box_system.K, box_system.fixed, box_system.load, box_system.read
    pytest.importorskip("distributed")
    serial = compliance_matrix(K, fixed, load, read, block_columns=16)
    parallel = compliance_matrix(K, fixed, load, read, workers=2, block_columns=16, block_bytes=20_000)
    assert np.abs(serial - parallel).max() <= 1e-12 * np.abs(serial).max()


@pytest.mark.slow
def test_default_seat_p2_columns_equal_direct_fem(tmp_path):
    """The full-size path: P2 on the default seat at 6 mm (~36k dofs)."""
    from hailstorm.precompute import mesh_default_seat

    mesh = mesh_default_seat(0.006)
    gf = hailstorm.runtime.load(build_bundle(tmp_path / "p2", mesh=mesh, order=2))
    rows = np.arange(gf.n_vertices)
    for j in gf.contact_vertices[[0, gf.contact_vertices.size // 2]]:
        basis, K, f, u = _direct_column(mesh, 2, gf.young, gf.poisson, gf.surface_nodes[j], 2)
        expected = u[vertex_dofs(basis, gf.surface_nodes).ravel()]
        assert np.linalg.norm(gf.compliance(rows, [j])[:, 2] - expected) <= 1e-9 * np.linalg.norm(expected)


@pytest.mark.parametrize("order", [1, 2])
def test_hat_columns_equal_direct_fem_with_a_hat_traction(tmp_path, small_box, order):
    """load="hat": column (j, d) is the response to the traction e_d φ_j / a_j,
    checked against scikit-fem's own assembly of that traction (a LinearForm on
    the boundary with φ_j interpolated from a scalar P1 field)."""
    from skfem import ElementTetP1, FacetBasis, LinearForm

    gf = hailstorm.runtime.load(build_bundle(tmp_path / "hat", mesh=small_box, order=order, young=1e6, poisson=0.3, load="hat"))
    assert gf.manifest["options"]["load"] == "hat"
    basis = elasticity_basis(small_box, order)
    K = stiffness_matrix(basis, 1e6, 0.3)
    facets = basis.mesh.boundary_facets()
    fb = FacetBasis(basis.mesh, basis.elem, facets=facets, intorder=4)
    fb_scalar = FacetBasis(basis.mesh, ElementTetP1(), facets=facets, intorder=4)
    rows = np.arange(gf.n_vertices)
    for j, d in [(int(gf.contact_vertices[3]), 2), (int(gf.contact_vertices[-1]), 0)]:
        indicator = np.zeros(fb_scalar.N)
        indicator[gf.surface_nodes[j]] = 1.0

        @LinearForm
        def traction(v, w):
            return w["phi"] * v[d] / gf.areas[j]

        f = traction.assemble(fb, phi=fb_scalar.interpolate(indicator))
        total = f[vertex_dofs(basis, np.arange(small_box.points.shape[0]))[:, d]].sum()
        if order == 2:
            total += f[basis.edge_dofs[d]].sum()
        assert total == pytest.approx(1.0, rel=1e-12)  # one newton in all
        u = solve(*condense(K, f, D=clamp_dofs(basis, small_box)))
        expected = u[vertex_dofs(basis, gf.surface_nodes).ravel()]
        got = gf.compliance(rows, [j])[:, d]
        assert np.linalg.norm(got - expected) <= 1e-10 * np.linalg.norm(expected)


def test_hat_and_point_bundles_have_different_keys(tmp_path, small_box):
    a = hailstorm.runtime.load(build_bundle(tmp_path / "a", mesh=small_box, load="point"))
    b = hailstorm.runtime.load(build_bundle(tmp_path / "b", mesh=small_box, load="hat"))
    assert a.manifest["key"] != b.manifest["key"]
    assert not np.allclose(a.D, b.D)
    with pytest.raises(ValueError, match="unknown load"):
        build_bundle(tmp_path / "c", mesh=small_box, load="smeared")


def test_solver_registry_drives_factorize_batches_and_the_cli(box_system):
    """Every registered solver factorizes the clamped box system and solves a load to its residual
    (a check independent of the other solvers: ``K_ff x = b``); its batch is the one the problem
    uses; the names the CLI offers are the registry's; an unknown name is refused once, at the
    registry, with the choices."""
    import scipy.sparse as sp

    from hailstorm.cli import _parser
    from hailstorm.precompute.fem import free_dofs
    from hailstorm.precompute.greens import SOLVER_SPECS, SOLVERS, column_problem, factorize, solver_spec

    K, fixed = box_system.K, box_system.fixed
    free = free_dofs(K.shape[0], fixed)
    Kff = sp.csr_matrix(K)[free][:, free]
    nn = rigid_modes_on_dofs(box_system.basis)[free]
    b = np.random.default_rng(3).normal(size=(Kff.shape[0], 2))
    for name, spec in SOLVER_SPECS.items():
        assert spec.name == name and solver_spec(name) is spec
        f = factorize(Kff, name, near_null=nn if spec.needs_near_null else None, tol=1e-12)
        x = f.solve(b)
        # direct solvers: backward stable (residual ~ eps cond); AMG: solved to tol = 1e-12
        assert np.linalg.norm(Kff @ x - b) <= 1e-9 * np.linalg.norm(b), name
        problem = column_problem(K, fixed, box_system.load[:3], box_system.read, solver=name,
                                 near_null=rigid_modes_on_dofs(box_system.basis) if spec.needs_near_null else None)
        assert problem.batch == spec.batch and problem.spec is spec
    assert SOLVERS == tuple(SOLVER_SPECS)
    pre = next(a for a in _parser()._subparsers._group_actions[0].choices["precompute"]._actions
               if a.dest == "solver")
    assert tuple(pre.choices) == SOLVERS and pre.default == SOLVERS[0]
    with pytest.raises(ValueError, match="unknown solver 'lu'; choose one of"):
        solver_spec("lu")
    with pytest.raises(ValueError, match="needs the rigid-body modes"):
        factorize(Kff, "amg")
