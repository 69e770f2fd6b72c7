"""A compressed compliance: the hierarchical matrix (H-matrix) a compressed bundle stores instead of D.

The compliance of a padded seat is smooth away from its load: a block of D whose
rows and columns are clusters of vertices far apart (relative to their size) is
numerically low rank. An H-matrix keeps such *far* blocks as factors
``U @ V.T`` and every other (*near*) block dense. This module is the stored form
and its evaluation (what the runtime reads); its construction, the cluster trees,
the admissibility and the truncation, is the offline stage's
(:mod:`hailstorm.precompute.hmatrix`).

Storage (four arrays of a format-3 bundle, :mod:`hailstorm.runtime.bundle.format`):

* ``hmatrix_rows`` (3n,) int -- tree position -> row of D (vertex-major dofs);
* ``hmatrix_cols`` (3c,) int -- tree position -> column of D;
* ``hmatrix_blocks`` (k, 6) int -- per block ``r0, r1, c0, c1`` (its rows and
  columns in tree order, half-open), ``rank`` (-1 for a dense block) and
  ``offset`` into the data;
* ``hmatrix_data`` (N,) float64 -- a dense block's entries (column-major), or
  a far block's ``U`` (``(r1 - r0) x rank``, column-major) followed by its
  ``V`` (``(c1 - c0) x rank``).

The blocks tile the matrix: every entry lies in exactly one block
(:meth:`HMatrix.check`).

The runtime's compiled kernels read a dense D. :func:`expanded` gives them one
without holding it in memory: the H-matrix expanded once, column block by
column block, into ``<cache>/expanded/`` and memory-mapped from there (a
stamped file of this project, rebuilt when its stamp does not match), so a
compressed bundle costs the runtime what a dense one does: the pages of D it
touches.
"""

from __future__ import annotations

import functools
import logging
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping

import numpy as np

from hailstorm.runtime.bundle.stamps import default_cache_dir, forget, is_stamped, stamp, stamped_hash
from hailstorm.runtime.compiled.hblocks import hmatrix_entries, hmatrix_matvec

__all__ = ["EXPAND_COLUMNS", "EXPANDED_BUDGET", "FLOAT32_TOL", "HMATRIX_ARRAYS", "HMatrix", "expanded",
           "expansion_dtype", "prune_expansions"]

log = logging.getLogger(__name__)

#: columns of D expanded at a time into the memory-mapped cache (bounds the expansion's memory)
EXPAND_COLUMNS = 512

#: bytes the expansions in ``<cache>/expanded/`` may hold together: writing one that takes them past it
#: removes the oldest others (:func:`prune_expansions`; an expansion is rebuilt on its next use)
EXPANDED_BUDGET = 4 << 30

#: the least compression tolerance whose bundles expand into float32 (:func:`expansion_dtype`): float32
#: rounds an entry by at most 2^-24 ~ 6e-8 of itself, under 1 % of such a tolerance
FLOAT32_TOL = 1e-5


def expansion_dtype(tol: float) -> np.dtype:
    """The type a compressed D of tolerance ``tol`` is expanded into: float32 from :data:`FLOAT32_TOL` up
    (half the bytes every kernel reads, for a rounding under 1 % of the compression's error), else float64."""
    return np.dtype(np.float32 if tol >= FLOAT32_TOL else np.float64)

#: the bundle arrays an H-matrix is stored in, by :class:`HMatrix` attribute
HMATRIX_ARRAYS = {"hmatrix_rows": "row_dofs", "hmatrix_cols": "col_dofs", "hmatrix_blocks": "blocks",
                  "hmatrix_data": "data"}


