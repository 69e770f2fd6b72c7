"""The capacitance object of a contact set: W = G^T D_VV G, its factorisation, low-rank updates, the active set.

The unilateral solve's own parts (the result :class:`ActiveSet`, the convex QP
:func:`nonnegative_qp` and their tolerances) are in :mod:`hailstorm.runtime.contact.active_set`.

See :mod:`hailstorm.runtime.contact` for the notation, sign conventions and the
documented degenerate cases; the tolerances are in
:mod:`hailstorm.runtime.contact.policy`. The blocks of D and the contact
compliance are the compiled kernels of :mod:`hailstorm.runtime.compiled.blocks` and
:mod:`hailstorm.runtime.compiled.wmatrix`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from hailstorm.runtime.compiled import blocks as kernels
from hailstorm.runtime.compiled import wmatrix as w_kernels
from hailstorm.runtime.contact.active_set import (ACTIVE_SET_TOL, BLOCK_PIVOT_ROUNDS, QP_SHIFT, ActiveSet,
                                                  nonnegative_qp)
from hailstorm.runtime.bundle.compliance import (
    ComplianceSource,
    apply_columns,
    column_dofs,
    constraint_rows,
    dof3,
    gather,
    response_columns,
    vertex_block,
)
from hailstorm.runtime.contact.policy import COND_LIMIT, EMBED_BLOCKS_FROM, SUBSET_REUSE_FROM, SPDFactor, is_rigid
from hailstorm.runtime.contact.validate import ContactMode, Mode, check_contacts, check_mode, check_patch
from hailstorm.runtime.contact.near_field import NearField, near_field
from hailstorm.runtime.contact.weights import (
    contact_points,
    dense_B,
    interpolate,
    locate,
    pad,
    patch_weights,
    vertex_forces,
)

__all__ = ["ACTIVE_SET_TOL", "ActiveSet", "Capacitance", "build", "capacitance", "contact_compliance", "from_weights",
           "nonnegative_qp"]  # (the active set's names re-exported: its module is the seam's other side)


def _constraint_rows(M: np.ndarray, loc: np.ndarray, w: np.ndarray, normals: np.ndarray, mode: Mode) -> np.ndarray:
    """``G^T M`` for a C-contiguous M with rows indexed by V-dofs (3|V|, q): (m, q)."""
    return kernels.weighted_rows(M, np.arange(M.shape[0] // 3), np.ascontiguousarray(loc, dtype=np.intp),
                                 np.ascontiguousarray(w, dtype=np.float64),
                                 np.ascontiguousarray(normals, dtype=np.float64), ContactMode(mode).sticky)


def contact_compliance(D_VV: np.ndarray, loc: np.ndarray, w: np.ndarray, normals: np.ndarray,
                       mode: Mode) -> np.ndarray:
    """The contact compliance ``W = G^T D_VV G`` (symmetrised) of a gathered block ``D_VV``.

    Parameters
    ----------
    D_VV : (3|V|, 3|V|) float ndarray
        The block of D (:func:`hailstorm.runtime.bundle.compliance.vertex_block`).
    loc, w : (s, P) int / float ndarrays
        Position in V and weight of each contact's vertices.
    normals : (s, 3) float ndarray
        Unit normals (read by frictionless contacts).
    mode : {"sticky", "frictionless"}

    Returns
    -------
    (m, m) float ndarray
        ``m = 3s`` (sticky) or ``s`` (frictionless).
    """
    # G^T D_VV^T G = W^T: the kernels read the C-contiguous one of D_VV and its transpose
    M = D_VV.T if D_VV.flags.f_contiguous and not D_VV.flags.c_contiguous else np.ascontiguousarray(D_VV)
    Y = _constraint_rows(M, loc, w, normals, mode)
    return w_kernels.contact_compliance(Y, np.ascontiguousarray(loc, dtype=np.intp),
                                      np.ascontiguousarray(w, dtype=np.float64),
                                      np.ascontiguousarray(normals, dtype=np.float64), ContactMode(mode).sticky)


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



@dataclass(eq=False)
class Capacitance:
    """The capacitance (effective contact stiffness) of a set of point or patch contacts.

    Build with :func:`capacitance`. All arrays refer to the contacts in the
    order given (after :meth:`add` the new contact is last; :meth:`remove`
    keeps the order of the rest).

    Attributes
    ----------
    gf : ComplianceSource
        The bundle.
    mode : {"sticky", "frictionless"}
    tri_idx : (s,) int ndarray
    bary : (s, 3) float ndarray
        Barycentric coordinates of the contact points (patch centres).
    normals : (s, 3) float ndarray
        Outward unit normals (used by frictionless and unilateral contact,
        and as the plane of a patch).
    V : (len(V),) int ndarray
        Sorted union of the vertices carrying the contacts' forces (the
        contacted triangles' vertices for point contacts).
    loc : (s, P) int ndarray
        Position in ``V`` of each contact's weighted vertices (B's sparsity;
        ``P = 3`` for point contacts).
    weights : (s, P) float ndarray
        Force-distribution weights (block ``(loc[k, j], k)`` of B is
        ``weights[k, j] I3``): ``bary`` for point contacts, the patch
        weights of :func:`hailstorm.runtime.contact.weights.patch_weights` otherwise.
    patch_radius : (s,) float ndarray
        Patch radius of each contact [m]; 0 for point contacts.
    local : (s, p, p) float ndarray
        The near-field blocks added to the diagonal of ``W``
        (:meth:`hailstorm.runtime.contact.near_field.NearField.blocks`; zero
        without a near field), ``p`` = :attr:`per_contact`.
    near : NearField or None
        The near field resolved at build (:func:`hailstorm.runtime.contact.near_field.near_field`).
    D_VV : (3|V|, 3|V|) float ndarray
        Compliance block ``D[V, V]`` (zero columns at clamped vertices),
        gathered on first use (a fresh solve never needs it).
    column_dofs : (3|V|,) int ndarray
        Column dofs of D for V (-1 at clamped vertices).
    W : (m, m) float ndarray
        Contact compliance ``G^T D_VV G + blockdiag(local)`` over *all* constrained components
        (``G = B`` sticky, ``m = 3s``; ``G = B N`` frictionless, ``m = s``).
        Rows/columns of rigid contacts are zero.
    rigid : (s,) bool ndarray
        Contacts whose weight lies entirely on clamped vertices.
    exact : bool
        True if ``K`` is the true inverse; False if ``W`` was singular or ill
        conditioned and ``K`` is its pseudo-inverse.

    Notes
    -----
    :meth:`solve` is the active-set solve (what :func:`solve_contacts` runs);
    :meth:`forces` its bilateral case. A fresh build keeps the Cholesky factor of ``W[live, live]``
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

    gf: ComplianceSource
    mode: ContactMode
    tri_idx: np.ndarray
    bary: np.ndarray
    normals: np.ndarray
    V: np.ndarray
    loc: np.ndarray
    W: np.ndarray
    rigid: np.ndarray
    exact: bool
    column_dofs: np.ndarray = field(repr=False)
    weights: np.ndarray
    patch_radius: np.ndarray
    _factor: SPDFactor | None = field(default=None, repr=False)  # set unless _K is (see _solve_live)
    _K: np.ndarray | None = field(default=None, repr=False)
    _R: np.ndarray | None = field(default=None, repr=False)  # kept full-surface response D[:, V] B
    _D_VV: np.ndarray | None = field(default=None, repr=False)  # gathered on first use
    _Y: np.ndarray | None = field(default=None, repr=False)  # (D_VV G)^T of the build (until add/remove)
    #: pressure profile of the patches ("hertz" or "uniform")
    patch_profile: str = "hertz"
    #: radius :meth:`add` uses when not given (a scalar ``patch_radius`` at build; else 0)
    default_patch_radius: float = 0.0
    local: np.ndarray | None = None
    near: NearField | None = None

    def __post_init__(self) -> None:
        self.mode = ContactMode(self.mode)
        if self.local is None:
            self.local = np.zeros((self.s, self.per_contact, self.per_contact))

    # -- sizes and derived matrices ------------------------------------------
    @property
    def s(self) -> int:
        """Number of contacts."""
        return int(self.tri_idx.size)

    @property
    def per_contact(self) -> int:
        """Constrained components per contact: 3 (sticky) or 1 (frictionless)."""
        return self.mode.dofs

    @property
    def D_VV(self) -> np.ndarray:
        """Compliance block ``D[V, V]``, (3|V|, 3|V|) (zero columns at clamped vertices)."""
        if self._D_VV is None:
            self._D_VV = vertex_block(self.gf, self.V)
        return self._D_VV

    @property
    def live_dofs(self) -> np.ndarray:
        """Indices into ``W`` of the constrained components of non-rigid contacts."""
        p = self.per_contact
        live = np.flatnonzero(~self.rigid)
        return (p * live[:, None] + np.arange(p)).ravel()

    @property
    def B(self) -> np.ndarray:
        """Force-distribution matrix B, (3|V|, 3s) (see :func:`barycentric_matrix`, :func:`patch_matrix`)."""
        return dense_B(self.V.size, self.loc, self.weights)

    @property
    def G(self) -> np.ndarray:
        """Constraint matrix ``B`` (sticky) or ``B N`` (frictionless), (3|V|, m)."""
        B = self.B
        if self.mode.sticky:
            return B
        return np.einsum("rkj,kj->rk", B.reshape(B.shape[0], self.s, 3), self.normals)

    def loaded_columns(self) -> tuple[np.ndarray, np.ndarray]:
        """The columns of D the contacts load and the forces on them per unit multiplier.

        Returns
        -------
        cols : (c,) int ndarray
            Column dofs of D of the non-clamped dofs of V (vertex-major).
        G : (c, m) float ndarray
            Rows ``cols`` of :attr:`G`: the surface displacement per unit
            multiplier is ``D[:, cols] @ G``.
        """
        loaded = self.column_dofs >= 0
        return self.column_dofs[loaded], np.ascontiguousarray(self.G[loaded])

    def vertex_response(self) -> np.ndarray:
        """Displacement of the vertices V per unit constraint multiplier, ``D_VV G``, (3|V|, m).

        From the build's ``(D_VV G)^T`` (no ``D_VV`` needed) until :meth:`add`
        or :meth:`remove`; then from ``D_VV``.
        """
        if self._Y is not None and self._Y.shape[0] == self.W.shape[0]:
            return np.ascontiguousarray(self._Y.T)
        return self.D_VV @ self.G

    @property
    def K(self) -> np.ndarray:
        """Capacitance ``W[live, live]^-1`` (pseudo-inverse if not :attr:`exact`), (a, a).

        ``live`` = :attr:`live_dofs`: rigid contacts are excluded.
        """
        if self._K is None:
            self._K = self._live_factor().inverse()
        return self._K

    def _live_factor(self) -> SPDFactor:
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
        if self.mode.sticky:
            return ubar.reshape(-1)
        return np.einsum("ki,ki->k", ubar, self.normals)

    def _expand(self, lam: np.ndarray) -> np.ndarray:
        """Constraint multipliers (m,) -> contact forces (s, 3)."""
        if self.mode.sticky:
            return lam.reshape(-1, 3)
        return lam[:, None] * self.normals

    def _multipliers(self, c: np.ndarray) -> np.ndarray:
        """Multipliers (m,) of all live contacts for constrained components ``c``."""
        if not self.rigid.any():  # every component is live (the common case: no index juggling)
            return self._solve_live(c)
        live = self.live_dofs
        lam = np.zeros_like(c)
        if live.size:
            lam[live] = self._solve_live(c[live])
        return lam

    def _subset_multipliers(self, c: np.ndarray, act: np.ndarray) -> np.ndarray:
        """Multipliers (m,) with only the (non-rigid) contacts ``act`` constrained: ``W[a, a] x = c[a]``.

        While few live components are released (``r``), the factor of ``W[live, live]``
        serves: with ``K = W^-1`` over the live components, ``W_aa^-1 = K_aa - K_ar
        K_rr^-1 K_ra`` (the inverse of a principal block by its Schur complement), so
        ``x = y_a - K_ar K_rr^-1 y_r`` for ``y = K [c_a; 0]``: ``|r| + 1`` solves with the
        kept factor (or columns of an explicit ``K``) and an ``|r| x |r|`` factor, no
        ``O(|a|^3)`` re-factorisation. ``W_aa`` is a principal block of an SPD ``W``,
        no worse conditioned. Many released, few active (below
        :data:`~hailstorm.runtime.contact.policy.SUBSET_REUSE_FROM`), a pseudo-inverse,
        or an ill-conditioned ``K_rr``: a fresh factorisation of ``W[a, a]`` (the one
        policy, :class:`SPDFactor`).
        """
        p = self.per_contact
        dofs = (p * np.flatnonzero(act)[:, None] + np.arange(p)).ravel()
        lam = np.zeros(self.W.shape[0])
        if dofs.size == 0:
            return lam
        live = self.live_dofs
        na, nl = dofs.size, live.size
        nr = nl - na
        # reuse when its solves (~2 nl^2 flops per column, 3x potrf's rate) cost less than the factor
        if self.exact and 0 < nr and na >= SUBSET_REUSE_FROM and 6 * (nr + 1) * nl * nl + nr ** 3 < na ** 3:
            keep = np.zeros(nl, bool)
            keep[np.searchsorted(live, dofs)] = True  # act's components among the live ones
            r = np.flatnonzero(~keep)
            z = np.zeros(nl)
            z[keep] = c[dofs]
            y = self._solve_live(z)
            if self._K is not None:
                Kr = self._K[:, r]
            else:
                E = np.zeros((nl, nr))
                E[r, np.arange(nr)] = 1.0
                Kr = self._live_factor().solve(E)
            Frr = SPDFactor(Kr[r], symmetric=False)
            if Frr.exact:
                x = y - Kr @ Frr.solve(y[r])
                lam[dofs] = x[keep]
                return lam
        W_aa = self.W.take(dofs, axis=0).take(dofs, axis=1)
        lam[dofs] = SPDFactor(W_aa, symmetric=True).solve(c[dofs])
        return lam

    def solve(self, ubar: np.ndarray, *, unilateral: bool = False, max_iter: int | None = None) -> ActiveSet:
        """Contact forces for prescribed contact-point displacements, optionally unilateral.

        Parameters
        ----------
        ubar : (s, 3) float ndarray
            Prescribed contact-point displacements [m] (frictionless: only
            ``ubar . n`` is imposed).
        unilateral : bool
            Contacts may only push: a contact whose force would pull
            (``f . n > 0``) is released and the rest re-solved; a released
            contact is re-activated if the seat would penetrate the prescribed
            position (``(u - ubar) . n > 0``). Active-set iteration (block
            pivoting); frictionless, once a set repeats, after
            :data:`BLOCK_PIVOT_ROUNDS` rounds, or at once for a ``W`` singular to
            working precision (then with a contact compliance of
            :data:`QP_SHIFT`), the convex QP's projected Newton method
            (:func:`nonnegative_qp`, which converges for any SPD ``W``);
            sticky, one flip per iteration once a set repeats (a sticky
            contact is released as a whole). Needs the contact normals.
        max_iter : int, optional
            Bound on active-set iterations (default ``2 s + 10``; the QP's
            iterations are bounded by it separately); a positive integer.

        Returns
        -------
        ActiveSet

        Raises
        ------
        ValueError
            ``ubar`` of the wrong shape or not finite; ``unilateral`` without normals;
            ``max_iter`` not a positive integer.
        RuntimeError
            The active set did not settle within ``max_iter`` iterations.
        """
        ubar = self._displacements(ubar)
        s = self.s
        if max_iter is not None and (isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer))
                                     or max_iter < 1):
            raise ValueError(f"max_iter must be a positive integer (active-set iterations), got {max_iter!r}")
        rigid = self.rigid
        c = self._reduce(ubar)
        it = 1
        active = ~rigid
        lam = self._multipliers(c)
        if unilateral:
            n = self.normals
            if s and not np.any(n, axis=1).all():
                raise ValueError("unilateral contact needs the contact normals")
            p = self.per_contact
            cn = np.einsum("ki,ki->k", ubar, n)
            seen: set[bytes] = set()
            limit = 2 * s + 10 if max_iter is None else int(max_iter)
            single = False
            for it in range(1, limit + 1):
                if it > 1:
                    lam = self._subset_multipliers(c, active)
                fn = np.einsum("ki,ki->k", self._expand(lam), n)
                wl = self.W @ lam  # constrained components of the contact displacement
                un = np.einsum("ki,ki->k", wl.reshape(s, 3), n) if p == 3 else wl
                fscale = max(float(np.abs(fn).max(initial=0.0)), np.finfo(float).tiny)
                uscale = max(float(np.abs(cn).max(initial=0.0)), float(np.abs(un).max(initial=0.0)),
                             np.finfo(float).tiny)
                pull = active & (fn > ACTIVE_SET_TOL * fscale)
                pen = ~active & ~rigid & (un - cn > ACTIVE_SET_TOL * uscale)
                viol = np.flatnonzero(pull | pen)
                if viol.size == 0:
                    break
                key = active.tobytes()
                if p == 1 and (key in seen or it >= BLOCK_PIVOT_ROUNDS or not self.exact):
                    # frictionless: the convex QP's solver, which cannot cycle, from here
                    lam, active, extra = self._unilateral_qp(c, lam, limit, cn)
                    it += extra
                    break
                if key in seen:
                    single = True  # block pivoting cycled: one flip per iteration
                seen.add(key)
                if single:
                    viol = viol[-1:]
                active = active.copy()
                active[viol] = ~active[viol]
            else:
                raise RuntimeError(f"unilateral contact: active set did not settle in {limit} iterations")
        f = self._expand(lam)
        if not active.all():
            f = np.where(active[:, None], f, 0.0)
        if not active.all():
            lam = np.where(np.repeat(active, self.per_contact), lam, 0.0)
        return ActiveSet(forces=f, active=active, iterations=it, multipliers=lam)

    def _unilateral_qp(self, c: np.ndarray, lam: np.ndarray, limit: int,
                       cn: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """The frictionless unilateral solve as the convex QP :func:`nonnegative_qp` over
        the live contacts (``x = -lambda``: ``min 1/2 x^T W x + c^T x``, ``x >= 0``), from
        the block-pivoting iterate; then the set it finds re-solved exactly
        (:meth:`_subset_multipliers`, as block pivoting ends) when that meets the same
        tolerances, else the QP's own multipliers. Returns ``(lam, active, iterations)``."""
        live = np.flatnonzero(~self.rigid)
        W = self.W[np.ix_(live, live)]
        x0 = np.maximum(-lam[live], 0.0)
        if not self.exact and live.size:  # singular (more contacts than the seat's vertices can tell
            # apart): a contact compliance of QP_SHIFT of the mean one makes the minimiser unique; the
            # pseudo-inverse's multipliers are no useful start
            W = W + QP_SHIFT * float(np.diag(W).mean()) * np.eye(live.size)
            x0 = None
        x, iters = nonnegative_qp(W, c[live], x0, tol=ACTIVE_SET_TOL, max_iter=limit)
        active = np.zeros(self.s, bool)
        active[live[x > 0]] = True
        exact = self._subset_multipliers(c, active)
        un2 = self.W @ exact
        fscale = max(float(np.abs(exact).max(initial=0.0)), np.finfo(float).tiny)
        uscale = max(float(np.abs(cn).max(initial=0.0)), float(np.abs(un2).max(initial=0.0)), np.finfo(float).tiny)
        ok = not (active & (exact > ACTIVE_SET_TOL * fscale)).any() and \
            not (~active & ~self.rigid & (un2 - cn > ACTIVE_SET_TOL * uscale)).any()
        if ok:
            return exact, active, iters
        lam = np.zeros(self.s)
        lam[live] = -x
        return lam, active, iters

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
        return self._expand(self._multipliers(self._reduce(self._displacements(ubar))))

    def _displacements(self, ubar: np.ndarray) -> np.ndarray:
        """Prescribed contact-point displacements checked (real, finite, (s, 3)) as float64."""
        if np.iscomplexobj(ubar) or np.asarray(ubar).dtype.kind not in "biuf":
            raise ValueError(f"displacements must be real numbers [m], got {np.asarray(ubar).dtype}")
        ubar = np.asarray(ubar, dtype=np.float64)
        if ubar.shape != (self.s, 3):
            raise ValueError(f"displacements must have shape ({self.s}, 3) to match the contacts, got {ubar.shape}")
        if not np.isfinite(ubar).all():
            raise ValueError("displacements contain NaN or infinity")
        return ubar

    def vertex_forces(self, forces: np.ndarray) -> np.ndarray:
        """Vertex forces ``f_V = B f_s`` as a (len(V), 3) array."""
        return vertex_forces(self.V.size, self.loc, self.weights, np.asarray(forces, dtype=np.float64).reshape(-1, 3))

    def vertex_displacement(self, solution: ActiveSet) -> np.ndarray:
        """Displacement of the vertices V under a solution's forces, ``D_VV B f``, (len(V), 3).

        Right after the build this is ``Y^T lam`` with the build's
        ``Y = (D_VV G)^T`` (no ``D_VV`` needed); after :meth:`add` or
        :meth:`remove`, ``D_VV`` times the vertex forces.
        """
        if self._Y is not None and solution.multipliers.size == self._Y.shape[0]:
            return (self._Y.T @ solution.multipliers).reshape(-1, 3)
        return (self.D_VV @ self.vertex_forces(solution.forces).reshape(-1)).reshape(-1, 3)

    def contact_displacement(self, forces: np.ndarray) -> np.ndarray:
        """Contact-point displacements ``B^T D_VV B f_s`` (plus the near field's ``local f_s``)
        caused by contact forces, (s, 3)."""
        f = np.asarray(forces, dtype=np.float64).reshape(-1, 3)
        g = self.vertex_forces(f).reshape(-1)
        return interpolate((self.D_VV @ g).reshape(-1, 3), self.loc, self.weights) + self.near_displacement(f)

    def near_displacement(self, forces: np.ndarray) -> np.ndarray:
        """The near field's share of the contact-point displacements, ``local f_s``, (s, 3)
        (zero without a near field; frictionless: along the normals)."""
        f = np.asarray(forces, dtype=np.float64).reshape(-1, 3)
        if self.local is None or not self.local.any():
            return np.zeros_like(f)
        if self.mode.sticky:
            return np.einsum("kij,kj->ki", self.local, f)
        return (self.local[:, 0, 0] * np.einsum("ki,ki->k", f, self.normals))[:, None] * self.normals

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
        return apply_columns(self.gf, self.column_dofs, g, rows)

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
            self._R = response_columns(self.gf, self.column_dofs, self.loc, self.weights)
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
        M = gather(self.gf, dof3(r), self.column_dofs)  # D[rows, V], (3r, 3|V|)
        return _constraint_rows(np.ascontiguousarray(M.T), self.loc, self.weights, self.normals, self.mode).T

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
        t, b, n = check_contacts(
            self.gf, np.array([tri], dtype=np.intp), np.asarray(bary, dtype=np.float64).reshape(1, 3),
            None if normal is None else np.asarray(normal, dtype=np.float64).reshape(1, 3),
        )
        a_new = self.default_patch_radius if patch_radius is None else float(patch_radius)
        pv, pw = _contact_weights(self.gf, t, b, n, np.array([a_new]), self.patch_profile)
        L_new = _near_blocks(self.gf, self.near, t, b, n, np.array([a_new]), pv, pw, self.mode)
        if L_new is None:
            L_new = np.zeros((1, self.per_contact, self.per_contact))
        gf = self.gf
        old_s = self.s
        p = self.per_contact
        K_old = self.K if self.exact else None
        # grow V (kept sorted) and D_VV: gather only the new rows / columns of D
        tv = pv[0]
        newv = np.setdiff1d(tv, self.V)
        V = np.union1d(self.V, newv).astype(np.intp)
        pos_old = np.searchsorted(V, self.V)
        cols = column_dofs(gf, V)
        if newv.size:
            # insert the new vertices' rows/columns (slice copies, V stays sorted)
            pn = dof3(np.searchsorted(V, newv))
            po = np.delete(np.arange(3 * V.size), pn)
            D_VV = _embed(self.D_VV, po, 3 * V.size)
            D_VV[:, pn] = gather(gf, dof3(V), cols[pn])
            D_VV[np.ix_(pn, po)] = gather(gf, dof3(newv), cols[po])
        else:
            D_VV = self.D_VV
        loc_old = pos_old[self.loc]
        loc_new = np.searchsorted(V, tv)[None, :]
        rigid_new = bool(is_rigid(gf.fixed, pv, pw)[0])
        # new blocks of W: c = G_old^T D_VV G_new, d = G_new^T D_VV G_new
        # D_VV B_new, (3|V|, 3): columns (vertex b, component y) weighted by w_b
        DGn = np.einsum("rby,b->ry", D_VV[:, dof3(loc_new[0])].reshape(D_VV.shape[0], -1, 3), pw[0])
        if not self.mode.sticky:
            DGn = DGn @ n[0][:, None]
        DGn = np.ascontiguousarray(DGn)
        c = _constraint_rows(DGn, loc_old, self.weights, self.normals, self.mode)  # (m_old, p)
        d = _constraint_rows(DGn, loc_new, pw, n, self.mode)
        d = 0.5 * (d + d.T)
        # W is symmetrised (contact_compliance): its new column is the mean of G_old^T D G_new and
        # (G_new^T D G_old)^T, which differ where D is not symmetric (a hat-load bundle)
        GnD = np.einsum("byr,b->ry", D_VV[dof3(loc_new[0]), :].reshape(-1, 3, D_VV.shape[1]), pw[0])  # D_VV^T G_new
        if not self.mode.sticky:
            GnD = GnD @ n[0][:, None]
        c = 0.5 * (c + _constraint_rows(np.ascontiguousarray(GnD), loc_old, self.weights, self.normals, self.mode))
        if not rigid_new:
            d = d + L_new[0]
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
        lo, wo = pad(loc_old, self.weights, P)
        ln, wn = pad(loc_new, pw, P)
        self.loc = np.vstack([lo, ln])
        self.weights = np.vstack([wo, wn])
        self.patch_radius = np.append(self.patch_radius, a_new)
        self.local = np.concatenate([self.local, L_new if not rigid_new else np.zeros_like(L_new)])
        self.V, self._D_VV, self.W, self.column_dofs = V, D_VV, W, cols
        self._Y = None
        self.rigid = np.append(self.rigid, rigid_new)
        if self._R is not None:
            Rn = response_columns(gf, column_dofs(gf, tv), np.arange(tv.size)[None, :], pw)
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
        dk = dof3(np.flatnonzero(vkeep))
        if not vkeep.all() and self._D_VV is not None:
            drop = dof3(np.flatnonzero(~vkeep))
            self._D_VV = np.delete(np.delete(self._D_VV, drop, axis=0), drop, axis=1)
        self.column_dofs = self.column_dofs[dk]
        self._Y = None
        self.V = self.V[vkeep]
        self.loc = newpos[loc]
        wd = np.arange(p * k, p * k + p)
        self.W = np.delete(np.delete(self.W, wd, axis=0), wd, axis=1)
        self.tri_idx, self.bary, self.normals = self.tri_idx[keep], self.bary[keep], self.normals[keep]
        self.weights, self.patch_radius = self.weights[keep], self.patch_radius[keep]
        self.local = self.local[keep]
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
        self._factor = SPDFactor(self.W[np.ix_(live, live)])
        self.exact = self._factor.exact
        self._K = None


def capacitance(
    gf: ComplianceSource,
    tri_idx: Any,
    bary: Any,
    *,
    normals: Any = None,
    mode: Mode = "sticky",
    patch_radius: Any = None,
    patch_profile: str = "hertz",
    near_field: str | NearField | None = None,
) -> Capacitance:
    """Build the capacitance of a set of point or patch contacts.

    Parameters
    ----------
    gf : ComplianceSource
        Loaded bundle (see :func:`hailstorm.runtime.bundle.read.load`).
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
        :mod:`hailstorm.runtime.contact.weights`;
        :func:`~hailstorm.runtime.contact.sphere_patch.hertz_radius` gives the physical
        radius for a load). A scalar is also the radius :meth:`Capacitance.add`
        uses by default.
    patch_profile : {"hertz", "uniform"}
        Pressure profile over a patch.
    near_field : {"auto", "layer", "halfspace", "none"}, NearField or None
        Resolve patches smaller than the surface elements with the half-space
        near field (:mod:`hailstorm.runtime.contact.near_field`): each patch's
        compliance is D's, minus the kernel's of the same hat loads, plus the
        kernel's of the contact's own disc (``"auto"``: on a bundle of hat-load
        columns). None / "none" (default): the discrete model, the patch's
        compliance as the mesh gives it.

    Returns
    -------
    Capacitance

    Raises
    ------
    ValueError, IndexError
        On malformed input (see :func:`solve_contacts`).
    """
    mode = check_mode(mode)
    t, b, n = check_contacts(gf, tri_idx, bary, normals)
    a = check_patch(patch_radius, t.size, patch_profile)
    cap = build(gf, t, b, n, mode, a, patch_profile, resolve_near_field(gf, near_field))
    if patch_radius is not None and np.ndim(patch_radius) == 0:
        cap.default_patch_radius = float(patch_radius)
    return cap


def _contact_weights(gf: ComplianceSource, t: np.ndarray, b: np.ndarray, n: np.ndarray | None,
                     a: np.ndarray | None, profile: str) -> tuple[np.ndarray, np.ndarray]:
    """(s, P) vertex lists and weights: barycentric (point) or patch."""
    if a is None or not a.any():
        return np.asarray(gf.triangles)[t], b
    return patch_weights(gf, t, b, a, n, profile=profile)


def resolve_near_field(gf: ComplianceSource, near: str | NearField | None) -> NearField | None:
    """A near-field choice as its object, with the bundle's material (None: the mesh alone).

    ``"auto"``: the layer kernel (the half-space's plus the regular part of the pad on its
    rigid base, :mod:`hailstorm.runtime.contact.layer_kernel`) if the bundle's columns answer
    hat loads (``options.load == "hat"``, the loads the kernel's subtraction needs), else none.
    """
    if near is None or isinstance(near, NearField):
        return near
    if near == "auto":
        options = (getattr(gf, "manifest", None) or {}).get("options", {})
        near = "layer" if options.get("load") == "hat" else "none"
    return near_field(near, float(gf.young), float(gf.poisson))


def _near_blocks(gf: ComplianceSource, near: NearField | None, t: np.ndarray, b: np.ndarray, n: np.ndarray | None,
                 a: np.ndarray | None, pv: np.ndarray, w: np.ndarray, mode: Mode) -> np.ndarray | None:
    """The near-field blocks (s, p, p) of patch contacts (None: no near field)."""
    if a is None or near is None or n is None or not np.any(a > 0):
        return None
    X = contact_points(np.asarray(gf.vertices), np.asarray(gf.triangles), t, b)
    return near.blocks(gf, a, pv, w, X, n, ContactMode(mode).sticky)


def build(gf: ComplianceSource, t: np.ndarray, b: np.ndarray, n: np.ndarray | None, mode: Mode,
          a: np.ndarray | None = None, profile: str = "hertz", near: NearField | None = None) -> Capacitance:
    """The capacitance of validated contacts (:mod:`hailstorm.runtime.contact.validate`).

    ``n`` may be None only for sticky point contacts (which never look at the
    normals; they are then stored as zeros and :meth:`Capacitance.solve`
    refuses unilateral contact).
    """
    if n is None:
        if not ContactMode(mode).sticky or a is not None:
            raise ValueError("normals are needed for frictionless and patch contacts")  # pragma: no cover
        n = np.zeros((t.size, 3))
    pv, w = _contact_weights(gf, t, b, n, a, profile)
    cap = from_weights(gf, t, b, n, mode, pv, w, a, profile, local=_near_blocks(gf, near, t, b, n, a, pv, w, mode))
    cap.near = near
    return cap


def from_weights(gf: ComplianceSource, t: np.ndarray, b: np.ndarray, n: np.ndarray, mode: Mode, pv: np.ndarray,
                 w: np.ndarray, a: np.ndarray | None = None, profile: str = "hertz",
                 local: np.ndarray | None = None) -> Capacitance:
    """The capacitance of contacts whose force-distribution weights B are given.

    The one constructor of :class:`Capacitance`: :func:`build` (the contact
    API) computes the weights first; the storm's contact set
    (:class:`hailstorm.runtime.storm.contact_set.ContactSets`) passes the patch
    weights it caches per stone.

    Parameters
    ----------
    gf : ComplianceSource
        The bundle.
    t : (s,) int ndarray
        Contacted triangles.
    b : (s, 3) float ndarray
        Barycentric coordinates of the contact points (patch centres).
    n : (s, 3) float ndarray
        Outward unit contact normals.
    mode : {"sticky", "frictionless"}
    pv, w : (s, P) int / float ndarrays
        Vertices carrying each contact's force and their weights (B's block
        ``(pv[k, j], k)`` is ``w[k, j] I3``; padding: weight 0).
    a : (s,) float ndarray, optional
        Patch radii [m] (None: point contacts).
    profile : {"hertz", "uniform"}
        Pressure profile the patch weights were made with (recorded for :meth:`Capacitance.add`).
    local : (s, p, p) float ndarray, optional
        Near-field blocks added to W's diagonal blocks (:mod:`hailstorm.runtime.contact.near_field`).

    Returns
    -------
    Capacitance
        With the Cholesky factor (or pseudo-inverse) of ``W[live, live]``
        under :mod:`hailstorm.runtime.contact.policy`.
    """
    V, loc = locate(pv)
    cols = column_dofs(gf, V)
    w = np.ascontiguousarray(w, dtype=np.float64)
    n = np.ascontiguousarray(n, dtype=np.float64)
    mode = ContactMode(mode)
    Y = constraint_rows(gf, V, loc, w, n, mode.sticky)  # (D_VV G)^T
    W = w_kernels.contact_compliance(Y, loc, w, n, mode.sticky)
    rigid = is_rigid(gf.fixed, pv, w)
    p = mode.dofs
    if local is not None:
        local = np.where(rigid[:, None, None], 0.0, np.asarray(local, dtype=np.float64))
        for k in range(t.size):
            W[p * k:p * k + p, p * k:p * k + p] += local[k]
    if rigid.any():
        dead = np.repeat(rigid, p)
        W[dead, :] = 0.0
        W[:, dead] = 0.0
        live = np.flatnonzero(~dead)
        factor = SPDFactor(W[np.ix_(live, live)], symmetric=True)
    else:
        factor = SPDFactor(W, symmetric=True)
    return Capacitance(
        gf=gf, mode=mode, tri_idx=t, bary=b, normals=n, V=V, loc=loc, W=W, rigid=rigid, exact=factor.exact,
        column_dofs=cols, _factor=factor, _Y=Y, weights=w,
        patch_radius=np.zeros(t.size) if a is None else a, patch_profile=profile, local=local,
    )
