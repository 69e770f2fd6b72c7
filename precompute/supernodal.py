"""A supernodal Cholesky solve for many unit right-hand sides: the columns of D.

Column k of D is ``K_ff⁻¹ e_j`` read at the surface dofs, for a unit force at
contactable dof j. A general solver runs a full forward and backward solve per
column (4 nnz(L) floating-point operations). This one uses what the columns
have in common:

* **unit loads**: the forward solve ``L y = P e_j`` touches only the
  elimination-tree path from j's supernode to the root; a batch of w columns
  of nearby vertices (D's columns are in the mesh's vertex order) visits the
  union of their paths;
* **surface reads**: the backward solve ``Lᵀ x = y`` is needed only on the
  supernodes holding a read dof and their ancestors;
* **supernodes**: columns of L with one row pattern are dense panels, so the
  solves on a batch are matrix products (BLAS ``dgemm``, the diagonal blocks'
  triangular solves as products with their inverses).

The factor is SciPy's SuperLU in symmetric mode (minimum degree on A + Aᵀ, no
pivoting: ``P K Pᵀ = L diag(d) Lᵀ`` with a unit-diagonal L, here scaled to
``L diag(√d)``), so nnz(L) is the factor's own count, not a proxy. Its
columns are renumbered in a postorder of the elimination tree (the same
factor, chains of columns made consecutive) and cut into relaxed supernodes
(:data:`RELAX`, as CHOLMOD's supernodal analysis does: a narrow supernode
merges into its parent at the cost of a few explicit zeros), which halves
their number on the default seat and made the sweeps ~20 % faster (measured
at 3 mm, P1 and P2).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

#: right-hand sides per batch at most: measured fastest per column on the default seat at 3 mm
#: (P2: 2.2 against 2.6 ms for 64; P1: 0.21-0.29 against 0.27-0.31 ms; 32 slower still)
DEFAULT_BATCH = 128


@dataclass(frozen=True, eq=False)
class SupernodalFactor:
    """``P K Pᵀ = L Lᵀ`` of an SPD matrix in supernodes (build with :func:`supernodal_factor`).

    Attributes
    ----------
    perm : (n,) int ndarray
        Position in L of each dof (``perm[i]``: row and column of dof i).
    start : (ns + 1,) int ndarray
        First column of each supernode.
    parent : (ns,) int ndarray
        Parent supernode in the elimination tree (-1 at a root); parents follow
        their children.
    rows, roff : int ndarrays
        Rows below each supernode's diagonal block: ``rows[roff[s]:roff[s + 1]]``.
    below, boff : float64 ndarray, int ndarray
        Each supernode's block below its diagonal, column-major, from ``boff[s]``.
    dinv, doff : float64 ndarray, int ndarray
        The inverse of each supernode's diagonal block, column-major, from ``doff[s]``.
    col_sn : (n,) int ndarray
        Supernode of each column of L.
    nnz_L : int
        Entries of L (its lower triangle, diagonal included).
    """

    perm: np.ndarray
    start: np.ndarray
    parent: np.ndarray
    rows: np.ndarray
    roff: np.ndarray
    below: np.ndarray
    boff: np.ndarray
    dinv: np.ndarray
    doff: np.ndarray
    col_sn: np.ndarray
    nnz_L: int

    @property
    def n(self) -> int:
        """Order of the matrix."""
        return int(self.perm.size)

    def closure(self, positions: np.ndarray) -> np.ndarray:
        """The supernodes holding ``positions`` (in L) and all their ancestors, ascending."""
        mark = np.zeros(self.start.size - 1, dtype=bool)
        for s in np.unique(self.col_sn[positions]):
            while s >= 0 and not mark[s]:
                mark[s] = True
                s = self.parent[s]
        return np.flatnonzero(mark)

    def flops(self, supernodes: np.ndarray) -> int:
        """Floating-point operations of one right-hand side's solve on ``supernodes`` (one of the two sweeps)."""
        nc = np.diff(self.start)[supernodes]
        mb = np.diff(self.roff)[supernodes]
        return int(np.sum(nc * nc + 2 * nc * mb))


class PatternError(np.linalg.LinAlgError):
    """The factor's sparsity pattern cannot be recovered (entries cancelled to exact
    zeros and the generic-valued refactorisation ordered differently, e.g. a 1e18
    stiffness contrast); :func:`hailstorm.precompute.greens.factorize` then uses CHOLMOD."""