@dataclass(frozen=True, eq=False)
class HMatrix:
    """A matrix stored as dense near blocks and low-rank far blocks ``U @ V.T``.

    Attributes
    ----------
    shape : (int, int)
        Of the matrix it stands for (D: ``(3n, 3c)``).
    row_dofs, col_dofs : (m,), (n,) int ndarray
        Tree position -> row / column of the matrix.
    blocks : (k, 6) int ndarray
        ``r0, r1, c0, c1, rank, offset`` per block (rank -1: dense).
    data : (N,) float64 ndarray
        The blocks' numbers (see the module's docstring).
    """

    shape: tuple[int, int]
    row_dofs: np.ndarray
    col_dofs: np.ndarray
    blocks: np.ndarray
    data: np.ndarray

    # ---------------------------------------------------------------- reading
    def factors(self, b: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Block ``b``: ``(dense, None)`` or ``(U, V)`` (views into :attr:`data`)."""
        r0, r1, c0, c1, k, off = (int(x) for x in self.blocks[b])
        m, n = r1 - r0, c1 - c0
        if k < 0:
            return self.data[off:off + m * n].reshape(m, n, order="F"), None
        U = self.data[off:off + m * k].reshape(m, k, order="F")
        V = self.data[off + m * k:off + (m + n) * k].reshape(n, k, order="F")
        return U, V

    @property
    def stored(self) -> int:
        """Numbers stored (dense entries and factors)."""
        return int(self.data.size)

    @property
    def ranks(self) -> np.ndarray:
        """Rank of each far (factored) block."""
        k = self.blocks[:, 4]
        return k[k >= 0]

    def columns(self, cols: np.ndarray) -> np.ndarray:
        """``H[:, cols]``, dense, rows in the matrix's own order.

        Parameters
        ----------
        cols : (p,) int array_like
            Columns of the matrix (original order; repeats allowed).

        Returns
        -------
        (m, p) float64 ndarray, column-major
        """
        cols = np.asarray(cols, dtype=np.intp).ravel()
        pos = self._col_position[cols]
        order = np.argsort(pos, kind="stable")
        spos = pos[order]
        out_p = np.zeros((self.shape[0], cols.size), order="F")
        lo = np.searchsorted(spos, self.blocks[:, 2], side="left")
        hi = np.searchsorted(spos, self.blocks[:, 3], side="left")
        for b in np.flatnonzero(hi > lo):
            r0, r1, c0 = (int(x) for x in self.blocks[b, :3])
            sel = order[lo[b]:hi[b]]
            local = spos[lo[b]:hi[b]] - c0
            X, V = self.factors(int(b))
            out_p[r0:r1, sel] = X[:, local] if V is None else X @ V[local].T
        out = np.empty_like(out_p)
        out[self.row_dofs] = out_p
        return out

    def entries(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """``H[np.ix_(rows, cols)]``, dense: only the blocks the rows and columns meet are read,
        and of a far block only its factors' rows ``U[rows]`` and ``V[cols]`` (compiled:
        :func:`hailstorm.runtime.compiled.hblocks.hmatrix_entries`; :meth:`entries_ref` in numpy).

        Parameters
        ----------
        rows, cols : (r,), (p,) int array_like
            Rows and columns of the matrix (original order; repeats allowed).

        Returns
        -------
        (r, p) float64 ndarray, column-major
        """
        rs, ro, cs, co, out = self._sorted_positions(rows, cols)
        if out.size:
            hmatrix_entries(self.blocks, self.data, rs, ro, cs, co, out)
        return out

    def entries_ref(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """:meth:`entries` in numpy, block by block (the reference the compiled kernel is held to)."""
        rs, ro, cs, co, out = self._sorted_positions(rows, cols)
        if out.size == 0:
            return out
        B = self.blocks
        rlo, rhi = np.searchsorted(rs, B[:, 0]), np.searchsorted(rs, B[:, 1])
        clo, chi = np.searchsorted(cs, B[:, 2]), np.searchsorted(cs, B[:, 3])
        for b in np.flatnonzero((rhi > rlo) & (chi > clo)).tolist():
            r0, _, c0 = (int(x) for x in B[b, :3])
            ri, ci = rs[rlo[b]:rhi[b]] - r0, cs[clo[b]:chi[b]] - c0
            X, V = self.factors(b)
            out[np.ix_(ro[rlo[b]:rhi[b]], co[clo[b]:chi[b]])] = X[np.ix_(ri, ci)] if V is None else X[ri] @ V[ci].T
        return out

    def pairs(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The entries ``H[rows[k], cols[k]]``, (k,) float64: each from its own block."""
        rows = np.asarray(rows, dtype=np.intp).ravel()
        cols = np.asarray(cols, dtype=np.intp).ravel()
        if rows.shape != cols.shape:
            raise ValueError(f"rows and cols differ in length: {rows.size} and {cols.size}")
        out = np.zeros(rows.size)
        if rows.size == 0:
            return out
        rpos, cpos = self._row_position[rows], self._col_position[cols]
        grid, ra, ca = self._block_grid
        blk = grid[np.searchsorted(ra, rpos, side="right") - 1, np.searchsorted(ca, cpos, side="right") - 1]
        order = np.argsort(blk, kind="stable")
        bounds = np.flatnonzero(np.diff(blk[order])) + 1
        for grp in np.split(order, bounds):
            b = int(blk[grp[0]])
            r0, _, c0 = (int(x) for x in self.blocks[b, :3])
            ri, ci = rpos[grp] - r0, cpos[grp] - c0
            X, V = self.factors(b)
            out[grp] = X[ri, ci] if V is None else np.einsum("kr,kr->k", X[ri], V[ci])
        return out

    def _sorted_positions(self, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, ...]:
        """Tree positions of ``rows``, ``cols`` sorted (``rs``, ``cs``), where each goes in the
        result (``ro``, ``co``), and the zero (r, p) F-ordered result."""
        rows = np.asarray(rows, dtype=np.intp).ravel()
        cols = np.asarray(cols, dtype=np.intp).ravel()
        rpos, cpos = self._row_position[rows], self._col_position[cols]
        ro, co = np.argsort(rpos, kind="stable"), np.argsort(cpos, kind="stable")
        return rpos[ro], ro, cpos[co], co, np.zeros((rows.size, cols.size), order="F")

    def matvec(self, x: np.ndarray) -> np.ndarray:
        """``H @ x`` for ``x`` of shape (n,) or (n, p) in the original column order (a vector
        compiled: :func:`hailstorm.runtime.compiled.hblocks.hmatrix_matvec`; :meth:`matvec_ref`
        in numpy)."""
        x = np.asarray(x, dtype=float)
        if x.ndim != 1:
            return self.matvec_ref(x)
        yp = hmatrix_matvec(self.blocks, self.data, np.ascontiguousarray(x[self.col_dofs]), self.shape[0])
        y = np.empty_like(yp)
        y[self.row_dofs] = yp
        return y

    def matvec_ref(self, x: np.ndarray) -> np.ndarray:
        """:meth:`matvec` in numpy, block by block (the reference the compiled kernel is held to)."""
        x = np.asarray(x, dtype=float)
        xp = x[self.col_dofs]
        yp = np.zeros((self.shape[0],) + x.shape[1:])
        for b in range(len(self.blocks)):
            r0, r1, c0, c1 = (int(v) for v in self.blocks[b, :4])
            X, V = self.factors(b)
            yp[r0:r1] += X @ xp[c0:c1] if V is None else X @ (V.T @ xp[c0:c1])
        y = np.empty_like(yp)
        y[self.row_dofs] = yp
        return y

    def to_dense(self, dtype: np.dtype | type = np.float64) -> np.ndarray:
        """The matrix it stands for: dense, column-major (the layout of a dense bundle's D), in ``dtype``
        (rounded to nearest from the float64 products)."""
        dense = self.columns(np.arange(self.shape[1]))
        return dense if np.dtype(dtype) == np.float64 else dense.astype(dtype, order="F")

    @functools.cached_property
    def _col_position(self) -> np.ndarray:
        inv = np.empty(self.shape[1], dtype=np.intp)
        inv[self.col_dofs] = np.arange(self.shape[1])
        return inv

    @functools.cached_property
    def _row_position(self) -> np.ndarray:
        inv = np.empty(self.shape[0], dtype=np.intp)
        inv[self.row_dofs] = np.arange(self.shape[0])
        return inv

    @functools.cached_property
    def kernel_arrays(self) -> tuple[np.ndarray, ...]:
        """What a compiled kernel reads an entry through
        (:func:`hailstorm.runtime.compiled.hblocks.d_entry`): ``(rpos, rcell, cpos, ccell, grid,
        blocks, data)``, the tree position and grid cell of each row and column, the block of
        each grid cell (:attr:`_block_grid`), the block table and the numbers. Built once."""
        grid, ra, ca = self._block_grid
        rpos, cpos = self._row_position.astype(np.int64), self._col_position.astype(np.int64)
        rcell = np.searchsorted(ra, rpos, side="right").astype(np.int64) - 1
        ccell = np.searchsorted(ca, cpos, side="right").astype(np.int64) - 1
        return (rpos, rcell, cpos, ccell, grid, np.ascontiguousarray(self.blocks, dtype=np.int64),
                np.ascontiguousarray(self.data, dtype=np.float64))

    @functools.cached_property
    def _block_grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(grid, row_cuts, col_cuts)``: the block holding each cell of the grid the blocks' edges
        cut the matrix into (tree positions ``row_cuts[i]..`` x ``col_cuts[j]..``)."""
        B = self.blocks
        ra, ca = np.unique(B[:, 0]), np.unique(B[:, 2])
        grid = np.full((ra.size, ca.size), -1, dtype=np.int64)
        i0, i1 = np.searchsorted(ra, B[:, 0]), np.searchsorted(ra, B[:, 1])
        j0, j1 = np.searchsorted(ca, B[:, 2]), np.searchsorted(ca, B[:, 3])
        for b in range(len(B)):
            grid[i0[b]:i1[b], j0[b]:j1[b]] = b
        return grid, ra, ca

    # ---------------------------------------------------------------- storage
    def to_arrays(self) -> dict[str, np.ndarray]:
        """The bundle arrays (:data:`HMATRIX_ARRAYS`)."""
        return {name: np.asarray(getattr(self, attr)) for name, attr in HMATRIX_ARRAYS.items()}

    @classmethod
    def from_arrays(cls, shape: tuple[int, int], arrays: Mapping[str, np.ndarray]) -> "HMatrix":
        """The H-matrix stored in a bundle's arrays, checked (:meth:`check`)."""
        h = cls((int(shape[0]), int(shape[1])),
                *(np.asarray(arrays[name], dtype=np.float64 if attr == "data" else np.int64)
                  for name, attr in HMATRIX_ARRAYS.items()))
        h.check()
        return h

    def check(self) -> None:
        """Raise ValueError unless the permutations are permutations and the blocks tile the matrix
        with their numbers inside :attr:`data`."""
        m, n = self.shape
        for name, p, size in (("rows", self.row_dofs, m), ("columns", self.col_dofs, n)):
            if p.shape != (size,) or not np.array_equal(np.sort(p), np.arange(size)):
                raise ValueError(f"the H-matrix's {name} are not a permutation of 0..{size - 1}")
        B = self.blocks
        if B.ndim != 2 or B.shape[1] != 6:
            raise ValueError(f"the H-matrix's block table has shape {B.shape}, expected (k, 6)")
        r0, r1, c0, c1, k, off = B.T
        if np.any((r0 < 0) | (r1 > m) | (r0 >= r1) | (c0 < 0) | (c1 > n) | (c0 >= c1) | (k < -1) | (off < 0)):
            raise ValueError("an H-matrix block lies outside the matrix or has a negative rank or offset")
        size = np.where(k < 0, (r1 - r0) * (c1 - c0), (r1 - r0 + c1 - c0) * np.maximum(k, 0))
        if np.any(off + size > self.data.size):
            raise ValueError("an H-matrix block's numbers run past the end of its data")
        if int(((r1 - r0) * (c1 - c0)).sum()) != m * n:
            raise ValueError("the H-matrix's blocks do not tile the matrix (their areas do not add up to it)")
        # a block table that sums right along every row and every column: each entry is covered once
        for lo, hi, width, size, full in ((r0, r1, c1 - c0, m, n), (c0, c1, r1 - r0, n, m)):
            cover = np.zeros(size + 1, dtype=np.int64)
            np.add.at(cover, lo, width)
            np.add.at(cover, hi, -width)
            if not np.all(np.cumsum(cover)[:size] == full):
                raise ValueError("the H-matrix's blocks do not cover every entry exactly once")


