"""Access to the compliance D of a bundle: column dofs, block gathers, column products.

Split out of :mod:`hailstorm.runtime.contact` (which re-exports nothing private from
here; import these helpers from this module). Everything here is about
reading blocks of the (possibly memory-mapped, C- or Fortran-ordered)
compliance ``D`` fast; nothing knows about contacts.

* ``_dof3(V)`` -- vertex-major x, y, z dof indices of vertices;
* ``_column_dofs(gf, V)`` -- column dofs of D for surface vertices (-1 at clamped ones);
* ``_gather(gf, rows, cols)`` -- ``D[rows, cols]`` with zero clamped columns;
* ``_apply_columns(gf, cols, g, rows)`` -- ``D[rows, cols] @ g``;
* :func:`columns_times` -- blocked ``D[:, cols] @ x`` for a column-major D;
* ``_compiled(gf, backend)`` -- whether the numba kernels of
  :mod:`hailstorm.runtime.compiled.blocks` serve this D.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from hailstorm.runtime.compiled import blocks as _kernels

__all__ = ["COLUMN_BLOCK", "GATHER_FRACTION", "columns_times"]

_log = logging.getLogger(__name__)

#: Full-surface displacement: gather columns of a C-ordered D below this
#: fraction of its columns, else one gemv with the whole D (memory-bound).
GATHER_FRACTION: float = 0.12


def _compiled(gf: Any, backend: str) -> bool:
    """True if the contact API should use the compiled kernels: ``backend`` is the
    resolved ``"numba"`` and D is column-major (as bundles are written; the kernels
    read whole columns). Any other layout takes the numpy path."""
    global _announced
    D = gf.D
    use = backend == "numba" and D.ndim == 2 and D.flags.f_contiguous and not D.flags.c_contiguous
    if use and not _announced:
        _announced = True
        _log.info("contact solves use the compiled kernels (numba): loaded in ~0.3 s, or compiled "
                  "in ~10 s the first time after an install")
    return use


_announced = False


def _dof3(idx: np.ndarray) -> np.ndarray:
    """Vertex-major x, y, z dof indices of vertex (or block) indices."""
    idx = np.asarray(idx, dtype=np.intp)
    return (3 * idx[:, None] + np.arange(3)).ravel()



def _unique_inverse(idx: np.ndarray, n: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(idx, return_inverse=True)`` for non-negative integers below ``n``
    (default ``idx.max() + 1``), through a mark array: the same (sorted) result at a
    fraction of the cost for the short index lists of the contact loop. ``inv`` has
    ``idx``'s shape."""
    idx = np.asarray(idx, dtype=np.intp)
    if idx.size == 0 or idx.min() < 0:
        V, inv = np.unique(idx, return_inverse=True)
        return V.astype(np.intp), inv.reshape(idx.shape).astype(np.intp)
    n = int(idx.max()) + 1 if n is None else n
    mark = np.zeros(n, dtype=bool)
    mark[idx] = True
    V = np.flatnonzero(mark)
    pos = np.empty(n, dtype=np.intp)
    pos[V] = np.arange(V.size)
    return V, pos[idx]


def _column_dofs(gf: Any, V: np.ndarray) -> np.ndarray:
    """Column dofs of D for the vertices V (vertex-major), -1 at clamped vertices."""
    cb = gf.column_of[V]
    cols = _dof3(np.maximum(cb, 0))
    cols[np.repeat(cb < 0, 3)] = -1
    return cols


#: Columns of D multiplied per block in :func:`columns_times` (a 4671 x 32 block
#: stays in cache; measured 2.5 ms vs 4.0 ms for one big gather at s = 100).
COLUMN_BLOCK = 32