def supernodal_factor(A: sp.spmatrix) -> SupernodalFactor:
    """Factorize the SPD ``A`` (SuperLU, symmetric mode) and arrange L in supernodes.

    Raises
    ------
    numpy.linalg.LinAlgError
        ``A`` is not positive definite (a pivot is not positive).
    PatternError
        The factor's pattern cannot be recovered (see :class:`PatternError`).
    """
    from hailstorm.precompute.supernodal_kernels import gather_panels, pattern_is_closed  # compiled

    A = sp.csc_matrix(A)
    n = A.shape[0]
    lu = _superlu(A)
    if not np.array_equal(lu.perm_r, lu.perm_c):  # pragma: no cover (SPD input never pivots)
        raise np.linalg.LinAlgError("the factorization pivoted: the matrix is not positive definite")
    d = lu.U.diagonal()
    if not np.all(d > 0):
        raise np.linalg.LinAlgError("the matrix is not positive definite (a non-positive pivot)")
    L = lu.L.tocsc()
    perm = lu.perm_c.astype(np.int64)
    del lu
    L.sort_indices()
    if not pattern_is_closed(L.indptr.astype(np.int64), L.indices.astype(np.int64), np.full(n, -1)):
        L = _with_symbolic_pattern(L, A, perm)  # exact zeros were left out (e.g. Poisson's ratio 0)
    # postorder the elimination tree (an equivalent ordering: L stays lower triangular with the
    # same entries): chains of columns become consecutive, so supernodes are found and merge
    post = _postorder(L)
    rank = np.empty_like(post)
    rank[post] = np.arange(post.size)
    L = L[post][:, post].tocsc()
    L.sort_indices()  # a symmetric renumbering keeps the pattern a Cholesky pattern: no second check
    perm = rank[perm]
    d = d[post]
    indptr = L.indptr.astype(np.int64)
    indices = L.indices.astype(np.int64)
    count = np.diff(indptr)
    # column j + 1 continues j's supernode when its pattern is j's minus j
    nxt = np.zeros(n, dtype=bool)
    if n > 1:
        j = np.arange(n - 1)
        cand = (count[:-1] == count[1:] + 1) & (indices[np.minimum(indptr[:-2] + 1, indices.size - 1)] == j + 1)
        for c in np.flatnonzero(cand):
            nxt[c] = np.array_equal(indices[indptr[c] + 1:indptr[c + 1]], indices[indptr[c + 1]:indptr[c + 2]])
    start = np.concatenate([[0], np.flatnonzero(~nxt[:-1]) + 1, [n]]).astype(np.int64) if n else np.zeros(1, np.int64)
    fundamental_mb = count[start[1:] - 1] - 1
    last_first = indices[np.minimum(indptr[start[1:] - 1] + 1, indices.size - 1)]
    fundamental_parent = np.where(fundamental_mb > 0, np.searchsorted(start, last_first, side="right") - 1, -1)
    start = _relaxed(start, fundamental_mb, fundamental_parent)
    ns = start.size - 1
    nc = np.diff(start)
    top = start[1:] - 1  # a supernode's last column: its rows below are the supernode's
    mb = count[top] - 1
    col_sn = np.repeat(np.arange(ns, dtype=np.int64), nc)
    roff = np.concatenate([[0], np.cumsum(mb)]).astype(np.int64)
    first = indptr[top] + 1  # first below-diagonal entry of each supernode's last column
    rows = indices[np.repeat(first - roff[:-1], mb) + np.arange(roff[-1])]
    parent = np.where(mb > 0, col_sn[indices[np.minimum(first, indices.size - 1)]], -1)
    boff = np.concatenate([[0], np.cumsum(mb * nc)]).astype(np.int64)
    doff = np.concatenate([[0], np.cumsum(nc * nc)]).astype(np.int64)
    below = np.zeros(boff[-1])
    diag = np.zeros(doff[-1])
    gather_panels(indptr, indices, L.data, np.sqrt(d), start, rows, roff, boff, doff, below, diag,
                  np.full(n, -1, dtype=np.int64))
    nnz = int(L.nnz)
    del L
    dinv = _inverse_diagonal_blocks(diag, start, doff)
    return SupernodalFactor(perm, start, parent.astype(np.int64), rows, roff, below, boff, dinv, doff, col_sn, nnz)


def _superlu(A: sp.csc_matrix):
    """SuperLU in symmetric mode: minimum degree on A + Aᵀ, diagonal pivots (a Cholesky factor
    as L diag(d) Lᵀ for an SPD ``A``)."""
    from scipy.sparse.linalg import splu

    return splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True})


