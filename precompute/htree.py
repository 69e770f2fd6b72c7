"""The H-matrix's geometry: cluster trees of the vertices and the admissible block partition.

What :mod:`hailstorm.precompute.hmatrix` compresses D on, and
:mod:`hailstorm.precompute.hstream` streams it by:

* :func:`cluster_tree` -- recursive bisection of the vertices (leaves of at most
  ``leaf`` vertices); every cluster is a contiguous range of the tree's order;
* :func:`admissible_blocks` -- the block partition: a pair of clusters with
  ``min(diam) <= eta * dist`` (bounding boxes, :func:`admissible`) is a far block, a
  pair with a leaf that is not is a near block, any other pair is split into its children;
* :func:`dofs`, :func:`permuted`, :func:`block_slices` -- a vertex's three dofs, a matrix
  in tree order, and the dof ranges of a block in it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Cluster", "ClusterTree", "Partition", "admissible", "admissible_blocks", "block_slices", "cluster_tree",
           "dofs", "permuted"]


@dataclass
class Cluster:
    """A node of a :class:`ClusterTree`: the points ``tree.perm[start:stop]``.

    Attributes
    ----------
    start, stop : int
        Range in the tree's ordering.
    lo, hi : ndarray, shape (3,)
        Bounding box of the cluster's points.
    level : int
        Depth (the root is 0).
    children : tuple of int
        Indices of the two halves in ``tree.nodes`` (empty for a leaf).
    """

    start: int
    stop: int
    lo: np.ndarray
    hi: np.ndarray
    level: int
    children: tuple[int, ...] = ()

    @property
    def size(self) -> int:
        """Number of points."""
        return self.stop - self.start

    @property
    def diam(self) -> float:
        """Diagonal of the bounding box."""
        return float(np.linalg.norm(self.hi - self.lo))


@dataclass
class ClusterTree:
    """Binary cluster tree of a point set.

    Attributes
    ----------
    perm : ndarray of int, shape (n,)
        Tree order -> point index; every cluster is a contiguous range of it.
    nodes : list of Cluster
        ``nodes[0]`` is the root.
    """

    perm: np.ndarray
    nodes: list[Cluster]

    def leaves(self) -> list[int]:
        """Indices of the leaves, in tree order."""
        return [i for i, c in enumerate(self.nodes) if not c.children]

    def indices(self, node: int) -> np.ndarray:
        """Point indices of cluster ``node``."""
        c = self.nodes[node]
        return self.perm[c.start:c.stop]

    @property
    def depth(self) -> int:
        """Largest level of a node."""
        return max(c.level for c in self.nodes)


def cluster_tree(points: np.ndarray, leaf: int = 32, split: str = "middle") -> ClusterTree:
    """Recursive bisection of ``points`` along the longest axis of each cluster's bounding box.

    Parameters
    ----------
    points : ndarray, shape (n, d)
        Coordinates.
    leaf : int
        A cluster of at most ``leaf`` points is not split.
    split : {"middle", "median"}
        Where a cluster is cut: at the middle of its bounding box (geometric
        bisection: clusters of one level have about one size in space, the
        leaves from 1 to ``leaf`` points) or at the median point (halves of
        sizes differing by at most one, leaves of ``leaf // 2`` to ``leaf``
        points, their size in space set by the local density).

    Returns
    -------
    ClusterTree
        A cluster of coincident points is a leaf whatever its size.
    """
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or len(P) == 0:
        raise ValueError("points must be a non-empty (n, d) array")
    if leaf < 1:
        raise ValueError(f"leaf must be >= 1, got {leaf}")
    if split not in ("middle", "median"):
        raise ValueError(f"split must be 'middle' or 'median', got {split!r}")
    perm = np.arange(len(P))
    nodes = [Cluster(0, len(P), P.min(axis=0), P.max(axis=0), 0)]
    stack = [0]
    while stack:
        i = stack.pop()
        c = nodes[i]
        axis = int(np.argmax(c.hi - c.lo))
        if c.size <= leaf or c.hi[axis] <= c.lo[axis]:
            continue
        idx = perm[c.start:c.stop].copy()
        order = np.argsort(P[idx, axis], kind="stable")
        perm[c.start:c.stop] = idx[order]
        if split == "median":
            half = c.size // 2
        else:
            half = int(np.searchsorted(P[idx[order], axis], 0.5 * (c.lo[axis] + c.hi[axis]), side="right"))
        kids = []
        for a, b in ((c.start, c.start + half), (c.start + half, c.stop)):
            q = P[perm[a:b]]
            nodes.append(Cluster(a, b, q.min(axis=0), q.max(axis=0), c.level + 1))
            kids.append(len(nodes) - 1)
        c.children = tuple(kids)
        stack.extend(kids)
    return ClusterTree(perm, nodes)


def _box_distance(a: Cluster, b: Cluster) -> float:
    gap = np.maximum(0.0, np.maximum(a.lo - b.hi, b.lo - a.hi))
    return float(np.linalg.norm(gap))


def admissible(a: Cluster, b: Cluster, eta: float) -> bool:
    """``min(diam a, diam b) <= eta * dist(a, b)`` on bounding boxes, with a positive distance."""
    d = _box_distance(a, b)
    return d > 0.0 and min(a.diam, b.diam) <= eta * d


@dataclass
class Partition:
    """The leaves of a block cluster tree.

    Attributes
    ----------
    far : list of (int, int, int)
        Admissible blocks ``(row node, column node, level)``: low rank.
    near : list of (int, int, int)
        Inadmissible leaves (a row or column leaf): dense.
    visited : dict of int to list of (int, int)
        Every block pair the recursion reached, by level (what peeling must
        separate at that level).
    """

    far: list[tuple[int, int, int]] = field(default_factory=list)
    near: list[tuple[int, int, int]] = field(default_factory=list)
    visited: dict[int, list[tuple[int, int]]] = field(default_factory=dict)


def admissible_blocks(rows: ClusterTree, cols: ClusterTree, eta: float) -> Partition:
    """Split ``rows x cols`` into admissible (far) and dense (near) blocks.

    Starting from the two roots: an admissible pair is a far block; otherwise,
    if either is a leaf, a near block; otherwise the four pairs of children.

    Parameters
    ----------
    rows, cols : ClusterTree
    eta : float
        Admissibility parameter (:func:`admissible`).

    Returns
    -------
    Partition
        Its blocks cover every (row, column) pair exactly once.
    """
    part = Partition()
    stack = [(0, 0, 0)]
    while stack:
        i, j, lev = stack.pop()
        part.visited.setdefault(lev, []).append((i, j))
        a, b = rows.nodes[i], cols.nodes[j]
        if admissible(a, b, eta):
            part.far.append((i, j, lev))
        elif not a.children or not b.children:
            part.near.append((i, j, lev))
        else:
            stack.extend((ci, cj, lev + 1) for ci in a.children for cj in b.children)
    return part


def dofs(vertices: np.ndarray) -> np.ndarray:
    """The three dofs (x, y, z) of each vertex, vertex-major."""
    v = np.asarray(vertices, dtype=np.intp)
    return (3 * v[:, None] + np.arange(3)).ravel()


def permuted(A: np.ndarray, rows: ClusterTree, cols: ClusterTree) -> np.ndarray:
    """``A`` (vertex-major dofs of the points of ``rows`` and ``cols``) in tree order."""
    return np.ascontiguousarray(np.asarray(A)[np.ix_(dofs(rows.perm), dofs(cols.perm))])


def block_slices(rows: ClusterTree, cols: ClusterTree, i: int, j: int) -> tuple[slice, slice]:
    """The dof ranges (tree order) of the block of row cluster ``i`` and column cluster ``j``."""
    a, b = rows.nodes[i], cols.nodes[j]
    return slice(3 * a.start, 3 * a.stop), slice(3 * b.start, 3 * b.stop)
