"""Green's functions: the compliance D from one factorization and many solves.

Column (j, d) of the compliance D is the displacement of every output vertex
under a unit nodal force at contactable vertex j in direction d:
K_ff u = e_(j,d), read at the output dofs. Three solvers share one interface
(:func:`compliance_matrix`):

``"cholmod"`` (default)
    Sparse Cholesky of K_ff (CHOLMOD through ``cholespy``, fill-reducing
    ordering), right-hand sides solved in memory-bounded blocks.
``"splu"``
    SciPy's SuperLU, one factorization, blocked solves. Portable fallback.
``"amg"``
    Conjugate gradients preconditioned by pyamg smoothed aggregation with the
    six rigid-body modes as near-null space, for meshes too large to factor.
    Each column is solved to the relative residual ``tol``.
"""

from __future__ import annotations

import os
from typing import Callable, Iterator

import numpy as np
import scipy.sparse as sp

from hailstorm.precompute.fem import free_dofs

SOLVERS = ("cholmod", "splu", "amg")

#: Bytes of dense right-hand-side/solution blocks held at once (memory bound).
DEFAULT_BLOCK_BYTES = 256 * 2**20
#: Right-hand sides per block: measured fastest per column for CHOLMOD's
#: supernodal solve on the default seat (blocks of 8-32 stay in cache; 1 is
#: 2x slower, 1024 is 1.8x slower).
DEFAULT_BLOCK_COLUMNS = 32


class _Cholmod:
    def __init__(self, A: sp.csc_matrix):
        import cholespy

        A = sp.tril(A, format="csc")  # CHOLMOD reads one triangle
        A.sort_indices()
        self._s = cholespy.CholeskySolverD(
            A.shape[0], A.indptr.astype(np.int32), A.indices.astype(np.int32),
            A.data.astype(np.float64), cholespy.MatrixType.CSC,
        )

    def solve(self, B: np.ndarray) -> np.ndarray:
        B = np.ascontiguousarray(B, dtype=np.float64)
        X = np.empty_like(B)
        self._s.solve(B, X)
        return X


class _SuperLU:
    def __init__(self, A: sp.csc_matrix):
        from scipy.sparse.linalg import splu

        self._lu = splu(A.tocsc(), permc_spec="COLAMD")

    def solve(self, B: np.ndarray) -> np.ndarray:
        # SuperLU's multi-column solve is slower per column than one at a time
        B = np.asarray(B, dtype=np.float64)
        return np.column_stack([self._lu.solve(B[:, k]) for k in range(B.shape[1])])


class _AMG:
    def __init__(self, A: sp.csr_matrix, near_null: np.ndarray, tol: float):
        import pyamg

        self.A = A.tocsr()
        self.tol = tol
        self.ml = pyamg.smoothed_aggregation_solver(self.A, B=near_null, symmetry="hermitian", max_coarse=500)
        self.iterations: list[int] = []

    def solve(self, B: np.ndarray) -> np.ndarray:
        B = np.asarray(B, dtype=np.float64)
        X = np.empty_like(B)
        for k in range(B.shape[1]):
            res: list[float] = []
            X[:, k] = self.ml.solve(B[:, k], tol=self.tol, accel="cg", maxiter=500, residuals=res)
            self.iterations.append(len(res) - 1)
        return X


def factorize(A: sp.spmatrix, solver: str = "cholmod", *, near_null: np.ndarray | None = None, tol: float = 1e-10):
    """A reusable solver object for the SPD matrix ``A`` (``.solve(B)`` -> X).

    Parameters
    ----------
    A
        Symmetric positive definite sparse matrix (the clamped K_ff).
    solver
        ``"cholmod"``, ``"splu"`` or ``"amg"`` (see module docstring).
    near_null
        (n, 6) rigid-body modes, required for ``"amg"``.
    tol
        Relative residual tolerance of the AMG path.
    """
    if solver == "cholmod":
        return _Cholmod(sp.csc_matrix(A))
    if solver == "splu":
        return _SuperLU(sp.csc_matrix(A))
    if solver == "amg":
        if near_null is None:
            raise ValueError("the AMG solver needs the rigid-body modes (near_null)")
        return _AMG(sp.csr_matrix(A), near_null, tol)
    raise ValueError(f"unknown solver {solver!r}; choose one of {SOLVERS}")


