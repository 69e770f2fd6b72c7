"""Compressing the compliance: the H-matrix of a bundle's D.

The construction side of :mod:`hailstorm.runtime.bundle.hmatrix` (which stores and
evaluates the result), on the cluster trees and the admissible block partition of
:mod:`hailstorm.precompute.htree`
(:func:`~hailstorm.precompute.htree.cluster_tree`,
:func:`~hailstorm.precompute.htree.admissible_blocks`):

* :func:`compress` -- a matrix on that partition: far blocks truncated by SVD to
  a relative Frobenius tolerance per block (kept dense where the factors would
  be larger), near blocks dense;
* :func:`compress_compliance` -- the H-matrix of a bundle's D (rows: every
  surface vertex, columns: the contactable ones) at a target column error,
  measured on exact columns drawn at random (:func:`column_errors`);
* :func:`compress_bundle` -- a compressed copy of a dense bundle (format 3).

Its source is the dense D, read block by block (a memory-mapped bundle's D is
read once per far and near block, never whole): the construction saves the
stored bytes (:doc:`scale`), not the solves.
"""

from __future__ import annotations

import hashlib
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hailstorm.precompute.htree import ClusterTree, Partition, admissible_blocks, block_slices, cluster_tree, dofs
from hailstorm.runtime.bundle.format import ARRAY_SPECS, MANIFEST_HASH, BundleError
from hailstorm.runtime.bundle.hmatrix import HMatrix
from hailstorm.runtime.bundle.read import GreensFunctions, load
from hailstorm.runtime.bundle.write import check_writable, write_bundle

__all__ = [
    "DEFAULT_ETA",
    "DEFAULT_LEAF",
    "ERROR_COLUMNS",
    "TOL_RANGE",
    "Compressed",
    "check_tol",
    "compliance_record",
    "column_errors",
    "compress",
    "compress_bundle",
    "compress_compliance",
    "compressed_key",
    "svd",
    "low_rank",
    "truncation_rank",
]

log = logging.getLogger("hailstorm.precompute")

#: admissibility of the stored H-matrix: 4.9-14.5x fewer numbers than D on the seat at 6-3 mm
#: at tol 1e-2, columns within 0.3-1.0 % (docs/_generated/compression_*.txt)
DEFAULT_ETA = 2.0
#: vertices per leaf cluster (96 dofs): the near blocks stay small, the tree shallow
DEFAULT_LEAF = 32
#: exact columns drawn at random to measure a compressed D's error (all of them when fewer)
ERROR_COLUMNS = 200
#: the target column errors --tol accepts: below 1e-12 rounding is the error, above 0.1 a
#: contact's stiffness is no longer the one the seat has
TOL_RANGE = (1e-12, 0.1)
#: whole columns of D read at a time into a column cluster's slab
SLAB_COLUMNS = 256
#: halvings of the per-block truncation when the measured column error misses the target
RETRIES = 4


