"""How compressible is the compliance D, and how many FE solves would each way of building it need?

Evidence for storing the compliance compressed, with error control (docs/scale.md, "How compressible is D"),
measured on a bundle's dense D before anything is built (nothing here changes
the bundle format or the runtime):

1. **Hierarchical (H-matrix) compression.** A cluster tree of the vertices
   (:func:`cluster_tree`: recursive bisection of the bounding box across its
   longest axis, leaves of at most ``leaf`` vertices), the standard
   admissibility ``min(diam s, diam t) <= eta * dist(s, t)`` on bounding boxes
   (:func:`admissible_blocks`), admissible blocks truncated by SVD to a relative
   Frobenius tolerance ``tol`` per block, the others dense (:func:`compress`;
   :func:`measure` gets every tolerance's figures from one SVD per block).
   Measured on the symmetric block (contactable rows and columns) and on all
   rows: stored numbers against dense, the ranks, the error of the whole matrix
   (Frobenius; the largest relative 2-norm error of a column), the error of
   the contact stiffness ``1 / (g^T D g)`` of random point contacts
   (:func:`random_contacts`), which is what the storm reads, and of the forces
   of sets of them pressed together (:func:`force_errors`: their coupling).
2. **Solves to build it by peeling** (Lin, Lu & Ying, J. Comput. Phys. 230
   (2011) 4071): per level, the admissible blocks are probed with random loads
   on groups of column clusters that share no row cluster
   (:func:`peeling_solves`), ``(k_max + p)`` loads per group and pass, a range
   and a co-range pass; the dense near field by unit loads on all vertices of
   a colour at once. An estimate from the measured ranks, against the dense
   build's ``3 c``.
3. **Several well-separated unit loads per solve.** :func:`colouring` colours
   the contactable vertices greedily so that same-coloured vertices are at
   least ``s`` apart (``3 x colours`` solves); :func:`probe_error` reads a
   column's rows within ``r = s / 2`` from its colour's summed columns and
   measures the contamination by the others, and how much of the column lies
   beyond ``r`` (what a near-field-only model drops); :func:`coloured_forms`
   gives the contacts' ``G^T D~ G`` of that model.

Run ``python -m studies.compression_study`` (``--help``): without
``--gf`` it uses the default seat (``meshes/default_scene.toml`` ``[seat]``,
built or read from the cache), ``--mesh-size`` builds it at another size.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from typing import Any, Callable, Sequence

import numpy as np

from hailstorm.precompute.hmatrix import compress, svd
from hailstorm.precompute.htree import (
    Cluster,
    ClusterTree,
    Partition,
    admissible,
    admissible_blocks,
    block_slices,
    cluster_tree,
    dofs,
    permuted,
)
from studies import record

__all__ = ["Cluster", "ClusterTree", "Partition", "admissible", "admissible_blocks", "cluster_tree",
           "colour_lower_bound", "coloured_forms", "colouring", "compress", "contact_vectors", "dofs",
           "force_errors", "main",
           "measure", "peeling_solves", "probe_error", "random_contacts"]


def measure(A: np.ndarray, rows: ClusterTree, cols: ClusterTree, part: Partition, tols: Sequence[float],
            Gr: np.ndarray | None = None, Gc: np.ndarray | None = None) -> list[dict[str, Any]]:
    """What :func:`compress` would give at each tolerance, from one SVD per far block.

    Parameters
    ----------
    A, rows, cols, part
        As for :func:`compress`.
    tols : sequence of float
    Gr, Gc : ndarray, shape (3 n_rows, P) and (3 n_cols, P), optional
        Contact vectors (:func:`contact_vectors`) on the rows' and the
        columns' points: the quadratic forms ``g^T H g`` are returned.

    Returns
    -------
    list of dict
        Per tolerance: ``tol``, ``far``, ``near`` (block counts), ``stored``,
        ``dense`` (numbers), ``near_stored`` (numbers in dense blocks),
        ``ranks``, ``factored`` (stored as factors, else dense and exact) and
        ``levels`` (per far block), ``frob`` (``||A - H||_F /
        ||A||_F``), ``col_err`` (per column, ``||(A - H) e_j|| / ||A e_j||``;
        0 for a zero column), and with probes ``W`` = ``Gr^T A Gc`` and
        ``W_H`` = ``Gr^T H Gc`` (``(P, P)``: single contacts on the diagonal,
        their couplings off it).
    """
    Ap = permuted(A, rows, cols)
    m, n = Ap.shape
    col_norm2 = np.einsum("ij,ij->j", Ap, Ap)
    total2 = float(col_norm2.sum())
    T = len(tols)
    err2 = np.zeros(T)
    col_err2 = np.zeros((T, n))
    stored = np.zeros(T, dtype=np.int64)
    ranks = np.zeros((T, len(part.far)), dtype=np.int64)
    factored = np.zeros((T, len(part.far)), dtype=bool)
    probes = Gr is not None and Gc is not None
    if probes:
        Grp = np.asarray(Gr)[dofs(rows.perm)]
        Gcp = np.asarray(Gc)[dofs(cols.perm)]
        W = Grp.T @ (Ap @ Gcp)
        P = W.shape[0]
        WE = np.zeros((T, P, P))
    for b, (i, j, _) in enumerate(part.far):
        r, c = block_slices(rows, cols, i, j)
        B = Ap[r, c]
        U, s, Vt = svd(B)
        s2 = s * s
        tail = np.concatenate([np.cumsum(s2[::-1])[::-1], [0.0]])
        ctail = np.vstack([np.cumsum((s2[:, None] * Vt * Vt)[::-1], axis=0)[::-1], np.zeros((1, Vt.shape[1]))])
        if probes:
            lr = np.flatnonzero(np.abs(Grp[r]).sum(axis=0))
            lc = np.flatnonzero(np.abs(Gcp[c]).sum(axis=0))
            if lr.size and lc.size:  # (g_p^T U_i s_i)(V_i^T g_q) for the contacts touching the block
                a = (U.T @ Grp[r][:, lr]) * s[:, None]
                bb = Vt @ Gcp[c][:, lc]
        for t, tol in enumerate(tols):
            k = int(np.argmax(tail <= tol * tol * tail[0]))
            ranks[t, b] = k
            factored[t, b] = k * (B.shape[0] + B.shape[1]) < B.size
            if not factored[t, b]:  # kept dense, and exact (as compress keeps it)
                stored[t] += B.size
                continue
            stored[t] += k * (B.shape[0] + B.shape[1])
            err2[t] += tail[k]
            col_err2[t, c] += ctail[k]
            if probes and lr.size and lc.size:
                WE[t][np.ix_(lr, lc)] += a[k:].T @ bb[k:]
    near_stored = 0
    for i, j, _ in part.near:
        r, c = block_slices(rows, cols, i, j)
        near_stored += (r.stop - r.start) * (c.stop - c.start)
    inv = np.zeros(n, dtype=np.intp)
    inv_dofs = dofs(cols.perm)
    inv[inv_dofs] = np.arange(n)  # original column -> tree column
    safe = np.where(col_norm2 > 0, col_norm2, 1.0)
    out = []
    levels = np.array([lev for _, _, lev in part.far], dtype=np.int64)
    for t, tol in enumerate(tols):
        res: dict[str, Any] = {
            "tol": float(tol), "far": len(part.far), "near": len(part.near), "stored": int(stored[t] + near_stored),
            "dense": int(m * n), "near_stored": int(near_stored), "ranks": ranks[t], "factored": factored[t],
            "levels": levels,
            "frob": float(np.sqrt(err2[t] / total2)) if total2 > 0 else 0.0,
            "col_err": np.sqrt(col_err2[t] / safe)[inv] * (col_norm2[inv] > 0),
        }
        if probes:
            res["W"] = W
            res["W_H"] = W - WE[t]
        out.append(res)
    return out


# --------------------------------------------------------------------------
# point contacts
# --------------------------------------------------------------------------
def random_contacts(vertices: np.ndarray, triangles: np.ndarray, allowed: np.ndarray, count: int,
                    seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random point contacts: uniform points (by area) on triangles whose vertices are all ``allowed``.

    Parameters
    ----------
    vertices : ndarray, shape (n, 3)
    triangles : ndarray of int, shape (m, 3)
    allowed : ndarray of bool, shape (n,)
        E.g. the contactable vertices.
    count : int
    seed : int

    Returns
    -------
    tri : ndarray of int, shape (count, 3)
        The three vertices of each contact's triangle.
    weights : ndarray, shape (count, 3)
        Barycentric coordinates of the point (positive, summing to 1).
    normals : ndarray, shape (count, 3)
        The triangle's unit normal: the contact's direction.
    """
    V, T = np.asarray(vertices, float), np.asarray(triangles, np.intp)
    ok = T[np.asarray(allowed, bool)[T].all(axis=1)]
    if len(ok) == 0:
        raise ValueError("no triangle has all three vertices allowed")
    nrm = np.cross(V[ok[:, 1]] - V[ok[:, 0]], V[ok[:, 2]] - V[ok[:, 0]])
    area = np.linalg.norm(nrm, axis=1)
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(ok), size=count, p=area / area.sum())
    u, v = rng.random(count), rng.random(count)
    su = np.sqrt(u)
    w = np.column_stack([1 - su, su * (1 - v), su * v])
    return ok[pick], w, nrm[pick] / area[pick, None]


