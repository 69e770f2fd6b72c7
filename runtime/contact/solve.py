"""The contact solve: :func:`solve_contacts` and :class:`ContactSolution`.

The notation and the documented degenerate cases are in :mod:`hailstorm.runtime.contact`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hailstorm.runtime.compiled import point_solve as kernels
from hailstorm.runtime.contact import policy
from hailstorm.runtime.contact.capacitance_build import build, resolve_near_field
from hailstorm.runtime.contact.near_field import NearField
from hailstorm.runtime.bundle.compliance import ComplianceSource, apply_columns, reader
from hailstorm.runtime.contact.validate import ContactMode, Mode, check_contacts, check_mode, check_patch
from hailstorm.runtime.contact.weights import PATCH_PROFILES, interpolate, vertex_forces

__all__ = ["ContactSolution", "solve_contacts"]


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
    vertices : (len(V),) int ndarray
        Contacted vertices V.
    vertex_forces : (len(V), 3) float ndarray
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


def _point_contacts(gf: ComplianceSource, triangles: Any, barycentric: Any, displacements: Any, mode: Mode,
                    want_u: bool) -> ContactSolution | None:
    """:func:`solve_contacts` for bilateral point contacts in one compiled call
    (:func:`hailstorm.runtime.compiled.point_solve.point_contacts`: the same validation, blocks,
    factorisation policy and products fused), or None where the general path must
    decide: malformed input (it raises the error), rigid contacts, coincident
    contacts (pseudo-inverse), no contacts, more than
    :data:`~hailstorm.runtime.contact.policy.POINT_FAST_MAX` contacts, a D read from its
    H-matrix (no dense D to fuse over)."""
    t = np.asarray(triangles)
    if t.ndim != 1 or not 0 < t.size <= policy.POINT_FAST_MAX or t.dtype.kind not in "iu":
        return None
    # C-contiguous float64 / int64: one compiled specialisation serves every caller
    b = np.ascontiguousarray(barycentric, dtype=np.float64)
    u = np.ascontiguousarray(displacements, dtype=np.float64)
    s = t.size
    if b.shape != (s, 3) or u.shape != (s, 3):
        return None
    Dt = reader(gf).kernel_D
    if Dt is None:  # a D read from its H-matrix: the general path
        return None
    t = np.ascontiguousarray(t, dtype=np.int64)
    code, f, cd, V, g, uall = kernels.point_contacts(
        Dt, gf.column_of, gf.contactable, gf.fixed, gf.triangles, gf.vertices, t, b, u,
        ContactMode(mode).sticky, want_u, policy.BARY_SUM_TOL, policy.BARY_NEG_TOL, policy.COND_LIMIT,
        policy.RIGID_WEIGHT)
    if code:
        return None
    return ContactSolution(
        forces=f, surface_displacement=uall.reshape(-1, 3) if want_u else None, active=np.ones(s, bool),
        rigid=np.zeros(s, bool), contact_displacement=cd, iterations=1, vertices=V, vertex_forces=g,
    )


def solve_contacts(
    gf: ComplianceSource,
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
    near_field: str | NearField | None = None,
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
    near_field : {"auto", "layer", "halfspace", "none"} or None
        Resolve patches smaller than the surface elements at their own scale
        (:mod:`hailstorm.runtime.contact.near_field`); ``contact_displacement``
        then includes the near field. Default: the discrete model.

    Notes
    -----
    The blocks of D are read by the compiled kernels of
    :mod:`hailstorm.runtime.compiled.blocks` (W: :mod:`hailstorm.runtime.compiled.wmatrix`); up to
    :data:`~hailstorm.runtime.contact.policy.POINT_FAST_MAX` bilateral point
    contacts with ``normals=None`` and ``rows`` "all" or None are solved in
    one compiled call of the same algorithm. The first call in a process loads
    the kernels (~0.3 s; compiling them takes ~10 s once after an install).

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
    mode = check_mode(mode)
    if np.iscomplexobj(displacements) or np.asarray(displacements).dtype.kind not in "biuf":
        raise ValueError(f"displacements must be real numbers [m], got {np.asarray(displacements).dtype}")
    if (not unilateral and normals is None and patch_radius is None and patch_profile in PATCH_PROFILES
            and (rows is None or (isinstance(rows, str) and rows == "all"))):
        fast = _point_contacts(gf, triangles, barycentric, displacements, mode, rows is not None)
        if fast is not None:
            return fast
    # sticky bilateral contacts never look at the normals
    t, b, n = check_contacts(gf, triangles, barycentric, normals,
                             need_normals=unilateral or not mode.sticky or patch_radius is not None)
    a = check_patch(patch_radius, t.size, patch_profile)
    ubar = _prescribed(displacements, t.size)
    rows_arr, want_u = _rows(rows)
    cap = build(gf, t, b, n, mode, a, patch_profile, resolve_near_field(gf, near_field))
    return _solution(gf, cap, cap.solve(ubar, unilateral=unilateral, max_iter=max_iter), rows_arr, want_u)


def _prescribed(displacements: Any, s: int) -> np.ndarray:
    """The prescribed contact-point displacements as (s, 3) float64, or ValueError (wrong
    shape, NaN or infinity)."""
    ubar = np.asarray(displacements, dtype=np.float64)
    if ubar.shape != (s, 3):
        raise ValueError(f"displacements must have shape ({s}, 3) to match triangles, got {ubar.shape}")
    if not np.isfinite(ubar).all():
        raise ValueError("displacements contain NaN or infinity")
    return ubar


def _rows(rows: Any) -> tuple[np.ndarray | None, bool]:
    """:func:`solve_contacts`'s ``rows`` read: the rows to evaluate (None: every vertex) and
    whether to evaluate the surface displacement at all; ValueError for a string other than "all"."""
    if isinstance(rows, str):
        if rows != "all":
            raise ValueError(f"rows must be 'all', None or an index array, got {rows!r}")
        return None, True
    if rows is None:
        return None, False
    return np.asarray(rows), True


def _solution(gf: ComplianceSource, cap: Any, sol: Any, rows_arr: np.ndarray | None,
              want_u: bool) -> ContactSolution:
    """The :class:`ContactSolution` of the contact set ``cap`` (its capacitance,
    :func:`~hailstorm.runtime.contact.contact_capacitance.build`) and its solve ``sol``: the
    vertex forces, the surface displacement at ``rows_arr`` (when ``want_u``), and the contact
    points' displacement (from that field when it covers every vertex, else from the contact
    set's own columns; with the near field)."""
    f = sol.forces
    g = vertex_forces(cap.V.size, cap.loc, cap.weights, f)
    gflat = g.reshape(-1)
    u = apply_columns(gf, cap.column_dofs, gflat, rows_arr) if want_u else None
    uV = u[cap.V] if u is not None and rows_arr is None else cap.vertex_displacement(sol)
    return ContactSolution(
        forces=f,
        surface_displacement=u,
        active=sol.active,
        rigid=cap.rigid.copy(),
        contact_displacement=interpolate(uV, cap.loc, cap.weights) + cap.near_displacement(f),
        iterations=sol.iterations,
        vertices=cap.V,
        vertex_forces=g,
    )
