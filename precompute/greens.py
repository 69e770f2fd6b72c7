"""Green's functions: the compliance D from one factorization and many solves.

Column (j, d) of the compliance D is the displacement of every output vertex
under a unit nodal force at contactable vertex j in direction d:
K_ff u = e_(j,d), read at the output dofs. Four solvers share one interface
(:func:`compliance_matrix`):

``"supernodal"`` (default)
    Sparse Cholesky of K_ff (SciPy's SuperLU in symmetric mode, minimum degree)
    arranged in supernodes, and triangular solves pruned for what a column of D
    is: a unit force (the forward solve follows only the elimination-tree paths
    of a batch's loads) read at the surface (the backward solve skips the
    subtrees that hold no surface dof), as BLAS matrix products on batches of
    :data:`hailstorm.precompute.supernodal.DEFAULT_BATCH` columns
    (:mod:`hailstorm.precompute.supernodal`; docs: "Scale", "Near the FLOP bound").
``"cholmod"``
    Sparse Cholesky of K_ff (CHOLMOD through ``cholespy``, fill-reducing
    ordering), right-hand sides solved in memory-bounded blocks. cholespy
    builds a simplicial LLᵀ factor (METIS ordering), which CHOLMOD solves at
    most four right-hand sides at a time, without BLAS: the time per column
    does not depend on the block width past 4. The general-purpose direct
    solver of the studies.
``"splu"``
    SciPy's SuperLU, one factorization, blocked solves. Portable fallback.
``"amg"``
    Conjugate gradients preconditioned by pyamg smoothed aggregation with the
    six rigid-body modes as near-null space, for meshes too large to factor.
    Each column is solved to the relative residual ``tol``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Callable

import numpy as np

from hailstorm.runtime.resources import require_extra
import scipy.sparse as sp

from hailstorm.precompute.fem import free_dofs
from hailstorm.precompute.resources import DEFAULT_STORE_BYTES
from hailstorm.precompute.supernodal import DEFAULT_BATCH, PatternError, SupernodalSolver

_log = logging.getLogger(__name__)

#: Right-hand sides per triangular solve of the general solvers: measured fastest per column
#: for cholespy's (simplicial) CHOLMOD solve on the default seat (blocks of 8-32 stay in cache;
#: 1 is 2x slower, 1024 is 1.8x slower).
DEFAULT_BLOCK_COLUMNS = 32


class _DenseColumns:
    """``solve_columns`` for a solver that solves dense right-hand sides (every row),
    ``batch`` columns at a time."""

    nnz_L: int | None = None
    flops: int = 0
    batch: int = DEFAULT_BLOCK_COLUMNS

    def solve(self, B: np.ndarray) -> np.ndarray:  # pragma: no cover (each solver has its own)
        raise NotImplementedError

    def solve_columns(self, B: sp.spmatrix, read: np.ndarray) -> np.ndarray:
        """``K⁻¹ B`` at the rows ``read`` (-1: a zero row), Fortran order."""
        B = sp.csc_matrix(B)
        out = np.zeros((read.size, B.shape[1]), order="F")
        live = read >= 0
        for s in range(0, B.shape[1], self.batch):
            e = min(B.shape[1], s + self.batch)
            out[live, s:e] = self.solve(B[:, s:e].toarray())[read[live]]
        return out


class _Cholmod(_DenseColumns):
    def __init__(self, A: sp.csc_matrix):
        cholespy = require_extra("cholespy", "precompute", "the cholmod solver (cholespy)")

        A = sp.tril(A, format="csc")  # CHOLMOD reads one triangle
        A.sort_indices()
        try:
            self._s = cholespy.CholeskySolverD(
                A.shape[0], A.indptr.astype(np.int32), A.indices.astype(np.int32),
                A.data.astype(np.float64), cholespy.MatrixType.CSC,
            )
        except (ValueError, RuntimeError) as exc:  # cholespy's "Matrix is not positive definite!"
            if "positive definite" in str(exc):
                raise NotPositiveDefinite(f"CHOLMOD: {exc}") from None
            raise

    def solve(self, B: np.ndarray) -> np.ndarray:
        B = np.ascontiguousarray(B, dtype=np.float64)
        X = np.empty_like(B)
        self._s.solve(B, X)
        return X


class _SuperLU(_DenseColumns):
    def __init__(self, A: sp.csc_matrix):
        from scipy.sparse.linalg import splu

        self._lu = splu(A.tocsc(), permc_spec="COLAMD")

    def solve(self, B: np.ndarray) -> np.ndarray:
        # SuperLU's multi-column solve is slower per column than one at a time
        B = np.asarray(B, dtype=np.float64)
        return np.column_stack([self._lu.solve(B[:, k]) for k in range(B.shape[1])])


class _AMG(_DenseColumns):
    def __init__(self, A: sp.csr_matrix, near_null: np.ndarray, tol: float):
        pyamg = require_extra("pyamg", "precompute", "the amg solver (pyamg)")

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


def factorize(A: sp.spmatrix, solver: str = "supernodal", *, near_null: np.ndarray | None = None,
              tol: float = 1e-10, threads: int | None = None, batch: int | None = None):
    """A reusable solver object for the SPD matrix ``A``.

    Every solver object has ``.solve(B) -> X`` (dense, every row),
    ``.solve_columns(B, read) -> X[read]`` (sparse right-hand sides, the rows
    read), ``.nnz_L`` (entries of its factor, ``None`` if it does not know) and
    ``.flops`` (floating-point operations of its triangular solves so far, 0
    if it does not count them).

    Parameters
    ----------
    A
        Symmetric positive definite sparse matrix (the clamped K_ff).
    solver
        ``"supernodal"``, ``"cholmod"``, ``"splu"`` or ``"amg"`` (see module docstring).
    near_null
        (n, 6) rigid-body modes, required for ``"amg"``.
    tol
        Relative residual tolerance of the AMG path.
    threads
        Sweeps at once of the supernodal solver (default: the cores this
        process may use; the other solvers use their libraries' threads).
    batch
        Right-hand sides per triangular solve in ``solve_columns`` (default:
        :func:`solver_batch`).
    """
    spec = solver_spec(solver)
    if spec.needs_near_null and near_null is None:
        raise ValueError(f"the {spec.title} solver needs the rigid-body modes (near_null)")
    try:
        return spec.build(A, near_null=near_null, tol=tol, threads=threads,
                          batch=spec.batch if batch is None else int(batch))
    except PatternError as exc:  # the supernodal factor's pattern check (e.g. a 1e18 stiffness contrast)
        _log.info("supernodal solver: %s; using CHOLMOD (cholespy) instead", exc)
        return factorize(A, "cholmod", near_null=near_null, tol=tol, threads=threads)
    except np.linalg.LinAlgError as exc:
        # a Cholesky factor that meets a non-positive pivot on an SPD matrix: rounding at an extreme
        # stiffness contrast (materials and clamps are checked before the solve); LU pivots its way
        if not spec.cholesky:
            raise
        _log.info("%s solver: %s (rounding at an extreme stiffness contrast); using SuperLU's LU instead",
                  spec.title, _one_line(exc))
        return SOLVER_SPECS["splu"].build(A, near_null=near_null, tol=tol, threads=threads)


class NotPositiveDefinite(np.linalg.LinAlgError):
    """A Cholesky factorization met a non-positive pivot."""


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


@dataclass(frozen=True)
class SolverSpec:
    """One solver of the registry :data:`SOLVER_SPECS`: its name, its properties and how to build it.

    Attributes
    ----------
    name : str
        What ``build_bundle(solver=...)`` and ``hailstorm precompute --solver`` take.
    title : str
        Its name in messages.
    batch : int
        Right-hand sides per triangular solve it is fastest with (measured; see
        :data:`~hailstorm.precompute.supernodal.DEFAULT_BATCH` and :data:`DEFAULT_BLOCK_COLUMNS`).
    proxy_fill : bool
        A direct solver that does not report its factor's nnz(L): :func:`cholesky_nnz` counts a proxy.
    threads : bool
        Takes ``factorize(threads=...)`` (sweeps at once); the others use their libraries' threads.
    needs_near_null : bool
        Needs the rigid-body modes (``near_null``).
    uses_tol : bool
        Iterative: solves each column to the relative residual ``tol`` (part of the bundle's key).
    cholesky : bool
        A Cholesky factor: a non-positive pivot (rounding at an extreme stiffness contrast) makes
        :func:`factorize` fall back to SuperLU's LU.
    make : callable
        ``make(A, near_null, tol, threads, batch)`` -> the solver object.
    """

    name: str
    title: str
    batch: int
    proxy_fill: bool
    threads: bool
    needs_near_null: bool
    uses_tol: bool
    cholesky: bool
    make: Callable[..., object]

    def build(self, A: sp.spmatrix, *, near_null: np.ndarray | None = None, tol: float = 1e-10,
              threads: int | None = None, batch: int | None = None) -> object:
        """The solver object for the SPD ``A`` (see :func:`factorize`)."""
        return self.make(A, near_null, tol, threads, self.batch if batch is None else max(1, int(batch)))


def _dense(cls: type) -> Callable[..., object]:
    """``make`` of a :class:`_DenseColumns` solver: built, then given its batch."""
    def make(A, near_null, tol, threads, batch):
        made = cls(sp.csr_matrix(A), near_null, tol) if cls is _AMG else cls(sp.csc_matrix(A))
        made.batch = batch
        return made
    return make


#: The solvers, by name (the order is the CLI's ``--solver`` choices'; the first is the default).
SOLVER_SPECS: dict[str, SolverSpec] = {
    spec.name: spec for spec in (
        SolverSpec("supernodal", "supernodal", DEFAULT_BATCH, proxy_fill=False, threads=True,
                   needs_near_null=False, uses_tol=False, cholesky=True,
                   make=lambda A, near_null, tol, threads, batch: SupernodalSolver(A, batch=batch, threads=threads)),
        SolverSpec("cholmod", "CHOLMOD", DEFAULT_BLOCK_COLUMNS, proxy_fill=True, threads=False,
                   needs_near_null=False, uses_tol=False, cholesky=True, make=_dense(_Cholmod)),
        SolverSpec("splu", "SuperLU", DEFAULT_BLOCK_COLUMNS, proxy_fill=True, threads=False,
                   needs_near_null=False, uses_tol=False, cholesky=False, make=_dense(_SuperLU)),
        SolverSpec("amg", "AMG", DEFAULT_BLOCK_COLUMNS, proxy_fill=False, threads=False,
                   needs_near_null=True, uses_tol=True, cholesky=False, make=_dense(_AMG)),
    )
}

#: the solver names (kept for callers of the tuple; :data:`SOLVER_SPECS` is the registry)
SOLVERS = tuple(SOLVER_SPECS)

#: direct solvers that do not report their factor's nnz(L) (kept; :attr:`SolverSpec.proxy_fill`)
PROXY_FILL = frozenset(name for name, spec in SOLVER_SPECS.items() if spec.proxy_fill)


def solver_spec(solver: str) -> SolverSpec:
    """The registry's entry for the solver name ``solver``.

    Raises
    ------
    ValueError
        Not a solver's name.
    """
    try:
        return SOLVER_SPECS[solver]
    except (KeyError, TypeError):
        raise ValueError(f"unknown solver {solver!r}; choose one of {SOLVERS}") from None


def solver_batch(solver: str) -> int:
    """Right-hand sides per triangular solve that ``solver`` is fastest with (measured)."""
    return solver_spec(solver).batch


@dataclass(frozen=True, eq=False)
class ColumnProblem:
    """The clamped system and the columns of D to compute, in a form a worker can receive.

    Everything a process needs to compute any column block of D: the free-dof
    stiffness K_ff (shipped once per worker, factorized once there), the
    solver choice, where each column's load goes and which rows are read.
    Build it with :func:`column_problem`; solve blocks with :meth:`solve`.

    Attributes
    ----------
    Kff : scipy.sparse.csr_matrix
        Stiffness restricted to the free dofs.
    solver, tol : str, float
        See :func:`factorize`.
    near_null : ndarray or None
        Rigid-body modes on the free dofs (AMG only).
    load_pos : (ncols,) int ndarray or None
        Free-dof index of each column's unit force (``None`` with ``loads``).
    loads : scipy.sparse.csc_matrix or None
        (n_free, ncols) load vectors instead of unit forces.
    read_pos : (n_rows,) int ndarray
        Free-dof index read out by each row of D, -1 for clamped rows (zero).
    batch : int
        Right-hand sides per triangular solve (:func:`solver_batch`).
    """

    Kff: sp.csr_matrix
    solver: str
    tol: float
    near_null: np.ndarray | None
    load_pos: np.ndarray | None
    loads: sp.csc_matrix | None
    read_pos: np.ndarray
    batch: int = DEFAULT_BLOCK_COLUMNS

    @property
    def spec(self) -> SolverSpec:
        """The registry's entry of :attr:`solver`."""
        return solver_spec(self.solver)

    @property
    def shape(self) -> tuple[int, int]:
        """Shape of D: (rows read, columns)."""
        ncols = self.loads.shape[1] if self.loads is not None else self.load_pos.size  # type: ignore[union-attr]
        return int(self.read_pos.size), int(ncols)

    def factor(self, threads: int | None = None):
        """Factorize K_ff with this problem's solver (a solver object, :func:`factorize`, solving
        ``batch`` right-hand sides at a time); ``threads``: see there."""
        return factorize(self.Kff, self.solver, near_null=self.near_null, tol=self.tol, threads=threads,
                         batch=self.batch)

    def solve(self, factor, start: int, stop: int) -> np.ndarray:
        """Columns ``start:stop`` of D, (n_rows, stop - start), Fortran order.

        ``factor`` is what :meth:`factor` returned (in this process). The
        right-hand sides are solved ``batch`` at a time.
        """
        if self.loads is not None:
            rhs = self.loads[:, start:stop]
        else:
            rhs = sp.csc_matrix((np.ones(stop - start), self.load_pos[start:stop],  # type: ignore[index]
                                 np.arange(stop - start + 1)), shape=(self.Kff.shape[0], stop - start))
        return factor.solve_columns(rhs, self.read_pos)


def column_problem(
    K: sp.spmatrix,
    fixed_dofs: np.ndarray,
    load_dofs: np.ndarray,
    read_dofs: np.ndarray,
    *,
    solver: str = "supernodal",
    near_null: np.ndarray | None = None,
    tol: float = 1e-10,
    loads: sp.spmatrix | None = None,
    batch: int | None = None,
) -> ColumnProblem:
    """The :class:`ColumnProblem` of D for a unit force on each of ``load_dofs``
    (or each column of ``loads``), read at ``read_dofs``, clamped on ``fixed_dofs``.

    See :func:`compliance_matrix` for the parameters. Raises ``ValueError`` if
    a load dof is clamped.
    """
    spec = solver_spec(solver)
    n = K.shape[0]
    free = free_dofs(n, fixed_dofs)
    where = np.full(n, -1, dtype=np.int64)
    where[free] = np.arange(free.size)
    load_pos = free_loads = None
    if loads is None:
        load_pos = where[np.asarray(load_dofs)]
        if np.any(load_pos < 0):
            raise ValueError("a load dof is clamped: forces on the clamp never deform the solid")
    else:
        free_loads = sp.csc_matrix(loads)[free]
    K = sp.csr_matrix(K)
    Kff = K[free][:, free]
    nn = None if near_null is None else near_null[free]
    return ColumnProblem(Kff, solver, tol, nn, load_pos, free_loads, where[np.asarray(read_dofs)],
                         int(max(1, spec.batch if batch is None else batch)))


def column_blocks(n_rows: int, ncols: int, block_bytes: int = DEFAULT_STORE_BYTES,
                  batch: int = DEFAULT_BLOCK_COLUMNS) -> list[tuple[int, int]]:
    """Split D's ``ncols`` columns into blocks of about ``block_bytes`` of float64 each.

    A block is the unit of work (one task, one piece of D written to disk);
    its width is a multiple of ``batch`` where possible.

    Returns
    -------
    list of (start, stop)
    """
    width = max(1, int(block_bytes) // (8 * max(n_rows, 1)))
    if width > batch:
        width -= width % batch
    width = min(width, max(ncols, 1))
    return [(s, min(s + width, ncols)) for s in range(0, ncols, width)]


def cholesky_nnz(A: sp.spmatrix) -> int:
    """nnz(L) of a sparse Cholesky factor of the SPD ``A`` under a minimum-degree ordering.

    CHOLMOD (through cholespy) does not report its factor, so this factors
    ``A`` once more with SuperLU in symmetric mode (minimum degree on
    A + Aᵀ, no pivoting: L has the Cholesky pattern of that ordering).
    cholespy orders with METIS nested dissection (``CHOLMOD_NESDIS``), so
    this is a close proxy, not the exact count: on the default seat at 3 mm
    it gives 1 294 319, against the exact 1 312 708 of CHOLMOD with AMD
    (simplicial), 1 435 443 (AMD, supernodal, with its padding) and
    1 454 528 of MKL PARDISO with METIS (measured). Costs about one
    factorization (0.8 s at 3 mm, measured).
    """
    from scipy.sparse.linalg import splu

    lu = splu(sp.csc_matrix(A), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
              options={"SymmetricMode": True})
    return int(lu.L.nnz)


def compliance_matrix(
    K: sp.spmatrix,
    fixed_dofs: np.ndarray,
    load_dofs: np.ndarray,
    read_dofs: np.ndarray,
    *,
    solver: str = "supernodal",
    near_null: np.ndarray | None = None,
    tol: float = 1e-10,
    block_bytes: int = DEFAULT_STORE_BYTES,
    block_columns: int | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    loads: sp.spmatrix | None = None,
    progress: Callable[[int], None] | None = None,
) -> np.ndarray:
    """The compliance D in memory: ``D[:, k]`` = displacement at ``read_dofs``
    for a unit force on dof ``load_dofs[k]``, with zero displacement on ``fixed_dofs``.

    (The offline pipeline streams D to disk block by block instead,
    :mod:`hailstorm.precompute.blocks`; this is for tests, studies and small meshes.)

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
        Size of one block of D (the unit of work) and right-hand sides per
        triangular solve (default: :func:`solver_batch`).
    workers, scheduler
        Solve the blocks on a local Dask cluster of ``workers`` processes, or
        on the Dask cluster at ``scheduler`` (:mod:`hailstorm.precompute.cluster`);
        default: in this process. Results do not depend on it.
    loads
        (n_dofs, ncols) sparse load vectors, one column each, instead of
        unit forces (e.g. :func:`hat_load_matrix`); entries on clamped dofs
        are dropped (they go straight into the support).
    progress
        Called with the number of columns finished after every block.

    Returns
    -------
    ndarray, shape (len(read_dofs), len(load_dofs)), Fortran order
    """
    from hailstorm.runtime.bundle.format import RoundedBlock
    from hailstorm.precompute.cluster import cluster_client, solve_blocks

    problem = column_problem(K, fixed_dofs, load_dofs, read_dofs, solver=solver, near_null=near_null, tol=tol,
                             loads=loads, batch=block_columns)
    n_rows, ncols = problem.shape
    D = np.zeros((n_rows, ncols), order="F")  # column-major: blocks of columns are contiguous
    blocks = column_blocks(n_rows, ncols, block_bytes, problem.batch)

    def put(i: int, values: "np.ndarray | RoundedBlock") -> None:
        start, stop = blocks[i]
        D[:, start:stop] = values.values if isinstance(values, RoundedBlock) else values  # float64 either way
        if progress is not None:
            progress(stop - start)

    with cluster_client(workers=workers, scheduler=scheduler) as client:
        solve_blocks(problem, blocks, range(len(blocks)), put, client=client)
    return D


def hat_load_matrix(basis, nodes: np.ndarray, areas: np.ndarray) -> sp.csc_matrix:
    """Consistent loads of unit "vertex pressure masks" (James & Pai), one column per (vertex, direction).

    Column (k, d) is the load vector of the traction e_d φ_j / a_j on the
    boundary, with φ_j the P1 hat function of surface vertex j = ``nodes[k]``
    (a volume node) and a_j = ∫ φ_j its lumped area: one newton in total,
    spread over the vertex's patch and integrated consistently for the
    basis's element order. For P2 this is the load a corner point force
    should have been (a point force on a P2 corner node converges poorly for
    distributed loads; see the docs' speed-against-accuracy study, "Choosing settings").

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
