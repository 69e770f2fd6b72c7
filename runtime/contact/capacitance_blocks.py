"""The blocks a capacitance is built from: the contacts' weights (B), their near-field blocks, ``G^T M`` and W.

Shared by the build (:mod:`hailstorm.runtime.contact.capacitance_build`), the low-rank
updates (:mod:`hailstorm.runtime.contact.capacitance_update`) and the read-outs
(:mod:`hailstorm.runtime.contact.capacitance_readout`) of
:class:`~hailstorm.runtime.contact.contact_capacitance.Capacitance`. The products are the
compiled kernels of :mod:`hailstorm.runtime.compiled.blocks`; the notation is
:mod:`hailstorm.runtime.contact`'s.
"""

from __future__ import annotations

import numpy as np

from hailstorm.runtime.bundle.compliance import ComplianceSource
from hailstorm.runtime.compiled import blocks as kernels
from hailstorm.runtime.compiled import wmatrix as w_kernels
from hailstorm.runtime.contact.near_field import NearField
from hailstorm.runtime.contact.validate import ContactMode, Mode
from hailstorm.runtime.contact.weights import contact_points, patch_weights

__all__ = ["constrained_rows", "contact_compliance", "contact_weights", "near_blocks"]


def constrained_rows(M: np.ndarray, loc: np.ndarray, w: np.ndarray, normals: np.ndarray, mode: Mode) -> np.ndarray:
    """``G^T M`` for a C-contiguous M with rows indexed by V-dofs.

    Parameters
    ----------
    M : (3|V|, q) float ndarray
        C-contiguous, rows vertex-major over V.
    loc, w : (s, P) int / float ndarrays
        Position in V and weight of each contact's vertices.
    normals : (s, 3) float ndarray
        Unit normals (read by frictionless contacts).
    mode : {"sticky", "frictionless"}

    Returns
    -------
    (m, q) float ndarray
        ``m = 3s`` (sticky) or ``s`` (frictionless).
    """
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
    loc, w, normals, mode
        As in :func:`constrained_rows`.

    Returns
    -------
    (m, m) float ndarray
        ``m = 3s`` (sticky) or ``s`` (frictionless).
    """
    # G^T D_VV^T G = W^T: the kernels read the C-contiguous one of D_VV and its transpose
    M = D_VV.T if D_VV.flags.f_contiguous and not D_VV.flags.c_contiguous else np.ascontiguousarray(D_VV)
    Y = constrained_rows(M, loc, w, normals, mode)
    return w_kernels.contact_compliance(Y, np.ascontiguousarray(loc, dtype=np.intp),
                                      np.ascontiguousarray(w, dtype=np.float64),
                                      np.ascontiguousarray(normals, dtype=np.float64), ContactMode(mode).sticky)


def contact_weights(gf: ComplianceSource, t: np.ndarray, b: np.ndarray, n: np.ndarray | None,
                    a: np.ndarray | None, profile: str) -> tuple[np.ndarray, np.ndarray]:
    """The vertices carrying each contact's force and their weights (B's sparsity and entries).

    Parameters
    ----------
    gf : ComplianceSource
        The bundle.
    t : (s,) int ndarray
        Contacted triangles.
    b : (s, 3) float ndarray
        Barycentric coordinates of the contact points (patch centres).
    n : (s, 3) float ndarray or None
        Outward unit normals (the plane of a patch).
    a : (s,) float ndarray or None
        Patch radii [m]; None or all zero: point contacts.
    profile : {"hertz", "uniform"}
        Pressure profile of the patches.

    Returns
    -------
    pv, w : (s, P) int / float ndarrays
        Barycentric (the triangles' vertices, ``b``) for point contacts, else
        :func:`hailstorm.runtime.contact.weights.patch_weights`.
    """
    if a is None or not a.any():
        return np.asarray(gf.triangles)[t], b
    return patch_weights(gf, t, b, a, n, profile=profile)


def near_blocks(gf: ComplianceSource, near: NearField | None, t: np.ndarray, b: np.ndarray, n: np.ndarray | None,
                a: np.ndarray | None, pv: np.ndarray, w: np.ndarray, mode: Mode) -> np.ndarray | None:
    """The near-field blocks of patch contacts, added to W's diagonal blocks.

    Parameters
    ----------
    gf : ComplianceSource
        The bundle.
    near : NearField or None
        The near field (:func:`hailstorm.runtime.contact.near_field.near_field`).
    t, b, n, a
        Contacted triangles, barycentric coordinates, unit normals and patch radii
        (as :func:`contact_weights`).
    pv, w : (s, P) int / float ndarrays
        The contacts' vertices and weights (:func:`contact_weights`).
    mode : {"sticky", "frictionless"}

    Returns
    -------
    (s, p, p) float ndarray or None
        :meth:`hailstorm.runtime.contact.near_field.NearField.blocks` (``p`` = 3 sticky,
        1 frictionless); None without a near field, normals or patches.
    """
    if a is None or near is None or n is None or not np.any(a > 0):
        return None
    X = contact_points(np.asarray(gf.vertices), np.asarray(gf.triangles), t, b)
    return near.blocks(gf, a, pv, w, X, n, ContactMode(mode).sticky)