def contact_vectors(index_of: np.ndarray, tri: np.ndarray, weights: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Contact load vectors ``g`` on a point set: ``w_k n`` at the dofs of each contact's vertex ``k``.

    Parameters
    ----------
    index_of : ndarray of int, shape (n_vertices,)
        Vertex -> its index in the point set (``-1``: not in it; its weights are dropped).
    tri, weights, normals
        From :func:`random_contacts`.

    Returns
    -------
    ndarray, shape (3 n_points, count)
    """
    index_of = np.asarray(index_of)
    G = np.zeros((3 * int(index_of.max() + 1), len(tri)))
    for p, (t, w, nv) in enumerate(zip(tri, weights, normals, strict=True)):
        for v, wk in zip(t, w, strict=True):
            i = index_of[v]
            if i >= 0:
                G[3 * i:3 * i + 3, p] += wk * nv
    return G


# --------------------------------------------------------------------------
# peeling
# --------------------------------------------------------------------------
def _greedy_groups(items: Sequence[int], conflicts: dict[int, set[int]]) -> dict[int, int]:
    colour: dict[int, int] = {}
    for it in items:
        used = {colour[o] for o in conflicts.get(it, ()) if o in colour}
        c = 0
        while c in used:
            c += 1
        colour[it] = c
    return colour


def _groups(pairs: list[tuple[int, int]], probed: set[int], side: int) -> dict[int, int]:
    """Colour the ``probed`` clusters of one side (0: rows, 1: columns) so that no two of a colour
    meet the same cluster of the other side in ``pairs``."""
    by_other: dict[int, list[int]] = {}
    for pr in pairs:
        by_other.setdefault(pr[1 - side], []).append(pr[side])
    conflicts: dict[int, set[int]] = {}
    for members in by_other.values():
        live = [x for x in members if x in probed]
        for x in live:
            conflicts.setdefault(x, set()).update(y for y in live if y != x)
    return _greedy_groups(sorted(probed), conflicts)


def peeling_solves(rows: ClusterTree, cols: ClusterTree, part: Partition, ranks: Sequence[int],
                   oversampling: int = 10) -> dict[str, Any]:
    """Estimate of the solves (right-hand sides) that peeling needs to build the H-matrix.

    At each level with admissible blocks, the column clusters holding one are
    grouped so that no two of a group meet the same row cluster among the
    blocks the recursion reached at that level (coarser far blocks are known
    and subtracted; anything else would contaminate); each group takes
    ``k_g + p`` random loads (``k_g`` the largest rank of its blocks) for the
    range, and the row clusters, grouped the same way, as many for the
    co-range. The near field is read from unit loads in each direction on all
    column points of one colour at once, the points coloured so that no two of
    a colour meet a common row cluster among the near blocks (``3 x colours``
    solves; what the loads do elsewhere is the far field, known by then).

    Parameters
    ----------
    rows, cols, part
        As for :func:`compress`.
    ranks : sequence of int
        Rank of each far block (``part.far`` order; :func:`measure`'s ``ranks``).
    oversampling : int
        ``p``.

    Returns
    -------
    dict
        ``levels``: per level ``(level, far blocks, column groups, row groups,
        k_max, solves)``; ``far_solves``, ``near_colours``, ``near_solves``, ``total``.
    """
    ranks = np.asarray(ranks)
    rank_of = {(i, j): int(k) for (i, j, _), k in zip(part.far, ranks, strict=True)}
    levels = []
    far_total = 0
    for lev in sorted(part.visited):
        far = [(i, j) for i, j, lv in part.far if lv == lev]
        if not far:
            continue
        solves = 0
        ng = []
        for side in (1, 0):
            probed = {pr[side] for pr in far}
            g = _groups(part.visited[lev], probed, side)
            kmax: dict[int, int] = {}
            for pr in far:
                kmax[g[pr[side]]] = max(kmax.get(g[pr[side]], 0), rank_of[pr])
            solves += sum(k + oversampling for k in kmax.values())
            ng.append(len(kmax))
        levels.append((lev, len(far), ng[0], ng[1], max(rank_of[pr] for pr in far), solves))
        far_total += solves
    # near field: colour the column points so that no two of a colour meet a common row cluster among
    # the near blocks; one solve per colour and direction reads them all (the far field is peeled off)
    rows_of = [[] for _ in range(len(cols.perm))]  # tree position -> near row clusters
    members: dict[int, list[np.ndarray]] = {}
    for i, j, _ in part.near:
        b = cols.nodes[j]
        for q in range(b.start, b.stop):
            rows_of[q].append(i)
        members.setdefault(i, []).append(np.arange(b.start, b.stop))
    members_arr = {i: np.unique(np.concatenate(m)) for i, m in members.items()}
    colour = np.full(len(cols.perm), -1, dtype=np.intp)
    for q in range(len(cols.perm)):
        if not rows_of[q]:
            continue
        used = colour[np.concatenate([members_arr[i] for i in rows_of[q]])]
        used = np.unique(used[used >= 0])
        free = np.setdiff1d(np.arange(len(used) + 1), used)
        colour[q] = free[0]
    near_colours = int(colour.max()) + 1 if (colour >= 0).any() else 0
    near_solves = 3 * near_colours
    return {"levels": levels, "far_solves": int(far_total), "near_colours": near_colours, "near_solves": near_solves,
            "total": int(far_total + near_solves)}


# --------------------------------------------------------------------------
# several well-separated unit loads per solve
# --------------------------------------------------------------------------
def colouring(points: np.ndarray, separation: float) -> np.ndarray:
    """Greedy colouring: vertices of one colour are at least ``separation`` apart (Euclidean).

    Vertices are taken in order along the longest bounding-box axis (a sweep),
    each given the smallest colour none of its already coloured neighbours
    closer than ``separation`` has.

    Parameters
    ----------
    points : ndarray, shape (n, 3)
    separation : float

    Returns
    -------
    ndarray of int, shape (n,)
        Colours ``0 .. k-1``.
    """
    from scipy.spatial import cKDTree

    P = np.asarray(points, float)
    tree = cKDTree(P)
    axis = int(np.argmax(np.ptp(P, axis=0))) if len(P) else 0
    order = np.argsort(P[:, axis], kind="stable")
    colour = np.full(len(P), -1, dtype=np.intp)
    near = tree.query_ball_point(P, separation)
    for v in order:
        nb = np.asarray(near[v], dtype=np.intp)
        nb = nb[(colour[nb] >= 0) & (np.linalg.norm(P[nb] - P[v], axis=1) < separation)]
        used = np.zeros(len(nb) + 1, bool)
        cs = colour[nb]
        used[cs[cs <= len(nb)]] = True
        colour[v] = int(np.argmin(used))
    return colour


def colour_lower_bound(points: np.ndarray, separation: float) -> int:
    """Most vertices in one open ball of radius ``separation / 2`` around a vertex: pairwise closer
    than ``separation``, so every colouring needs at least this many colours."""
    from scipy.spatial import cKDTree

    P = np.asarray(points, float)
    tree = cKDTree(P)
    counts = tree.query_ball_point(P, np.nextafter(separation / 2, 0), return_length=True)
    return int(np.max(counts))


def _colour_sums(A: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """``S[:, 3 c + b] = sum of A[:, 3 j + b] over the columns j of colour c``."""
    import scipy.sparse as sp

    nc = int(colours.max()) + 1
    cols = np.arange(3 * len(colours))
    P = sp.csr_matrix((np.ones(len(cols)), (cols, 3 * np.repeat(colours, 3) + np.tile(np.arange(3), len(colours)))),
                      shape=(len(cols), 3 * nc))
    return np.asarray((P.T @ np.asarray(A).T).T)


def probe_error(A: np.ndarray, row_points: np.ndarray, col_points: np.ndarray, colours: np.ndarray,
                radius: float) -> dict[str, np.ndarray]:
    """Reading each column near its own vertex from a solve that loads its whole colour at once.

    Parameters
    ----------
    A : ndarray, shape (3 n_rows, 3 n_cols)
        Vertex-major, exact columns.
    row_points, col_points : ndarray, shape (n_rows, 3), (n_cols, 3)
    colours : ndarray of int, shape (n_cols,)
        :func:`colouring` of ``col_points``.
    radius : float
        Rows within it (inclusive) of the column's vertex are read.

    Returns
    -------
    dict
        Per column (``3 n_cols``): ``contamination`` = ``||S_c[R] - A[R, j]|| /
        ||A[R, j]||`` (``S_c`` the sum of the colour's columns in the same
        direction, ``R`` the rows within ``radius``), ``beyond`` =
        ``||A[~R, j]|| / ||A[:, j]||`` (zero columns: 0).
    """
    from scipy.spatial import cKDTree

    A = np.asarray(A)
    S = _colour_sums(A, np.asarray(colours))
    near = cKDTree(np.asarray(row_points, float)).query_ball_point(np.asarray(col_points, float), radius)
    n = len(col_points)
    cont, beyond = np.zeros(3 * n), np.zeros(3 * n)
    total = np.einsum("ij,ij->j", A, A)
    for j in range(n):
        R = dofs(np.asarray(near[j], dtype=np.intp))
        far = np.ones(A.shape[0], dtype=bool)
        far[R] = False
        out2 = np.einsum("ij,ij->j", A[far, 3 * j:3 * j + 3], A[far, 3 * j:3 * j + 3])
        for b in range(3):
            col = 3 * j + b
            a = A[R, col]
            na = float(a @ a)
            if na > 0:
                d = S[R, 3 * colours[j] + b] - a
                cont[col] = np.sqrt(float(d @ d) / na)
            if total[col] > 0:
                beyond[col] = np.sqrt(out2[b] / total[col])
    return {"contamination": cont, "beyond": beyond}


def coloured_forms(A: np.ndarray, row_points: np.ndarray, col_index_of: np.ndarray, vertices: np.ndarray,
                   colours: np.ndarray, radius: float, Gr: np.ndarray, tri: np.ndarray, weights: np.ndarray,
                   normals: np.ndarray) -> np.ndarray:
    """``Gr^T D~ Gc`` of point contacts for the near-field model read from coloured solves.

    Column ``l`` of ``D~`` is its colour's summed column (:func:`probe_error`)
    on the rows within ``radius`` of vertex ``l``, and zero beyond.

    Parameters
    ----------
    A : ndarray, shape (3 n_rows, 3 n_cols)
        Exact columns, vertex-major.
    row_points : ndarray, shape (n_rows, 3)
    col_index_of : ndarray of int, shape (n_vertices,)
        Vertex -> column point index (``-1``: none; its weight is dropped).
    vertices : ndarray, shape (n_vertices, 3)
    colours : ndarray of int, shape (n_cols,)
    radius : float
    Gr : ndarray, shape (3 n_rows, P)
        The contacts on the rows (:func:`contact_vectors`).
    tri, weights, normals
        The same contacts (:func:`random_contacts`).

    Returns
    -------
    ndarray, shape (P, P)
    """
    S = _colour_sums(np.asarray(A), np.asarray(colours))
    R = np.asarray(row_points, float)
    V = np.asarray(vertices, float)
    Y = np.zeros((S.shape[0], len(tri)))
    for q, (t, w, nv) in enumerate(zip(tri, weights, normals, strict=True)):
        for v, wv in zip(t, w, strict=True):
            j = col_index_of[v]
            if j < 0:
                continue
            near = np.repeat(np.linalg.norm(R - V[v], axis=1) <= radius, 3)
            Y[near, q] += wv * (S[near, 3 * colours[j]:3 * colours[j] + 3] @ nv)
    return np.asarray(Gr).T @ Y


def force_errors(W: np.ndarray, W2: np.ndarray, sets: np.ndarray) -> np.ndarray:
    """Relative error of the forces of simultaneous contacts pressed to one depth.

    Parameters
    ----------
    W, W2 : ndarray, shape (P, P)
        Exact and approximate ``G^T D G`` of ``P`` point contacts.
    sets : ndarray of int, shape (K, m)
        Each row: ``m`` contacts in contact at once.

    Returns
    -------
    ndarray, shape (K,)
        ``||f2 - f|| / ||f||`` with ``W[s, s] f = 1`` (a common unit
        depth) and the same for ``W2``.
    """
    out = np.zeros(len(sets))
    for i, st in enumerate(np.asarray(sets)):
        one = np.ones(len(st))
        f = np.linalg.solve(W[np.ix_(st, st)], one)
        f2 = np.linalg.solve(W2[np.ix_(st, st)], one)
        out[i] = np.linalg.norm(f2 - f) / np.linalg.norm(f)
    return out


# --------------------------------------------------------------------------
# the study
# --------------------------------------------------------------------------
def _table(keys: Sequence[str], rows: list[Sequence[Any]]) -> list[str]:
    out = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    out += ["| " + " | ".join(str(x) for x in r) + " |" for r in rows]
    return out


def _pct(x: float) -> str:
    return f"{100 * x:.3g}"


def _header(argv: Sequence[str]) -> list[str]:
    cmd = "python -m studies.compression_study " + " ".join(shlex.quote(a) for a in argv)
    return [f"$ {cmd.strip()}", record.stamp()]


def _load(args: argparse.Namespace) -> Any:
    import hailstorm.runtime

    if args.gf:
        return hailstorm.runtime.load(args.gf)
    from hailstorm.precompute import build_bundle
    from hailstorm.runtime.storm.scene import SeatSettings

    seat = SeatSettings.default()
    return hailstorm.runtime.load(build_bundle(None, mesh_size=args.mesh_size or seat.mesh_size, order=seat.order,
                                               load=seat.load, young=seat.young, poisson=seat.poisson))


def _floats(text: str) -> list[float]:
    return [float(x) for x in text.split(",") if x.strip()]


def main(argv: list[str] | None = None) -> None:
    """Print the three measurements (see the module notes) for one bundle."""
    ap = argparse.ArgumentParser(prog="python -m studies.compression_study", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gf", help="bundle directory (default: the default seat, built or read from the cache)")
    ap.add_argument("--mesh-size", type=float, default=None,
                    help="without --gf: the default seat at this element size [m] (default: [seat] mesh_size)")
    ap.add_argument("--leaf", type=int, default=32, help="largest leaf of the cluster trees [vertices] (default 32)")
    ap.add_argument("--split", default="middle", choices=("middle", "median"),
                    help="where clusters are cut: bounding box middle or median point (default middle)")
    ap.add_argument("--eta", default="1,2", help="admissibility parameters (default 1,2)")
    ap.add_argument("--tols", default="1e-1,1e-2,1e-3,1e-4",
                    help="relative tolerances of the far blocks (default 1e-1,1e-2,1e-3,1e-4)")
    ap.add_argument("--probes", type=int, default=300, help="random point contacts (default 300)")
    ap.add_argument("--sets", type=int, default=200, help="random sets of simultaneous contacts (default 200)")
    ap.add_argument("--set-size", type=int, default=20, help="contacts per set (default 20)")
    ap.add_argument("--oversampling", type=int, default=10, help="peeling's p (default 10)")
    ap.add_argument("--pad", type=float, default=0.015, help="pad thickness h [m] (default 0.015)")
    ap.add_argument("--separations", default="2,3,4,6", help="separations s in pad thicknesses (default 2,3,4,6)")
    ap.add_argument("--skip-all-rows", action="store_true", help="H-matrix of the contactable rows only")
    ap.add_argument("--out", help="also write the output to this file")
    args = ap.parse_args(argv)
    lines: list[str] = []

    def emit(*text: str) -> None:
        for t in text:
            print(t, flush=True)
            lines.append(t)

    t_start = time.perf_counter()
    emit(*_header(sys.argv[1:] if argv is None else argv))
    gf = _load(args)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(1):  # many small SVDs: one BLAS thread each is faster, and the machine is shared
        _study(gf, args, emit, t_start)
    if args.out:
        record.write(args.out, lines)


def _study(gf: Any, args: argparse.Namespace, emit: Callable[..., None], t_start: float) -> None:
    etas, tols, seps = _floats(args.eta), _floats(args.tols), _floats(args.separations)
    man = gf.manifest
    V = np.asarray(gf.vertices, float)
    contactable = np.asarray(gf.contactable, bool)
    ci = np.flatnonzero(contactable)
    col_vertex = np.empty(len(ci), dtype=np.intp)
    col_vertex[gf.column_of[ci]] = ci  # column block -> vertex
    D = np.asarray(gf.D)
    n, c = len(V), len(ci)
    opts = man.get("options", {})
    emit(f"# bundle {gf.path}: {man['mesh'].get('source', '?')}, order {opts.get('order')}, load "
         f"{opts.get('load')!r}; {n} surface vertices, {c} contactable; D {D.shape[0]} x {D.shape[1]} "
         f"({D.nbytes / 2**20:.0f} MiB); its dense build: {3 * c} solves, "
         f"{man.get('timings_s', {}).get('solve', float('nan')):.1f} s of solves")
    col_index = np.full(n, -1, dtype=np.intp)
    col_index[col_vertex] = np.arange(c)
    cases = {"contactable x contactable": (D[dofs(col_vertex)], col_vertex, col_index)}
    if not args.skip_all_rows:
        cases["all rows x contactable"] = (D, np.arange(n), np.arange(n))
    tri, w, nv = random_contacts(V, gf.triangles, contactable, args.probes, seed=0)
    rng = np.random.default_rng(1)
    sets = np.array([rng.choice(args.probes, size=min(args.set_size, args.probes), replace=False)
                     for _ in range(args.sets)])
    Gc = contact_vectors(col_index, tri, w, nv)
    col_tree = cluster_tree(V[col_vertex], args.leaf, args.split)
    timings: dict[str, float] = {}

    def errors(W: np.ndarray, W2: np.ndarray) -> list[str]:
        st = np.abs(np.diag(W) / np.diag(W2) - 1.0)  # relative error of a contact's stiffness 1 / (g^T D g)
        fe = force_errors(W, W2, sets)
        return [f"{np.median(st):.1e}", f"{st.max():.1e}", f"{np.median(fe):.1e}", f"{fe.max():.1e}"]

    hrows, rank_rows, peel_rows, level_rows = [], [], [], []
    bins = [0, 1, 4, 8, 16, 32, 64, 10**9]
    bin_names = ["0", "1-3", "4-7", "8-15", "16-31", "32-63", ">=64"]
    for name, (A, row_vertex, row_index) in cases.items():
        row_tree = col_tree if row_vertex is col_vertex else cluster_tree(V[row_vertex], args.leaf, args.split)
        Gr = contact_vectors(row_index, tri, w, nv)
        leaves = [row_tree.nodes[i].size for i in row_tree.leaves()]
        emit(f"# {name}: cut at the {args.split}, leaf <= {args.leaf}; row tree depth {row_tree.depth}, {len(leaves)} "
             f"leaves of {min(leaves)}-{max(leaves)} vertices (mean {np.mean(leaves):.1f}); column tree depth "
             f"{col_tree.depth}, {len(col_tree.leaves())} leaves")
        for eta in etas:
            t0 = time.perf_counter()
            part = admissible_blocks(row_tree, col_tree, eta)
            res = measure(A, row_tree, col_tree, part, tols, Gr, Gc)
            timings[f"H-matrix, {name}, eta {eta:g} (all tols)"] = time.perf_counter() - t0
            for r in res:
                k = r["ranks"]
                hrows.append([name, f"{eta:g}", f"{r['tol']:g}", r["far"], r["near"], _pct(r["stored"] / r["dense"]),
                              f"{r['dense'] / r['stored']:.1f}", _pct(r["near_stored"] / r["stored"]),
                              f"{r['frob']:.1e}", f"{np.max(r['col_err']):.1e}", *errors(r["W"], r["W_H"])])
                hist = np.histogram(k, bins=bins)[0]
                kk = k if k.size else np.zeros(1, dtype=int)
                rank_rows.append([name, f"{eta:g}", f"{r['tol']:g}", int(kk.min()), int(np.median(kk)),
                                  int(np.percentile(kk, 90)), int(kk.max()), *map(int, hist)])
                pe = peeling_solves(row_tree, col_tree, part, k, args.oversampling)
                peel_rows.append([name, f"{eta:g}", f"{r['tol']:g}", len(pe["levels"]),
                                  max((lv[2] for lv in pe["levels"]), default=0),
                                  max((lv[4] for lv in pe["levels"]), default=0), pe["far_solves"], pe["near_colours"],
                                  pe["near_solves"], pe["total"], 3 * c, f"{pe['total'] / (3 * c):.2f}"])
                if name.startswith("contactable"):
                    for lv in pe["levels"]:
                        level_rows.append([f"{eta:g}", f"{r['tol']:g}", *lv])

    emit("", "## 1. H-matrix compression (far blocks: truncated SVD to tol in each block's Frobenius norm)", "",
         "stored = numbers kept / dense numbers [%]; ratio = dense / kept; near = share of the kept numbers in dense "
         "blocks [%]; frob = ||D - H||_F / ||D||_F; col max = max over columns of ||(D - H) e_j|| / ||D e_j||; "
         f"stiffness = |(1/g^T H g) / (1/g^T D g) - 1| over {args.probes} random point contacts (normal, uniform on "
         f"contactable triangles); forces = ||f_H - f|| / ||f|| of {args.sets} random sets of {args.set_size} of them "
         "pressed to one depth (G^T D G f = 1)", "")
    emit(*_table(["rows x columns", "eta", "tol", "far blocks", "near blocks", "stored %", "ratio", "near %",
                  "frob", "col max", "stiffness median", "stiffness max", "forces median", "forces max"], hrows))
    emit("", "### Ranks of the far blocks (3 dofs per vertex)", "")
    emit(*_table(["rows x columns", "eta", "tol", "min", "median", "p90", "max", *[f"#{b}" for b in bin_names]],
                 rank_rows))
    emit("", f"## 2. Solves to build it by peeling (Lin, Lu & Ying 2011), estimated from the ranks (p = "
         f"{args.oversampling})", "",
         "per level: (k_max + p) random loads per group of column clusters (range pass) and per group of row "
         "clusters (co-range pass), a group's clusters meeting no common cluster at that level; near field: unit "
         "loads on all vertices of a colour, vertices of one colour meeting no common row cluster in the near blocks, "
         "3 x colours; dense = 3 c solves", "")
    emit(*_table(["rows x columns", "eta", "tol", "levels", "max groups", "max k", "far solves", "near colours",
                  "near solves", "total", "dense", "total / dense"], peel_rows))
    emit("", "### Per level (contactable x contactable)", "")
    emit(*_table(["eta", "tol", "level", "far blocks", "column groups", "row groups", "k_max", "solves"], level_rows))

    t0 = time.perf_counter()
    cp = V[col_vertex]
    sep_rows = []
    Gr = contact_vectors(np.arange(n), tri, w, nv)
    W = Gr.T @ (D @ Gc)
    for sh in seps:
        s = sh * args.pad
        r = s / 2
        col = colouring(cp, s)
        k = int(col.max()) + 1
        pe = probe_error(D, V, cp, col, r)
        cont, beyond = pe["contamination"], pe["beyond"]
        Wt = coloured_forms(D, V, col_index, V, col, r, Gr, tri, w, nv)
        sep_rows.append([f"{sh:g} h = {s * 1e3:g}", f"{r * 1e3:g}", k, colour_lower_bound(cp, s), 3 * k,
                         f"{k / c:.3f}", _pct(np.median(cont)), _pct(np.percentile(cont, 90)), _pct(cont.max()),
                         _pct(np.median(beyond)), _pct(beyond.max()), *errors(W, Wt)])
    timings["coloured loads (all separations)"] = time.perf_counter() - t0
    emit("", f"## 3. Several well-separated unit loads per solve (h = pad thickness = {args.pad * 1e3:g} mm)", "",
         "colours: greedy, same colour >= s apart (Euclidean); bound: most vertices within s/2 of one vertex (every "
         "colouring needs as many); solves = 3 x colours; contamination = ||S_c[R] - D[R, j]|| / ||D[R, j]|| over "
         "the rows R within r = s/2 of column j's vertex (S_c: its colour's summed columns) [%]; beyond r = "
         "||D[~R, j]|| / ||D[:, j]|| [%]; stiffness, forces: as in 1 for the near-field model D~ (colour sums within "
         "r, zero beyond)", "")
    emit(*_table(["s [mm]", "r [mm]", "colours", "bound", "solves", "solves / dense", "contamination median",
                  "p90", "max", "beyond r median", "beyond r max", "stiffness median", "stiffness max",
                  "forces median", "forces max"], sep_rows))
    emit("", "## Run time (one BLAS thread)", "")
    emit(*_table(["part", "s"], [[k, f"{v:.1f}"] for k, v in timings.items()]
                 + [["total (with loading the bundle)", f"{time.perf_counter() - t_start:.1f}"]]))


if __name__ == "__main__":
    main()
