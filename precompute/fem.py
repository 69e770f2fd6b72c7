"""Linear elasticity with scikit-fem: the stiffness matrix and its boundary data.

Small plain functions in the scikit-fem style:

* :func:`check_material` - E > 0, -1 < nu < 1/2, with clear errors;
* :func:`elasticity_basis` - vector P1 or P2 tetrahedra on a :class:`TetMesh`;
* :func:`stiffness_matrix` - the symmetric positive semi-definite K, for one
  material or one (E, nu) per tetrahedron;
* :func:`clamp_dofs`, :func:`vertex_dofs` - where the clamp is, and the x, y, z
  degrees of freedom of mesh vertices (for point loads and read-outs);
* :func:`solve_direct` - one direct solve with the clamp (the reference every
  Green's function is checked against).
"""

from __future__ import annotations

import numpy as np

from hailstorm.runtime.resources import require_extra
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from hailstorm.precompute.tetmesh import TetMesh

#: Defaults for a padded saddle treated as one homogeneous solid (see the docs, "Choosing settings").
DEFAULT_YOUNG = 2.0e6
DEFAULT_POISSON = 0.35


def check_material(young: float, poisson: float) -> tuple[float, float]:
    """Validate Young's modulus [Pa] and Poisson's ratio; return them as floats.

    Raises
    ------
    ValueError
        If E <= 0 or not finite, or nu is outside (-1, 0.5). nu = 0.5 is an
        incompressible material that displacement elements cannot represent.
    """
    young, poisson = float(young), float(poisson)
    if not np.isfinite(young) or young <= 0:
        raise ValueError(f"Young's modulus must be a positive number of pascals, got E = {young!r}")
    if not np.isfinite(poisson):
        raise ValueError(f"Poisson's ratio must be a number with -1 < nu < 0.5, got nu = {poisson!r}")
    if poisson >= 0.5:
        raise ValueError(
            f"Poisson's ratio must satisfy -1 < nu < 0.5, got nu = {poisson!r} "
            "(nu >= 0.5 is incompressible: a displacement formulation cannot represent it)"
        )
    if poisson <= -1.0:
        raise ValueError(
            f"Poisson's ratio must satisfy -1 < nu < 0.5, got nu = {poisson!r} "
            "(nu <= -1 is not a stable material: its shear modulus E / (2 (1 + nu)) is not positive)"
        )
    return young, poisson


def lame_parameters(young: float, poisson: float) -> tuple[float, float]:
    """Lamé parameters (lambda, mu) from (E, nu)."""
    young, poisson = check_material(young, poisson)
    lam = young * poisson / ((1 + poisson) * (1 - 2 * poisson))
    mu = young / (2 * (1 + poisson))
    return lam, mu


def skfem_mesh(mesh: TetMesh):
    """The scikit-fem ``MeshTet`` of a :class:`TetMesh` (same node numbering)."""
    require_extra("skfem", "precompute", "assembling elasticity (scikit-fem)")
    from skfem import MeshTet

    return MeshTet(np.ascontiguousarray(mesh.points.T), np.ascontiguousarray(mesh.tets.T))


def elasticity_basis(mesh: TetMesh, order: int = 1):
    """Vector Lagrange basis of degree ``order`` (1 or 2) on the tetrahedra.

    Node ``i`` of ``mesh.points`` is vertex ``i`` of the basis for either order
    (P2 adds edge nodes after the vertices).
    """
    from skfem import Basis, ElementTetP1, ElementTetP2, ElementVector

    if order not in (1, 2):
        raise ValueError(f"element order must be 1 or 2, got {order!r}")
    elem = ElementVector(ElementTetP1() if order == 1 else ElementTetP2())
    # strains of P_k are P_(k-1) on affine tets: their products are integrated
    # exactly by a rule of degree 2(k-1); degree 2 covers P1 and P2
    return Basis(skfem_mesh(mesh), elem, intorder=2)


def stiffness_matrix(basis, young, poisson) -> sp.csr_matrix:
    """Assemble the linear-elastic stiffness K (symmetric, singular before clamping).

    Parameters
    ----------
    basis
        From :func:`elasticity_basis`.
    young, poisson : float or (T,) array_like
        One material for the whole body, or one (E [Pa], nu) per tetrahedron
        (element-wise constant Lamé parameters: a body of several materials).
    """
    from skfem import BilinearForm, asm
    from skfem.helpers import ddot, sym_grad, trace
    from skfem.models.elasticity import linear_elasticity

    if np.ndim(young) == 0 and np.ndim(poisson) == 0:
        lam, mu = lame_parameters(young, poisson)
        return asm(linear_elasticity(Lambda=lam, Mu=mu), basis).tocsr()
    n = basis.nelems
    young = np.broadcast_to(np.asarray(young, dtype=float), (n,))
    poisson = np.broadcast_to(np.asarray(poisson, dtype=float), (n,))
    pairs = np.unique(np.column_stack([young, poisson]), axis=0)
    for e, nu in pairs:
        check_material(e, nu)
    lam = young * poisson / ((1 + poisson) * (1 - 2 * poisson))
    mu = young / (2 * (1 + poisson))
    nqp = basis.X.shape[1]

    @BilinearForm
    def form(u, v, w):
        eu, ev = sym_grad(u), sym_grad(v)
        return 2.0 * w["mu"] * ddot(eu, ev) + w["lam"] * trace(eu) * trace(ev)

    return asm(form, basis, lam=np.repeat(lam[:, None], nqp, axis=1), mu=np.repeat(mu[:, None], nqp, axis=1)).tocsr()


