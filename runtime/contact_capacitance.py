"""The capacitance object of a contact set: W = G^T D_VV G, its factorisation and low-rank updates.

Split out of :mod:`hailstorm.runtime.contact` (which re-exports the public names, so
``from hailstorm.runtime.contact import Capacitance, capacitance`` keeps working). See
that module's docstring for the notation, sign conventions and the
documented degenerate cases. The tuning constants (:data:`COND_LIMIT`,
:data:`PINV_RCOND`, :data:`EMBED_BLOCKS_FROM`, :data:`SPARSE_FROM`,
:data:`POINT_FAST_MAX`) live here: set them on this module.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal, Sequence, cast, overload

import numpy as np
import scipy.linalg as sla

from hailstorm.runtime.compiled import blocks as _kernels
from hailstorm.runtime.compiled import resolve_backend
from hailstorm.runtime.gather import _apply_columns, _column_dofs, _compiled, _dof3, _gather, _gather_vertices
from hailstorm.runtime.weights import (
    _dense_B,
    _gT,
    _gT_csr,
    _interpolate,
    _locate_lists,
    _pad,
    _vertex_forces,
    patch_weights,
    triangle_normals,
)

__all__ = [
    "COND_LIMIT",
    "EMBED_BLOCKS_FROM",
    "PINV_RCOND",
    "POINT_FAST_MAX",
    "SPARSE_FROM",
    "Capacitance",
    "capacitance",
    "spd_inverse",
]

Mode = Literal["sticky", "frictionless"]

#: Above this (lower-bound) condition estimate of W, use the pseudo-inverse.
COND_LIMIT: float = 1e10
#: Relative eigenvalue cut-off of the pseudo-inverse.
PINV_RCOND: float = 1e-10
#: Barycentric coordinates must sum to one within this and be >= -BARY_NEG_TOL.
BARY_SUM_TOL: float = 1e-6
BARY_NEG_TOL: float = 1e-9


#: From this size of D_VV on, :meth:`Capacitance.add` grows it by block copies.
EMBED_BLOCKS_FROM: int = 300
#: From this many contacts on, W is formed with a sparse G (less work, more overhead).
SPARSE_FROM: int = 16
#: Up to this many bilateral point contacts, ``solve_contacts`` with numba takes the
#: one-call compiled solve (:func:`hailstorm.runtime.compiled.blocks.point_contacts`); above
#: it the block kernels, which win from s = 64-80 on (measured on the default seat).
POINT_FAST_MAX: int = 64


def _contact_compliance(D_VV: np.ndarray, loc, bary, normals, mode) -> np.ndarray:
    """``W = G^T D_VV G`` (symmetrised).

    ``G^T D_VV^T G = (G^T D_VV G)^T``, so the symmetrised W is the same (up to
    rounding) from ``D_VV`` or its transpose: use whichever is C-contiguous
    (the gathers of a column-major D return an F-ordered ``D_VV``), so that
    neither product copies ``D_VV``.
    """
    M = D_VV.T if D_VV.flags.f_contiguous and not D_VV.flags.c_contiguous else D_VV
    if loc.shape[0] >= SPARSE_FROM:
        GT = _gT_csr(M.shape[0] // 3, loc, bary, normals, mode)
        L = np.asarray(GT @ M)  # G^T M, (m, 3|V|)
        W = np.asarray(GT @ np.ascontiguousarray(L.T))
    else:
        L = _gT(M, loc, bary, normals, mode)
        W = _gT(np.ascontiguousarray(L.T), loc, bary, normals, mode)
    return 0.5 * (W + W.T)


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
        if self._pinv is None:  # pragma: no cover - m > 0: one of the two is always set
            raise RuntimeError("empty factorisation")
        return self._pinv.copy()


def spd_inverse(W: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive semi-definite matrix under the contact API's one policy.

    The Cholesky inverse when ``W`` is well conditioned (condition estimate below
    :data:`COND_LIMIT`), else the pseudo-inverse (eigenvalues below
    :data:`PINV_RCOND` times the largest dropped): the same factorisation as
    :class:`Capacitance`. For contacts that (nearly) coincide this is the
    min-norm split of their common force: finite and symmetric.

    Parameters
    ----------
    W : (m, m) ndarray
        A contact compliance (symmetrised here).

    Returns
    -------
    (m, m) ndarray
        Symmetric ``K``, the capacitance.
    """
    return _Factor(np.asarray(W, dtype=np.float64)).inverse()