def expanded(H: HMatrix, tag: str, *, dtype: np.dtype | type = np.float64, cache: str | os.PathLike | None = None,
             rebuild: bool = False) -> np.ndarray:
    """``H`` as a dense, column-major, read-only memory-mapped array of ``dtype``, expanded once into the cache.

    Parameters
    ----------
    H : HMatrix
    tag : str
        What identifies ``H`` (the bundle's key and the hash of its data): the
        cache file's name and the stamp it must match.
    dtype : float64 or float32
        Of the expansion (:func:`expansion_dtype`; part of the file's name and stamp).
    cache : path, optional
        The cache directory (default :func:`hailstorm.runtime.bundle.stamps.default_cache_dir`).
    rebuild : bool
        Expand again even if a stamped expansion is there.

    Returns
    -------
    ndarray, shape ``H.shape``
        Memory-mapped from ``<cache>/expanded/<tag>.npy``; where the cache
        cannot hold it (unwritable, or less free space than D's bytes), the
        expansion in memory instead (logged).
    """
    dtype = np.dtype(dtype)
    tag = f"{tag}-{dtype.name}"
    folder = Path(cache) if cache is not None else default_cache_dir() / "expanded"
    target = folder / f"{tag[:40]}-{dtype.name}.npy"
    if not rebuild and target.is_file() and is_stamped(target, tag):
        try:
            return np.load(target, mmap_mode="r")
        except FileNotFoundError:  # pruned by another process since the check: expand it again
            pass
    need = H.shape[0] * H.shape[1] * dtype.itemsize
    try:
        folder.mkdir(parents=True, exist_ok=True)
        free = shutil.disk_usage(folder).free
        if free < need + (64 << 20):
            raise OSError(f"{need / 2**30:.2f} GiB needed, {free / 2**30:.2f} GiB free")
        fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=folder)
        os.close(fd)
        try:
            out = np.lib.format.open_memmap(tmp, mode="w+", dtype=dtype, shape=H.shape, fortran_order=True)
            for j in range(0, H.shape[1], EXPAND_COLUMNS):
                out[:, j:j + EXPAND_COLUMNS] = H.columns(np.arange(j, min(j + EXPAND_COLUMNS, H.shape[1])))
            out.flush()
            del out
            os.replace(tmp, target)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise
    except OSError as exc:
        log.info("expanding the compressed D in memory (%.2f GiB): the cache %s cannot hold it (%s)",
                 need / 2**30, folder, exc)
        return H.to_dense(dtype)
    stamp(target, tag)
    prune_expansions(folder, keep=target)
    return np.load(target, mmap_mode="r")


