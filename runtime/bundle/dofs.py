"""Dof indices of D: vertex-major x, y, z triples, the column dofs of surface vertices.

* :func:`dof3` -- vertex-major x, y, z dof indices of vertices;
* :func:`column_dofs` -- column dofs of D for surface vertices (-1 at clamped ones);
* :func:`unique_inverse` -- ``np.unique(..., return_inverse=True)`` for short index lists.

(:mod:`hailstorm.runtime.bundle.compliance` re-exports them with the readers of D.)
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["column_dofs", "dof3", "unique_inverse"]


def dof3(idx: np.ndarray) -> np.ndarray:
    """Vertex-major x, y, z dof indices of vertex (or block) indices, (3k,)."""
    idx = np.asarray(idx, dtype=np.intp)
    return (3 * idx[:, None] + np.arange(3)).ravel()


def unique_inverse(idx: np.ndarray, n: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(idx, return_inverse=True)`` for non-negative integers below ``n``.

    Through a mark array (default size ``idx.max() + 1``): the same (sorted)
    result at a fraction of the cost for the short index lists of the contact
    loop.

    Parameters
    ----------
    idx : int array_like
    n : int, optional
        An upper bound of ``idx`` (exclusive).

    Returns
    -------
    V : (u,) intp ndarray
        The sorted distinct values.
    inv : intp ndarray of ``idx``'s shape
        ``V[inv] == idx``.
    """
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


def column_dofs(gf: Any, V: np.ndarray) -> np.ndarray:
    """Column dofs of D for the vertices V (vertex-major), -1 at clamped vertices, (3|V|,)."""
    cb = gf.column_of[V]
    cols = dof3(np.maximum(cb, 0))
    cols[np.repeat(cb < 0, 3)] = -1
    return cols
