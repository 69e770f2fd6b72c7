"""Point contacts on the seat through the precomputed compliance (capacitance method).

Notation (see ``DESIGN.md`` and the course hint). Contact ``k`` sits on surface
triangle ``t_k`` with barycentric coordinates ``beta_k``. ``V`` is the sorted
union of the contacted triangles' vertices and

* ``D_VV`` is the ``3|V| x 3|V|`` block of the compliance ``D`` (columns of
  clamped vertices are zero: a force there goes into the support);
* ``B`` (the hint's symbol) is ``3|V| x 3s`` with block ``(i, k) = beta_{k,i} I3``;
  vertex forces are ``f_V = B f_s`` and contact-point displacements
  ``u_s = B^T u_V``;
* the *contact compliance* is ``W = B^T D_VV B`` and the *capacitance*
  (effective stiffness, the hint's ``K^beta``, DESIGN's ``K_s``) is ``K = W^-1``,
  so prescribed contact-point displacements ``ubar`` give ``f_s = K ubar``;
* the surface then moves by ``u = D[:, V] B f_s``.

Frictionless contacts constrain only the normal component: with ``N`` the
block-diagonal ``3s x s`` matrix of the unit normals, ``W_n = N^T W N`` and the
forces are ``f_s = N W_n^-1 N^T ubar``. Internally both modes are one case:
a constraint matrix ``G = B N`` (``N = I`` for sticky contacts) with
``m = 3s`` or ``m = s`` constrained components ("dofs").

Sign conventions
----------------
* ``forces`` are the forces applied **to the seat** [N] (a stone feels ``-f``).
* Normals are **outward** unit normals of the seat surface. A stone pressing
  on the seat prescribes ``ubar . n < 0`` and produces ``f . n < 0``; a contact
  with ``f . n > 0`` would *pull* (adhesion), and unilateral contact releases it.
* Displacements are in metres, positive along the coordinate axes.

Degenerate cases (documented choices)
-------------------------------------
* **Rigid contacts.** A contact whose barycentric weight lies entirely on clamped
  vertices (e.g. any point of a triangle whose three vertices are all clamped)
  cannot move: its rows and columns of ``W`` are zero. It is excluded from the
  solve (no zero block is ever inverted), flagged in ``rigid``, its reported
  force is ``0`` and its contact displacement is ``0``. Callers (the storm)
  treat rigid contacts as a hard wall; the prescribed displacement there simply
  cannot be imposed and is ignored.
* **Singular / ill-conditioned W** (coincident or nearly coincident contacts,
  more contacts on a patch than its vertices have degrees of freedom). ``W`` is
  factorised by Cholesky when its (cheap, diagonal-of-L based) condition
  estimate is below :data:`COND_LIMIT`. Otherwise ``K`` is the rank-revealing
  pseudo-inverse of ``W`` (symmetric eigendecomposition; eigenvalues below
  :data:`PINV_RCOND` times the largest are dropped). The pseudo-inverse gives
  the minimum-norm forces that best realise the prescription: coincident
  contacts share the force equally and stay finite even when they prescribe
  conflicting displacements (least-squares compromise). No Tikhonov shift is
  applied to well-conditioned systems, so the regular case is exact.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal, Sequence

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

__all__ = [
    "COND_LIMIT",
    "PINV_RCOND",
    "Capacitance",
    "ContactSolution",
    "barycentric_matrix",
    "capacitance",
    "solve_contacts",
    "triangle_normals",
]

Mode = Literal["sticky", "frictionless"]

#: Above this (lower-bound) condition estimate of W, use the pseudo-inverse.
COND_LIMIT: float = 1e10
#: Relative eigenvalue cut-off of the pseudo-inverse.
PINV_RCOND: float = 1e-10
#: Barycentric coordinates must sum to one within this and be >= -BARY_NEG_TOL.
BARY_SUM_TOL: float = 1e-6
BARY_NEG_TOL: float = 1e-9
#: Full-surface displacement: gather columns of a C-ordered D below this
#: fraction of its columns, else one gemv with the whole D (memory-bound).
GATHER_FRACTION: float = 0.12


# --------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------
def triangle_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Outward unit normals of oriented (counter-clockwise from outside) triangles.

    Parameters
    ----------
    vertices : (n, 3) float ndarray
    triangles : (k, 3) int ndarray

    Returns
    -------
    (k, 3) float ndarray
        Unit normals; zero rows for degenerate (zero-area) triangles.
    """
    p = np.asarray(vertices, dtype=np.float64)[np.asarray(triangles)]
    a = p[:, 1] - p[:, 0]
    b = p[:, 2] - p[:, 0]
    nrm = np.empty_like(a)
    nrm[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    nrm[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    nrm[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    ln = np.sqrt(np.einsum("ki,ki->k", nrm, nrm))[:, None]
    return nrm / np.where(ln > 0, ln, 1.0)


def _dof3(idx: np.ndarray) -> np.ndarray:
    """Vertex-major x, y, z dof indices of vertex (or block) indices."""
    idx = np.asarray(idx, dtype=np.intp)
    return (3 * idx[:, None] + np.arange(3)).ravel()


def _locate(triangles: np.ndarray, tri_idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """V (sorted union of the triangles' vertices) and loc (s, 3): position in V."""
    verts = np.asarray(triangles)[tri_idx]
    V, loc = np.unique(verts, return_inverse=True)
    return V.astype(np.intp), loc.reshape(verts.shape).astype(np.intp)


def _dense_B(nV: int, loc: np.ndarray, bary: np.ndarray) -> np.ndarray:
    s = loc.shape[0]
    Bs = np.zeros((nV, s))
    np.add.at(Bs, (loc, np.repeat(np.arange(s), 3).reshape(s, 3)), bary)
    return np.kron(Bs, np.eye(3))


def barycentric_matrix(
    triangles: np.ndarray, tri_idx: np.ndarray, bary: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The barycentric force-distribution matrix B of the course hint.

    Parameters
    ----------
    triangles : (m, 3) int ndarray
        Surface triangles.
    tri_idx : (s,) int ndarray
        Contacted triangle of each contact.
    bary : (s, 3) float ndarray
        Barycentric coordinates of each contact in its triangle.

    Returns
    -------
    V : (|V|,) int ndarray
        Sorted union of the contacted triangles' vertices.
    B : (3|V|, 3s) float ndarray
        Block ``(i, k) = beta_{k,i} I3``: vertex forces ``f_V = B f_s``,
        contact-point displacements ``u_s = B^T u_V``. Several contacts may
        share vertices or a triangle; a vertex listed twice in one triangle
        accumulates its weights.
    """
    tri_idx = np.asarray(tri_idx, dtype=np.intp).reshape(-1)
    bary = np.asarray(bary, dtype=np.float64).reshape(tri_idx.size, 3)
    V, loc = _locate(triangles, tri_idx)
    return V, _dense_B(V.size, loc, bary)


def _gT(M: np.ndarray, loc: np.ndarray, bary: np.ndarray, normals: np.ndarray, mode: str) -> np.ndarray:
    """``G^T M`` for M with rows indexed by V-dofs (3|V|, q); G = B (sticky) or B N."""
    s = loc.shape[0]
    q = M.shape[1]
    if s == 0 or q == 0:
        return np.zeros((3 * s if mode == "sticky" else s, q))
    T = M.reshape(M.shape[0] // 3, 3 * q)[loc]  # (s, 3 vertices, 3q)
    R = np.matmul(bary[:, None, :], T).reshape(s, 3, q)  # B^T M
    if mode == "sticky":
        return R.reshape(3 * s, q)
    return np.einsum("kxq,kx->kq", R, normals)


def _gT_csr(nV: int, loc: np.ndarray, bary: np.ndarray, normals: np.ndarray, mode: str) -> sp.csr_matrix:
    """``G^T`` as a CSR matrix (m, 3|V|): 3 (sticky) or 9 (frictionless) entries a row."""
    s = loc.shape[0]
    idx = 3 * loc[:, None, :] + np.arange(3)[None, :, None]  # (k, x, a) -> dof 3 loc_ka + x
    if mode == "sticky":
        data = np.broadcast_to(bary[:, None, :], (s, 3, 3))
        return sp.csr_matrix((data.ravel(), idx.ravel(), np.arange(0, 9 * s + 1, 3)), shape=(3 * s, 3 * nV))
    data = bary[:, None, :] * normals[:, :, None]  # (k, x, a)
    return sp.csr_matrix((data.ravel(), idx.ravel(), np.arange(0, 9 * s + 1, 9)), shape=(s, 3 * nV))


#: From this size of D_VV on, :meth:`Capacitance.add` grows it by block copies.
EMBED_BLOCKS_FROM: int = 300
#: From this many contacts on, W is formed with a sparse G (less work, more overhead).
SPARSE_FROM: int = 16


def _contact_compliance(D_VV: np.ndarray, loc, bary, normals, mode) -> np.ndarray:
    """``W = G^T D_VV G`` (symmetrised)."""
    if loc.shape[0] >= SPARSE_FROM:
        GT = _gT_csr(D_VV.shape[0] // 3, loc, bary, normals, mode)
        L = np.asarray(GT @ D_VV)  # G^T D_VV, (m, 3|V|)
        W = np.asarray(GT @ L.T).T
    else:
        L = _gT(D_VV, loc, bary, normals, mode)
        W = _gT(np.ascontiguousarray(L.T), loc, bary, normals, mode).T
    return 0.5 * (W + W.T)


def _vertex_forces(nV: int, loc: np.ndarray, bary: np.ndarray, forces: np.ndarray) -> np.ndarray:
    """``B f`` as (|V|, 3)."""
    g = np.zeros((nV, 3))
    np.add.at(g, loc.ravel(), (bary[:, :, None] * forces[:, None, :]).reshape(-1, 3))
    return g


def _interpolate(uV: np.ndarray, loc: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """``B^T u_V`` as (s, 3) from vertex values (|V|, 3)."""
    return np.matmul(bary[:, None, :], uV[loc]).reshape(-1, 3)


_potrf, _potrs, _potri = sla.lapack.get_lapack_funcs(("potrf", "potrs", "potri"), dtype=np.float64)


class _Factor:
    """Factorisation of a symmetric positive semi-definite W; never a singular solve.

    Cholesky if W is well conditioned (the condition estimate from the
    diagonal of the factor is below :data:`COND_LIMIT`), else the
    rank-revealing pseudo-inverse (eigenvalues below ``PINV_RCOND * max``
    dropped).
    """

    def __init__(self, W: np.ndarray):
        m = W.shape[0]
        self.m = m
        self.exact = True
        self._cho = None
        self._pinv = None
        if m == 0:
            return
        Ws = 0.5 * (W + W.T)
        if np.isfinite(Ws).all():
            c, info = _potrf(Ws, lower=0, clean=1, overwrite_a=0)
            if info == 0:
                d = np.abs(np.diag(c))
                if d.min() > 0 and (d.max() / d.min()) ** 2 < COND_LIMIT:
                    self._cho = c
                    return
        self.exact = False
        lam, Q = np.linalg.eigh(Ws)
        keep = lam > PINV_RCOND * max(float(lam.max()), 0.0)
        Qk = Q[:, keep]
        K = (Qk / lam[keep]) @ Qk.T
        self._pinv = 0.5 * (K + K.T)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        if self.m == 0:
            return np.zeros_like(rhs)
        if self._cho is not None:
            x, info = _potrs(self._cho, rhs, lower=0)
            if info != 0:  # pragma: no cover - only on invalid arguments
                raise np.linalg.LinAlgError(f"LAPACK potrs failed (info={info})")
            return x
        return self._pinv @ rhs

    def inverse(self) -> np.ndarray:
        if self.m == 0:
            return np.zeros((0, 0))
        if self._cho is not None:
            K, info = _potri(self._cho, lower=0)
            if info != 0:  # pragma: no cover
                raise np.linalg.LinAlgError(f"LAPACK potri failed (info={info})")
            return np.triu(K) + np.triu(K, 1).T
        return self._pinv.copy()


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


def _gather(gf: Any, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """D[rows, cols] with zero columns where ``cols == -1`` (clamped vertices)."""
    D = gf.D
    dead = cols < 0
    cc = np.where(dead, 0, cols)
    if rows.size == 0 or cols.size == 0:
        return np.zeros((rows.size, cols.size))
    if D.flags.c_contiguous:
        out = np.take(D.reshape(-1), (rows[:, None] * D.shape[1] + cc[None, :]).ravel()).reshape(rows.size, cols.size)
        out = np.asarray(out)
    else:  # e.g. Fortran order: contiguous column take first, then the rows
        # Gather through the C-ordered transpose so the inner loop walks down one
        # contiguous column (measured 2x faster than D[np.ix_(rows, cc)] at s = 100;
        # np.take would first copy all of D to C order).
        out = np.asarray(D.T[np.ix_(cc, rows)]).T
    if dead.any():
        out[:, dead] = 0.0
    return out


def _apply_columns(gf: Any, cols: np.ndarray, g: np.ndarray, rows: np.ndarray | None) -> np.ndarray:
    """``D[rows, cols] @ g`` as (r, 3) (all rows if ``rows`` is None), skipping clamped columns."""
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


def _runs(idx: np.ndarray) -> list[tuple[int, int, int]]:
    """Maximal runs of consecutive values in an increasing index array: (start, stop, value0)."""
    if idx.size == 0:
        return []
    br = np.flatnonzero(np.diff(idx) != 1) + 1
    starts = np.concatenate([[0], br])
    stops = np.concatenate([br, [idx.size]])
    return [(int(a), int(b), int(idx[a])) for a, b in zip(starts, stops)]


def _embed(M: np.ndarray, pos: np.ndarray, size: int) -> np.ndarray:
    """(size, size) array with ``out[pos][:, pos] = M`` by contiguous block copies.

    The rest is left uninitialised (the caller fills it).
    """
    out = np.empty((size, size))
    if M.shape[0] < EMBED_BLOCKS_FROM:  # small: one fancy-indexed copy beats a loop over blocks
        out[np.ix_(pos, pos)] = M
        return out
    runs = _runs(pos)
    for a0, a1, r0 in runs:
        for b0, b1, c0 in runs:
            out[r0:r0 + a1 - a0, c0:c0 + b1 - b0] = M[a0:a1, b0:b1]
    return out


def _rigid(gf: Any, tri_idx: np.ndarray, bary: np.ndarray) -> np.ndarray:
    """Contacts whose barycentric weight lies entirely on clamped vertices."""
    verts = gf.triangles[tri_idx]
    free_w = np.where(gf.fixed[verts], 0.0, np.abs(bary)).sum(axis=1)
    return free_w <= 1e-12


# --------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------
def _check_contacts(
    gf: Any,
    tri_idx: Any,
    bary: Any,
    normals: Any = None,
    need_normals: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Validate contact triangles, barycentric coordinates and normals.

    The triangles' normals are computed (and checked) only if ``normals`` is
    None and ``need_normals``; otherwise None is returned for them.
    """
    t = np.asarray(tri_idx)
    if t.ndim != 1:
        raise ValueError(f"triangles must have shape (s,), got {t.shape}")
    s = t.size
    if s and not np.issubdtype(t.dtype, np.integer):
        raise ValueError(f"triangles must be integer triangle indices, got dtype {t.dtype}")
    t = t.astype(np.intp, copy=False)
    m = gf.triangles.shape[0]
    if s and (t.min() < 0 or t.max() >= m):
        bad = t[(t < 0) | (t >= m)]
        raise IndexError(f"triangle indices {bad[:5].tolist()} are outside 0..{m - 1}")
    b = np.asarray(bary, dtype=np.float64)
    if b.shape != (s, 3):
        raise ValueError(f"barycentric must have shape ({s}, 3) to match triangles, got {b.shape}")
    if not np.isfinite(b).all():
        raise ValueError("barycentric coordinates contain NaN or infinity")
    if s:
        err = np.abs(b.sum(axis=1) - 1.0)
        if err.max() > BARY_SUM_TOL:
            k = int(np.argmax(err))
            raise ValueError(f"barycentric coordinates of contact {k} sum to {b[k].sum()!r}, not 1 (tolerance {BARY_SUM_TOL})")
        if b.min() < -BARY_NEG_TOL:
            k = int(np.argmin(b.min(axis=1)))
            raise ValueError(f"barycentric coordinates of contact {k} are negative ({b[k].tolist()}): the point lies outside its triangle")
    verts = gf.triangles[t]
    ok = gf.contactable[verts] | gf.fixed[verts]
    if not ok.all():
        k = int(np.flatnonzero(~ok.all(axis=1))[0])
        raise ValueError(
            f"contact {k} lies on triangle {int(t[k])} whose vertices {verts[k].tolist()} are not all "
            "contactable or clamped: the bundle holds no compliance column for them"
        )
    if normals is None and not need_normals:
        n = None
    elif normals is None:
        n = triangle_normals(gf.vertices, verts)
        if s and not np.any(n, axis=1).all():
            raise ValueError("a contacted triangle is degenerate (zero area): pass normals explicitly")
    else:
        n = np.asarray(normals, dtype=np.float64)
        if n.shape != (s, 3):
            raise ValueError(f"normals must have shape ({s}, 3), got {n.shape}")
        if not np.isfinite(n).all():
            raise ValueError("normals contain NaN or infinity")
        ln = np.linalg.norm(n, axis=1, keepdims=True)
        if np.any(ln == 0):
            raise ValueError("normals contain a zero vector")
        n = n / ln
    return t, b, n


def _check_mode(mode: str) -> str:
    if mode not in ("sticky", "frictionless"):
        raise ValueError(f"mode must be 'sticky' or 'frictionless', got {mode!r}")
    return mode


# --------------------------------------------------------------------------
# capacitance
# --------------------------------------------------------------------------
@dataclass(eq=False)
class Capacitance:
    """The capacitance (effective contact stiffness) of a set of point contacts.

    Build with :func:`capacitance`. All arrays refer to the contacts in the
    order given (after :meth:`add` the new contact is last; :meth:`remove`
    keeps the order of the rest).

    Attributes
    ----------
    gf : GreensFunctions
        The bundle.
    mode : {"sticky", "frictionless"}
    tri_idx : (s,) int ndarray
    bary : (s, 3) float ndarray
    normals : (s, 3) float ndarray
        Outward unit normals (used by frictionless and unilateral contact).
    V : (|V|,) int ndarray
        Sorted union of the contacted triangles' vertices.
    loc : (s, 3) int ndarray
        Position in ``V`` of each contacted triangle's vertices (B's sparsity).
    D_VV : (3|V|, 3|V|) float ndarray
        Compliance block ``D[V, V]`` (zero columns at clamped vertices).
    W : (m, m) float ndarray
        Contact compliance ``G^T D_VV G`` over *all* constrained components
        (``G = B`` sticky, ``m = 3s``; ``G = B N`` frictionless, ``m = s``).
        Rows/columns of rigid contacts are zero.
    rigid : (s,) bool ndarray
        Contacts whose weight lies entirely on clamped vertices.
    exact : bool
        True if ``K`` is the true inverse; False if ``W`` was singular or ill
        conditioned and ``K`` is its pseudo-inverse.

    Notes
    -----
    A fresh build keeps the Cholesky factor of ``W[live, live]``
    (:meth:`forces` is then two triangular solves); the explicit capacitance
    :attr:`K` is formed on first use and afterwards maintained by the
    low-rank updates of :meth:`add` and :meth:`remove`.
    """

    gf: Any
    mode: str
    tri_idx: np.ndarray
    bary: np.ndarray
    normals: np.ndarray
    V: np.ndarray
    loc: np.ndarray
    D_VV: np.ndarray
    W: np.ndarray
    rigid: np.ndarray
    exact: bool
    _cols: np.ndarray = field(repr=False)  # column dofs of D for V (-1 at clamped vertices)
    _factor: _Factor | None = field(default=None, repr=False)
    _K: np.ndarray | None = field(default=None, repr=False)

    # -- sizes and derived matrices ------------------------------------------
    @property
    def s(self) -> int:
        """Number of contacts."""
        return int(self.tri_idx.size)

    @property
    def per_contact(self) -> int:
        """Constrained components per contact: 3 (sticky) or 1 (frictionless)."""
        return 3 if self.mode == "sticky" else 1

    @property
    def live_dofs(self) -> np.ndarray:
        """Indices into ``W`` of the constrained components of non-rigid contacts."""
        p = self.per_contact
        live = np.flatnonzero(~self.rigid)
        return (p * live[:, None] + np.arange(p)).ravel()

    @property
    def B(self) -> np.ndarray:
        """Barycentric matrix B, (3|V|, 3s) (see :func:`barycentric_matrix`)."""
        return _dense_B(self.V.size, self.loc, self.bary)

    @property
    def G(self) -> np.ndarray:
        """Constraint matrix ``B`` (sticky) or ``B N`` (frictionless), (3|V|, m)."""
        B = self.B
        if self.mode == "sticky":
            return B
        return np.einsum("rkj,kj->rk", B.reshape(B.shape[0], self.s, 3), self.normals)

    @property
    def K(self) -> np.ndarray:
        """Capacitance ``W[live, live]^-1`` (pseudo-inverse if not :attr:`exact`), (a, a).

        ``live`` = :attr:`live_dofs`: rigid contacts are excluded.
        """
        if self._K is None:
            self._K = self._factor.inverse()
        return self._K

    # -- solves ------------------------------------------------------------
    def _reduce(self, ubar: np.ndarray) -> np.ndarray:
        """Prescribed displacements as constrained components (m,)."""
        if self.mode == "sticky":
            return ubar.reshape(-1)
        return np.einsum("ki,ki->k", ubar, self.normals)

    def _expand(self, lam: np.ndarray) -> np.ndarray:
        """Constraint multipliers (m,) -> contact forces (s, 3)."""
        if self.mode == "sticky":
            return lam.reshape(-1, 3)
        return lam[:, None] * self.normals

    def _multipliers(self, c: np.ndarray) -> np.ndarray:
        live = self.live_dofs
        lam = np.zeros_like(c)
        if live.size:
            lam[live] = self._K @ c[live] if self._K is not None else self._factor.solve(c[live])
        return lam

    def forces(self, ubar: np.ndarray) -> np.ndarray:
        """Forces on the seat that impose prescribed contact-point displacements.

        Parameters
        ----------
        ubar : (s, 3) float ndarray
            Prescribed displacements of the contact points [m] (frictionless:
            only the normal component ``ubar . n`` is imposed).

        Returns
        -------
        (s, 3) float ndarray
            Forces applied to the seat [N]; zero at rigid contacts.
        """
        ubar = np.asarray(ubar, dtype=np.float64)
        if ubar.shape != (self.s, 3):
            raise ValueError(f"ubar must have shape ({self.s}, 3), got {ubar.shape}")
        if not np.isfinite(ubar).all():
            raise ValueError("ubar contains NaN or infinity")
        return self._expand(self._multipliers(self._reduce(ubar)))

    def vertex_forces(self, forces: np.ndarray) -> np.ndarray:
        """Vertex forces ``f_V = B f_s`` as a (|V|, 3) array."""
        return _vertex_forces(self.V.size, self.loc, self.bary, np.asarray(forces, dtype=np.float64).reshape(-1, 3))

    def contact_displacement(self, forces: np.ndarray) -> np.ndarray:
        """Contact-point displacements ``B^T D_VV B f_s`` caused by contact forces, (s, 3)."""
        g = self.vertex_forces(forces).reshape(-1)
        return _interpolate((self.D_VV @ g).reshape(-1, 3), self.loc, self.bary)

    def surface_displacement(self, forces: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """Surface displacement ``u = D[:, V] B f_s``.

        Parameters
        ----------
        forces : (s, 3) float ndarray
            Contact forces on the seat [N].
        rows : (r,) int ndarray, optional
            Surface vertices where the displacement is wanted. Default: every
            surface vertex (one matrix-vector product with ``D[:, V]``, or
            with the whole ``D`` when V covers much of it).

        Returns
        -------
        (r, 3) or (n, 3) float ndarray
        """
        g = self.vertex_forces(forces).reshape(-1)
        return _apply_columns(self.gf, self._cols, g, rows)

    def surface_response(self, rows: np.ndarray | None = None) -> np.ndarray:
        """Surface displacement per unit constraint multiplier, ``D[rows, V] G``.

        ``u = surface_response() @ lam`` for multipliers ``lam`` (sticky: the
        flattened contact forces; frictionless: the signed normal forces).

        Parameters
        ----------
        rows : (r,) int ndarray, optional
            Surface vertices; default every surface vertex.

        Returns
        -------
        (3r, m) float ndarray
            Vertex-major rows; ``m = 3s`` (sticky) or ``s`` (frictionless).
        """
        n = self.gf.vertices.shape[0]
        r = np.arange(n) if rows is None else np.asarray(rows)
        if r.ndim != 1 or (r.size and not np.issubdtype(r.dtype, np.integer)):
            raise ValueError(f"rows must be a 1-D array of vertex indices, got shape {r.shape} dtype {r.dtype}")
        if r.size and (r.min() < 0 or r.max() >= n):
            raise IndexError(f"rows hold vertex indices outside 0..{n - 1}")
        M = _gather(self.gf, _dof3(r), self._cols)  # D[rows, V], (3r, 3|V|)
        GT = _gT_csr(self.V.size, self.loc, self.bary, self.normals, self.mode)
        return np.asarray(GT @ M.T).T

    # -- low-rank updates ----------------------------------------------------
    def add(self, tri: int, bary: Sequence[float], normal: Sequence[float] | None = None) -> int:
        """Add one contact, updating ``K`` by a bordered-inverse (SMW) update.

        The new contact becomes the last one. Only the new rows/columns of
        ``D_VV`` are gathered and ``K`` is updated in ``O(m^2)`` from the Schur
        complement ``S = d - c^T K c`` of the new block:
        ``K' = [[K + K c S^-1 c^T K, -K c S^-1], [-S^-1 c^T K, S^-1]]``.
        If ``K`` is a pseudo-inverse, or the new contact makes ``W`` singular
        or ill conditioned (it coincides with an existing one), the
        capacitance is re-factorised instead.

        Parameters
        ----------
        tri : int
            Contacted triangle.
        bary : (3,) float
            Barycentric coordinates.
        normal : (3,) float, optional
            Outward unit normal; default the triangle's.

        Returns
        -------
        int
            Index of the new contact.
        """
        t, b, n = _check_contacts(
            self.gf, np.array([tri], dtype=np.intp), np.asarray(bary, dtype=np.float64).reshape(1, 3),
            None if normal is None else np.asarray(normal, dtype=np.float64).reshape(1, 3),
        )
        gf = self.gf
        old_s = self.s
        p = self.per_contact
        K_old = self.K if self.exact else None
        # grow V (kept sorted) and D_VV: gather only the new rows / columns of D
        tv = gf.triangles[t[0]]
        newv = np.setdiff1d(tv, self.V)
        V = np.union1d(self.V, newv).astype(np.intp)
        pos_old = np.searchsorted(V, self.V)
        cols = _column_dofs(gf, V)
        if newv.size:
            # insert the new vertices' rows/columns (slice copies, V stays sorted)
            pn = _dof3(np.searchsorted(V, newv))
            po = np.delete(np.arange(3 * V.size), pn)
            D_VV = _embed(self.D_VV, po, 3 * V.size)
            D_VV[:, pn] = _gather(gf, _dof3(V), cols[pn])
            D_VV[np.ix_(pn, po)] = _gather(gf, _dof3(newv), cols[po])
        else:
            D_VV = self.D_VV
        loc_old = pos_old[self.loc]
        loc_new = np.searchsorted(V, tv)[None, :]
        rigid_new = bool(_rigid(gf, t, b)[0])
        # new blocks of W: c = G_old^T D_VV G_new, d = G_new^T D_VV G_new
        # D_VV B_new, (3|V|, 3): columns (vertex b, component y) weighted by beta_b
        DGn = np.einsum("rby,b->ry", D_VV[:, _dof3(loc_new[0])].reshape(-1, 3, 3), b[0])
        if self.mode != "sticky":
            DGn = DGn @ n[0][:, None]
        c = _gT(DGn, loc_old, self.bary, self.normals, self.mode)  # (m_old, p)
        d = _gT(DGn, loc_new, b, n, self.mode)
        d = 0.5 * (d + d.T)
        mo = p * old_s
        W = np.zeros((mo + p, mo + p))
        W[:mo, :mo] = self.W
        if not rigid_new:
            if self.rigid.any():
                c[np.repeat(self.rigid, p)] = 0.0
            W[:mo, mo:] = c
            W[mo:, :mo] = c.T
            W[mo:, mo:] = d
        self.tri_idx = np.append(self.tri_idx, t)
        self.bary = np.vstack([self.bary, b])
        self.normals = np.vstack([self.normals, n])
        self.loc = np.vstack([loc_old, loc_new])
        self.V, self.D_VV, self.W, self._cols = V, D_VV, W, cols
        self.rigid = np.append(self.rigid, rigid_new)
        if rigid_new:
            return old_s
        if K_old is None:
            self._refactor()
            return old_s
        cl = c[~np.repeat(self.rigid[:old_s], p)]  # (a, p) rows of the live components
        Kc = K_old @ cl
        S = d - cl.T @ Kc
        S = 0.5 * (S + S.T)
        wscale = max(float(np.abs(np.diag(W)).max()), np.finfo(float).tiny)
        lam_min = float(np.linalg.eigvalsh(S).min()) if p > 1 else float(S[0, 0])
        if lam_min < wscale / COND_LIMIT:
            self._refactor()  # the new contact (nearly) coincides with others
            return old_s
        Sinv = np.linalg.inv(S)
        a = K_old.shape[0]
        KcS = Kc @ Sinv
        K = np.empty((a + p, a + p))
        K[:a, :a] = K_old + KcS @ Kc.T
        K[:a, a:] = -KcS
        K[a:, :a] = -KcS.T
        K[a:, a:] = Sinv
        self._K = 0.5 * (K + K.T)
        self._factor = None
        return old_s

    def remove(self, k: int) -> None:
        """Remove contact ``k``, updating ``K`` by a low-rank downdate.

        For an exact inverse ``K = W^-1`` partitioned into kept (``a``) and
        removed (``b``) components, the inverse of ``W_aa`` is
        ``K_aa - K_ab K_bb^-1 K_ba``: no re-factorisation. If ``K`` is a
        pseudo-inverse the capacitance is re-factorised instead.

        Parameters
        ----------
        k : int
            Contact index (negative indices count from the end).
        """
        s = self.s
        if not -s <= k < s:
            raise IndexError(f"contact index {k} out of range for {s} contacts")
        k %= s
        p = self.per_contact
        keep = np.ones(s, bool)
        keep[k] = False
        was_rigid = bool(self.rigid[k])
        kpos = int(np.count_nonzero(~self.rigid[:k]))  # position among the live contacts
        K_old = self.K if (self.exact and not was_rigid) else None
        loc = self.loc[keep]
        vkeep = np.zeros(self.V.size, bool)
        vkeep[loc.ravel()] = True
        newpos = np.cumsum(vkeep) - 1
        dk = _dof3(np.flatnonzero(vkeep))
        if not vkeep.all():
            drop = _dof3(np.flatnonzero(~vkeep))
            self.D_VV = np.delete(np.delete(self.D_VV, drop, axis=0), drop, axis=1)
        self._cols = self._cols[dk]
        self.V = self.V[vkeep]
        self.loc = newpos[loc]
        wd = np.arange(p * k, p * k + p)
        self.W = np.delete(np.delete(self.W, wd, axis=0), wd, axis=1)
        self.tri_idx, self.bary, self.normals = self.tri_idx[keep], self.bary[keep], self.normals[keep]
        self.rigid = self.rigid[keep]
        if was_rigid:
            return
        if K_old is None:
            self._refactor()
            return
        a = K_old.shape[0]
        rem = np.arange(p * kpos, p * kpos + p)
        kp = np.setdiff1d(np.arange(a), rem)
        Kbb = K_old[np.ix_(rem, rem)]
        Kab = K_old[np.ix_(kp, rem)]
        K = K_old[np.ix_(kp, kp)] - Kab @ np.linalg.solve(Kbb, Kab.T)
        self._K = 0.5 * (K + K.T)
        self._factor = None

    def _refactor(self) -> None:
        live = self.live_dofs
        self._factor = _Factor(self.W[np.ix_(live, live)])
        self.exact = self._factor.exact
        self._K = None


def capacitance(
    gf: Any,
    tri_idx: Any,
    bary: Any,
    *,
    normals: Any = None,
    mode: Mode = "sticky",
) -> Capacitance:
    """Build the capacitance of a set of point contacts.

    Parameters
    ----------
    gf : GreensFunctions
        Loaded bundle (see :func:`runtime.bundle.load`).
    tri_idx : (s,) int array_like
        Contacted surface triangles.
    bary : (s, 3) float array_like
        Barycentric coordinates (sum to 1, non-negative).
    normals : (s, 3) float array_like, optional
        Outward contact normals (normalised here); default: the contacted
        triangles' outward unit normals.
    mode : {"sticky", "frictionless"}
        ``"sticky"`` constrains all three components of each contact point;
        ``"frictionless"`` only the normal one.

    Returns
    -------
    Capacitance

    Raises
    ------
    ValueError, IndexError
        On malformed input (see :func:`solve_contacts`).
    """
    mode = _check_mode(mode)
    t, b, n = _check_contacts(gf, tri_idx, bary, normals)
    return _build(gf, t, b, n, mode)


def _build(gf: Any, t: np.ndarray, b: np.ndarray, n: np.ndarray, mode: str) -> Capacitance:
    V, loc = _locate(gf.triangles, t)
    cols = _column_dofs(gf, V)
    D_VV = _gather(gf, _dof3(V), cols)
    W = _contact_compliance(D_VV, loc, b, n, mode)
    rigid = _rigid(gf, t, b)
    p = 3 if mode == "sticky" else 1
    if rigid.any():
        dead = np.repeat(rigid, p)
        W[dead, :] = 0.0
        W[:, dead] = 0.0
        live = np.flatnonzero(~dead)
        factor = _Factor(W[np.ix_(live, live)])
    else:
        factor = _Factor(W)
    return Capacitance(
        gf=gf, mode=mode, tri_idx=t, bary=b, normals=n, V=V, loc=loc, D_VV=D_VV,
        W=W, rigid=rigid, exact=factor.exact, _cols=cols, _factor=factor,
    )


# --------------------------------------------------------------------------
# the solver
# --------------------------------------------------------------------------
@dataclass
class ContactSolution:
    """Result of :func:`solve_contacts`.

    Attributes
    ----------
    forces : (s, 3) float ndarray
        Forces applied **to the seat** at the contact points [N]
        (zero at released and rigid contacts).
    surface_displacement : (n, 3) or (r, 3) float ndarray or None
        Displacement of every surface vertex (``rows="all"``), of the
        requested ``rows``, or None (``rows=None``) [m].
    active : (s,) bool ndarray
        Contacts that carry force (not released by unilateral contact and
        not rigid).
    rigid : (s,) bool ndarray
        Contacts entirely on clamped vertices (hard wall; force reported 0).
    contact_displacement : (s, 3) float ndarray
        Displacement of the contact points ``B^T u_V`` [m]. Equals the
        prescription at active sticky contacts (normal component only for
        frictionless ones); zero at rigid contacts.
    iterations : int
        Active-set iterations (1 without unilateral contact).
    vertices : (|V|,) int ndarray
        Contacted vertices V.
    vertex_forces : (|V|, 3) float ndarray
        Forces at V, ``B f`` [N].
    """

    forces: np.ndarray
    surface_displacement: np.ndarray | None
    active: np.ndarray
    rigid: np.ndarray
    contact_displacement: np.ndarray
    iterations: int = 1
    vertices: np.ndarray = field(default_factory=lambda: np.zeros(0, np.intp))
    vertex_forces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


def _solve_subset(cap: Capacitance, c: np.ndarray, act: np.ndarray) -> np.ndarray:
    """Multipliers (m,) with only contacts ``act`` constrained (fresh factorisation)."""
    p = cap.per_contact
    dofs = (p * np.flatnonzero(act)[:, None] + np.arange(p)).ravel()
    lam = np.zeros(cap.W.shape[0])
    if dofs.size:
        lam[dofs] = _Factor(cap.W[np.ix_(dofs, dofs)]).solve(c[dofs])
    return lam


def solve_contacts(
    gf: Any,
    triangles: Any,
    barycentric: Any,
    displacements: Any,
    *,
    mode: Mode = "sticky",
    unilateral: bool = False,
    normals: Any = None,
    rows: Any = "all",
    max_iter: int | None = None,
) -> ContactSolution:
    """Forces and deformation for prescribed contact-point displacements.

    Parameters
    ----------
    gf : GreensFunctions
        Loaded bundle.
    triangles : (s,) int array_like
        Contacted surface triangle of each contact.
    barycentric : (s, 3) float array_like
        Barycentric coordinates of each contact point (non-negative within
        1e-9, summing to 1 within 1e-6).
    displacements : (s, 3) float array_like
        Prescribed contact-point displacements ``ubar`` [m]. A stone pressing
        on the seat has ``ubar . n < 0`` (n the outward normal).
    mode : {"sticky", "frictionless"}
        Constrain all components, or the normal component only.
    unilateral : bool
        If True, contacts may only push: a contact whose force would pull
        (``f . n > 0``) is released and the rest re-solved; a released contact
        is re-activated if the seat would penetrate the prescribed position
        (``(u - ubar) . n > 0``). Active-set iteration (block pivoting, falling
        back to one flip per iteration if a set repeats), at most ``max_iter``
        iterations (default ``2 s + 10``). A sticky contact is released as a
        whole (all three components).
    normals : (s, 3) float array_like, optional
        Outward contact normals; default the contacted triangles' normals.
    rows : "all", None or (r,) int array_like
        Where to evaluate the surface displacement.
    max_iter : int, optional
        Bound on active-set iterations.

    Returns
    -------
    ContactSolution

    Raises
    ------
    ValueError
        Shape mismatch, NaN/inf, barycentric coordinates not summing to 1 or
        negative, contact on a vertex without a compliance column, bad mode
        or rows.
    IndexError
        Triangle (or row) index out of range.
    RuntimeError
        If the unilateral active set does not settle within ``max_iter``.
    """
    mode = _check_mode(mode)
    # sticky bilateral contacts never look at the normals
    t, b, n = _check_contacts(gf, triangles, barycentric, normals,
                              need_normals=unilateral or mode == "frictionless")
    s = t.size
    ubar = np.asarray(displacements, dtype=np.float64)
    if ubar.shape != (s, 3):
        raise ValueError(f"displacements must have shape ({s}, 3) to match triangles, got {ubar.shape}")
    if not np.isfinite(ubar).all():
        raise ValueError("displacements contain NaN or infinity")
    if isinstance(rows, str):
        if rows != "all":
            raise ValueError(f"rows must be 'all', None or an index array, got {rows!r}")
        rows_arr: np.ndarray | None = None
        want_u = True
    elif rows is None:
        rows_arr, want_u = None, False
    else:
        rows_arr, want_u = np.asarray(rows), True

    cap = _build(gf, t, b, n, mode)
    rigid = cap.rigid
    c = cap._reduce(ubar)
    it = 1
    active = ~rigid
    lam = cap._multipliers(c)
    if unilateral:
        p = cap.per_contact
        cn = np.einsum("ki,ki->k", ubar, n)
        seen: set[bytes] = set()
        limit = 2 * s + 10 if max_iter is None else int(max_iter)
        single = False
        for it in range(1, limit + 1):
            if it > 1:
                lam = _solve_subset(cap, c, active)
            fn = np.einsum("ki,ki->k", cap._expand(lam), n)
            wl = cap.W @ lam  # constrained components of the contact displacement
            un = np.einsum("ki,ki->k", wl.reshape(s, 3), n) if p == 3 else wl
            fscale = max(float(np.abs(fn).max(initial=0.0)), np.finfo(float).tiny)
            uscale = max(float(np.abs(cn).max(initial=0.0)), float(np.abs(un).max(initial=0.0)),
                         np.finfo(float).tiny)
            pull = active & (fn > 1e-10 * fscale)
            pen = ~active & ~rigid & (un - cn > 1e-10 * uscale)
            viol = np.flatnonzero(pull | pen)
            if viol.size == 0:
                break
            key = active.tobytes()
            if key in seen:
                single = True  # block pivoting cycled: one flip per iteration
            seen.add(key)
            if single:
                viol = viol[-1:]
            active = active.copy()
            active[viol] = ~active[viol]
        else:
            raise RuntimeError(f"unilateral contact: active set did not settle in {limit} iterations")
    f = cap._expand(lam)
    if not active.all():
        f = np.where(active[:, None], f, 0.0)
    g = _vertex_forces(cap.V.size, cap.loc, b, f)
    gflat = g.reshape(-1)
    u = _apply_columns(gf, cap._cols, gflat, rows_arr) if want_u else None
    if u is not None and rows_arr is None:
        uV = u[cap.V]
    else:
        uV = (cap.D_VV @ gflat).reshape(-1, 3)
    return ContactSolution(
        forces=f,
        surface_displacement=u,
        active=active,
        rigid=rigid.copy(),
        contact_displacement=_interpolate(uV, cap.loc, b),
        iterations=it,
        vertices=cap.V,
        vertex_forces=g,
    )