def _with_symbolic_pattern(L: sp.csc_matrix, A: sp.csc_matrix, perm: np.ndarray) -> sp.csc_matrix:
    """``L`` on the full Cholesky pattern of its ordering, the entries it left out (exact zeros)
    stored as zeros: the pattern is that of the factor of a matrix with A's pattern and generic
    values (symmetric, diagonally dominant: no cancellation), which SuperLU orders the same way."""
    G = sp.csc_matrix(A, copy=True)
    G.data = np.random.default_rng(0).uniform(0.5, 1.0, G.data.size)
    G = (G + G.T).tocsc()
    G.setdiag(np.asarray(abs(G).sum(axis=1)).ravel() + 1.0)
    lu = _superlu(G)
    if not np.array_equal(lu.perm_c, perm):  # pragma: no cover (the ordering depends on the pattern only)
        raise PatternError("cannot recover the factor's pattern: the ordering changed")
    full = lu.L.tocsc()
    del lu
    full.sort_indices()
    n = L.shape[0]
    key = lambda M: np.repeat(np.arange(n, dtype=np.int64), np.diff(M.indptr)) * n + M.indices  # noqa: E731
    at = np.searchsorted(key(full), key(L))
    data = np.zeros(full.nnz)
    data[at] = L.data
    return sp.csc_matrix((data, full.indices, full.indptr), shape=L.shape)


def _postorder(L: sp.csc_matrix) -> np.ndarray:
    """A postorder of the elimination tree of the (sorted) lower-triangular ``L``: the columns in
    the order to renumber them, every subtree's columns consecutive and before its root."""
    n = L.shape[0]
    indptr, indices = L.indptr, L.indices
    has_parent = np.diff(indptr) > 1
    parent = np.full(n, -1, dtype=np.int64)
    parent[has_parent] = indices[indptr[:-1][has_parent] + 1]  # the first row below the diagonal
    order = np.argsort(parent, kind="stable")  # children grouped by parent, ascending
    first_child = np.searchsorted(parent[order], np.arange(n))
    last_child = np.searchsorted(parent[order], np.arange(n), side="right")
    out = np.empty(n, dtype=np.int64)
    k = 0
    for root in np.flatnonzero(parent < 0):
        stack = [(int(root), int(first_child[root]))]
        while stack:
            node, nxt = stack[-1]
            if nxt < last_child[node]:
                stack[-1] = (node, nxt + 1)
                child = int(order[nxt])
                stack.append((child, int(first_child[child])))
            else:
                stack.pop()
                out[k] = node
                k += 1
    return out


#: relaxed supernodes (as CHOLMOD's supernodal analysis does): a supernode is merged into its
#: parent when that follows it and the merged one has at most this many columns with at most
#: this fraction of explicit zeros: fewer, wider products for the sweeps
RELAX = ((4, 1.0), (16, 0.8), (48, 0.1), (2**62, 0.05))


