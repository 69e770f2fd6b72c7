"""The builders of a capacitance: from contacts (:func:`capacitance`, :func:`build`) or from their weights.

:func:`capacitance` is the contact API's (validated input, :class:`Capacitance` out);
:func:`build` takes contacts already checked (:mod:`hailstorm.runtime.contact.validate`),
computes their force-distribution weights and near-field blocks and hands them to
:func:`from_weights`, the one constructor, which the storm's contact set also calls with
the patch weights it caches. :func:`resolve_near_field` turns a near-field choice into its
object. The notation is :mod:`hailstorm.runtime.contact`'s.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hailstorm.runtime.bundle.compliance import ComplianceSource, column_dofs, constraint_rows
from hailstorm.runtime.compiled import wmatrix as w_kernels
from hailstorm.runtime.contact.capacitance_blocks import contact_weights, near_blocks
from hailstorm.runtime.contact.contact_capacitance import Capacitance
from hailstorm.runtime.contact.near_field import NearField, near_field
from hailstorm.runtime.contact.policy import SPDFactor, is_rigid
from hailstorm.runtime.contact.validate import ContactMode, Mode, check_contacts, check_mode, check_patch
from hailstorm.runtime.contact.weights import locate

__all__ = ["build", "capacitance", "from_weights", "resolve_near_field"]


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


def resolve_near_field(gf: ComplianceSource, near: str | NearField | None) -> NearField | None:
    """A near-field choice as its object, with the bundle's material (None: the mesh alone).

    Parameters
    ----------
    gf : ComplianceSource
        The bundle (its ``young``, ``poisson`` and manifest options are read).
    near : {"auto", "layer", "halfspace", "none"}, NearField or None
        ``"auto"``: the layer kernel (the half-space's plus the regular part of the pad on
        its rigid base, :mod:`hailstorm.runtime.contact.layer_kernel`) if the bundle's
        columns answer hat loads (``options.load == "hat"``, the loads the kernel's
        subtraction needs), else none. A NearField or None is returned as it is.

    Returns
    -------
    NearField or None
    """
    if near is None or isinstance(near, NearField):
        return near
    if near == "auto":
        options = (getattr(gf, "manifest", None) or {}).get("options", {})
        near = "layer" if options.get("load") == "hat" else "none"
    return near_field(near, float(gf.young), float(gf.poisson))


def build(gf: ComplianceSource, t: np.ndarray, b: np.ndarray, n: np.ndarray | None, mode: Mode,
          a: np.ndarray | None = None, profile: str = "hertz", near: NearField | None = None) -> Capacitance:
    """The capacitance of validated contacts (:mod:`hailstorm.runtime.contact.validate`).

    Parameters
    ----------
    gf : ComplianceSource
        The bundle.
    t, b : (s,) int / (s, 3) float ndarrays
        Contacted triangles and barycentric coordinates.
    n : (s, 3) float ndarray or None
        Outward unit normals. None only for sticky point contacts (which never
        look at the normals; they are then stored as zeros and
        :meth:`Capacitance.solve` refuses unilateral contact).
    mode : {"sticky", "frictionless"}
    a : (s,) float ndarray, optional
        Patch radii [m] (None: point contacts).
    profile : {"hertz", "uniform"}
        Pressure profile of the patches.
    near : NearField, optional
        The near field (:func:`resolve_near_field`); None: the mesh alone.

    Returns
    -------
    Capacitance
        From :func:`from_weights`, with the weights of
        :func:`~hailstorm.runtime.contact.capacitance_blocks.contact_weights`.
    """
    if n is None:
        if not ContactMode(mode).sticky or a is not None:
            raise ValueError("normals are needed for frictionless and patch contacts")  # pragma: no cover
        n = np.zeros((t.size, 3))
    pv, w = contact_weights(gf, t, b, n, a, profile)
    cap = from_weights(gf, t, b, n, mode, pv, w, a, profile, local=near_blocks(gf, near, t, b, n, a, pv, w, mode))
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
    gf, t, b
        The bundle, contacted triangles and barycentric coordinates of the contact points
        (as :func:`~hailstorm.runtime.contact.capacitance_blocks.contact_weights`).
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
        column_dofs=cols, weights=w,
        patch_radius=np.zeros(t.size) if a is None else a, patch_profile=profile, local=local,
        factor=factor, Y=Y,
    )
