"""The runtime's reads of D from a compressed bundle's H-matrix, D never expanded.

:func:`hailstorm.runtime.bundle.compliance.reader` gives a compressed bundle loaded with
``expand=False`` (or too large to expand, :func:`hailstorm.runtime.bundle.read.load`) an
:class:`HMatrixReader`: every block of D the contact API and the storm read (``D_VV``,
``D[rows, V]``, ``D[:, V] g``, the storm kernels' single entries, ...) is evaluated from the
H-matrix's own blocks
(:meth:`~hailstorm.runtime.bundle.hmatrix.HMatrix.entries`,
:meth:`~hailstorm.runtime.bundle.hmatrix.HMatrix.columns`), so a solve costs the blocks it
touches, not a dense D of the whole surface (7.5 GiB in float32 for the 13 000 contactable
vertices of the seat at 1.2 mm). The numbers are the H-matrix's, as the expansion's are (in
float64, where the expansion may round them to float32).
"""

from __future__ import annotations

import numpy as np

from hailstorm.runtime.bundle.dofs import column_dofs, dof3
from hailstorm.runtime.bundle.hmatrix import HMatrix
from hailstorm.runtime.compiled import blocks as kernels

__all__ = ["HMatrixReader"]


class HMatrixReader:
    """Blocks of D evaluated from an H-matrix (the methods of
    :class:`hailstorm.runtime.bundle.compliance.DenseReader`, same arguments and results).

    Parameters
    ----------
    H : HMatrix
        The compressed D, ``(3n, 3c)``.
    column_of : (n,) int ndarray
        D's column block of each surface vertex, -1 where not contactable.
    """

    def __init__(self, H: HMatrix, column_of: np.ndarray) -> None:
        self.H = H
        self.column_of = np.asarray(column_of)

    #: no dense ``D.T`` for the fused compiled paths (they step aside)
    kernel_D = None
    #: D is read from its H-matrix, never expanded (:attr:`DenseReader.compressed` is False)
    compressed = True

    @property
    def kernel_entries(self) -> tuple[np.ndarray, ...]:
        """What the storm's kernels read entries of D through
        (:func:`hailstorm.runtime.compiled.hblocks.d_entry`): the H-matrix's kernel arrays."""
        return self.H.kernel_arrays

    def entries_at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """``D[rows, cols]`` elementwise for index arrays of one (broadcast) shape."""
        rows, cols = np.broadcast_arrays(np.asarray(rows, dtype=np.intp), np.asarray(cols, dtype=np.intp))
        return self.H.pairs(rows.ravel(), cols.ravel()).reshape(rows.shape)

    def gather(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """``D[rows, cols]``, zero columns where ``cols == -1``, (r, c) float64."""
        cols = np.asarray(cols, dtype=np.intp)
        dead = cols < 0
        out = self.H.entries(rows, np.where(dead, 0, cols))
        if dead.any():
            out[:, dead] = 0.0
        return out

    def vertex_block(self, V: np.ndarray) -> np.ndarray:
        """``D_VV`` (zero columns at clamped vertices), (3|V|, 3|V|)."""
        V = np.asarray(V, dtype=np.intp)
        return self.gather(dof3(V), column_dofs(self, V))

    def apply_all(self, cols: np.ndarray, g: np.ndarray) -> np.ndarray:
        """``D[:, cols] @ g`` as (n, 3), clamped columns skipped: one product with the whole
        H-matrix (compiled; measured 3x faster than the 60 columns of 20 point contacts)."""
        cols = np.asarray(cols, dtype=np.intp)
        live = cols >= 0
        x = np.zeros(self.H.shape[1])
        np.add.at(x, cols[live], np.asarray(g, dtype=np.float64)[live])
        return self.H.matvec(x).reshape(-1, 3)

    def constraint_rows(self, V: np.ndarray, loc: np.ndarray, w: np.ndarray, normals: np.ndarray,
                        sticky: bool) -> np.ndarray:
        """``Y = (D_VV G)^T``, (m, 3|V|): the weighted rows of ``D_VV^T``."""
        M = np.ascontiguousarray(self.vertex_block(V).T)
        return kernels.weighted_rows(M, np.arange(M.shape[0] // 3), loc, w, normals, sticky)

    def response_columns(self, cols: np.ndarray, loc: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """Full-surface response ``D[:, U] B`` (3n, 3k), F-ordered, of contacts on the vertices
        whose column dofs are ``cols`` (-1 clamped)."""
        cols = np.asarray(cols, dtype=np.intp)
        Mt = np.ascontiguousarray(self.H.columns(np.maximum(cols, 0)).T)  # (3|U|, 3n)
        blocks = np.where(cols[::3] >= 0, np.arange(cols.size // 3), -1)  # clamped vertices' rows skipped
        return kernels.weighted_rows(Mt, blocks, np.ascontiguousarray(loc, dtype=np.intp),
                                     np.ascontiguousarray(weights, dtype=np.float64),
                                     np.zeros((loc.shape[0], 3)), True).T

    def pair_blocks(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The 3 x 3 blocks ``D[rows[k], cols[k]]`` (contactable ``cols``), (k, 3, 3)."""
        rows = np.asarray(rows, dtype=np.intp)
        r = 3 * rows[:, None, None] + np.arange(3)[None, :, None]
        c = 3 * self.column_of[np.asarray(cols, dtype=np.intp)][:, None, None] + np.arange(3)[None, None, :]
        return self.entries_at(r, c)
