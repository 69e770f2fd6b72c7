"""The low-rank updates of a capacitance: one contact added (bordered inverse) or removed (downdate).

:class:`LowRankUpdates` is the part of
:class:`~hailstorm.runtime.contact.contact_capacitance.Capacitance` that changes its
contact set in place: :meth:`~LowRankUpdates.add` grows ``V``, ``D_VV`` and ``W`` by the
new contact's rows and columns and updates ``K`` by the Schur complement of the new
block; :meth:`~LowRankUpdates.remove` deletes them and downdates ``K``; either
re-factorises ``W`` when ``K`` is a pseudo-inverse or the update would be ill
conditioned. The algebra is in the module's pure functions (the grown block of D,
the new blocks of W, the bordered and the downdated inverse); the notation is
:mod:`hailstorm.runtime.contact`'s.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from hailstorm.runtime.bundle.compliance import ComplianceSource, column_dofs, dof3, gather, response_columns
from hailstorm.runtime.contact.capacitance_blocks import constrained_rows, contact_weights, near_blocks
from hailstorm.runtime.contact.near_field import NearField
from hailstorm.runtime.contact.policy import COND_LIMIT, EMBED_BLOCKS_FROM, SPDFactor, is_rigid
from hailstorm.runtime.contact.validate import ContactMode, check_contacts
from hailstorm.runtime.contact.weights import pad

__all__ = ["LowRankUpdates", "embed"]


def _runs(idx: np.ndarray) -> list[tuple[int, int, int]]:
    """Maximal runs of consecutive values in an increasing index array: (start, stop, value0)."""
    if idx.size == 0:
        return []
    br = np.flatnonzero(np.diff(idx) != 1) + 1
    starts = np.concatenate([[0], br])
    stops = np.concatenate([br, [idx.size]])
    return [(int(a), int(b), int(idx[a])) for a, b in zip(starts, stops)]


def embed(M: np.ndarray, pos: np.ndarray, size: int) -> np.ndarray:
    """(size, size) array with ``out[pos][:, pos] = M`` by contiguous block copies.

    Parameters
    ----------
    M : (k, k) float ndarray
        The block to place.
    pos : (k,) int ndarray
        Increasing rows/columns of the output that receive ``M``.
    size : int
        Size of the output.

    Returns
    -------
    (size, size) float ndarray
        The rest is left uninitialised (the caller fills it). Below
        :data:`~hailstorm.runtime.contact.policy.EMBED_BLOCKS_FROM` rows one
        fancy-indexed copy; from it on, one slice copy per pair of runs of ``pos``.
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