def compliance_matrix(
    K: sp.spmatrix,
    fixed_dofs: np.ndarray,
    load_dofs: np.ndarray,
    read_dofs: np.ndarray,
    *,
    solver: str = "cholmod",
    near_null: np.ndarray | None = None,
    tol: float = 1e-10,
    block_bytes: int = DEFAULT_BLOCK_BYTES,
    block_columns: int = DEFAULT_BLOCK_COLUMNS,
    workers: int | None = None,
    loads: sp.spmatrix | None = None,
    progress: Callable[[int], None] | None = None,
) -> np.ndarray:
    """The compliance D: ``D[:, k]`` = displacement at ``read_dofs`` for a unit
    force on dof ``load_dofs[k]``, with zero displacement on ``fixed_dofs``.

    Parameters
    ----------
    K
        Assembled stiffness (all dofs).
    fixed_dofs
        Clamped dofs (their rows/columns are removed).
    load_dofs
        Dofs that receive a unit force, one column each. Must be free.
        Ignored when ``loads`` is given.
    read_dofs
        Dofs read out, one row each (clamped ones read zero).
    solver, near_null, tol
        See :func:`factorize`. ``near_null`` is (n_dofs, 6) over *all* dofs.
    block_bytes, block_columns
        Memory bound and column count of one block of dense right-hand sides.
    loads
        (n_dofs, ncols) sparse load vectors, one column each, instead of
        unit forces (e.g. :func:`hat_load_matrix`); entries on clamped dofs
        are dropped (they go straight into the support).
    workers
        Processes solving blocks in parallel, each with its own factorization
        (``None``: :func:`default_workers`). Results do not depend on it.
    progress
        Called with the number of columns finished after every block.

    Returns
    -------
    ndarray, shape (len(read_dofs), len(load_dofs)), Fortran order
    """
    n = K.shape[0]
    free = free_dofs(n, fixed_dofs)
    where = np.full(n, -1, dtype=np.int64)
    where[free] = np.arange(free.size)
    if loads is None:
        load_pos = where[np.asarray(load_dofs)]
        if np.any(load_pos < 0):
            raise ValueError("a load dof is clamped: forces on the clamp never deform the solid")
        ncols = load_pos.size
        free_loads = None
    else:
        free_loads = sp.csc_matrix(loads)[free]
        load_pos = None
        ncols = free_loads.shape[1]
    read_pos = where[np.asarray(read_dofs)]
    read_live = np.flatnonzero(read_pos >= 0)

    K = sp.csr_matrix(K)
    Kff = K[free][:, free]
    nn = None if near_null is None else near_null[free]
    D = np.zeros((len(read_dofs), ncols), order="F")  # column-major: blocks of columns are contiguous
    block = int(max(1, min(ncols, block_columns, block_bytes // (16 * max(free.size, 1)))))
    blocks = [np.arange(s, min(s + block, ncols)) for s in range(0, ncols, block)]
    if workers is None:
        workers = default_workers(ncols, solver)
    task = _BlockSolver(Kff, solver, nn, tol, load_pos, read_pos[read_live], free_loads)
    results: Iterator[np.ndarray]
    if workers <= 1:
        results = map(task, blocks)
        pool = None
    else:
        import multiprocessing as mp

        # spawn: a fresh interpreter per worker (fork after BLAS threads start is unsafe)
        pool = mp.get_context("spawn").Pool(workers, initializer=_init_worker, initargs=(task,))
        results = pool.imap(_run_worker, blocks)
    try:
        for cols, values in zip(blocks, results):
            D[read_live[:, None], cols[None, :]] = values
            if progress is not None:
                progress(cols.size)
    finally:
        if pool is not None:
            pool.terminate()
    return D


def default_workers(ncols: int, solver: str) -> int:
    """Worker processes for ``ncols`` right-hand sides.

    ``HAILSTORM_WORKERS`` if set, else one: on the 2-core reference machine a
    second process did not pay for its start-up (~1 s) and its own
    factorization at the default seat's size (see the README's benchmark).
    """
    env = os.environ.get("HAILSTORM_WORKERS")
    if env:
        return max(1, int(env))
    return 1


class _BlockSolver:
    """Factor once (lazily, in whichever process runs it), then solve column blocks."""

    def __init__(self, Kff, solver, near_null, tol, load_pos, read_rows, loads=None):
        self.Kff, self.solver, self.near_null, self.tol = Kff, solver, near_null, tol
        self.load_pos, self.read_rows, self.loads = load_pos, read_rows, loads
        self._fact = None

    def __getstate__(self):
        state = dict(self.__dict__)
        state["_fact"] = None
        return state

    def __call__(self, cols: np.ndarray) -> np.ndarray:
        if self._fact is None:
            self._fact = factorize(self.Kff, self.solver, near_null=self.near_null, tol=self.tol)
        if self.loads is not None:
            rhs = self.loads[:, cols].toarray()
        else:
            rhs = np.zeros((self.Kff.shape[0], cols.size))
            rhs[self.load_pos[cols], np.arange(cols.size)] = 1.0
        return self._fact.solve(rhs)[self.read_rows]


_WORKER_TASK: _BlockSolver | None = None


def _init_worker(task: _BlockSolver) -> None:
    global _WORKER_TASK
    _WORKER_TASK = task


def _run_worker(cols: np.ndarray) -> np.ndarray:
    assert _WORKER_TASK is not None
    return _WORKER_TASK(cols)


def hat_load_matrix(basis, nodes: np.ndarray, areas: np.ndarray) -> sp.csc_matrix:
    """Consistent loads of unit "vertex pressure masks" (James & Pai), one column per (vertex, direction).

    Column (k, d) is the load vector of the traction e_d φ_j / a_j on the
    boundary, with φ_j the P1 hat function of surface vertex j = ``nodes[k]``
    (a volume node) and a_j = ∫ φ_j its lumped area: one newton in total,
    spread over the vertex's patch and integrated consistently for the
    basis's element order. For P2 this is the load a corner point force
    should have been (a point force on a P2 corner node converges poorly for
    distributed loads; see the README's speed-vs-accuracy study).

    Returns
    -------
    scipy.sparse.csc_matrix, shape (basis.N, 3 len(nodes))
    """
    from skfem import BilinearForm, ElementTetP1, ElementVector, FacetBasis
    from skfem.helpers import dot

    facets = basis.mesh.boundary_facets()
    test = FacetBasis(basis.mesh, basis.elem, facets=facets, intorder=4)
    trial = FacetBasis(basis.mesh, ElementVector(ElementTetP1()), facets=facets, intorder=4)

    @BilinearForm
    def surface_mass(u, v, w):
        return dot(u, v)

    M = surface_mass.assemble(trial, test).tocsc()  # (test dofs, P1 vector dofs)
    cols = np.asarray(trial.nodal_dofs[:, np.asarray(nodes)].T).ravel()  # vertex-major x, y, z
    return (M[:, cols] @ sp.diags(1.0 / np.repeat(areas, 3))).tocsc()


def lumped_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Lumped vertex areas a_i: a third of the area of each adjacent triangle.

    These are the diagonal of the hint's A (A = diag(a) ⊗ I3, f = A p).
    """
    p = vertices[triangles]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    a = np.zeros(vertices.shape[0])
    for k in range(3):
        np.add.at(a, triangles[:, k], area / 3.0)
    return a


def area_matrix(areas: np.ndarray) -> sp.dia_matrix:
    """The hint's A = diag(a) ⊗ I3 as a sparse diagonal (3n, 3n) matrix."""
    return sp.diags(np.repeat(areas, 3))


def traction_greens_function(D: np.ndarray, areas_of_columns: np.ndarray) -> np.ndarray:
    """Ξ = D A: displacement per unit traction (the hint's u = Ξ p = D f)."""
    return D * np.repeat(areas_of_columns, 3)[None, :]