def _facet_ids(basis, triangles: np.ndarray) -> np.ndarray:
    """Indices into ``basis.mesh.facets`` of the given boundary triangles."""
    facets = np.sort(basis.mesh.facets.T, axis=1).astype(np.int64)  # int64: the keys below reach n^3
    tris = np.sort(np.asarray(triangles), axis=1).astype(np.int64)
    n = basis.mesh.p.shape[1]
    key_f = (facets[:, 0] * n + facets[:, 1]) * n + facets[:, 2]
    key_t = (tris[:, 0] * n + tris[:, 1]) * n + tris[:, 2]
    order = np.argsort(key_f)
    pos = np.searchsorted(key_f[order], key_t)
    pos = np.minimum(pos, key_f.size - 1)
    found = key_f[order][pos] == key_t
    if not found.all():
        raise ValueError(f"{int((~found).sum())} group triangles are not facets of the mesh")
    return order[pos]


def clamp_dofs(basis, mesh: TetMesh, group: str = "clamp") -> np.ndarray:
    """All degrees of freedom on the ``group`` triangles (vertices, and edges for P2)."""
    if group not in mesh.groups:
        raise ValueError(f"mesh has no {group!r} group (it has: {sorted(mesh.groups)})")
    return np.asarray(basis.get_dofs(_facet_ids(basis, mesh.groups[group])).all(), dtype=np.int64)


def vertex_dofs(basis, vertex_ids) -> np.ndarray:
    """(k, 3) dof indices of the x, y, z components at mesh vertices ``vertex_ids``."""
    return np.asarray(basis.nodal_dofs[:, np.asarray(vertex_ids)].T, dtype=np.int64)


def free_dofs(n_dofs: int, fixed: np.ndarray) -> np.ndarray:
    """Complement of ``fixed`` in ``range(n_dofs)``."""
    mask = np.ones(n_dofs, dtype=bool)
    mask[fixed] = False
    return np.flatnonzero(mask)


def solve_direct(K: sp.spmatrix, f: np.ndarray, fixed: np.ndarray) -> np.ndarray:
    """Solve K u = f with u = 0 on ``fixed`` dofs by a sparse direct solve (reference)."""
    free = free_dofs(K.shape[0], fixed)
    u = np.zeros(K.shape[0] if f.ndim == 1 else (K.shape[0], f.shape[1]))
    Kff = K[free][:, free].tocsc()
    u[free] = spla.spsolve(Kff, f[free])
    return u


def rigid_body_modes(points: np.ndarray) -> np.ndarray:
    """The six rigid-body displacement fields at ``points`` as an (3N, 6) array.

    Interleaved x, y, z per node (scikit-fem's vector dof order for nodal dofs
    must be mapped by the caller). Used as the near-null space for AMG.
    """
    x, y, z = (points - points.mean(axis=0)).T
    n = points.shape[0]
    modes = np.zeros((n, 3, 6))
    modes[:, 0, 0] = modes[:, 1, 1] = modes[:, 2, 2] = 1.0
    modes[:, 0, 3], modes[:, 1, 3] = -y, x  # rotation about z
    modes[:, 1, 4], modes[:, 2, 4] = -z, y  # rotation about x
    modes[:, 0, 5], modes[:, 2, 5] = z, -x  # rotation about y
    return modes.reshape(3 * n, 6)


def rigid_modes_on_dofs(basis) -> np.ndarray:
    """The six rigid-body modes at every dof of ``basis`` (a scikit-fem vector basis), in its dof
    order: (n_dofs, 6), the near null space an algebraic multigrid solver takes."""
    locs = basis.doflocs.T  # (n_dofs, 3)
    comp = np.empty(locs.shape[0], dtype=np.int64)
    for d in range(3):
        comp[basis.nodal_dofs[d]] = d
        if basis.edge_dofs.size:
            comp[basis.edge_dofs[d]] = d
    modes = rigid_body_modes(locs)  # (3 n_dofs, 6): rows 3k+c = component c at location k
    return modes.reshape(-1, 3, 6)[np.arange(locs.shape[0]), comp]