def columns_times(D: np.ndarray, cols: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``D[:, cols] @ x`` for a column-major D, in cache-sized column blocks."""
    out = np.zeros(D.shape[0])
    for i in range(0, cols.size, COLUMN_BLOCK):
        out += D[:, cols[i:i + COLUMN_BLOCK]] @ x[i:i + COLUMN_BLOCK]
    return out


#: Vertex chunks gathered per block in :func:`_gather_vertex_rows` (bounds its index temporaries).
GATHER_BLOCK = 16384


def _vertex_triples(rows: np.ndarray) -> np.ndarray | None:
    """Vertices ``v`` if ``rows`` is exactly ``_dof3(v)`` (whole x, y, z triples), else None."""
    if rows.size % 3:
        return None
    v = rows[::3] // 3
    return v if np.array_equal(rows, _dof3(v)) else None


def _gather_vertex_rows(D: np.ndarray, V: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``D[_dof3(V), cols]`` for a column-major D, as an F-ordered (3|V|, c) array.

    In a Fortran-ordered D with a multiple of 3 rows, a vertex's x, y, z rows
    of one column are three adjacent doubles, so the gather takes 24-byte
    chunks (one index per vertex and column instead of three; measured 1.7x
    faster than the element-wise gather at s = 100). ``cols`` must be valid
    column indices.
    """
    nv = D.shape[0] // 3
    chunks = D.T.reshape(-1, 3)  # row c * nv + v: D[3v:3v+3, c]
    Mt = np.empty((cols.size, V.size, 3))
    # in column blocks: the index array stays small (a large temporary costs page faults)
    step = max(1, GATHER_BLOCK // max(V.size, 1))
    for i in range(0, cols.size, step):
        np.take(chunks, cols[i:i + step, None] * nv + V[None, :], axis=0, out=Mt[i:i + step])
    return Mt.reshape(cols.size, 3 * V.size).T


def _gather_vertices(gf: Any, V: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``D[_dof3(V), cols]`` with zero columns where ``cols == -1``: :func:`_gather`
    for whole vertex rows, without checking that the rows are vertex triples."""
    D = gf.D
    if V.size and cols.size and D.flags.f_contiguous and not D.flags.c_contiguous and D.shape[0] % 3 == 0:
        dead = cols < 0
        out = _gather_vertex_rows(D, V, np.where(dead, 0, cols))
        if dead.any():
            out[:, dead] = 0.0
        return out
    return _gather(gf, _dof3(V), cols)


def _gather(gf: Any, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """D[rows, cols] with zero columns where ``cols == -1`` (clamped vertices).

    For a column-major D the result is F-ordered (its transpose is C-contiguous).
    """
    D = gf.D
    dead = cols < 0
    cc = np.where(dead, 0, cols)
    if rows.size == 0 or cols.size == 0:
        return np.zeros((rows.size, cols.size))
    if D.flags.c_contiguous:
        out = np.take(D.reshape(-1), (rows[:, None] * D.shape[1] + cc[None, :]).ravel()).reshape(rows.size, cols.size)
        out = np.asarray(out)
    elif D.flags.f_contiguous and D.shape[0] % 3 == 0 and (V := _vertex_triples(rows)) is not None:
        out = _gather_vertex_rows(D, V, cc)
    else:  # e.g. Fortran order: contiguous column take first, then the rows
        # Gather through the C-ordered transpose so the inner loop walks down one
        # contiguous column (measured 2x faster than D[np.ix_(rows, cc)] at s = 100;
        # np.take would first copy all of D to C order).
        out = np.asarray(D.T[np.ix_(cc, rows)]).T
    if dead.any():
        out[:, dead] = 0.0
    return out


def _apply_columns(gf: Any, cols: np.ndarray, g: np.ndarray, rows: np.ndarray | None,
                   compiled: bool = False) -> np.ndarray:
    """``D[rows, cols] @ g`` as (r, 3) (all rows if ``rows`` is None), skipping clamped columns.

    ``compiled``: all rows through :func:`hailstorm.runtime.compiled.blocks.columns_times`
    (see :func:`_compiled`)."""
    if compiled and rows is None:
        return _kernels.columns_times(np.asarray(gf.D).T, cols, g).reshape(-1, 3)
    live = cols >= 0
    c, gl = cols[live], g[live]
    D = gf.D
    n = gf.vertices.shape[0]
    if rows is None:
        if c.size == 0:
            return np.zeros((n, 3))
        if D.flags.f_contiguous:
            return columns_times(D, c, gl).reshape(-1, 3)
        if c.size > GATHER_FRACTION * D.shape[1]:
            full = np.zeros(D.shape[1])
            full[c] = gl
            return np.asarray(D @ full).reshape(-1, 3)
        cv = c[::3] // 3  # whole 3-column blocks (a vertex's x, y, z are consecutive)
        return np.asarray(np.take(D.reshape(D.shape[0], -1, 3), cv, axis=1).reshape(D.shape[0], -1) @ gl).reshape(-1, 3)
    rows = np.asarray(rows)
    if rows.ndim != 1 or (rows.size and not np.issubdtype(rows.dtype, np.integer)):
        raise ValueError(f"rows must be a 1-D array of vertex indices, got shape {rows.shape} dtype {rows.dtype}")
    if rows.size and (rows.min() < 0 or rows.max() >= n):
        raise IndexError(f"rows hold vertex indices outside 0..{n - 1}")
    if c.size == 0 or rows.size == 0:
        return np.zeros((rows.size, 3))
    return (_gather(gf, _dof3(rows), c) @ gl).reshape(-1, 3)

