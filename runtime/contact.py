"""Point and patch contacts on the seat through the precomputed compliance (capacitance method).

Module layout (one seam per module; every name that was importable from
``hailstorm.runtime.contact`` still is):

* :mod:`hailstorm.runtime.contact` (this module) -- the solver :func:`solve_contacts`
  (unilateral active set, surface displacement) and :class:`ContactSolution`;
* :mod:`hailstorm.runtime.contact_capacitance` -- the capacitance object
  :class:`Capacitance` / :func:`capacitance` (``W``, its factorisation,
  low-rank :meth:`~Capacitance.add` / :meth:`~Capacitance.remove`), input
  validation and the tuning constants (:data:`COND_LIMIT`, ...: set them
  there, not here);
* :mod:`hailstorm.runtime.weights` -- the force-distribution weights ``B`` of point
  and patch contacts, :func:`hertz_radius`;
* :mod:`hailstorm.runtime.gather` -- fast access to blocks of ``D``.

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

Patch contacts (``patch_radius=a``) replace ``beta_k`` by the weights of a
pressure disc of radius ``a`` (the consistent nodal load of a Hertz profile,
:func:`hailstorm.runtime.weights.patch_weights`): ``B`` keeps its shape ``3|V| x 3s``
with block ``(i, k) = w_{k,i} I3`` over the patch vertices, and everything
below (``W``, ``K``, rigid contacts, the low-rank updates, the active set)
is unchanged. A point load is singular (its stiffness vanishes as the mesh is
refined); a patch load of fixed radius converges with the mesh.

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
from typing import Any

import numpy as np

from hailstorm.runtime import contact_capacitance as _cap
from hailstorm.runtime.compiled import blocks as _kernels
from hailstorm.runtime.compiled import resolve_backend
from hailstorm.runtime.contact_capacitance import (
    COND_LIMIT,
    PINV_RCOND,
    Capacitance,
    Mode,
    _build,
    _check_contacts,
    _check_mode,
    _check_patch,
    _Factor,
    capacitance,
)
from hailstorm.runtime.gather import _apply_columns, _compiled
from hailstorm.runtime.weights import (
    PATCH_PROFILES,
    _interpolate,
    _vertex_forces,
    barycentric_matrix,
    contact_points,
    hertz_radius,
    patch_matrix,
    patch_weights,
    triangle_normals,
)

__all__ = [
    "COND_LIMIT",
    "PINV_RCOND",
    "Capacitance",
    "ContactSolution",
    "barycentric_matrix",
    "capacitance",
    "contact_points",
    "hertz_radius",
    "patch_matrix",
    "patch_weights",
    "solve_contacts",
    "triangle_normals",
]


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


def _point_contacts_compiled(gf: Any, triangles: Any, barycentric: Any, displacements: Any, mode: Mode,
                             want_u: bool) -> ContactSolution | None:
    """:func:`solve_contacts` for bilateral point contacts in one compiled call
    (:func:`hailstorm.runtime.compiled.blocks.point_contacts`), or None where the general
    path must decide: malformed input (it raises the error), rigid contacts,
    coincident contacts (pseudo-inverse), no contacts, more than
    :data:`hailstorm.runtime.contact_capacitance.POINT_FAST_MAX` contacts."""
    t = np.asarray(triangles)
    if t.ndim != 1 or not 0 < t.size <= _cap.POINT_FAST_MAX or t.dtype.kind not in "iu":
        return None
    # C-contiguous float64 / int64: one compiled specialisation serves every caller
    b = np.ascontiguousarray(barycentric, dtype=np.float64)
    u = np.ascontiguousarray(displacements, dtype=np.float64)
    s = t.size
    if b.shape != (s, 3) or u.shape != (s, 3):
        return None
    t = np.ascontiguousarray(t, dtype=np.int64)
    code, f, cd, V, g, uall = _kernels.point_contacts(
        np.asarray(gf.D).T, gf.column_of, gf.contactable, gf.fixed, gf.triangles, gf.vertices, t, b, u,
        mode == "sticky", want_u, _cap.BARY_SUM_TOL, _cap.BARY_NEG_TOL, _cap.COND_LIMIT)
    if code:
        return None
    return ContactSolution(
        forces=f, surface_displacement=uall.reshape(-1, 3) if want_u else None, active=np.ones(s, bool),
        rigid=np.zeros(s, bool), contact_displacement=cd, iterations=1, vertices=V, vertex_forces=g,
    )


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
    patch_radius: Any = None,
    patch_profile: str = "hertz",
    backend: str = "auto",
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
    patch_radius : None, float or (s,) float array_like
        ``None``/0: point contacts (default). ``a > 0`` [m]: patch contacts
        spreading each force over a pressure disc of radius ``a`` (see
        :func:`capacitance`; :func:`hertz_radius` for the physical radius).
        ``contact_displacement`` is then the force-weighted mean displacement
        of the patch, ``B^T u_V``, and that is what ``displacements``
        prescribes.
    patch_profile : {"hertz", "uniform"}
        Pressure profile over a patch.
    backend : {"auto", "numba", "numpy"}
        Build ``D_VV``, ``W`` and the full-surface displacement with the
        compiled kernels (``"auto"``: when numba is installed and D is
        column-major; see :func:`capacitance`). Up to
        :data:`~hailstorm.runtime.contact_capacitance.POINT_FAST_MAX` bilateral point
        contacts with ``normals=None`` and ``rows`` "all" or None are then
        solved in one compiled call (5-11x faster than numpy). Same results to
        rounding. The first call in a process loads the kernels (~0.3 s;
        compiling them takes ~10 s once after an install).

    Returns
    -------
    ContactSolution

    Raises
    ------
    ValueError
        Shape mismatch, NaN/inf, barycentric coordinates not summing to 1 or
        negative, contact on a vertex without a compliance column, bad mode,
        rows or backend (``"numba"`` without numba installed).
    IndexError
        Triangle (or row) index out of range.
    RuntimeError
        If the unilateral active set does not settle within ``max_iter``.
    """
    mode = _check_mode(mode)
    backend = resolve_backend(backend)
    if (not unilateral and normals is None and patch_radius is None and patch_profile in PATCH_PROFILES
            and (rows is None or (isinstance(rows, str) and rows == "all")) and _compiled(gf, backend)):
        fast = _point_contacts_compiled(gf, triangles, barycentric, displacements, mode, rows is not None)
        if fast is not None:
            return fast
    # sticky bilateral contacts never look at the normals
    t, b, n = _check_contacts(gf, triangles, barycentric, normals,
                              need_normals=unilateral or mode == "frictionless" or patch_radius is not None)
    a = _check_patch(patch_radius, t.size, patch_profile)
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

    cap = _build(gf, t, b, n, mode, a, patch_profile, backend)
    rigid = cap.rigid
    c = cap._reduce(ubar)
    it = 1
    active = ~rigid
    lam = cap._multipliers(c)
    if unilateral:
        assert n is not None  # validated with need_normals=True whenever unilateral
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
    g = _vertex_forces(cap.V.size, cap.loc, cap.weights, f)
    gflat = g.reshape(-1)
    u = _apply_columns(gf, cap._cols, gflat, rows_arr, _compiled(gf, backend)) if want_u else None
    if u is not None and rows_arr is None:
        uV = u[cap.V]
    else:
        uV = (cap.D_VV @ gflat).reshape(-1, 3)
    return ContactSolution(
        forces=f,
        surface_displacement=u,
        active=active,
        rigid=rigid.copy(),
        contact_displacement=_interpolate(uV, cap.loc, cap.weights),
        iterations=it,
        vertices=cap.V,
        vertex_forces=g,
    )