def prune_expansions(folder: str | os.PathLike, keep: str | os.PathLike | None = None,
                     budget: int | None = None) -> list[Path]:
    """Remove the oldest expansions in ``folder`` until those left hold at most ``budget`` bytes.

    Only files this project wrote there are candidates: ``*-float32.npy`` and
    ``*-float64.npy`` whose stamp (:func:`hailstorm.runtime.bundle.stamps.stamped_hash`)
    still matches them and names their own type; anything else in ``folder``,
    and ``keep`` (the expansion just written), stays. Oldest first by
    modification time. A removed expansion is rebuilt on its next use.

    Parameters
    ----------
    folder : path
        ``<cache>/expanded``.
    keep : path, optional
        Never removed.
    budget : int, optional
        Bytes (default :data:`EXPANDED_BUDGET`).

    Returns
    -------
    list of Path
        The files removed.
    """
    budget = EXPANDED_BUDGET if budget is None else int(budget)
    keep_path = Path(keep).resolve() if keep is not None else None
    ours = []
    for p in Path(folder).glob("*.npy"):
        dtype = p.stem.rsplit("-", 1)[-1]
        sha = stamped_hash(p) if dtype in ("float32", "float64") else None
        if sha is None or not sha.endswith(f"-{dtype}"):
            continue
        try:
            st = p.stat()
        except OSError:
            continue
        ours.append((st.st_mtime_ns, st.st_size, p))
    total = sum(size for _, size, _ in ours)
    removed = []
    for _, size, p in sorted(ours):
        if total <= budget:
            break
        if keep_path is not None and p.resolve() == keep_path:
            continue
        try:
            p.unlink()
        except OSError as exc:
            log.debug("could not remove the expansion %s: %s", p, exc)
            continue
        forget(p)
        total -= size
        removed.append(p)
        log.info("removed the expansion %s (%.2f GiB; the expansions' budget is %.2f GiB)", p.name,
                 size / 2**30, budget / 2**30)
    return removed
