"""Compressing D while it is solved: the H-matrix from column blocks as they come, D never held whole.

:func:`hailstorm.precompute.hmatrix.compress` reads a finished D one column cluster at a
time, so the dense D must first exist (on disk: 15 GiB for the 13 000 contactable
vertices of the seat at 1.2 mm, P1). :class:`StreamedH` takes the same partition and
is fed D's column blocks instead, in any order, each block once:

* the columns are solved in the column tree's order (:func:`tree_order`), so a
  block touches few column clusters, each over a contiguous range;
* a near block keeps its columns as they come (dense, exact);
* a far block ``B`` keeps a truncated SVD ``U diag(s) V^T`` of the columns seen so
  far and adds each new set ``C`` by Brand's update (Linear Algebra Appl. 415 (2006)
  20): ``[U Q] [[diag(s), U^T C], [0, R]] [V E]^T`` with ``Q R`` the part of ``C``
  outside ``U``, re-factored and truncated (``C`` itself factored first, by a randomized
  range finder when it is tall: :func:`_factor`). Each update drops at most ``tol_b / u``
  of the block's norm so far (``u`` the updates the block will get, known from the
  block layout), so the sum stays within ``tol_b ||B||_F``; the end truncates once
  more within what is left of that budget;
* a few exact columns, drawn at random before the solve, are kept to measure the
  result's column error (:meth:`StreamedH.errors`);
* its whole state can be written to a checkpoint file and read back
  (:meth:`StreamedH.save`, :meth:`StreamedH.resume`), so an interrupted solve goes on
  from the blocks it had, and ends with the numbers an uninterrupted one gives.

Memory: the H-matrix's own numbers, the factors of the blocks being updated and one
block of D. The truncation is the same per-block Frobenius rule as ``compress``'s,
reached by another path, so the two H-matrices differ within the tolerance.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from hailstorm.precompute.hmatrix import low_rank, svd
from hailstorm.precompute.htree import ClusterTree, Partition, block_slices, dofs
from hailstorm.runtime.bundle.atomic import replacing
from hailstorm.runtime.bundle.format import RoundedBlock
from hailstorm.runtime.bundle.hmatrix import HMatrix

__all__ = ["CHECKPOINT_VERSION", "StreamedH", "streamed_key", "tree_order"]

#: the layout of :meth:`StreamedH.save`'s file (a checkpoint of another layout is not resumed)
CHECKPOINT_VERSION = 1


def streamed_key(key: str, tol: float) -> str:
    """The cache key of the streamed H-matrix, at ``tol``, of the dense bundle of key ``key`` (its own:
    the same target as :func:`hailstorm.precompute.hmatrix.compressed_key`'s, other numbers)."""
    return hashlib.sha256(f"{key}\0hmatrix stream tol {float(tol)!r}".encode()).hexdigest()


def tree_order(problem: Any, cols: ClusterTree) -> Any:
    """``problem`` (a :class:`hailstorm.precompute.greens.ColumnProblem`) with its columns in the
    order of the column tree ``cols`` (its dofs, :func:`~hailstorm.precompute.htree.dofs`): column
    ``j`` of the result is column ``dofs(cols.perm)[j]`` of D."""
    cd = dofs(cols.perm)
    if problem.loads is not None:
        return dataclasses.replace(problem, loads=problem.loads[:, cd].tocsc())
    return dataclasses.replace(problem, load_pos=np.asarray(problem.load_pos)[cd])


def _factor(C: np.ndarray, budget: float, cc: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """``X, Vc`` (``Vc`` orthonormal) with ``||C - X Vc^T||_F <= budget``; ``cc = ||C||_F^2``.

    A tall ``C`` (the far blocks' new columns: rows of a whole cluster, a block's few columns)
    by a randomized range finder whose sample doubles until it misses at most half the
    budget, then the SVD of ``Q^T C`` within the rest (cost ``m q k``, not the ``m q^2`` of
    an SVD of ``C``); a wide or small one by :func:`~hailstorm.precompute.hmatrix.low_rank`."""
    m, q = C.shape
    if not cc > 0:
        return C[:, :0], np.zeros((q, 0))
    if m < 4 * q or q < 16:
        return low_rank(C, budget / np.sqrt(cc), rng)
    ell = 16
    while True:
        Q, _ = np.linalg.qr(C @ rng.standard_normal((q, ell)))
        B = Q.T @ C
        missed = max(cc - float(np.einsum("ij,ij->", B, B)), 0.0)
        if missed <= 0.25 * budget * budget or 2 * ell >= q:
            break
        ell *= 2
    if missed > 0.25 * budget * budget:  # the sample reached the width: the exact SVD
        return low_rank(C, budget / np.sqrt(cc), rng)
    Ub, sb, Vbt = svd(B)
    k = _truncate(sb, np.sqrt(max(budget * budget - missed, 0.0)))
    return Q @ (Ub[:, :k] * sb[:k]), Vbt[:k].T


def _truncate(s: np.ndarray, budget: float) -> int:
    """Smallest rank whose dropped tail ``||s[k:]||`` is at most ``budget`` (>= 0)."""
    tail = np.sqrt(np.concatenate([np.cumsum((s * s)[::-1])[::-1], [0.0]]))
    return int(np.argmax(tail <= budget))


def _write_concatenated(f, parts: list[np.ndarray]) -> None:
    """Write to the open file ``f`` an ``.npy`` float64 vector that is the concatenation of ``parts``,
    each flattened in Fortran order, without building it (one part's copy at most)."""
    total = sum(int(x.size) for x in parts)
    np.lib.format.write_array_header_2_0(f, {"descr": np.lib.format.dtype_to_descr(np.dtype(np.float64)),
                                             "fortran_order": False, "shape": (total,)})
    for x in parts:
        f.write(np.asarray(x, dtype=np.float64).ravel(order="F").data)


@dataclasses.dataclass
class _Far:
    """A far block's state: ``U diag(s) V^T`` of the columns seen, the updates left, what was dropped."""

    U: np.ndarray
    s: np.ndarray
    V: np.ndarray
    updates: int
    norm2: float = 0.0
    dropped: float = 0.0


class StreamedH:
    """The H-matrix of D on a block partition, built from D's column blocks in any order.

    Parameters
    ----------
    rows, cols : ClusterTree
        Rows over every surface vertex, columns over the contactable ones (D's vertex-major dofs).
    part : Partition
        :func:`hailstorm.precompute.htree.admissible_blocks` of ``rows``, ``cols``.
    tol : float
        Each far block ``B`` ends within ``tol ||B||_F`` of itself (as ``compress``'s).
    blocks : sequence of (int, int)
        The column ranges (tree order) the solve will deliver, each once.
    keep : (k,) int array_like
        Columns of D (its own order) to keep exactly, for :attr:`kept`.

    Attributes
    ----------
    kept : dict of int to ndarray
        D's column ``j`` (all rows) for each ``j`` of ``keep`` delivered so far.
    """

    def __init__(self, rows: ClusterTree, cols: ClusterTree, part: Partition, tol: float,
                 blocks: Any, keep: Any = ()) -> None:
        if not tol >= 0:
            raise ValueError(f"tol must be >= 0, got {tol}")
        self.tol = float(tol)
        self.rd, self.cd = dofs(rows.perm), dofs(cols.perm)
        self.shape = (self.rd.size, self.cd.size)
        far = [block_slices(rows, cols, i, j) for i, j, _ in part.far]
        near = [block_slices(rows, cols, i, j) for i, j, _ in part.near]
        self.ranges = np.array([(r.start, r.stop, c.start, c.stop) for r, c in far + near], dtype=np.int64)
        self.n_far = len(far)
        starts = np.array([b[0] for b in blocks], dtype=np.int64)
        stops = np.array([b[1] for b in blocks], dtype=np.int64)
        self._far: dict[int, _Far] = {}
        for b in range(self.n_far):
            r0, r1, c0, c1 = self.ranges[b]
            u = int(np.count_nonzero((starts < c1) & (stops > c0)))
            self._far[b] = _Far(np.zeros((r1 - r0, 0)), np.zeros(0), np.zeros((c1 - c0, 0)), max(u, 1))
        self._near: dict[int, np.ndarray] = {}
        pos = np.empty(self.shape[1], dtype=np.int64)
        pos[self.cd] = np.arange(self.shape[1])
        self._keep = {int(pos[j]): int(j) for j in np.asarray(keep, dtype=np.int64).ravel()}
        self.kept: dict[int, np.ndarray] = {}
        self.columns_seen = 0
        self._rng = np.random.default_rng(0)
        #: the starts of the column ranges added so far (what a checkpoint holds)
        self.starts: list[int] = []
        self._busy = False  # within add(): the state is mid-update (not saved)

    def add(self, start: int, values: np.ndarray | RoundedBlock) -> None:
        """Columns ``start:start + k`` (tree order) of D, ``values`` (n_rows, k) in D's row order."""
        if isinstance(values, RoundedBlock):
            values = values.values
        values = np.asarray(values, dtype=np.float64)
        if values.ndim != 2 or values.shape[0] != self.shape[0]:
            raise ValueError(f"a block of D has {self.shape[0]} rows, got shape {values.shape}")
        self._busy = True
        self._add(start, values)
        self.starts.append(int(start))
        self._busy = False

    def _add(self, start: int, values: np.ndarray) -> None:
        stop = start + values.shape[1]
        for p in range(start, stop):
            if p in self._keep:
                self.kept[self._keep[p]] = values[:, p - start].copy()
        T = values[self.rd]  # rows in tree order: each block's rows are a contiguous range
        hit = np.flatnonzero((self.ranges[:, 2] < stop) & (self.ranges[:, 3] > start))
        for b in hit.tolist():
            r0, r1, c0, c1 = (int(x) for x in self.ranges[b])
            a0, a1 = max(c0, start), min(c1, stop)
            C = T[r0:r1, a0 - start:a1 - start]
            if b < self.n_far:
                self._update(self._far[b], C, np.arange(a0 - c0, a1 - c0))
            else:
                dense = self._near.get(b)
                if dense is None:
                    dense = self._near[b] = np.zeros((r1 - r0, c1 - c0), order="F")
                dense[:, a0 - c0:a1 - c0] = C
        self.columns_seen += stop - start

    def _update(self, f: _Far, C: np.ndarray, idx: np.ndarray) -> None:
        """Brand's update of ``f`` with the columns ``C`` at its local positions ``idx``.

        ``C`` is first factored as ``X Vc^T`` (:func:`_factor`, half this update's budget), so a
        tall block costs ``m q k``, not ``m q^2``; with ``V`` zero on the
        new positions ``[V, E Vc]`` is orthonormal and the core is ``[[diag(s), U^T X], [0, R]]``,
        ``Q R = X - U U^T X``."""
        cc = float(np.einsum("ij,ij->", C, C))
        f.norm2 += cc
        budget = self.tol / f.updates * np.sqrt(f.norm2)
        X, Vc = _factor(C, 0.5 * budget, cc, self._rng)
        f.dropped += 0.5 * budget
        r, kc = f.s.size, X.shape[1]
        P = f.U.T @ X
        Rm = X - f.U @ P
        P2 = f.U.T @ Rm  # once more (and into P): keeps [U Q] orthonormal to rounding, X = U P + Rm exact
        Rm -= f.U @ P2
        P += P2
        Q, Rq = np.linalg.qr(Rm)
        K = np.zeros((r + Q.shape[1], r + kc))
        K[:r, :r] = np.diag(f.s)
        K[:r, r:] = P
        K[r:, r:] = Rq
        Uk, sk, Vkt = svd(K)
        k = _truncate(sk, 0.5 * budget)
        f.dropped += float(np.sqrt(np.sum(sk[k:] ** 2)))
        Vk = Vkt[:k].T
        V = f.V @ Vk[:r]
        V[idx] += Vc @ Vk[r:]
        f.U = np.hstack([f.U, Q]) @ Uk[:, :k]
        f.s = sk[:k]
        f.V = V

    def save(self, path: str | os.PathLike, tag: dict) -> bool:
        """Write the state to ``path`` (one ``.npz``, replaced atomically and synced to disk).

        ``tag`` (JSON: the solve's key, tolerance, blocks, ...) is stored with it; :meth:`resume`
        reads the state back only under an equal tag. Returns False, writing nothing, while an
        :meth:`add` is under way (an interruption inside it: the state is half-updated).
        """
        if self._busy:
            return False
        far = [self._far[b] for b in range(self.n_far)]
        near = sorted(self._near)
        kept = sorted(self.kept)
        # the blocks' numbers go to disk piece by piece: a concatenation would hold a second H at once
        pieces = {
            "far_data": [x for f in far for x in (f.U, f.s, f.V)],
            "near_data": [self._near[b] for b in near],
        }
        arrays = {
            "meta": np.array(json.dumps({"version": CHECKPOINT_VERSION, "tag": tag, "shape": list(self.shape),
                                         "tol": self.tol, "columns_seen": self.columns_seen,
                                         "rng": self._rng.bit_generator.state})),
            "starts": np.asarray(self.starts, dtype=np.int64),
            "far_rank": np.array([f.s.size for f in far], dtype=np.int64),
            "far_updates": np.array([f.updates for f in far], dtype=np.int64),
            "far_norms": np.array([(f.norm2, f.dropped) for f in far], dtype=np.float64).reshape(-1, 2),
            "near_ids": np.asarray(near, dtype=np.int64),
            "kept_ids": np.asarray(kept, dtype=np.int64),
            "kept_data": np.array([self.kept[j] for j in kept], dtype=np.float64).reshape(len(kept), self.shape[0]),
        }
        path = Path(path)
        with replacing(path) as tmp, open(tmp, "wb") as fh:
            with zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED, allowZip64=True) as z:  # np.savez's layout
                for name, x in arrays.items():
                    with z.open(f"{name}.npy", "w", force_zip64=True) as f:
                        np.lib.format.write_array(f, np.asanyarray(x), allow_pickle=False)
                for name, parts in pieces.items():
                    with z.open(f"{name}.npy", "w", force_zip64=True) as f:
                        _write_concatenated(f, parts)
            fh.flush()
            os.fsync(fh.fileno())
        return True

    def resume(self, path: str | os.PathLike, tag: dict) -> bool:
        """Take the state :meth:`save` wrote to ``path`` under an equal ``tag``; True if it did.

        Nothing changes (False) when there is no such file, or it is unreadable, of another
        layout, or for other inputs (``tag``, shape, tolerance or block partition differ);
        the caller then starts afresh. Must be called before any :meth:`add`.
        """
        if self.starts:
            raise RuntimeError("resume() before any add()")
        try:
            with np.load(path, allow_pickle=False) as z:
                a = {k: z[k] for k in z.files}
            meta = json.loads(str(a["meta"]))
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
            return False
        try:
            return self._restore(a, meta, tag)
        except (KeyError, ValueError, IndexError, TypeError):  # a damaged file: nothing taken
            return False

    def _restore(self, a: dict[str, np.ndarray], meta: dict, tag: dict) -> bool:
        """:meth:`resume`'s work on the file's arrays ``a`` and its ``meta``."""
        if (meta.get("version") != CHECKPOINT_VERSION or meta.get("tag") != json.loads(json.dumps(tag))
                or meta.get("shape") != list(self.shape) or meta.get("tol") != self.tol
                or a["far_rank"].size != self.n_far or a["far_updates"].tolist() != [self._far[b].updates
                                                                                   for b in range(self.n_far)]):
            return False
        far: dict[int, _Far] = {}
        data, o = a["far_data"], 0
        for b in range(self.n_far):
            r0, r1, c0, c1 = (int(x) for x in self.ranges[b])
            m, n, k = r1 - r0, c1 - c0, int(a["far_rank"][b])
            U = data[o:o + m * k].reshape(m, k, order="F")
            s = data[o + m * k:o + m * k + k]
            V = data[o + m * k + k:o + (m + n + 1) * k].reshape(n, k, order="F")
            o += (m + n + 1) * k
            far[b] = _Far(U.copy(), s.copy(), V.copy(), int(a["far_updates"][b]), *map(float, a["far_norms"][b]))
        if o != data.size:
            return False
        near: dict[int, np.ndarray] = {}
        data, o = a["near_data"], 0
        for b in a["near_ids"].tolist():
            r0, r1, c0, c1 = (int(x) for x in self.ranges[b])
            near[b] = data[o:o + (r1 - r0) * (c1 - c0)].reshape(r1 - r0, c1 - c0, order="F").copy()
            o += (r1 - r0) * (c1 - c0)
        if o != data.size:
            return False
        self._far, self._near = far, near
        self.kept = {int(j): a["kept_data"][i].copy() for i, j in enumerate(a["kept_ids"].tolist())}
        self.starts = [int(x) for x in a["starts"]]
        self.columns_seen = int(meta["columns_seen"])
        self._rng.bit_generator.state = meta["rng"]
        return True

    def errors(self, H: HMatrix) -> tuple[np.ndarray, np.ndarray]:
        """The kept columns (D's order, sorted) and ``||H e_j - D e_j|| / ||D e_j||`` for each."""
        cols = np.array(sorted(self.kept), dtype=np.int64)
        if cols.size == 0:
            return cols, np.zeros(0)
        exact = np.column_stack([self.kept[j] for j in cols.tolist()])
        diff = np.linalg.norm(H.columns(cols) - exact, axis=0)
        norm = np.linalg.norm(exact, axis=0)
        return cols, np.where(norm > 0, diff / np.where(norm > 0, norm, 1.0), 0.0)

    def finish(self) -> HMatrix:
        """The H-matrix (far blocks factored as ``X V^T``, ``X = U s``; a far block whose factors would
        hold more numbers than itself dense; near blocks dense), in ``compress``'s layout.

        Raises
        ------
        ValueError
            Not every column was delivered.
        """
        if self.columns_seen != self.shape[1]:
            raise ValueError(f"{self.columns_seen} of D's {self.shape[1]} columns were delivered")
        # the layout first (factored far blocks, then the dense ones: far before near), then the numbers
        # into one array block by block, each block's state freed as it is copied: H is held once
        plan: list[tuple[int, int]] = []  # (block, rank k; -1: dense)
        dense: list[int] = []
        for b in range(self.n_far):
            f = self._far[b]
            k = _truncate(f.s, max(self.tol * np.sqrt(f.norm2) - f.dropped, 0.0))
            m, n = f.U.shape[0], f.V.shape[0]
            if k * (m + n) < m * n:
                plan.append((b, k))
            else:
                dense.append(b)
                self._far[b] = dataclasses.replace(f, U=f.U[:, :k], s=f.s[:k], V=f.V[:, :k])
        plan += [(b, -1) for b in dense] + [(b, -1) for b in range(self.n_far, len(self.ranges))]
        sizes = []
        for b, k in plan:
            r0, r1, c0, c1 = (int(x) for x in self.ranges[b])
            sizes.append(k * (r1 - r0 + c1 - c0) if k >= 0 else (r1 - r0) * (c1 - c0))
        starts = np.concatenate([[0], np.cumsum(sizes, dtype=np.int64)])
        data = np.empty(int(starts[-1]))
        table = []
        for (b, k), o in zip(plan, starts[:-1].tolist()):
            r0, r1, c0, c1 = (int(x) for x in self.ranges[b])
            m, n = r1 - r0, c1 - c0
            table.append((r0, r1, c0, c1, k, o))
            if b >= self.n_far:
                data[o:o + m * n] = self._near.pop(b).ravel(order="F")
                continue
            f = self._far[b]
            if k >= 0:  # factored: X = U s, then V
                data[o:o + m * k] = (f.U[:, :k] * f.s[:k]).ravel(order="F")
                data[o + m * k:o + k * (m + n)] = f.V[:, :k].ravel(order="F")
            else:  # a far block stored dense (its factors truncated above)
                data[o:o + m * n].reshape((m, n), order="F")[...] = (f.U * f.s) @ f.V.T
            self._far[b] = _Far(np.zeros((0, 0)), np.zeros(0), np.zeros((0, 0)), 1)  # free as we go
        return HMatrix(self.shape, self.rd.astype(np.int64), self.cd.astype(np.int64),
                       np.asarray(table, dtype=np.int64).reshape(-1, 6), data)
