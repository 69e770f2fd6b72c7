"""Contacts smaller than a surface element: the near field at the contact's own scale.

Part of the contact core (:mod:`hailstorm.runtime.contact`). A patch contact of
radius ``a`` spreads its force with the consistent nodal load of its pressure
disc (:func:`hailstorm.runtime.contact.weights.patch_weights`). When ``a`` is
small against the surface elements, the mesh cannot carry the disc: its
compliance ``w^T D w`` is then the mesh's (the disc smeared over the hat
functions of a few vertices), not the contact's, and it depends on where in
the triangle the contact sits.

The resolved model keeps what the mesh knows and replaces what it cannot::

    W_kk = w^T D w  -  w^T H w  +  c(a)  +  e(w)

* ``w^T D w``: the patch's compliance from the precomputed D (the body: the
  pad, its clamp, the shell, curvature, other materials);
* ``w^T H w``: the same hat loads on the near-field kernel, the elastic
  half-space of the local material (``H`` the ``1/r`` Boussinesq--Cerruti
  kernel integrated in closed form over the hat functions,
  :func:`hailstorm.runtime.compiled.near_field.hat_compliance`) -- what D holds of the near field *as the mesh
  represents it*;
* ``c(a)``: the kernel's compliance of the contact's own Hertz disc
  (:func:`halfspace_patch_compliance`), resolved at its own scale whatever
  the mesh;
* ``e(w)``: D's own error at the scale of one hat load, measured on the
  bundle (:mod:`hailstorm.runtime.contact.hat_defect`; ``NearField(defect=False)``
  leaves it out);
* with the ``"layer"`` kernel (the default's, ``"auto"``), ``+ T(w)``: the pad on its
  rigid base, whose regular part the mesh's hats sample coarsely when the contact is
  as wide as the pad is thick (:mod:`hailstorm.runtime.contact.layer_kernel`).

``D - H`` is the body's response minus the half-space's: smooth at the
contact (for a body thicker than the contact and a kernel of its material),
so the mesh carries it well; the near field is counted once, at the contact's
scale. The subtraction needs D's columns to answer hat loads (``load =
"hat"``, the consistent loads; :func:`hailstorm.precompute.greens.hat_load_matrix`):
a point-load column's near field is the mesh's singular point response,
which no kernel reproduces.

Measured (``python -m studies.resolution_study``, tables in
``docs/_generated/resolution_*.txt``): rigid spheres of Hertz radius 0.5-8 mm
pressed into a thick block of the pad's foam with the default seat's settings
(6 mm, P2, hat loads) carry Hertz's force on a vertex, an edge and a centroid
alike (the discrete model: +33..+1400 %, by site), and on the default seat the
force at a given depth is close to a 3 mm seat's for stones of 2.5-12.5 mm at
rest and at the peak of an impact at terminal speed, against up to +155 %
without it (``docs/choosing-settings.md`` quotes the figures).

The correction is a per-contact block on the diagonal of the contact
compliance ``W`` (in the contact's constrained components): the capacitance,
its low-rank updates, the active set and the storm's contact set see one W,
and :attr:`hailstorm.runtime.contact.Capacitance.local` holds the blocks. The
surface displacement ``D[:, V] B f`` stays the mesh-resolved field (the dent
as the mesh can show it); the contact point's own displacement includes the
near field (:meth:`~hailstorm.runtime.contact.Capacitance.contact_displacement`).
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import Any

import numpy as np

from hailstorm.runtime.compiled.near_field import hat_compliance
from hailstorm.runtime.contact.hat_defect import hat_defect, patch_defect
from hailstorm.runtime.contact.layer_kernel import layer_correction, layer_kernel, layer_surface

__all__ = [
    "NEAR_FIELDS",
    "NearField",
    "halfspace_patch_compliance",
    "near_field",
    "kernel_surface",
    "vertex_triangles",
]

#: the near-field choices ("none": the mesh alone, the discrete model; "halfspace": the
#: half-space kernel; "layer": the half-space's plus the regular part of a pad on its rigid
#: base, :mod:`hailstorm.runtime.contact.layer_kernel`; "auto": the layer kernel on a bundle
#: whose columns answer hat loads, else none)
NEAR_FIELDS = ("auto", "halfspace", "layer", "none")


def halfspace_patch_compliance(radius: Any, young: float, poisson: float) -> tuple[np.ndarray, np.ndarray]:
    """Normal and tangential self-compliance of a Hertz pressure disc on an elastic half-space [m/N].

    The Hertz-weighted mean displacement of the surface under the pressure
    ``p = p0 sqrt(1 - r^2/a^2)`` (normal) or the traction ``q = q0 sqrt(1 - r^2/a^2)``
    (tangential), per unit force:

    * ``c_n = 3 / (5 a E*)``, ``E* = E / (1 - nu^2)`` (Johnson eq. 3.41:
      ``u_z = pi p0 (2 a^2 - r^2) / (4 a E*)``, weighted by ``p``);
    * ``c_t = c_n (2 - nu) / (2 (1 - nu))`` (Johnson eq. 3.91, averaged over
      the direction); the same ratio as a rigid punch's.

    The normal-tangential coupling of a symmetric disc vanishes in the mean.

    Parameters
    ----------
    radius : float or array_like
        Disc radius ``a`` [m] (> 0).
    young, poisson : float
        The half-space's material [Pa], [-].

    Returns
    -------
    c_n, c_t : ndarray
        Broadcast shape of ``radius``.
    """
    a = np.asarray(radius, dtype=np.float64)
    if np.any(~(a > 0)):
        raise ValueError("halfspace_patch_compliance needs radii > 0")
    c_n = 3.0 * (1.0 - poisson**2) / (5.0 * young * a)
    return c_n, c_n * (2.0 - poisson) / (2.0 * (1.0 - poisson))


@dataclass(frozen=True)
class NearField:
    """The near field of sub-mesh patch contacts (module notes): one kernel, resolved once.

    Attributes
    ----------
    kernel : {"halfspace", "layer"}
        The near-field kernel: the half-space's, or the half-space's plus the regular part of
        the pad on its rigid base at the local thickness (the normal compliance's;
        :mod:`hailstorm.runtime.contact.layer_kernel`).
    young, poisson : float
        The material of the kernel (the bundle's under the contactable surface).
    defect : bool
        Add D's own error at the scale of one hat load to each patch
        (:mod:`hailstorm.runtime.contact.hat_defect`; default True, False for the studies
        that measure what it brings).
    """

    kernel: str
    young: float
    poisson: float
    defect: bool = True

    def compliance(self, radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The half-space's normal and tangential self-compliance of a Hertz disc of ``radius`` [m/N],
        ``c(a) = c(1) / a`` (with the ``"layer"`` kernel the layer's share is in :meth:`blocks`)."""
        return halfspace_patch_compliance(radius, self.young, self.poisson)

    def mesh_compliance(self, gf: Any, verts: np.ndarray, weights: np.ndarray, centres: np.ndarray,
                        normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The kernel's normal and tangential compliance of patches *as the mesh carries them*
        (their hat loads ``weights`` on ``verts``, padded (s, P)), ``w^T H w`` [m/N], (s,) each
        (:func:`hailstorm.runtime.compiled.near_field.hat_compliance`)."""
        X, T, areas, ptr, tri = kernel_surface(gf)
        whw = hat_compliance(np.ascontiguousarray(verts, dtype=np.int64), np.ascontiguousarray(weights, dtype=np.float64),
                             np.ascontiguousarray(centres, dtype=np.float64), np.ascontiguousarray(normals, dtype=np.float64),
                             X, T, areas, ptr, tri)
        k_n = (1.0 - self.poisson**2) / (np.pi * self.young)
        return k_n * whw, k_n * whw * (2.0 - self.poisson) / (2.0 * (1.0 - self.poisson))

    def mesh_defect(self, gf: Any, verts: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """D's own normal and tangential error at its hat scale for each patch, ``e(w)`` [m/N], (s,) each
        (:func:`hailstorm.runtime.contact.hat_defect.patch_defect`; zeros without :attr:`defect`)."""
        if not self.defect:
            s = np.asarray(verts).shape[0]
            return np.zeros(s), np.zeros(s)
        return patch_defect(hat_defect(gf, self.young, self.poisson, kernel_surface(gf), self.kernel == "layer"),
                            verts, weights)

    def blocks(self, gf: Any, radius: np.ndarray, verts: np.ndarray, weights: np.ndarray, centres: np.ndarray,
               normals: np.ndarray, sticky: bool) -> np.ndarray:
        """Per-contact correction ``c(a) - w^T H w + e(w)`` (``+ T(w)``, the layer's, on the
        normal with the ``"layer"`` kernel) in the constrained components, (s, p, p).

        ``p = 3`` (sticky: ``dn n n^T + dt (I - n n^T)``) or 1 (frictionless:
        ``dn``); zero for point contacts (``a = 0``).
        """
        a = np.asarray(radius, dtype=np.float64)
        s = a.size
        dn, dt = np.zeros(s), np.zeros(s)
        on = np.flatnonzero(a > 0)
        if on.size:
            cn, ct = self.compliance(a[on])
            mn, mt = self.mesh_compliance(gf, np.asarray(verts)[on], np.asarray(weights)[on],
                                          np.asarray(centres)[on], np.asarray(normals)[on])
            en, et = self.mesh_defect(gf, np.asarray(verts)[on], np.asarray(weights)[on])
            dn[on], dt[on] = cn - mn + en, ct - mt + et
            if self.kernel == "layer":
                dn[on] += layer_correction(layer_kernel(self.poisson), layer_surface(gf), self.young, a[on],
                                           np.asarray(verts)[on], np.asarray(weights)[on])
        if not sticky:
            return dn.reshape(s, 1, 1)
        n = np.asarray(normals, dtype=np.float64).reshape(s, 3)
        nn = n[:, :, None] * n[:, None, :]
        return dn[:, None, None] * nn + dt[:, None, None] * (np.eye(3) - nn)


def near_field(kind: str | None, young: float, poisson: float) -> NearField | None:
    """Resolve a near-field choice into its object (None: the mesh alone).

    Parameters
    ----------
    kind : {"halfspace", "layer", "none"} or None
        The kernel (``"auto"`` is resolved against a bundle by
        :func:`hailstorm.runtime.contact.capacitance_build.resolve_near_field`); ``"none"``/None keeps the discrete model (the patch's
        compliance is the mesh's, whatever its size).
    young, poisson : float
        The material under the contacts [Pa], [-].

    Raises
    ------
    ValueError
        An unknown kernel or an invalid material.
    """
    if kind is None or kind == "none":
        return None
    if kind not in NEAR_FIELDS or kind == "auto":
        raise ValueError(f"near_field must be one of {', '.join(map(repr, NEAR_FIELDS))}, got {kind!r}")
    if not (young > 0 and -1.0 < poisson < 0.5):
        raise ValueError("the near field needs E > 0 and -1 < nu < 0.5")
    return NearField(kernel=kind, young=float(young), poisson=float(poisson))


_SURFACES: "weakref.WeakKeyDictionary[Any, tuple[np.ndarray, ...]]" = weakref.WeakKeyDictionary()


def kernel_surface(gf: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A bundle's surface as the near-field kernel reads it, built once per bundle: vertices
    (n, 3) float64, triangles (m, 3) int64, lumped areas (n,), and :func:`vertex_triangles`
    (``ptr``, ``tri``)."""
    try:
        return _SURFACES[gf]
    except (KeyError, TypeError):
        pass
    T = np.ascontiguousarray(gf.triangles, dtype=np.int64)
    X = np.ascontiguousarray(gf.vertices, dtype=np.float64)
    out = (X, T, np.ascontiguousarray(gf.areas, dtype=np.float64), *vertex_triangles(T, X.shape[0]))
    try:
        _SURFACES[gf] = out
    except TypeError:  # pragma: no cover - not weak-referenceable
        pass
    return out


def vertex_triangles(triangles: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR map vertex -> the triangles holding it: ``tri[ptr[v]:ptr[v + 1]]``."""
    T = np.asarray(triangles)
    owner = T.ravel()
    order = np.argsort(owner, kind="stable")
    ptr = np.zeros(n + 1, dtype=np.int64)
    np.add.at(ptr, owner + 1, 1)
    return np.cumsum(ptr), (order // 3).astype(np.int64)
