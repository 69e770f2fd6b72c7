"""The capacitance object of a contact set: W = G^T D_VV G, its factorisation, K and the solves.

:class:`Capacitance` holds a contact set's state (the contacts, ``V``, ``W``, the factor
of ``W`` or the explicit ``K``) and solves it; its other parts are in their own modules:

* :mod:`hailstorm.runtime.contact.capacitance_build` -- the builders :func:`capacitance`,
  :func:`build`, :func:`from_weights` and :func:`resolve_near_field`;
* :mod:`hailstorm.runtime.contact.capacitance_blocks` -- the blocks W is built from
  (the contacts' weights, the near-field blocks, ``G^T M``, :func:`contact_compliance`);
* :mod:`hailstorm.runtime.contact.capacitance_update` -- the low-rank updates
  :meth:`~Capacitance.add` / :meth:`~Capacitance.remove` (:class:`LowRankUpdates`);
* :mod:`hailstorm.runtime.contact.capacitance_readout` -- the displacement read-outs
  (:class:`Readouts`);
* :mod:`hailstorm.runtime.contact.active_set` -- the unilateral solve's block pivoting, its
  result :class:`ActiveSet`, the convex QP :func:`nonnegative_qp` and their tolerances.

See :mod:`hailstorm.runtime.contact` for the notation, sign conventions and the
documented degenerate cases; the tolerances are in
:mod:`hailstorm.runtime.contact.policy`. The blocks of D and the contact
compliance are the compiled kernels of :mod:`hailstorm.runtime.compiled.blocks`.
"""

from __future__ import annotations

from dataclasses import KW_ONLY, InitVar, dataclass, field

import numpy as np

from hailstorm.runtime.bundle.compliance import ComplianceSource, vertex_block
from hailstorm.runtime.contact.active_set import ActiveSet, unilateral_solve
from hailstorm.runtime.contact.capacitance_readout import Readouts
from hailstorm.runtime.contact.capacitance_update import LowRankUpdates
from hailstorm.runtime.contact.near_field import NearField
from hailstorm.runtime.contact.policy import SPDFactor
from hailstorm.runtime.contact.validate import ContactMode
from hailstorm.runtime.contact.weights import dense_B

__all__ = ["Capacitance"]


