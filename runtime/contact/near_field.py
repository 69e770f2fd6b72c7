"""Contacts smaller than a surface element: the near field at the contact's own scale.

Part of the contact core (:mod:`hailstorm.runtime.contact`). A patch contact of
radius ``a`` spreads its force with the consistent nodal load of its pressure
disc (:func:`hailstorm.runtime.contact.weights.patch_weights`). When ``a`` is
small against the surface elements, the mesh cannot carry the disc: its
compliance ``w^T D w`` is then the mesh's (the disc smeared over the hat
functions of a few vertices), not the contact's, and it depends on where in
the triangle the contact sits.

The resolved model keeps what the mesh knows and replaces what it cannot::

    W_kk = w^T D w  -  w^T H w  +  c(a)

* ``w^T D w``: the patch's compliance from the precomputed D (the body: the
  pad, its clamp, the shell, curvature, other materials);
* ``w^T H w``: the same hat loads on the near-field kernel, the elastic
  half-space of the local material (``H`` the ``1/r`` Boussinesq--Cerruti
  kernel integrated in closed form over the hat functions,
  :func:`hat_halfspace_block`) -- what D holds of the near field *as the mesh
  represents it*;
* ``c(a)``: the kernel's compliance of the contact's own Hertz disc
  (:func:`halfspace_patch_compliance`), resolved at its own scale whatever
  the mesh.

``D - H`` is the body's response minus the half-space's: smooth at the
contact (for a body thicker than the contact and a kernel of its material),
so the mesh carries it well; the near field is counted once, at the contact's
scale. The subtraction needs D's columns to answer hat loads (``load =
"hat"``, the consistent loads; :func:`hailstorm.precompute.greens.hat_load_matrix`):
a point-load column's near field is the mesh's singular point response,
which no kernel reproduces.

Measured on a 6 mm P2 block of foam (E = 2 MPa, nu = 0.35; the docs'
verification page has the command): the normal compliance of a patch of
radius 1-18 mm within 2-3 % of the half-space's on a vertex, an edge and a
centroid alike (the discrete model: 15-90 % of it, by site).

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

__all__ = [
    "NEAR_FIELDS",
    "NearField",
    "halfspace_patch_compliance",
    "hat_halfspace_block",
    "hat_potential",
    "near_field",
    "surface_fans",
    "vertex_triangles",
]

#: the near-field choices ("none": the mesh alone, the discrete model; "auto": the half-space
#: kernel on a bundle whose columns answer hat loads, else none)
NEAR_FIELDS = ("auto", "halfspace", "none")


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
    kernel : {"halfspace"}
        The near-field kernel.
    young, poisson : float
        The material of the kernel (the bundle's under the contactable surface).
    """

    kernel: str
    young: float
    poisson: float

    def compliance(self, radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The kernel's normal and tangential self-compliance of a Hertz disc of ``radius`` [m/N]."""
        return halfspace_patch_compliance(radius, self.young, self.poisson)

    def mesh_compliance(self, gf: Any, verts: np.ndarray, weights: np.ndarray, centre: np.ndarray,
                        normal: np.ndarray) -> tuple[float, float]:
        """The kernel's normal and tangential compliance of one patch *as the mesh carries it*
        (its hat loads ``weights`` on ``verts``), ``w^T H w`` [m/N] (:func:`hat_halfspace_block`)."""
        m = weights > 0
        v, w = np.asarray(verts)[m], np.asarray(weights)[m]
        o = np.argsort(v)
        v, w = v[o], w[o]
        H = hat_halfspace_block(gf.vertices, gf.triangles, gf.areas, surface_fans(gf), v, centre, normal)
        k_n = (1.0 - self.poisson**2) / (np.pi * self.young)
        whw = float(w @ H @ w)
        return k_n * whw, k_n * whw * (2.0 - self.poisson) / (2.0 * (1.0 - self.poisson))

    def blocks(self, gf: Any, radius: np.ndarray, verts: np.ndarray, weights: np.ndarray, centres: np.ndarray,
               normals: np.ndarray, sticky: bool) -> np.ndarray:
        """Per-contact correction ``c(a) - w^T H w`` in the constrained components, (s, p, p).

        ``p = 3`` (sticky: ``dn n n^T + dt (I - n n^T)``) or 1 (frictionless:
        ``dn``); zero for point contacts (``a = 0``).
        """
        a = np.asarray(radius, dtype=np.float64)
        s = a.size
        dn, dt = np.zeros(s), np.zeros(s)
        for k in np.flatnonzero(a > 0):
            cn, ct = self.compliance(a[k])
            mn, mt = self.mesh_compliance(gf, verts[k], weights[k], centres[k], normals[k])
            dn[k], dt[k] = cn - mn, ct - mt
        if not sticky:
            return dn.reshape(s, 1, 1)
        n = np.asarray(normals, dtype=np.float64).reshape(s, 3)
        nn = n[:, :, None] * n[:, None, :]
        return dn[:, None, None] * nn + dt[:, None, None] * (np.eye(3) - nn)


def near_field(kind: str | None, young: float, poisson: float) -> NearField | None:
    """Resolve a near-field choice into its object (None: the mesh alone).

    Parameters
    ----------
    kind : {"halfspace", "none"} or None
        The kernel (``"auto"`` is resolved against a bundle by
        :func:`hailstorm.runtime.contact.contact_capacitance.resolve_near_field`); ``"none"``/None keeps the discrete model (the patch's
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


_FANS: "weakref.WeakKeyDictionary[Any, tuple[np.ndarray, np.ndarray]]" = weakref.WeakKeyDictionary()


def surface_fans(gf: Any) -> tuple[np.ndarray, np.ndarray]:
    """:func:`vertex_triangles` of a bundle's surface, built once per bundle."""
    try:
        return _FANS[gf]
    except (KeyError, TypeError):
        pass
    fans = vertex_triangles(np.asarray(gf.triangles), np.asarray(gf.vertices).shape[0])
    try:
        _FANS[gf] = fans
    except TypeError:  # pragma: no cover - not weak-referenceable
        pass
    return fans


def hat_potential(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """``I[i, t, c] = int_T phi_c(y) / |x_i - y| dy`` over plane triangles, in closed form [m].

    The single-layer potential of each corner's hat function ``phi_c`` (the
    linear function that is 1 at corner ``c`` and 0 at the others) over
    triangle ``T``, at points ``x_i`` of the same plane: what the half-space's
    ``1/r`` kernel (Boussinesq, Cerruti) makes of a hat traction. ``T`` is
    split into the three triangles ``(x, p, q)`` over its edges (signed by
    orientation); in polar coordinates about ``x`` the kernel cancels the
    Jacobian, and along each ray the linear ``phi`` integrates exactly, which
    leaves ``(h L / 2) int_0^1 (phi(x) + phi(y(s))) / |y(s) - x| ds`` over the
    edge ``y(s) = p + s (q - p)`` (``h`` the distance of ``x`` to its line,
    ``L`` its length): an ``asinh`` and a square root. Exact for ``x`` inside,
    on or outside ``T`` (an edge through ``x`` contributes 0).

    Parameters
    ----------
    points : (k, 2) ndarray
        Evaluation points in the plane.
    corners : (m, 3, 2) ndarray
        Triangle corners in the plane.

    Returns
    -------
    (k, m, 3) ndarray
    """
    x = np.asarray(points, dtype=np.float64)[:, None, :]  # (k, 1, 2)
    T = np.asarray(corners, dtype=np.float64)[None]  # (1, m, 3, 2)
    e1, e2 = T[..., 1, :] - T[..., 0, :], T[..., 2, :] - T[..., 0, :]
    det = e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0]  # (1, m): twice the signed area

    def phi(y: np.ndarray) -> np.ndarray:
        """The three hat functions of each triangle at points y (k, m, 2) -> (k, m, 3)."""
        d = y - T[..., 0, :]
        l1 = (d[..., 0] * e2[..., 1] - d[..., 1] * e2[..., 0]) / det
        l2 = (e1[..., 0] * d[..., 1] - e1[..., 1] * d[..., 0]) / det
        return np.stack([1.0 - l1 - l2, l1, l2], axis=-1)

    px = phi(np.broadcast_to(x, x.shape[:1] + T.shape[1:2] + (2,)))
    out = np.zeros(px.shape)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        p, q = T[..., a, :], T[..., b, :]
        pq = q - p
        L = np.linalg.norm(pq, axis=-1)  # (1, m)
        rel = p - x  # (k, m, 2)
        cross = rel[..., 0] * pq[..., 1] - rel[..., 1] * pq[..., 0]  # signed 2 area of (x, p, q)
        h = np.abs(cross) / L
        s0 = -np.einsum("kmd,kmd->km", rel, np.broadcast_to(pq, rel.shape)) / L**2
        r0 = np.linalg.norm(rel, axis=-1)
        r1 = np.linalg.norm(q - x, axis=-1)
        ok = h > 1e-12 * L
        hs = np.where(ok, h, 1.0)
        ash = np.arcsinh(L * (1.0 - s0) / hs) - np.arcsinh(-L * s0 / hs)
        A, B = phi(np.broadcast_to(p, rel.shape)), None
        Bq = phi(np.broadcast_to(q, rel.shape))
        B = Bq - A
        J = (px + A + B * s0[..., None]) / L[..., None] * ash[..., None] + B / L[..., None] ** 2 * (r1 - r0)[..., None]
        sign = np.sign(cross) * np.sign(det)
        out += np.where(ok[..., None], (sign * h * L / 2.0)[..., None] * J, 0.0)
    return out


def vertex_triangles(triangles: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """CSR map vertex -> the triangles holding it: ``tri[ptr[v]:ptr[v + 1]]``."""
    T = np.asarray(triangles)
    owner = T.ravel()
    order = np.argsort(owner, kind="stable")
    ptr = np.zeros(n + 1, dtype=np.intp)
    np.add.at(ptr, owner + 1, 1)
    return np.cumsum(ptr), (order // 3).astype(np.intp)


def hat_halfspace_block(vertices: np.ndarray, triangles: np.ndarray, areas: np.ndarray,
                        fan: tuple[np.ndarray, np.ndarray], verts: np.ndarray, centre: np.ndarray,
                        normal: np.ndarray) -> np.ndarray:
    """``1/r`` kernel of hat loads between patch vertices, on the tangent plane [1/m], (P, P).

    ``H[i, j] = (1 / a_j) sum_{T ni j} int_T phi_j(y) / |x_i - y| dy``: the
    half-space's response at vertex ``i`` to the hat traction of vertex ``j``
    (``phi_j / a_j``, one newton; what a ``load = "hat"`` column of D answers),
    up to the material factor (normal: ``(1 - nu^2) / (pi E)``), with the
    patch's vertices and their triangles projected on the plane through
    ``centre`` normal to ``normal``. Triangles that do not face along
    ``normal`` (the body's folds) are left out.
    """
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    t1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(n, t1)
    X = np.asarray(vertices, dtype=np.float64)

    def plane(p: np.ndarray) -> np.ndarray:
        d = p - centre
        return np.stack([d @ t1, d @ t2], axis=-1)

    ptr, tri = fan
    v = np.asarray(verts, dtype=np.intp)
    tris = np.unique(np.concatenate([tri[ptr[j]:ptr[j + 1]] for j in v]))
    T = np.asarray(triangles)[tris]
    # the kernel is the tangent plane's: only triangles facing along the normal (projected area at
    # least half their own) carry their share of a hat load onto it; a fold (the body's edge) does not
    P = X[T]
    tn = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    T = T[tn @ n >= 0.5 * np.linalg.norm(tn, axis=1)]
    I = hat_potential(plane(X[v]), plane(X[T]))  # (P, m, 3)
    # column j collects I[:, t, c] over the (t, c) where corner c of t is vertex j
    col = np.searchsorted(v, T)  # position of each corner in v (v sorted)
    hit = (col < v.size) & (v[np.minimum(col, v.size - 1)] == T)
    H = np.zeros((v.size, v.size))
    for c in range(3):
        m = hit[:, c]
        np.add.at(H.T, col[m, c], I[:, m, c].T)
    return H / np.asarray(areas, dtype=np.float64)[v][None, :]