def _grown_block(gf: ComplianceSource, V_old: np.ndarray, D_VV_old: np.ndarray,
                 tv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``V`` (kept sorted) and ``D_VV`` grown by the vertices ``tv``: only the new rows / columns of D gathered.

    Returns ``(V, D_VV, column dofs of V, positions of V_old in V)``.
    """
    newv = np.setdiff1d(tv, V_old)
    V = np.union1d(V_old, newv).astype(np.intp)
    pos_old = np.searchsorted(V, V_old)
    cols = column_dofs(gf, V)
    if newv.size:
        # insert the new vertices' rows/columns (slice copies, V stays sorted)
        pn = dof3(np.searchsorted(V, newv))
        po = np.delete(np.arange(3 * V.size), pn)
        D_VV = embed(D_VV_old, po, 3 * V.size)
        D_VV[:, pn] = gather(gf, dof3(V), cols[pn])
        D_VV[np.ix_(pn, po)] = gather(gf, dof3(newv), cols[po])
    else:
        D_VV = D_VV_old
    return V, D_VV, cols, pos_old


def _border_blocks(D_VV: np.ndarray, loc_old: np.ndarray, w_old: np.ndarray, n_old: np.ndarray,
                   loc_new: np.ndarray, pw: np.ndarray, n_new: np.ndarray,
                   mode: ContactMode) -> tuple[np.ndarray, np.ndarray]:
    """The new blocks of W: ``c = G_old^T D_VV G_new`` (m_old, p) and ``d = G_new^T D_VV G_new`` (p, p), symmetrised."""
    # D_VV B_new, (3|V|, 3): columns (vertex b, component y) weighted by w_b
    DGn = np.einsum("rby,b->ry", D_VV[:, dof3(loc_new[0])].reshape(D_VV.shape[0], -1, 3), pw[0])
    if not mode.sticky:
        DGn = DGn @ n_new[0][:, None]
    DGn = np.ascontiguousarray(DGn)
    c = constrained_rows(DGn, loc_old, w_old, n_old, mode)  # (m_old, p)
    d = constrained_rows(DGn, loc_new, pw, n_new, mode)
    d = 0.5 * (d + d.T)
    # W is symmetrised (contact_compliance): its new column is the mean of G_old^T D G_new and
    # (G_new^T D G_old)^T, which differ where D is not symmetric (a hat-load bundle)
    GnD = np.einsum("byr,b->ry", D_VV[dof3(loc_new[0]), :].reshape(-1, 3, D_VV.shape[1]), pw[0])  # D_VV^T G_new
    if not mode.sticky:
        GnD = GnD @ n_new[0][:, None]
    c = 0.5 * (c + constrained_rows(np.ascontiguousarray(GnD), loc_old, w_old, n_old, mode))
    return c, d


def _bordered_inverse(K_old: np.ndarray, cl: np.ndarray, d: np.ndarray, W: np.ndarray) -> np.ndarray | None:
    """The inverse of ``[[W_old, cl], [cl^T, d]]`` from ``K_old = W_old^-1`` by the Schur complement of ``d``.

    None when the Schur complement is (nearly) singular against the scale of ``W``'s
    diagonal (the new contact coincides with others): then re-factorise.
    """
    p = d.shape[0]
    Kc = K_old @ cl
    S = d - cl.T @ Kc
    S = 0.5 * (S + S.T)
    wscale = max(float(np.abs(np.diag(W)).max()), np.finfo(float).tiny)
    lam_min = float(np.linalg.eigvalsh(S).min()) if p > 1 else float(S[0, 0])
    if lam_min < wscale / COND_LIMIT:
        return None
    Sinv = np.linalg.inv(S)
    a = K_old.shape[0]
    KcS = Kc @ Sinv
    K = np.empty((a + p, a + p))
    K[:a, :a] = K_old + KcS @ Kc.T
    K[:a, a:] = -KcS
    K[a:, :a] = -KcS.T
    K[a:, a:] = Sinv
    return 0.5 * (K + K.T)


def _downdated_inverse(K_old: np.ndarray, rem: np.ndarray) -> np.ndarray:
    """The inverse of ``W`` without the components ``rem``, ``K_aa - K_ab K_bb^-1 K_ba``, from ``K_old = W^-1``."""
    a = K_old.shape[0]
    kp = np.setdiff1d(np.arange(a), rem)
    Kbb = K_old[np.ix_(rem, rem)]
    Kab = K_old[np.ix_(kp, rem)]
    K = K_old[np.ix_(kp, kp)] - Kab @ np.linalg.solve(Kbb, Kab.T)
    return 0.5 * (K + K.T)


class LowRankUpdates:
    """The low-rank updates of :class:`~hailstorm.runtime.contact.contact_capacitance.Capacitance`.

    A mixin: :meth:`add` and :meth:`remove` change the capacitance's contact set and
    every field that depends on it (declared below for reference;
    :class:`Capacitance` holds and documents them), and keep ``K`` exact without a
    re-factorisation where they can.
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
    column_dofs: np.ndarray
    weights: np.ndarray
    patch_radius: np.ndarray
    patch_profile: str
    default_patch_radius: float
    local: np.ndarray
    near: NearField | None
    _factor: SPDFactor | None
    _K: np.ndarray | None
    _R: np.ndarray | None
    _D_VV: np.ndarray | None
    _Y: np.ndarray | None
    s: int
    per_contact: int
    D_VV: np.ndarray
    K: np.ndarray
    live_dofs: np.ndarray

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
        pv, pw = contact_weights(self.gf, t, b, n, np.array([a_new]), self.patch_profile)
        L_new = near_blocks(self.gf, self.near, t, b, n, np.array([a_new]), pv, pw, self.mode)
        if L_new is None:
            L_new = np.zeros((1, self.per_contact, self.per_contact))
        gf = self.gf
        old_s = self.s
        p = self.per_contact
        K_old = self.K if self.exact else None
        # grow V (kept sorted) and D_VV: gather only the new rows / columns of D
        tv = pv[0]
        V, D_VV, cols, pos_old = _grown_block(gf, self.V, self.D_VV, tv)
        loc_old = pos_old[self.loc]
        loc_new = np.searchsorted(V, tv)[None, :]
        rigid_new = bool(is_rigid(gf.fixed, pv, pw)[0])
        c, d = _border_blocks(D_VV, loc_old, self.weights, self.normals, loc_new, pw, n, self.mode)
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
        K = _bordered_inverse(K_old, cl, d, W)
        if K is None:
            self._refactor()  # the new contact (nearly) coincides with others
            return old_s
        self._K = K
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
        self._K = _downdated_inverse(K_old, np.arange(p * kpos, p * kpos + p))
        self._factor = None

    def _refactor(self) -> None:
        """A fresh factorisation of ``W[live, live]`` (the explicit ``K`` dropped)."""
        live = self.live_dofs
        self._factor = SPDFactor(self.W[np.ix_(live, live)])
        self.exact = self._factor.exact
        self._K = None