def _relaxed(start: np.ndarray, mb: np.ndarray, parent: np.ndarray) -> np.ndarray:
    """Merge the fundamental supernodes (columns ``start[s]:start[s + 1]``, ``mb[s]`` rows below,
    elimination-tree ``parent``) into relaxed ones along :data:`RELAX`; returns the merged starts.

    A supernode merges into the next one only when that is its parent: the pattern of L below
    it is then contained in the merged pattern, and the entries it lacks are stored as zeros.
    """
    ns = start.size - 1
    if ns <= 1:
        return start
    nc = np.diff(start)
    entries = (nc * (nc + 1) // 2 + nc * mb).tolist()  # each supernode's entries of L
    nc, mb = nc.tolist(), mb.tolist()
    keep = [0]
    cols, true = nc[0], entries[0]
    for s in range(ns - 1):
        p = s + 1
        merged = cols + nc[p]
        zeros = 1.0 - (true + entries[p]) / (merged * (merged + 1) // 2 + merged * mb[p])
        if parent[s] == p and any(merged <= most and zeros <= frac for most, frac in RELAX):
            cols, true = merged, true + entries[p]
            continue
        keep.append(p)
        cols, true = nc[p], entries[p]
    return np.concatenate([start[keep], start[-1:]]).astype(np.int64)


def _inverse_diagonal_blocks(diag: np.ndarray, start: np.ndarray, doff: np.ndarray) -> np.ndarray:
    from scipy.linalg.lapack import dtrtri

    out = np.empty_like(diag)
    for s in range(start.size - 1):
        nc = int(start[s + 1] - start[s])
        block = diag[doff[s]:doff[s] + nc * nc].reshape(nc, nc, order="F")
        inv, info = dtrtri(block, lower=1)
        if info != 0:  # pragma: no cover (positive pivots: never singular)
            raise np.linalg.LinAlgError("a diagonal block of L is singular")
        out[doff[s]:doff[s] + nc * nc] = np.tril(inv).ravel(order="F")
    return out


class _Workspace:
    """One thread's work space for :func:`supernodal_kernels.solve_columns`."""

    def __init__(self, f: SupernodalFactor, batch: int):
        self.X = np.empty(f.n * batch)
        self.tmp = np.empty(batch * int(np.diff(f.start).max(initial=1)))
        self.W = np.empty(batch * max(int(np.diff(f.roff).max(initial=1)), 1))
        self.mark = np.zeros(f.start.size - 1, dtype=bool)


class SupernodalSolver:
    """Solves with K from its :class:`SupernodalFactor`, pruned for sparse right-hand sides.

    Parameters
    ----------
    A
        The SPD matrix (factorized here, :func:`supernodal_factor`).
    batch
        Right-hand sides per sweep at most: a call's columns are cut into
        a multiple of ``threads`` sweeps of about equal widths.
    threads
        Sweeps run at once, each on its own batch with BLAS single-threaded
        inside (measured 1.6-1.8x faster on two cores than one sweep on a
        two-threaded BLAS). A column's values do not depend on the thread
        count beyond rounding, and not at all when its batch is the same.
        Default: the cores this process may use. Each thread holds a work
        space of n x ``batch`` values.

    Attributes
    ----------
    factor : SupernodalFactor
    nnz_L : int
        Entries of the factor.
    flops : int
        Floating-point operations of the triangular solves done so far (each
        visited supernode's diagonal solve and the product below it, counted as
        a triangular solve would, over the stored panels: what pruning skipped
        is not counted, the relaxed supernodes' explicit zeros are).
    """

    def __init__(self, A: sp.spmatrix, batch: int = DEFAULT_BATCH, threads: int | None = None):
        self.factor = supernodal_factor(A)
        self.nnz_L = self.factor.nnz_L
        self.batch = max(1, int(batch))
        self.threads = max(1, int(threads if threads is not None else len(os.sched_getaffinity(0))))
        self.flops = 0
        self._spaces: list[_Workspace] = []
        self._read: tuple[bytes, np.ndarray, np.ndarray] | None = None
        self._blas = None

    def _read_plan(self, read: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = read.tobytes()
        if self._read is None or self._read[0] != key:
            pos = np.where(read >= 0, self.factor.perm[np.maximum(read, 0)], -1)
            self._read = (key, pos, self.factor.closure(pos[pos >= 0]))
        return self._read[1], self._read[2]

    def _batches(self, ncols: int) -> list[tuple[int, int]]:
        """Column ranges of the sweeps: a multiple of ``threads`` of them (every thread gets
        as many), each at most ``batch`` wide and of about equal widths."""
        if ncols == 0:
            return []
        n = self.threads * -(-ncols // (self.threads * self.batch))
        edges = np.linspace(0, ncols, min(n, ncols) + 1).round().astype(int)
        return list(zip(edges[:-1].tolist(), edges[1:].tolist()))

    def solve_columns(self, B: sp.spmatrix, read: np.ndarray) -> np.ndarray:
        """``K⁻¹ B`` at the rows ``read`` (-1: a zero row), (len(read), B.shape[1]), Fortran order.

        Only the supernodes that the columns of ``B`` load (forward) and that
        ``read`` needs (backward) are visited.
        """
        from threadpoolctl import ThreadpoolController

        from hailstorm.precompute.supernodal_kernels import solve_columns  # compiled: imported when used

        f = self.factor
        B = sp.csc_matrix(B)
        B.sort_indices()
        read = np.asarray(read, dtype=np.int64)
        pos, back = self._read_plan(read)
        out = np.empty((read.size, B.shape[1]), order="F")
        batches = self._batches(B.shape[1])
        if not batches:
            return out
        threads = min(self.threads, len(batches))
        while len(self._spaces) < threads:
            self._spaces.append(_Workspace(f, self.batch))

        def sweep(work: _Workspace, s: int, e: int) -> int:
            part = B[:, s:e]
            chunk = np.empty((read.size, e - s))
            flops = solve_columns(f.start, f.parent, f.rows, f.roff, f.boff, f.doff, f.below, f.dinv,
                                       f.col_sn, back, part.indptr.astype(np.int64), f.perm[part.indices],
                                       part.data.astype(np.float64), pos, chunk, work.X, work.tmp, work.W,
                                       work.mark)
            out[:, s:e] = chunk
            return int(flops) * (e - s)

        def lane(t: int) -> int:
            return sum(sweep(self._spaces[t], s, e) for s, e in batches[t::threads])

        # BLAS single-threaded whatever the threads here: a batch's columns do not depend on the count
        if self._blas is None:
            self._blas = ThreadpoolController()  # finds the BLAS libraries once (~2 ms), not per call
        with self._blas.limit(limits=1, user_api="blas"):
            if threads <= 1:
                self.flops += lane(0)
            else:
                with ThreadPoolExecutor(threads, thread_name_prefix="hailstorm-sweep") as ex:
                    self.flops += sum(ex.map(lane, range(threads)))
        return out

    def solve(self, B: np.ndarray) -> np.ndarray:
        """``K⁻¹ B`` for a dense (n,) or (n, m) ``B``, every row."""
        B = np.asarray(B, dtype=np.float64)
        X = self.solve_columns(sp.csc_matrix(B.reshape(B.shape[0], -1)), np.arange(self.factor.n))
        return X.reshape(B.shape)
