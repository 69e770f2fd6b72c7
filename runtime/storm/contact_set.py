"""The storm's contact set: a layer over the contact core's :class:`~hailstorm.runtime.contact.Capacitance`.

:class:`ContactSet` holds the capacitance of a set of (stone, triangle[, patch
radius]) -- W = Bᵀ D B and K = W⁻¹ from the one constructor
:func:`hailstorm.runtime.contact.capacitance_build.from_weights`, under the contact
core's one SPD policy (:class:`hailstorm.runtime.contact.policy.SPDFactor`) --
with what the storm adds: the stones, their reference points and anchors (the
sphere's offset over a patch) and the integrators' cached damping and modes. It is
built by :meth:`ContactSets.build` from the patch weights the storm caches per
stone, and kept while the set is unchanged.

A patch contact carries the sphere's law through the point of its impact, an affine
law like that of :func:`hailstorm.runtime.contact.hertz.press_spheres`: the disc's
pressure-weighted mean displacement lies ``o`` short of the stone's lowest point
(:func:`hailstorm.runtime.contact.weights.impact_offset` of the impact's patch,
:func:`~hailstorm.runtime.contact.weights.impact_radius`; times
:func:`~hailstorm.runtime.contact.weights.resolved_fraction`, as far as the mesh follows
the sphere, without the near field), so the contact's anchor lies ``o`` deeper
than the stone's radius (:attr:`ContactSet.rest` ``= R - o``) and its force is
``k (delta - o)``, K and W the capacitance's own. The stone reaches that
depth with no force (the narrow phase measures its gap with the radius
``R - o``: :meth:`hailstorm.runtime.storm.stones.Stones.contact_radius`; the
engagement is :meth:`hailstorm.runtime.storm.soft_contacts.SoftContacts.engage`). On a
half-space an impact then has the sphere's peak force and deepest indentation
(Hertz's for ``a << R``) and 0.990 of Hertz's duration
(``studies.hertz_study.affine_oscillator``; the linear law through the
origin it replaces, Hertz's secant stiffness, had 0.875, 0.915 and 0.977).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from hailstorm.runtime.contact.capacitance_build import from_weights, resolve_near_field
from hailstorm.runtime.contact.sphere_patch import impact_offset, resolved_fraction
from hailstorm.runtime.contact.weights import contact_points

if TYPE_CHECKING:  # annotations only
    from hailstorm.runtime.contact.contact_capacitance import Capacitance
    from hailstorm.runtime.storm.patches import Patches
    from hailstorm.runtime.storm.recording import StormStats
    from hailstorm.runtime.bundle.compliance import ElasticSource
    from hailstorm.runtime.storm.scene_sections import ContactSettings

__all__ = ["ContactSet", "ContactSets"]


@dataclass
class ContactSet:
    """The capacitance of the storm's current set of soft contacts (:meth:`ContactSets.build`),
    kept while the set (stones, triangles, patch radii) is unchanged.

    ``W`` and ``K`` are the capacitance's (:attr:`capacitance`); a patch contact's
    anchor ``rest`` is its stone's radius less the sphere's offset ``offset``
    (module docstring); ``G``, ``cols`` and ``DVV`` are
    :meth:`Capacitance.loaded_columns` and :meth:`Capacitance.vertex_response`.
    """

    key: tuple
    capacitance: Capacitance
    W: np.ndarray
    K: np.ndarray
    G: np.ndarray  # (c, m) forces at the loaded (non-clamped) dofs of V per unit multiplier
    cols: np.ndarray  # (c,) their columns of D
    DVV: np.ndarray  # (3|V|, m) displacement of V per unit multiplier
    stones: np.ndarray
    tris: np.ndarray
    bary: np.ndarray
    normals: np.ndarray
    X: np.ndarray  # undeformed contact points (s, 3) (the patch centres)
    rest: np.ndarray  # (s,) distance along the normal from the reference point to the stone's centre at zero force
    offset: np.ndarray  # (s,) the sphere's offset o over each patch (0: point contact); rest = R - offset
    patch_radius: np.ndarray  # (s,) patch radius [m] (0: point contact)
    verts: np.ndarray  # (s, P) vertices carrying each contact's force
    weights: np.ndarray  # (s, P) their weights (B: block (verts[k, p], k) = weights[k, p] I3)
    Kdiag: np.ndarray  # diag(K), a contiguous writable copy (what the compiled kernels take)
    C: np.ndarray | None = None  # exact-integrator dashpot (cached)
    modes: tuple | None = None  # (omega^2, Phi, sqrt(m)) of M^-1/2 K M^-1/2 (cached, contact_modes)
    mode_masses: np.ndarray | None = None  # the masses the cached modes (and C) were computed with


class ContactSets:
    """Builds the capacitance of a set of soft contacts (point contacts, or patches).

    Parameters
    ----------
    gf : ElasticSource
        The bundle (its D, surface and material).
    contact : ContactSettings
        ``mode`` (sticky: three multipliers per contact, else one) and
        ``near_field`` (patches below the mesh at their own scale,
        :mod:`hailstorm.runtime.contact.near_field`).
    normals : (m, 3) ndarray
        Outward unit normals of the triangles.
    patches : Patches
        The patch weights (cached per stone).
    """

    def __init__(self, gf: ElasticSource, contact: ContactSettings, normals: np.ndarray, patches: Patches) -> None:
        self.gf = gf
        self.contact = contact
        self.near = resolve_near_field(gf, contact.near_field) if contact.patch != "none" else None
        self.triangles = np.asarray(gf.triangles)
        self.young, self.poisson = float(gf.young), float(gf.poisson)
        self.X = np.asarray(gf.vertices, dtype=np.float64)
        self.normals = normals
        self.patches = patches

    def build(self, stones: np.ndarray, tris: np.ndarray, bary: np.ndarray, normals: np.ndarray, key: tuple,
              rest: np.ndarray, stats: StormStats, radius: np.ndarray | None = None,
              offset: np.ndarray | None = None) -> ContactSet:
        """The capacitance of the soft contacts ``stones`` on ``tris`` at ``bary`` with unit
        ``normals`` (:attr:`Stones.cnormal`; point contacts, or patches of ``radius``);
        ``rest``: the stones' radii; ``offset``: the sphere's offset of each contact's
        engagement (:meth:`offsets`, sized at its stone's first touch; None: 0)."""
        s = stones.size
        if radius is None:
            verts, w = self.triangles[tris], bary
            radius = np.zeros(s)
        else:
            verts, w = self.patches.weights(stones, tris, bary, radius, normals, stats)
        radius = np.asarray(radius, dtype=np.float64)
        verts = verts.astype(np.int64, copy=False)
        # reference point: the contact point (the patch centre); see below
        X = np.einsum("kj,kjd->kd", bary, self.X[self.triangles[tris]])
        local = None
        if self.near is not None and np.any(radius > 0):
            local = self.patches.near_blocks(self.near, stones, tris, bary, radius, verts, w, X, normals)
        cap = from_weights(self.gf, tris, bary, normals, self.contact.mode, verts, w, radius if np.any(radius > 0) else None,
                           local=local)
        if cap.rigid.any():
            raise RuntimeError("rigid contacts must be filtered before the capacitance")  # pragma: no cover
        W, K = cap.W, cap.K
        cols, G = cap.loaded_columns()
        # reference point: the contact point (the patch centre). A patch contact prescribes the
        # pressure-weighted mean normal displacement of the surface under the disc, measured from
        # the tangent plane at the contact point (the plane of the disc); the stone's lowest point
        # lies the sphere's offset below it. (Measuring from the weighted mean undeformed surface
        # point sum_p w_p X_p instead, which lies below the tangent plane on the convex seat, opens
        # every contact with a small gap: measured restitution 0.488 instead of 0.499 for the
        # single drop.)
        offset = np.zeros(s) if offset is None else np.asarray(offset, dtype=np.float64)
        stats.capacitance_rebuilds += 1
        return ContactSet(key=key, capacitance=cap, W=W, K=K, G=G, cols=cols, DVV=cap.vertex_response(),
                          stones=stones, tris=tris, bary=bary, normals=normals, X=X, rest=rest - offset,
                          offset=offset, patch_radius=radius.copy(), verts=verts, weights=cap.weights,
                          Kdiag=np.diag(K).copy())

    def patch_offsets(self, ids: np.ndarray, tris: np.ndarray, bary: np.ndarray, normals: np.ndarray,
                      radius: np.ndarray, stone_radius: np.ndarray, stats: StormStats) -> np.ndarray:
        """:meth:`offsets` of the patches of radius ``radius`` of stones ``ids`` on ``tris`` at
        ``bary`` with unit ``normals`` (their weights from the per-stone cache,
        :meth:`Patches.weights`), (s,) [m]."""
        verts, w = self.patches.weights(ids, tris, bary, radius, normals, stats)
        X = contact_points(self.X, self.triangles, tris, bary)
        return self.offsets(verts.astype(np.int64, copy=False), w, X, normals, radius, stone_radius)

    def offsets(self, verts: np.ndarray, w: np.ndarray, X: np.ndarray, normals: np.ndarray, radius: np.ndarray,
                stone_radius: np.ndarray) -> np.ndarray:
        """The sphere's offset over each impact patch (module docstring), (s,) [m]: the sphere's own
        (:func:`impact_offset`, ``a^2 / (5 R)`` for ``a << R``) with the near field (the sphere
        over its own disc), else as far as the mesh follows it (:func:`resolved_fraction`); 0 for
        point contacts (``radius`` 0)."""
        if not np.any(radius > 0):
            return np.zeros(radius.size)
        offset = impact_offset(radius, stone_radius)
        if self.near is not None:
            return offset
        return offset * resolved_fraction(self.X, verts, w, X, normals, radius)

    def warm_up(self, t: int) -> None:
        """Load (or compile) the kernels of :meth:`build` with the storm loop's argument types (one
        point contact on ``t``, and the near field's kernel on its vertices)."""
        t1 = np.array([t])
        third = np.full((1, 3), 1.0 / 3.0)
        verts = self.triangles[t1].astype(np.int64)
        from_weights(self.gf, t1, third, self.normals[t1], self.contact.mode, verts, third).K
        if self.near is not None:
            # the whole block once: measures the bundle's hat-scale defect and, with the layer kernel,
            # reads (or solves) the layer's curve and casts the thickness under every contactable vertex
            self.near.blocks(self.gf, np.array([1e-3]), verts, third, third @ self.X[verts[0]], self.normals[t1], False)