@dataclass(eq=False)
class Capacitance(LowRankUpdates, Readouts):
    """The capacitance (effective contact stiffness) of a set of point or patch contacts.

    Build with :func:`~hailstorm.runtime.contact.capacitance_build.capacitance` (the
    constructor itself is called by
    :func:`~hailstorm.runtime.contact.capacitance_build.from_weights` alone). All arrays
    refer to the contacts in the order given (after :meth:`add` the new contact is last;
    :meth:`remove` keeps the order of the rest).

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

    The class is assembled from its parts: the low-rank updates
    (:class:`~hailstorm.runtime.contact.capacitance_update.LowRankUpdates`), the
    read-outs (:class:`~hailstorm.runtime.contact.capacitance_readout.Readouts`) and the
    active set's block pivoting
    (:func:`~hailstorm.runtime.contact.active_set.unilateral_solve`, which :meth:`solve`
    runs); this module keeps the state, ``K`` and the bilateral solve.
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
    _factor: SPDFactor | None = field(default=None, init=False, repr=False)  # set unless _K is (see solve_live)
    _K: np.ndarray | None = field(default=None, init=False, repr=False)
    _R: np.ndarray | None = field(default=None, init=False, repr=False)  # kept full-surface response D[:, V] B
    _D_VV: np.ndarray | None = field(default=None, init=False, repr=False)  # gathered on first use
    _Y: np.ndarray | None = field(default=None, init=False, repr=False)  # (D_VV G)^T of the build (until add/remove)
    #: pressure profile of the patches ("hertz" or "uniform")
    patch_profile: str = "hertz"
    #: radius :meth:`add` uses when not given (a scalar ``patch_radius`` at build; else 0)
    default_patch_radius: float = 0.0
    local: np.ndarray | None = None
    near: NearField | None = None
    _: KW_ONLY
    # constructor only: the factorisation of W[live, live], kept as _factor until K is formed
    factor: InitVar[SPDFactor]
    # constructor only: (D_VV G)^T of the build, (m, 3|V|), kept as _Y until add / remove
    Y: InitVar[np.ndarray | None]

    def __post_init__(self, factor: SPDFactor, Y: np.ndarray | None) -> None:
        self.mode = ContactMode(self.mode)
        self._factor = factor
        self._Y = Y
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

    def solve_live(self, c: np.ndarray) -> np.ndarray:
        """``K c`` over the live components.

        Parameters
        ----------
        c : (a,) or (a, q) float ndarray
            Over the live components (:attr:`live_dofs`).

        Returns
        -------
        (a,) or (a, q) float ndarray
            With the explicit :attr:`K` once it is formed, else two triangular
            solves with the kept factor (no ``K`` formed).
        """
        return self._K @ c if self._K is not None else self._live_factor().solve(c)

    def live_columns(self, r: np.ndarray) -> np.ndarray:
        """Columns ``r`` of :attr:`K`, (a, len(r)), without forming ``K`` if it is not formed yet.

        Parameters
        ----------
        r : (q,) int ndarray
            Positions among the live components (:attr:`live_dofs`).

        Returns
        -------
        (a, q) float ndarray
            Columns of the explicit ``K``, else solves of the kept factor
            with the unit vectors ``e_r``.
        """
        if self._K is not None:
            return self._K[:, r]
        nl, nr = self.live_dofs.size, r.size
        E = np.zeros((nl, nr))
        E[r, np.arange(nr)] = 1.0
        return self._live_factor().solve(E)

    # -- solves ------------------------------------------------------------
    def _reduce(self, ubar: np.ndarray) -> np.ndarray:
        """Prescribed displacements as constrained components (m,)."""
        if self.mode.sticky:
            return ubar.reshape(-1)
        return np.einsum("ki,ki->k", ubar, self.normals)

    def multiplier_forces(self, lam: np.ndarray) -> np.ndarray:
        """Constraint multipliers as contact forces.

        Parameters
        ----------
        lam : (m,) float ndarray
            Multipliers (sticky: the flattened forces; frictionless: the signed normal forces).

        Returns
        -------
        (s, 3) float ndarray
        """
        if self.mode.sticky:
            return lam.reshape(-1, 3)
        return lam[:, None] * self.normals

    def _multipliers(self, c: np.ndarray) -> np.ndarray:
        """Multipliers (m,) of all live contacts for constrained components ``c``."""
        if not self.rigid.any():  # every component is live (the common case: no index juggling)
            return self.solve_live(c)
        live = self.live_dofs
        lam = np.zeros_like(c)
        if live.size:
            lam[live] = self.solve_live(c[live])
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
            pivoting, :func:`~hailstorm.runtime.contact.active_set.unilateral_solve`);
            frictionless, once a set repeats, after
            :data:`~hailstorm.runtime.contact.active_set.BLOCK_PIVOT_ROUNDS` rounds, or at
            once for a ``W`` singular to working precision (then with a contact compliance of
            :data:`~hailstorm.runtime.contact.active_set.QP_SHIFT`), the convex QP's projected
            Newton method (:func:`~hailstorm.runtime.contact.active_set.nonnegative_qp`, which
            converges for any SPD ``W``); sticky, one flip per iteration once a set repeats (a
            sticky contact is released as a whole). Needs the contact normals.
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
        if max_iter is not None and (isinstance(max_iter, bool) or not isinstance(max_iter, (int, np.integer))
                                     or max_iter < 1):
            raise ValueError(f"max_iter must be a positive integer (active-set iterations), got {max_iter!r}")
        c = self._reduce(ubar)
        it = 1
        active = ~self.rigid
        lam = self._multipliers(c)
        if unilateral:
            lam, active, it = unilateral_solve(self, ubar, c, lam, max_iter)
        f = self.multiplier_forces(lam)
        if not active.all():
            f = np.where(active[:, None], f, 0.0)
        if not active.all():
            lam = np.where(np.repeat(active, self.per_contact), lam, 0.0)
        return ActiveSet(forces=f, active=active, iterations=it, multipliers=lam)

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
        return self.multiplier_forces(self._multipliers(self._reduce(self._displacements(ubar))))

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