def svd(B: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Thin SVD ``U, s, Vt`` of ``B`` (LAPACK's gesdd, gesvd where it does not converge)."""
    import scipy.linalg

    try:
        return scipy.linalg.svd(B, full_matrices=False, lapack_driver="gesdd", check_finite=False)
    except np.linalg.LinAlgError:  # gesdd can fail to converge; gesvd is slower and sturdier
        return scipy.linalg.svd(B, full_matrices=False, lapack_driver="gesvd", check_finite=False)


def truncation_rank(s: np.ndarray, tol: float) -> int:
    """Smallest k with ``||s[k:]|| <= tol * ||s||`` (sum of the tail's squares from the small end)."""
    tail = np.concatenate([np.cumsum((s * s)[::-1])[::-1], [0.0]])
    return int(np.argmax(tail <= tol * tol * tail[0]))


#: blocks with both sides above this many rows are factored by a randomized range finder
#: (cost ~ m n k) rather than a full SVD (~ m n min(m, n)); at tol below RANDOMIZED_MIN_TOL the
#: error test ||B||^2 - ||Q^T B||^2 would cancel, and the full SVD is used
RANDOMIZED_MIN_SIDE = 192
RANDOMIZED_MIN_TOL = 1e-6


def low_rank(B: np.ndarray, tol: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Factors ``X, V`` (``X = U s``) of the smallest rank with ``||B - X V^T||_F <= tol ||B||_F``.

    A full SVD for small blocks and small ``tol``; otherwise a randomized range
    finder (Halko, Martinsson & Tropp, SIAM Rev. 53 (2011) 217) whose sample
    grows until the range error ``||B - Q Q^T B||_F^2 = ||B||_F^2 - ||Q^T B||_F^2``
    (exact for an orthonormal Q) is at most a quarter of the budget, then the SVD of
    ``Q^T B`` truncated within what remains: the bound holds exactly, not in
    expectation.
    """
    m, n = B.shape
    if min(m, n) < RANDOMIZED_MIN_SIDE or tol < RANDOMIZED_MIN_TOL:
        U, s, Vt = svd(B)
        k = truncation_rank(s, tol)
        return U[:, :k] * s[:k], Vt[:k].T
    total = float(np.einsum("ij,ij->", B, B))
    budget = tol * tol * total
    ell = 24
    while True:
        Q, _ = np.linalg.qr(B @ rng.standard_normal((n, ell)))
        C = Q.T @ B
        missed = max(total - float(np.einsum("ij,ij->", C, C)), 0.0)
        if missed <= budget / 4 or 2 * ell >= min(m, n):
            break
        ell *= 2
    if missed > budget / 4:  # the sample reached the block's size: the exact SVD
        U, s, Vt = svd(B)
        k = truncation_rank(s, tol)
        return U[:, :k] * s[:k], Vt[:k].T
    Uc, s, Vt = svd(C)
    tail = np.concatenate([np.cumsum((s * s)[::-1])[::-1], [0.0]])
    k = int(np.argmax(tail <= budget - missed))
    return Q @ (Uc[:, :k] * s[:k]), Vt[:k].T


# --------------------------------------------------------------------------
# compression
# --------------------------------------------------------------------------
def _bar(total: int, desc: str, show: bool) -> Any:
    """A tqdm bar over ``total`` steps on stderr, or a stand-in that counts nothing."""
    if show:
        from tqdm.auto import tqdm

        return tqdm(total=total, desc=desc, unit="block", leave=False)

    class _Quiet:
        def update(self, n: int = 1) -> None:
            pass

        def close(self) -> None:
            pass

    return _Quiet()


def compress(A: Any, rows: ClusterTree, cols: ClusterTree, part: Partition, tol: float, *,
             progress: bool = False) -> HMatrix:
    """Compress ``A`` on the partition ``part``: far blocks by truncated SVD, near blocks dense.

    Parameters
    ----------
    A : array_like, shape (3 n_rows, 3 n_cols)
        Vertex-major in the points of ``rows`` and ``cols`` (entry ``(3i+a, 3j+b)``);
        read one column cluster at a time, the rows its blocks span (a memory-mapped
        array is never read whole at once).
    rows, cols : ClusterTree
    part : Partition
        From :func:`admissible_blocks` on ``rows``, ``cols``.
    tol : float
        Each far block ``B`` is truncated to the smallest rank with
        ``||B - B_k||_F <= tol ||B||_F``, so ``||A - H||_F <= tol ||A||_F``
        (``tol = 0``: exact to rounding). A far block whose factors would hold
        more numbers than itself is kept dense (and exact).
    progress : bool
        A progress bar over the blocks.

    Returns
    -------
    HMatrix
        Its far (factored) blocks first, in ``part.far`` order, then the dense ones.
    """
    if not tol >= 0:
        raise ValueError(f"tol must be >= 0, got {tol}")
    rd, cd = dofs(rows.perm), dofs(cols.perm)
    table: list[tuple[int, ...]] = []
    chunks: list[np.ndarray] = []
    offset = 0

    def put(r: slice, c: slice, k: int, *arrays: np.ndarray) -> None:
        nonlocal offset
        table.append((r.start, r.stop, c.start, c.stop, k, offset))
        for x in arrays:
            chunks.append(np.asarray(x, dtype=np.float64).ravel(order="F"))
            offset += x.size

    rng = np.random.default_rng(0)
    far = [block_slices(rows, cols, i, j) for i, j, _ in part.far]
    near = [block_slices(rows, cols, i, j) for i, j, _ in part.near]

    def tag(rc: tuple[slice, slice]) -> tuple[int, int, int, int]:
        return rc[0].start, rc[0].stop, rc[1].start, rc[1].stop

    is_far = {tag(rc) for rc in far}
    by_cluster: dict[tuple[int, int], list[slice]] = {}
    for r, c in far + near:
        by_cluster.setdefault((c.start, c.stop), []).append(r)
    factors: dict[tuple[int, int, int, int], tuple[np.ndarray, np.ndarray]] = {}
    exact: dict[tuple[int, int, int, int], np.ndarray] = {}
    bar = _bar(len(far) + len(near), "compressing D", progress)
    for (c0, c1), row_ranges in sorted(by_cluster.items()):
        # the column cluster's blocks from one slab of A: its rows spanned by those blocks (tree order),
        # read SLAB_COLUMNS whole columns at a time (what a column-major, memory-mapped D reads fast)
        lo, hi = min(r.start for r in row_ranges), max(r.stop for r in row_ranges)
        slab = np.empty((hi - lo, c1 - c0))
        for j in range(c0, c1, SLAB_COLUMNS):
            k = min(j + SLAB_COLUMNS, c1)
            slab[:, j - c0:k - c0] = np.asarray(A[:, cd[j:k]], dtype=np.float64)[rd[lo:hi]]
        for r in row_ranges:
            c = slice(c0, c1)
            B = slab[r.start - lo:r.stop - lo]
            t = tag((r, c))
            bar.update()
            if t in is_far:
                X, V = low_rank(B, tol, rng)
                if X.shape[1] * (B.shape[0] + B.shape[1]) < B.size:
                    factors[t] = (X, V)
                    continue
            exact[t] = B.ravel(order="F")  # the copy put() stores as it is (column-major)
        del slab
    bar.close()
    for r, c in far:  # factored far blocks first, in the partition's order
        if tag((r, c)) in factors:
            X, V = factors[tag((r, c))]
            put(r, c, X.shape[1], X, V)
    for r, c in far + near:
        if tag((r, c)) in exact:
            put(r, c, -1, exact[tag((r, c))])
    data = np.concatenate(chunks) if chunks else np.zeros(0)
    return HMatrix((int(np.shape(A)[0]), int(np.shape(A)[1])), rd.astype(np.int64), cd.astype(np.int64),
                   np.asarray(table, dtype=np.int64).reshape(-1, 6), data)


def column_errors(H: HMatrix, D: Any, cols: np.ndarray) -> np.ndarray:
    """``||H e_j - D e_j|| / ||D e_j||`` for the columns ``cols`` of the exact ``D`` (0 for a zero column)."""
    cols = np.asarray(cols, dtype=np.intp)
    exact = np.asarray(D[:, cols], dtype=np.float64)
    diff = np.linalg.norm(H.columns(cols) - exact, axis=0)
    norm = np.linalg.norm(exact, axis=0)
    return np.where(norm > 0, diff / np.where(norm > 0, norm, 1.0), 0.0)


def check_tol(tol: float) -> float:
    """``tol`` as a float, or ValueError unless it is a target column error in :data:`TOL_RANGE`."""
    lo, hi = TOL_RANGE
    if isinstance(tol, bool) or not isinstance(tol, (int, float, np.floating)) or not np.isfinite(tol) \
            or not lo <= tol <= hi:
        raise ValueError(f"the compression tolerance must be a relative column error in [{lo:g}, {hi:g}], "
                         f"got {tol!r}")
    return float(tol)


@dataclass(frozen=True)
class Compressed:
    """A compressed compliance and what it cost (:func:`compress_compliance`).

    Attributes
    ----------
    H : HMatrix
    tol : float
        The target column error.
    block_tol : float
        The per-block truncation that met it.
    error : dict
        ``columns`` (how many exact columns were compared), ``max`` and ``median``
        relative column error, ``seed``.
    seconds : float
        Wall time of the compression and the error measurement.
    """

    H: HMatrix
    tol: float
    block_tol: float
    error: dict[str, Any] = field(default_factory=dict)
    seconds: float = 0.0


def compress_compliance(gf: GreensFunctions, tol: float, *, eta: float = DEFAULT_ETA, leaf: int = DEFAULT_LEAF,
                        columns: int = ERROR_COLUMNS, seed: int = 0, progress: bool = False) -> Compressed:
    """The H-matrix of a bundle's D whose columns sampled are within ``tol`` of D's.

    Rows are clustered over every surface vertex, columns over the contactable
    ones (:func:`cluster_tree`, :func:`admissible_blocks`); the far blocks are
    truncated to ``tol`` each (:func:`compress`) and the result's error is
    measured on ``columns`` exact columns of D drawn at random (all of D's when it
    has fewer). Where that error exceeds ``tol`` the truncation is halved (at
    most :data:`RETRIES` times).

    Raises
    ------
    ValueError
        ``tol`` is outside :data:`TOL_RANGE`, or unreachable: the message names
        the error reached.
    """
    tol = check_tol(tol)
    t0 = time.perf_counter()
    D = gf.D
    cv = gf.contact_vertices  # column block -> vertex
    V = np.asarray(gf.vertices, dtype=np.float64)
    rows, cols = cluster_tree(V, leaf=leaf), cluster_tree(V[cv], leaf=leaf)
    part = admissible_blocks(rows, cols, eta)
    rng = np.random.default_rng(seed)
    n = D.shape[1]
    picked = np.sort(rng.choice(n, size=min(columns, n), replace=False))
    block_tol = tol
    for _ in range(RETRIES + 1):
        H = compress(D, rows, cols, part, block_tol, progress=progress)
        err = column_errors(H, D, picked)
        if err.max(initial=0.0) <= tol:
            break
        block_tol /= 2
    else:
        raise ValueError(f"the compression tolerance {tol:g} is unreachable for {gf.path}: the closest H-matrix "
                         f"(per-block truncation {block_tol * 2:g}) has columns off by up to {err.max():.3g}")
    error = {"columns": int(picked.size), "max": float(err.max(initial=0.0)),
             "median": float(np.median(err)) if err.size else 0.0, "seed": int(seed)}
    return Compressed(H, tol, block_tol, error, time.perf_counter() - t0)


def compliance_record(c: Compressed, **extra: Any) -> dict[str, Any]:
    """The manifest's ``compliance`` entry of a compressed D (what ``hailstorm info`` prints): the
    storage, the target and per-block tolerances, the partition's parameters, the ranks, the
    stored and the dense bytes, the measured error and the seconds, plus ``extra``."""
    H = c.H
    return {
        "storage": "hmatrix", "shape": list(H.shape), "tol": c.tol, "block_tol": c.block_tol,
        "eta": DEFAULT_ETA, "leaf": DEFAULT_LEAF, "far_blocks": int(H.ranks.size),
        "blocks": int(len(H.blocks)), "max_rank": int(H.ranks.max(initial=0)),
        "stored_bytes": int(H.data.nbytes), "dense_bytes": int(H.shape[0] * H.shape[1] * 8),
        "error": c.error, **extra, "seconds": round(c.seconds, 3),
    }


def compressed_key(key: str, tol: float) -> str:
    """The cache key of the compressed copy, at ``tol``, of the dense bundle of key ``key``."""
    return hashlib.sha256(f"{key}\0hmatrix tol {float(tol)!r}".encode()).hexdigest()


def compress_bundle(src: str | os.PathLike, out: str | os.PathLike, tol: float, *, key: str | None = None,
                    seed: int = 0, progress: bool = False) -> Path:
    """Write a compressed copy of the dense bundle ``src`` at ``out`` (format 3).

    Everything but D is copied as is; D becomes the H-matrix of
    :func:`compress_compliance`. The manifest's ``compliance`` entry records
    the storage (``"hmatrix"``), the target ``tol``, the per-block truncation,
    the admissibility and leaf size, the stored and the dense bytes, and the
    error measured against exact columns drawn at random; ``hailstorm info``
    prints them. Written like any bundle (hashed, atomic, locked).

    Parameters
    ----------
    src
        A dense (format 2) float64 bundle.
    out
        Where to write (may be ``src``: replaced atomically once the copy is complete).
    tol
        Target relative error of D's columns, met on the columns sampled (:data:`TOL_RANGE`).
    key
        The copy's cache key (default: the SHA-256 of the source's key and ``tol``).
    seed
        Of the columns drawn to measure the error.
    progress
        A progress bar over the blocks.

    Raises
    ------
    BundleError
        ``src`` is not a valid dense float64 bundle, or ``out`` cannot be written.
    ValueError
        ``tol`` is out of range or unreachable.
    """
    tol = check_tol(tol)
    out = Path(out).absolute()
    check_writable(out.parent)
    gf = load(src, verify=True)
    if gf.hmatrix is not None:
        raise BundleError(f"{gf.path} is already compressed (tol {gf.manifest['compliance']['tol']:g}); "
                          "compress its dense source")
    if gf.D.dtype != np.float64:
        raise BundleError(f"{gf.path} stores D as {gf.D.dtype}; compress a float64 bundle")
    c = compress_compliance(gf, tol, seed=seed, progress=progress)
    log.info("compressed D %d x %d to %.1f %% of its numbers (max column error %.2g over %d exact columns) in %.1f s",
             *gf.D.shape, 100 * c.H.stored / gf.D.size, c.error["max"], c.error["columns"], c.seconds)
    manifest = {k: v for k, v in gf.manifest.items() if k not in ("format", "format_version", "arrays", MANIFEST_HASH)}
    manifest["key"] = key or compressed_key(gf.manifest["key"], tol)
    manifest["compliance"] = compliance_record(c, source_key=gf.manifest["key"])
    arrays: dict[str, Any] = {k: getattr(gf, k) for k in ARRAY_SPECS if k != "compliance"}
    arrays.update(c.H.to_arrays())
    in_place = Path(gf.path).absolute() == out  # replacing its own source: nobody else's bundle
    return write_bundle(out, arrays, manifest, expect_key=gf.manifest["key"] if in_place else None)