def _response_columns(gf: Any, cols: np.ndarray, loc: np.ndarray, weights: np.ndarray,
                      compiled: bool = False) -> np.ndarray:
    """Full-surface response ``D[:, U] B`` of contacts on the vertex list U, (3n, 3k), F-ordered.

    ``cols``: column dofs of U (``-1`` at clamped vertices); ``loc`` (k, P):
    positions in U of each contact's vertices, ``weights`` (k, P) theirs.
    ``compiled``: through :func:`hailstorm.runtime.compiled.blocks.weighted_rows`.
    """
    D = gf.D
    if compiled:
        blocks = np.where(cols[::3] >= 0, cols[::3] // 3, -1)
        zeros = np.zeros((loc.shape[0], 3))
        return _kernels.weighted_rows(np.asarray(D).T, blocks, loc, weights, zeros, True).T
    live = np.flatnonzero(cols >= 0)
    BT = _gT_csr(cols.size // 3, loc, weights, np.zeros((loc.shape[0], 3)), "sticky")[:, live]
    if D.flags.f_contiguous:
        Dt = np.take(D.T, cols[live], axis=0)  # columns of D = contiguous rows of D^T, (c, 3n)
    else:
        Dt = np.ascontiguousarray(np.asarray(D[:, cols[live]]).T)
    return np.asarray(BT @ Dt).T  # (3n, 3k), F-ordered


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


def _rigid(gf: Any, verts: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Contacts whose weight (on the (s, P) vertex lists ``verts``) lies entirely on clamped vertices."""
    free_w = np.where(gf.fixed[verts], 0.0, np.abs(w)).sum(axis=1)
    return free_w <= 1e-12


# --------------------------------------------------------------------------
# validation
# --------------------------------------------------------------------------
@overload
def _check_contacts(gf: Any, tri_idx: Any, bary: Any, normals: Any = None,
                    need_normals: Literal[True] = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


@overload
def _check_contacts(gf: Any, tri_idx: Any, bary: Any, normals: Any,
                    need_normals: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]: ...


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


def _check_mode(mode: str) -> Mode:
    if mode not in ("sticky", "frictionless"):
        raise ValueError(f"mode must be 'sticky' or 'frictionless', got {mode!r}")
    return cast(Mode, mode)


# --------------------------------------------------------------------------
# capacitance
# --------------------------------------------------------------------------
@dataclass(eq=False)
class Capacitance:
    """The capacitance (effective contact stiffness) of a set of point or patch contacts.

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
        Barycentric coordinates of the contact points (patch centres).
    normals : (s, 3) float ndarray
        Outward unit normals (used by frictionless and unilateral contact,
        and as the plane of a patch).
    V : (|V|,) int ndarray
        Sorted union of the vertices carrying the contacts' forces (the
        contacted triangles' vertices for point contacts).
    loc : (s, P) int ndarray
        Position in ``V`` of each contact's weighted vertices (B's sparsity;
        ``P = 3`` for point contacts).
    weights : (s, P) float ndarray
        Force-distribution weights (block ``(loc[k, j], k)`` of B is
        ``weights[k, j] I3``): ``bary`` for point contacts, the patch
        weights of :func:`hailstorm.runtime.weights.patch_weights` otherwise.
    patch_radius : (s,) float ndarray
        Patch radius of each contact [m]; 0 for point contacts.
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

    For a contact set that persists over many solves (a resting stone, a
    haptic probe held still), :meth:`keep_response` stores the full-surface
    response ``D[:, V] B`` once; every later :meth:`surface_displacement` of
    the whole surface is then one matrix-vector product with it instead of a
    gather of the columns of ``D``, and :meth:`add` / :meth:`remove` update it
    by columns.
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
    weights: np.ndarray
    patch_radius: np.ndarray
    _factor: _Factor | None = field(default=None, repr=False)  # set unless _K is (see _solve_live)
    _K: np.ndarray | None = field(default=None, repr=False)
    _R: np.ndarray | None = field(default=None, repr=False)  # kept full-surface response D[:, V] B
    #: pressure profile of the patches ("hertz" or "uniform")
    patch_profile: str = "hertz"
    #: radius :meth:`add` uses when not given (a scalar ``patch_radius`` at build; else 0)
    default_patch_radius: float = 0.0
    #: ``"numba"``: the build and the full-surface products use the compiled kernels
    #: (:mod:`hailstorm.runtime.compiled.blocks`); ``"numpy"``: numpy only
    backend: str = "numpy"

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
        """Force-distribution matrix B, (3|V|, 3s) (see :func:`barycentric_matrix`, :func:`patch_matrix`)."""
        return _dense_B(self.V.size, self.loc, self.weights)

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
            self._K = self._live_factor().inverse()
        return self._K

    def _live_factor(self) -> _Factor:
        """The factorisation of ``W[live, live]`` (kept while ``K`` is not formed explicitly)."""
        if self._factor is None:  # pragma: no cover - invariant: _factor or _K is always set
            raise RuntimeError("capacitance has neither a factorisation nor an explicit K")
        return self._factor

    def _solve_live(self, c: np.ndarray) -> np.ndarray:
        """``K c`` over the live components."""
        return self._K @ c if self._K is not None else self._live_factor().solve(c)

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
        if not self.rigid.any():  # every component is live (the common case: no index juggling)
            return self._solve_live(c)
        live = self.live_dofs
        lam = np.zeros_like(c)
        if live.size:
            lam[live] = self._solve_live(c[live])
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
        return _vertex_forces(self.V.size, self.loc, self.weights, np.asarray(forces, dtype=np.float64).reshape(-1, 3))

    def contact_displacement(self, forces: np.ndarray) -> np.ndarray:
        """Contact-point displacements ``B^T D_VV B f_s`` caused by contact forces, (s, 3)."""
        g = self.vertex_forces(forces).reshape(-1)
        return _interpolate((self.D_VV @ g).reshape(-1, 3), self.loc, self.weights)

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
        if rows is None and self._R is not None:
            f = np.asarray(forces, dtype=np.float64).reshape(-1)
            if f.size != self._R.shape[1]:
                raise ValueError(f"forces must have shape ({self.s}, 3), got {np.shape(forces)}")
            return (self._R @ f).reshape(-1, 3)
        g = self.vertex_forces(forces).reshape(-1)
        return _apply_columns(self.gf, self._cols, g, rows, _compiled(self.gf, self.backend))

    def keep_response(self) -> np.ndarray:
        """Form (once) and keep the full-surface response ``R = D[:, V] B``.

        ``R`` maps contact forces to the displacement of every surface vertex:
        ``u = R @ forces.ravel()``. Once kept, :meth:`surface_displacement`
        with ``rows=None`` is that one product (``3n x 3s`` doubles, read in
        one contiguous pass) instead of gathering the contacted columns of
        ``D`` on every call; :meth:`add` appends the new contact's columns and
        :meth:`remove` deletes them. Worth it when one contact set is solved
        many times (measured in ``tests/benchmarks/bench_contacts.py``: on the
        default seat at s = 100, forces + full-surface displacement take
        0.24 ms against 5-8 ms for a fresh solve; building the capacitance and
        forming R cost 9 ms). Memory: ``3n x 3s`` doubles (11 MB at n = 1557, s = 100).

        Returns
        -------
        (3n, 3s) float ndarray
            Vertex-major rows, contact-major columns (the kept array itself:
            do not modify it).
        """
        if self._R is None:
            self._R = _response_columns(self.gf, self._cols, self.loc, self.weights,
                                        _compiled(self.gf, self.backend))
        return self._R

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
        GT = _gT_csr(self.V.size, self.loc, self.weights, self.normals, self.mode)
        return np.asarray(GT @ M.T).T

    # -- low-rank updates ----------------------------------------------------
    def add(self, tri: int, bary: Sequence[float], normal: Sequence[float] | None = None,
            patch_radius: float | None = None) -> int:
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
        patch_radius : float, optional
            Patch radius [m] (0: point contact); default
            :attr:`default_patch_radius`.

        Returns
        -------
        int
            Index of the new contact.
        """
        t, b, n = _check_contacts(
            self.gf, np.array([tri], dtype=np.intp), np.asarray(bary, dtype=np.float64).reshape(1, 3),
            None if normal is None else np.asarray(normal, dtype=np.float64).reshape(1, 3),
        )
        a_new = self.default_patch_radius if patch_radius is None else float(patch_radius)
        pv, pw = _contact_weights(self.gf, t, b, n, np.array([a_new]), self.patch_profile, self.backend)
        gf = self.gf
        old_s = self.s
        p = self.per_contact
        K_old = self.K if self.exact else None
        # grow V (kept sorted) and D_VV: gather only the new rows / columns of D
        tv = pv[0]
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
        rigid_new = bool(_rigid(gf, pv, pw)[0])
        # new blocks of W: c = G_old^T D_VV G_new, d = G_new^T D_VV G_new
        # D_VV B_new, (3|V|, 3): columns (vertex b, component y) weighted by w_b
        DGn = np.einsum("rby,b->ry", D_VV[:, _dof3(loc_new[0])].reshape(D_VV.shape[0], -1, 3), pw[0])
        if self.mode != "sticky":
            DGn = DGn @ n[0][:, None]
        c = _gT(DGn, loc_old, self.weights, self.normals, self.mode)  # (m_old, p)
        d = _gT(DGn, loc_new, pw, n, self.mode)
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
        P = max(loc_old.shape[1], loc_new.shape[1])
        lo, wo = _pad(loc_old, self.weights, P)
        ln, wn = _pad(loc_new, pw, P)
        self.loc = np.vstack([lo, ln])
        self.weights = np.vstack([wo, wn])
        self.patch_radius = np.append(self.patch_radius, a_new)
        self.V, self.D_VV, self.W, self._cols = V, D_VV, W, cols
        self.rigid = np.append(self.rigid, rigid_new)
        if self._R is not None:
            Rn = _response_columns(gf, _column_dofs(gf, tv), np.arange(tv.size)[None, :], pw)
            self._R = np.asfortranarray(np.hstack([self._R, Rn]))
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
            Contact index, ``0 <= k < s`` (like a triangle index, a negative
            index is refused, not counted from the end).

        Raises
        ------
        IndexError
            ``k`` out of range.
        TypeError
            ``k`` not an integer.
        """
        s = self.s
        if isinstance(k, bool) or not isinstance(k, (int, np.integer)):
            raise TypeError(f"contact index must be an integer, got {k!r}")
        k = int(k)
        if not 0 <= k < s:
            raise IndexError(f"contact index {k} out of range for {s} contacts (0 <= k < {s})")
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
        self.weights, self.patch_radius = self.weights[keep], self.patch_radius[keep]
        self.rigid = self.rigid[keep]
        if self._R is not None:
            self._R = np.delete(self._R, np.arange(3 * k, 3 * k + 3), axis=1)
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
    patch_radius: Any = None,
    patch_profile: str = "hertz",
    backend: str = "auto",
) -> Capacitance:
    """Build the capacitance of a set of point or patch contacts.

    Parameters
    ----------
    gf : GreensFunctions
        Loaded bundle (see :func:`hailstorm.runtime.bundle.load`).
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
    patch_radius : None, float or (s,) float array_like
        ``None`` (default) or 0: point contacts (force on the contacted
        triangle's vertices with the barycentric weights). A radius ``a > 0``
        [m] spreads each contact's force over the disc of radius ``a`` around
        the contact point with the pressure ``patch_profile`` (see
        :mod:`hailstorm.runtime.weights`; :func:`hertz_radius` gives the physical
        radius for a load). A scalar is also the radius :meth:`Capacitance.add`
        uses by default.
    patch_profile : {"hertz", "uniform"}
        Pressure profile over a patch.
    backend : {"auto", "numba", "numpy"}
        ``"auto"`` (default) builds ``D_VV`` and ``W`` with the compiled kernels
        of :mod:`hailstorm.runtime.compiled.blocks` when numba is installed and D is
        column-major (as bundles are written), and so do the full-surface
        products of :meth:`Capacitance.surface_displacement` and
        :meth:`Capacitance.keep_response`. Same results to rounding.

    Returns
    -------
    Capacitance

    Raises
    ------
    ValueError, IndexError
        On malformed input (see :func:`solve_contacts`).
    """
    mode = _check_mode(mode)
    backend = resolve_backend(backend)
    t, b, n = _check_contacts(gf, tri_idx, bary, normals)
    a = _check_patch(patch_radius, t.size, patch_profile)
    cap = _build(gf, t, b, n, mode, a, patch_profile, backend)
    if patch_radius is not None and np.ndim(patch_radius) == 0:
        cap.default_patch_radius = float(patch_radius)
    return cap


def _check_patch(patch_radius: Any, s: int, profile: str) -> np.ndarray | None:
    """Patch radii as an (s,) array, or None for point contacts only."""
    from hailstorm.runtime.weights import PATCH_PROFILES

    if profile not in PATCH_PROFILES:
        raise ValueError(f"patch_profile must be one of {PATCH_PROFILES}, got {profile!r}")
    if patch_radius is None:
        return None
    a = np.asarray(patch_radius, dtype=np.float64)
    if a.ndim > 1 or (a.ndim == 1 and a.shape != (s,)):
        raise ValueError(f"patch_radius must be a scalar or have shape ({s},), got {a.shape}")
    if not np.isfinite(a).all() or np.any(a < 0):
        raise ValueError("patch_radius must be finite and non-negative")
    a = np.broadcast_to(a, (s,)).copy()
    return a if a.any() else None


def _contact_weights(gf: Any, t: np.ndarray, b: np.ndarray, n: np.ndarray | None, a: np.ndarray | None,
                     profile: str, backend: str = "numpy") -> tuple[np.ndarray, np.ndarray]:
    """(s, P) vertex lists and weights: barycentric (point) or patch."""
    if a is None or not a.any():
        return np.asarray(gf.triangles)[t], b
    return patch_weights(gf, t, b, a, n, profile=profile, backend=backend)


def _build(gf: Any, t: np.ndarray, b: np.ndarray, n: np.ndarray | None, mode: Mode,
           a: np.ndarray | None = None, profile: str = "hertz", backend: str = "numpy") -> Capacitance:
    """The capacitance of validated contacts. ``n`` may be None only for sticky point
    contacts (which never look at the normals; they are then stored as zeros).
    ``backend``: resolved (``"numba"`` or ``"numpy"``)."""
    if n is None:
        if mode != "sticky" or a is not None:
            raise ValueError("normals are needed for frictionless and patch contacts")  # pragma: no cover
        n = np.zeros((t.size, 3))
    pv, w = _contact_weights(gf, t, b, n, a, profile, backend)
    V, loc = _locate_lists(pv)
    cols = _column_dofs(gf, V)
    compiled = _compiled(gf, backend)
    if compiled:
        M = _kernels.vertex_block(V, np.asarray(gf.D).T, gf.column_of)  # D_VV^T
        D_VV = M.T
        Y = _kernels.weighted_rows(M, np.arange(V.size), loc, w, n, mode == "sticky")
        W = _kernels.contact_compliance(Y, loc, w, n, mode == "sticky")
    else:
        D_VV = _gather_vertices(gf, V, cols)
        W = _contact_compliance(D_VV, loc, w, n, mode)
    rigid = _rigid(gf, pv, w)
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
        W=W, rigid=rigid, exact=factor.exact, _cols=cols, _factor=factor, weights=w,
        patch_radius=np.zeros(t.size) if a is None else a, patch_profile=profile, backend=backend,
    )
