"""Contact force-distribution weights: the matrix B of point and patch contacts.

Part of the contact core (:mod:`hailstorm.runtime.contact`). A contact ``k`` spreads its force over a
few surface vertices with weights ``w_{k,i}`` that sum to one; ``B`` is the
``3|V| x 3s`` matrix with block ``(i, k) = w_{k,i} I3``, vertex forces are
``f_V = B f_s`` and the contact "displacement" is ``u_s = B^T u_V`` (the
weighted mean displacement of the patch). Internally a contact set is held as
two padded ``(s, P)`` arrays: ``loc`` (position of each weighted vertex in the
sorted vertex union ``V``) and ``w`` (its weight; padding has weight 0 and
points at the contact's first vertex, so it adds no vertex to ``V``).

Point contacts (the course hint)
    ``w_k = beta_k`` on the three vertices of the contacted triangle
    (``P = 3``): :func:`barycentric_matrix`.

Patch contacts (James & Pai's pressure masks)
    A point load on an elastic body is singular (Boussinesq: ``u ~ 1/r``), so
    the stiffness of a point contact goes to zero as the mesh is refined. A
    patch contact spreads the force over the physical contact disc of radius
    ``a`` (centred on the contact point, in the plane normal to the contact
    normal) with a pressure profile ``p`` (Hertz: ``p ~ sqrt(1 - r^2/a^2)``)
    and uses the *consistent* nodal load of that pressure on the P1 surface:

        ``w_{k,i} = \\int p(x) phi_i(x) dA / \\int p(x) dA``

    with ``phi_i`` the piecewise-linear hat function of vertex ``i``. This
    generalises ``beta`` exactly: as ``a -> 0`` the pressure tends to a Dirac
    at the contact point and ``w_k -> phi(x_k) = beta_k``; for a patch that
    covers many triangles it tends to ``p(x_i) * a_i`` (lumped areas). The
    weights are continuous in the contact position and in ``a``, so a stone
    sliding over the mesh sees no jumps. The integral is a product rule on
    the disc (Gauss in ``t = sqrt(1 - r^2/a^2)``, trapezoidal in the angle);
    each quadrature point is projected along the contact normal onto the
    nearest facing surface triangle whose vertices all own a column of D
    (contactable or clamped). Parts of the disc off that region (past the
    edge of the hail-facing surface) are dropped and the rest renormalised;
    if nothing is left the contact falls back to its barycentric weights.

:func:`hertz_radius` gives the Hertz contact radius
``a = (3 F R / (4 E*))^(1/3)``, ``E* = E / (1 - nu^2)``, of a rigid sphere of
radius ``R`` pressed with force ``F`` on the seat (the paraboloid's, ``a << R``);
:func:`sphere_radius` the sphere's own at any ``a / R``, which patch contacts are
sized by, and :func:`sphere_offset` the matching offset of the patch's mean
displacement below the sphere's lowest point. An impact's patch is sized for the
sphere's work as well as its force (:func:`impact_radius`, :func:`impact_offset`:
the patch whose linear law reaches the sphere's peak force and depth with the
sphere's energy; the storm's).
"""

from __future__ import annotations

import functools
import math
import weakref
from typing import Any

import numpy as np

from hailstorm.runtime.compiled import SampleGrid
from hailstorm.runtime.compiled.patches import disc_patch as one_patch_kernel
from hailstorm.runtime.compiled.sphere import impact_offsets_of_patch, impact_radii, sphere_qs, sphere_radii
from hailstorm.runtime.bundle.compliance import ComplianceSource, unique_inverse
from hailstorm.runtime.bundle.read import vertex_normals

__all__ = [
    "CREASE_ANGLE",
    "OFFSET_PEAK",
    "PATCH_DROP",
    "PATCH_FACING",
    "PATCH_PROFILES",
    "TriangleIndex",
    "barycentric_matrix",
    "contact_points",
    "corner_normals",
    "dense_B",
    "dense_Bs",
    "disc_rule",
    "disc_table",
    "hertz_radius",
    "impact_offset",
    "impact_radius",
    "interpolate",
    "locate",
    "pad",
    "patch_matrix",
    "patch_weights",
    "resolved_fraction",
    "smooth_normals",
    "sphere_mean_offset",
    "sphere_offset",
    "sphere_radius",
    "triangle_index",
    "triangle_normals",
    "vertex_forces",
]

#: Pressure profiles of a patch contact: Hertz ``sqrt(1 - r^2/a^2)`` or uniform.
PATCH_PROFILES = ("hertz", "uniform")
#: A surface triangle takes part in a patch if its normal makes less than
#: ~75 degrees with the contact normal (``n_t . n_k > PATCH_FACING``).
PATCH_FACING: float = 0.25
#: Weights below this fraction of a contact's largest weight are dropped.
PATCH_DROP: float = 1e-12


# --------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------
#: two triangles that meet at a vertex at more than this angle between their normals [rad] are
#: on either side of a sharp edge: neither smooths the other's corner normal (:func:`corner_normals`).
#: Measured on the default seat (400 stones, 0.4 s, dt 0.1 ms): at 30 degrees and below its stones
#: in flight overlap the facets by at most 0.03 mm, at 40-60 degrees by 0.37 mm (the smooth
#: normal tilted from the facets of an edge bent by 30-40 degrees: the contact's spring leans on a
#: plane the facets do not follow)
CREASE_ANGLE = math.radians(30.0)


def corner_normals(vertices: np.ndarray, triangles: np.ndarray, crease: float = CREASE_ANGLE) -> np.ndarray:
    """The surface's normal at each triangle's corners, read as a smooth surface but at its sharp
    edges: at corner ``i`` of triangle ``t`` (vertex ``v``), the area-weighted mean of the normals of
    the triangles around ``v`` within ``crease`` of ``t``'s normal (``t`` itself included), (m, 3, 3).

    Inside a smooth region every triangle around a vertex gives that vertex the same normal, so
    the normal interpolated over the triangles (:func:`hailstorm.runtime.compiled.narrow.contact_normal`)
    is continuous across their edges; a triangle on a sharp edge keeps its side's. Memory O(m):
    a vertex whose triangles all lie within ``crease / 2`` of their mean normal
    (:func:`hailstorm.runtime.bundle.read.vertex_normals`) takes that mean at every corner (any
    two of them are within ``crease``); only the others are summed corner by corner.

    Parameters
    ----------
    vertices : (n, 3) ndarray
    triangles : (m, 3) int ndarray
        Outward triangles.
    crease : float
        [rad].
    """
    X = np.asarray(vertices, dtype=np.float64)
    T = np.asarray(triangles, dtype=np.intp)
    weighted = np.cross(X[T[:, 1]] - X[T[:, 0]], X[T[:, 2]] - X[T[:, 0]])  # 2 x area x unit normal
    ln = np.linalg.norm(weighted, axis=1, keepdims=True)
    face = weighted / np.where(ln > 0, ln, 1.0)
    mean = vertex_normals(X, T)
    # the largest angle of a triangle's normal from its corner's vertex mean, per vertex
    cos_dev = np.ones(len(X))
    np.minimum.at(cos_dev, T.ravel(), np.einsum("kd,kd->k", np.repeat(face, 3, axis=0), mean[T.ravel()]))
    out = mean[T]
    mixed = np.flatnonzero(~(cos_dev >= math.cos(0.5 * crease)))
    if mixed.size:
        corners = np.flatnonzero(np.isin(T.ravel(), mixed))
        cv = T.ravel()[corners]
        order = np.argsort(cv, kind="stable")
        cv, corners = cv[order], corners[order]
        start = np.flatnonzero(np.r_[True, cv[1:] != cv[:-1]])
        ends = np.r_[start[1:], cv.size]
        flat = out.reshape(-1, 3)
        cos_c = math.cos(crease)
        for lo, hi in zip(start.tolist(), ends.tolist()):
            f = corners[lo:hi] // 3  # the triangles around this vertex, one per corner
            nf = face[f]
            keep = (nf @ nf.T) >= cos_c  # (k, k): corner i takes triangle j
            acc = keep.astype(np.float64) @ weighted[f]
            la = np.linalg.norm(acc, axis=1, keepdims=True)
            flat[corners[lo:hi]] = np.where(la > 0, acc / np.where(la > 0, la, 1.0), nf)
    return out


def smooth_normals(vertices: np.ndarray, triangles: np.ndarray, tris: np.ndarray, barycentric: np.ndarray,
                   crease: float = CREASE_ANGLE) -> np.ndarray:
    """The surface's smooth outward unit normal at points on it: the corner normals
    (:func:`corner_normals`, the storm's reading of the surface) interpolated by the barycentric
    coordinates.

    Unlike a triangle's own normal it does not jump from one facet to the next (except across
    a sharp edge, beyond ``crease``), so a contact pressed along it sees the smooth surface the
    mesh approximates, wherever on the mesh it lands.

    Parameters
    ----------
    vertices : (n, 3) float ndarray
    triangles : (m, 3) int ndarray
        The oriented surface triangles.
    tris : (k,) int ndarray
        The triangle each point lies on.
    barycentric : (k, 3) float ndarray
        Its barycentric coordinates there.
    crease : float
        [rad] (:func:`corner_normals`).

    Returns
    -------
    (k, 3) float ndarray
        Unit normals (the triangle's own where the interpolated one vanishes).
    """
    T = np.asarray(triangles)
    t = np.asarray(tris, dtype=np.intp).reshape(-1)
    n = np.einsum("kc,kcd->kd", np.asarray(barycentric, dtype=np.float64).reshape(-1, 3),
                  corner_normals(vertices, T, crease)[t])
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    flat = ln[:, 0] <= 1e-12
    if flat.any():
        n[flat] = triangle_normals(vertices, T[t[flat]])
        ln[flat] = 1.0
    return n / ln


def triangle_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Outward unit normals of oriented (counter-clockwise from outside) triangles.

    Parameters
    ----------
    vertices : (n, 3) float ndarray
    triangles : (k, 3) int ndarray

    Returns
    -------
    (k, 3) float ndarray
        Unit normals; zero rows for degenerate (zero-area) triangles.
    """
    p = np.asarray(vertices, dtype=np.float64)[np.asarray(triangles)]
    a = p[:, 1] - p[:, 0]
    b = p[:, 2] - p[:, 0]
    nrm = np.empty_like(a)
    nrm[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    nrm[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    nrm[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    ln = np.sqrt(np.einsum("ki,ki->k", nrm, nrm))[:, None]
    return nrm / np.where(ln > 0, ln, 1.0)


def contact_points(vertices: np.ndarray, triangles: np.ndarray, tri_idx: Any, bary: Any) -> np.ndarray:
    """Positions ``sum_a beta_a x_a`` of contacts given by triangle and barycentric coordinates, (s, 3)."""
    tri_idx = np.asarray(tri_idx, dtype=np.intp).reshape(-1)
    bary = np.asarray(bary, dtype=np.float64).reshape(tri_idx.size, 3)
    return np.einsum("ka,kad->kd", bary, np.asarray(vertices, dtype=np.float64)[np.asarray(triangles)[tri_idx]])


def hertz_radius(force: Any, stone_radius: Any, young: float, poisson: float, *,
                 a_min: float = 0.0, a_max: float | None = None) -> np.ndarray:
    """Hertz contact radius of a rigid sphere pressed on the (elastic) seat.

    ``a = (3 F R / (4 E*))^(1/3)`` with ``E* = E / (1 - nu^2)`` (rigid
    sphere on an elastic half-space; Johnson, *Contact Mechanics*, ch. 4),
    clipped to ``[a_min, a_max]``.

    Parameters
    ----------
    force : float or (s,) array_like
        Normal load [N]; the magnitude is used (a force on the seat pressing
        in has ``f . n < 0``).
    stone_radius : float or (s,) array_like
        Sphere radius R [m].
    young, poisson : float
        The seat's material [Pa], [-].
    a_min : float
        Floor [m], e.g. a fraction of the mesh size: the radius of a patch
        contact at vanishing load (0 recovers a point contact).
    a_max : float, optional
        Ceiling [m] (e.g. the stone radius).

    Returns
    -------
    ndarray
        Contact radius [m], broadcast shape of ``force`` and ``stone_radius``.
    """
    F = np.abs(np.asarray(force, dtype=np.float64))
    R = np.asarray(stone_radius, dtype=np.float64)
    if np.any(R < 0) or not (young > 0 and -1.0 < poisson < 0.5):
        raise ValueError("hertz_radius needs R >= 0, E > 0 and -1 < nu < 0.5")
    e_star = young / (1.0 - poisson**2)
    a = np.cbrt(3.0 * F * R / (4.0 * e_star))
    a = np.maximum(a, a_min)
    if a_max is not None:
        a = np.minimum(a, a_max)
    return a


#: the ``a / R`` at which :func:`sphere_offset` peaks (0.149 R); held there beyond
OFFSET_PEAK = 0.9099577964991118


def sphere_radius(force: Any, stone_radius: Any, young: float, poisson: float, *,
                  a_min: float = 0.0, a_max: float | None = None) -> np.ndarray:
    """Contact radius of a rigid sphere pressed on the (elastic) seat, at any ``a / R``.

    The inverse of the sphere's own law ``F = E* R^2 ((1 + x^2) atanh(x) - x)``,
    ``x = a / R`` (Sneddon 1965; :mod:`hailstorm.runtime.compiled.sphere`), which is
    :func:`hertz_radius` for ``a << R`` and stays below ``R`` at every force (Hertz's
    paraboloid reaches ``R`` at ``F = (4/3) E* R^2``). Clipped to ``[a_min, a_max]``.
    Parameters and result as :func:`hertz_radius`'s.
    """
    return _radius_of_force(sphere_radii, "sphere_radius", force, stone_radius, young, poisson, a_min, a_max)


def sphere_offset(patch_radius: Any, sphere_radius: Any) -> np.ndarray:
    """How far a patch's mean surface displacement lies short of the sphere's lowest point [m]
    (0 for a point contact, ``a = 0``): the offset that makes a patch of radius ``a``, whose
    compliance is Hertz's disc's ``3 / (5 a E*)``, carry the sphere's own force at its depth.

    ``R (x atanh(x) - (3/5) q(x) / x)`` with ``x = a / R`` and ``q`` the sphere's force
    (:mod:`hailstorm.runtime.compiled.sphere`): ``delta(a) - 3 F(a) / (5 a E*)``. For
    ``a << R`` it is ``a^2 / (5 R) (1 + x^2 / 15 + ...)``, the Hertz-weighted mean of the
    paraboloid ``r^2 / (2 R)`` (``<r^2> = 2 a^2 / 5``), so a patch is consistent with
    Hertz where Hertz holds and with the sphere beyond (on a half-space exactly) up to
    ``a/R`` = :data:`OFFSET_PEAK` (0.910), where it peaks at 0.149 R; it is held at that peak
    beyond (where it would fall to 0 at 0.993), so that a wider patch never has a smaller
    offset: contacts that wide are far outside the model's limits
    (:mod:`hailstorm.runtime.storm.limits`).
    """
    a = np.asarray(patch_radius, dtype=np.float64)
    R = np.asarray(sphere_radius, dtype=np.float64)
    a, R = np.broadcast_arrays(a, R)
    x = np.where(R > 0, np.minimum(a / np.where(R > 0, R, 1.0), OFFSET_PEAK), 0.0)
    q = sphere_qs(np.ascontiguousarray(x, dtype=np.float64).ravel()).reshape(x.shape)
    off = R * (x * np.arctanh(x) - 0.6 * q / np.where(x > 0, x, 1.0))
    return np.where(x > 0, off, 0.0)


def impact_radius(force: Any, stone_radius: Any, young: float, poisson: float, *,
                  a_min: float = 0.0, a_max: float | None = None) -> np.ndarray:
    """The patch radius of an impact whose peak force is ``force``: a Hertz disc whose
    linear law ``F = (delta - o) / c``, ``c = 3 / (5 a E*)``, reaches the sphere's peak
    ``(delta, F)`` with the sphere's work ``W`` (``c = 2 W / F^2``).

    ``R i(x)``, ``i(x) = 3 q(x)^2 / (10 w(x))`` at the sphere's own ``x = a / R``
    (:func:`sphere_radius`; :func:`hailstorm.runtime.compiled.sphere.impact_patch_x`):
    the sphere's radius for ``a << R`` (Hertz's law is its own linearisation's energy),
    1.1 % above it at ``a/R`` 0.5, 4.0 % at 0.8. Sized by the sphere's radius instead
    (with :func:`sphere_offset`), an impact on a half-space is 1.1 / 2.2 % soft in peak
    force at ``a/R`` 0.62 / 0.80.
    Clipped to ``[a_min, a_max]``; parameters and result as :func:`hertz_radius`'s.
    """
    return _radius_of_force(impact_radii, "impact_radius", force, stone_radius, young, poisson, a_min, a_max)


def _radius_of_force(radii: Any, name: str, force: Any, stone_radius: Any, young: float, poisson: float,
                     a_min: float, a_max: float | None) -> np.ndarray:
    """The numpy face of a compiled ``radii(F, R, e_star)`` over 1-d arrays: checked, broadcast, clipped."""
    F = np.abs(np.asarray(force, dtype=np.float64))
    R = np.asarray(stone_radius, dtype=np.float64)
    if np.any(R < 0) or not (young > 0 and -1.0 < poisson < 0.5):
        raise ValueError(f"{name} needs R >= 0, E > 0 and -1 < nu < 0.5")
    F, R = np.broadcast_arrays(F, R)
    e_star = young / (1.0 - poisson**2)
    a = radii(np.ascontiguousarray(F.ravel()), np.ascontiguousarray(R.ravel()), e_star).reshape(F.shape)
    a = np.maximum(a, a_min)
    if a_max is not None:
        a = np.minimum(a, a_max)
    return a


def impact_offset(patch_radius: Any, sphere_radius: Any) -> np.ndarray:
    """The offset [m] that goes with an impact patch of radius ``a_i`` (:func:`impact_radius`):
    ``delta - 2 W / F`` of the sphere whose impact patch it is, so the patch's linear law passes
    through the sphere's peak ``(delta, F)`` (its static point at that force too).

    ``R (x atanh(x) - 2 w(x) / q(x))`` at the ``x`` with ``i(x) = a_i / R``
    (:func:`hailstorm.runtime.compiled.sphere.impact_offset_of_patch`): ``a^2 / (5 R)`` for
    ``a << R`` like :func:`sphere_offset`, and growing with ``a_i`` at every size (no peak).
    """
    a = np.asarray(patch_radius, dtype=np.float64)
    R = np.asarray(sphere_radius, dtype=np.float64)
    a, R = np.broadcast_arrays(a, R)
    p = np.where(R > 0, a / np.where(R > 0, R, 1.0), 0.0)
    o = impact_offsets_of_patch(np.ascontiguousarray(p, dtype=np.float64).ravel()).reshape(p.shape)
    return R * o


def resolved_fraction(points: np.ndarray, verts: np.ndarray, weights: np.ndarray, centres: np.ndarray,
                      normals: np.ndarray, patch_radius: Any) -> np.ndarray:
    """How much of a sphere's offset a patch's mesh can follow, in ``[0, 1]``, (s,).

    An offset such as :func:`sphere_offset` assumes a surface that follows the sphere over
    the whole disc. A piecewise-linear surface can only do so where its
    triangles are small against the disc: a disc inside one triangle sees a
    plane, whose weighted mean is its value at the contact point, offset 0.
    The weights' tangential second moment about the contact point,
    ``m2 = sum_p w_p |rho_p|^2``, measures this: it is ``2 a^2 / 5`` plus an
    ``O(h^2)`` smear of the hat functions. The fraction is
    ``min(1, (2 a^2 / 5) / m2)``: 1 on a resolved patch, vanishing as the patch shrinks
    inside a triangle.

    Parameters
    ----------
    points : (n, 3) ndarray
        Undeformed surface vertices.
    verts, weights : (s, P) ndarrays
        Each contact's weighted vertices and weights (:func:`patch_weights`;
        padding has weight 0).
    centres, normals : (s, 3) ndarrays
        Contact points and unit normals.
    patch_radius : float or (s,) array_like
        ``a`` [m].
    """
    a = np.broadcast_to(np.asarray(patch_radius, dtype=np.float64), (verts.shape[0],))
    rho = np.asarray(points, dtype=np.float64)[verts] - centres[:, None, :]
    rho = rho - np.einsum("kpd,kd->kp", rho, normals)[..., None] * normals[:, None, :]
    m2 = np.einsum("kp,kpd,kpd->k", weights, rho, rho)
    m2_disc = 0.4 * a * a
    return np.where(m2 > m2_disc, m2_disc / np.where(m2 > 0, m2, 1.0), 1.0)


def sphere_mean_offset(points: np.ndarray, verts: np.ndarray, weights: np.ndarray, centres: np.ndarray,
                       normals: np.ndarray, patch_radius: Any, sphere_radius: Any) -> np.ndarray:
    """The patch-mean offset of a sphere's profile as the surface mesh can follow it [m], (s,):
    :func:`sphere_offset` times :func:`resolved_fraction` (parameters as there; ``sphere_radius``
    ``R`` [m])."""
    fraction = resolved_fraction(points, verts, weights, centres, normals, patch_radius)
    return sphere_offset(patch_radius, sphere_radius) * fraction


# --------------------------------------------------------------------------
# generalised B: padded (s, P) vertex lists and weights
# --------------------------------------------------------------------------
def locate(verts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """V (sorted union of the listed vertices) and loc (s, P): the position in V of each entry of ``verts``."""
    V, loc = unique_inverse(verts)
    return V.astype(np.intp), loc.reshape(verts.shape).astype(np.intp)


def pad(verts: np.ndarray, w: np.ndarray, P: int) -> tuple[np.ndarray, np.ndarray]:
    """Pad (s, p) vertex lists / weights to (s, P) with weight-0 copies of the first vertex."""
    s, p = verts.shape
    if p >= P:
        return verts, w
    return (np.hstack([verts, np.repeat(verts[:, :1], P - p, axis=1)]),
            np.hstack([w, np.zeros((s, P - p))]))


def dense_Bs(nV: int, loc: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Scalar weights (|V|, s): ``Bs[loc[k, p], k] += w[k, p]`` (B = Bs kron I3)."""
    s, P = loc.shape
    # bincount accumulates in the same (k, p) order as np.add.at, at a fraction of its cost
    idx = (loc * s + np.arange(s)[:, None]).ravel()
    return np.bincount(idx, weights=np.asarray(w, dtype=np.float64).ravel(), minlength=nV * s).reshape(nV, s)


def dense_B(nV: int, loc: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The dense force-distribution matrix B (3|V|, 3s), block ``(loc[k, p], k) = w[k, p] I3``."""
    s, P = loc.shape
    Bs = dense_Bs(nV, loc, w)
    B = np.zeros((3 * nV, 3 * s))
    for d in range(3):  # np.kron(Bs, np.eye(3)) without its overhead
        B[d::3, d::3] = Bs
    return B


def barycentric_matrix(
    triangles: np.ndarray, tri_idx: np.ndarray, bary: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The barycentric force-distribution matrix B of the course hint.

    Parameters
    ----------
    triangles : (m, 3) int ndarray
        Surface triangles.
    tri_idx : (s,) int ndarray
        Contacted triangle of each contact.
    bary : (s, 3) float ndarray
        Barycentric coordinates of each contact in its triangle.

    Returns
    -------
    V : (|V|,) int ndarray
        Sorted union of the contacted triangles' vertices.
    B : (3|V|, 3s) float ndarray
        Block ``(i, k) = beta_{k,i} I3``: vertex forces ``f_V = B f_s``,
        contact-point displacements ``u_s = B^T u_V``. Several contacts may
        share vertices or a triangle; a vertex listed twice in one triangle
        accumulates its weights.
    """
    tri_idx = np.asarray(tri_idx, dtype=np.intp).reshape(-1)
    bary = np.asarray(bary, dtype=np.float64).reshape(tri_idx.size, 3)
    V, loc = locate(np.asarray(triangles)[tri_idx])
    return V, dense_B(V.size, loc, bary)


def patch_matrix(gf: ComplianceSource, tri_idx: Any, bary: Any, radius: Any, normals: Any = None, *,
                 profile: str = "hertz") -> tuple[np.ndarray, np.ndarray]:
    """The patch force-distribution matrix B (block ``(i, k) = w_{k,i} I3``).

    Same as :func:`barycentric_matrix` with the weights of
    :func:`patch_weights` (``profile`` as there); ``radius = 0``
    gives the barycentric matrix.

    Returns
    -------
    V : (|V|,) int ndarray
    B : (3|V|, 3s) float ndarray
    """
    verts, w = patch_weights(gf, tri_idx, bary, radius, normals, profile=profile)
    V, loc = locate(verts)
    return V, dense_B(V.size, loc, w)


def vertex_forces(nV: int, loc: np.ndarray, w: np.ndarray, forces: np.ndarray) -> np.ndarray:
    """Vertex forces ``B f`` as (|V|, 3) from contact forces (s, 3)."""
    # bincount sums in index order from zero, as np.add.at does, at a fraction of its cost
    idx = loc.ravel()
    contrib = (w[:, :, None] * forces[:, None, :]).reshape(-1, 3)
    g = np.empty((nV, 3))
    for d in range(3):
        g[:, d] = np.bincount(idx, weights=contrib[:, d], minlength=nV)
    return g


def interpolate(uV: np.ndarray, loc: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Contact values ``B^T u_V`` as (s, 3) from vertex values (|V|, 3)."""
    return np.matmul(w[:, None, :], uV[loc]).reshape(-1, 3)


# --------------------------------------------------------------------------
# patch weights
# --------------------------------------------------------------------------
class TriangleIndex:
    """Per-bundle triangle data for patch location (built once per bundle: :func:`triangle_index`).

    Attributes
    ----------
    tris : (u,) int ndarray
        The usable triangles: every vertex owns a column of D (contactable or clamped).
    normals, p0, e1, e2 : (u, 3) float ndarrays
        Their unit normals, first corners and edges from it.
    radii : (u,) float ndarray
        Distance from each centroid to its farthest corner; ``reach`` the largest.
    grid : SampleGrid
        The centroids in a uniform grid.
    arrays : tuple
        The index as the compiled patch kernels take it
        (:mod:`hailstorm.runtime.compiled.patches`).
    """

    def __init__(self, gf: ComplianceSource):
        X = np.asarray(gf.vertices, dtype=np.float64)
        T = np.asarray(gf.triangles)
        self.usable = (gf.contactable | gf.fixed)[T].all(axis=1)
        self.tris = np.flatnonzero(self.usable)
        P = X[T[self.tris]]
        self.p0 = P[:, 0]
        self.e1 = P[:, 1] - P[:, 0]
        self.e2 = P[:, 2] - P[:, 0]
        self.normals = triangle_normals(X, T[self.tris])
        c = P.mean(axis=1)
        self.centroids = c
        self.radii = np.linalg.norm(P - c[:, None, :], axis=2).max(axis=1) if self.tris.size else np.zeros(0)
        self.reach = float(self.radii.max(initial=0.0))
        self.grid = SampleGrid.build(c, np.arange(self.tris.size), max(self.reach, 1e-6))
        g = self.grid
        self.arrays = (g.lo, g.h, g.dims, g.start, g.items, g.points, np.ascontiguousarray(self.radii),
                       np.ascontiguousarray(self.normals), np.ascontiguousarray(self.p0),
                       np.ascontiguousarray(self.e1), np.ascontiguousarray(self.e2), self.reach,
                       self.tris.astype(np.int64), np.ascontiguousarray(T, dtype=np.int64), int(X.shape[0]))


_INDEX_CACHE: "weakref.WeakKeyDictionary[Any, TriangleIndex]" = weakref.WeakKeyDictionary()


def triangle_index(gf: ComplianceSource) -> TriangleIndex:
    """The :class:`TriangleIndex` of a bundle (cached while the bundle lives, if it can be weakly referenced)."""
    try:
        idx = _INDEX_CACHE.get(gf)
    except TypeError:  # not weak-referenceable
        return TriangleIndex(gf)
    if idx is None:
        idx = TriangleIndex(gf)
        try:
            _INDEX_CACHE[gf] = idx
        except TypeError:  # pragma: no cover
            pass
    return idx


@functools.lru_cache(maxsize=256)
def disc_rule(n_r: int, n_t: int, profile: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit-disc product rule for ``int f p dA``: (x, y, weight), weights summing to 1.

    Gauss in ``t = sqrt(1 - r^2)`` (``n_r`` points), trapezoidal in the angle
    (``n_t``). Cached (a handful of ``n_r`` values occur); the arrays are read-only.
    """
    t, wt = np.polynomial.legendre.leggauss(n_r)
    t = 0.5 * (t + 1.0)
    wt = 0.5 * wt
    # r = sqrt(1 - t^2): r dr = -t dt; Hertz p = t -> t^2 dt, uniform -> t dt
    wt = wt * (t**2 if profile == "hertz" else t)
    r = np.sqrt(np.clip(1.0 - t**2, 0.0, None))
    th = 2.0 * np.pi * (np.arange(n_t) + 0.5) / n_t
    x = (r[:, None] * np.cos(th)[None, :]).ravel()
    y = (r[:, None] * np.sin(th)[None, :]).ravel()
    w = np.repeat(wt, n_t) / (wt.sum() * n_t)
    for arr in (x, y, w):
        arr.flags.writeable = False
    return x, y, w


@functools.lru_cache(maxsize=4)
def disc_table(profile: str, n_max: int = 40) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every :func:`disc_rule` ``(n_r, 4 n_r)`` for ``n_r <= n_max``, concatenated for the
    compiled kernels: (offsets (n_max + 2,), x, y, weight); rule ``n_r`` is
    ``offsets[n_r]:offsets[n_r + 1]`` (empty below 4)."""
    rules = [disc_rule(n, 4 * n, profile) if n >= 4 else (np.zeros(0),) * 3 for n in range(n_max + 1)]
    off = np.concatenate([[0], np.cumsum([r[0].size for r in rules])]).astype(np.int64)
    x, y, wt = (np.concatenate([r[i] for r in rules]) for i in range(3))
    return off, x, y, wt


def radial_points(a: float, h: float, resolution: float) -> int:
    """Gauss points along a patch radius: ``resolution`` per local mesh size ``h`` plus 4, in 4..40."""
    return int(min(max(math.ceil(resolution * a / max(h, 1e-300)) + 4, 4), 40))


def _one_patch(idx: TriangleIndex, x: np.ndarray, n: np.ndarray, a: float, h: float,
               profile: str, resolution: float) -> tuple[np.ndarray, np.ndarray] | None:
    """Vertices and weights of one patch (the compiled kernel); None if the disc hits no usable triangle."""
    if idx.tris.size == 0:
        return None
    n_r = radial_points(a, h, resolution)
    qx, qy, qw = disc_rule(n_r, 4 * n_r, profile)
    V, w = one_patch_kernel(np.ascontiguousarray(x, dtype=np.float64), np.ascontiguousarray(n, dtype=np.float64),
                            float(a), float(h), qx, qy, qw, PATCH_FACING, PATCH_DROP, idx.arrays)
    return (V.astype(np.intp), w) if V.size else None


def patch_weights(
    gf: ComplianceSource,
    tri_idx: Any,
    bary: Any,
    radius: Any,
    normals: Any = None,
    *,
    profile: str = "hertz",
    resolution: float = 3.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Force-distribution weights of patch contacts (consistent load of a pressure disc).

    Parameters
    ----------
    gf : GreensFunctions
        Loaded bundle (vertices, triangles, contactable, fixed).
    tri_idx : (s,) int array_like
        Contacted triangle of each contact.
    bary : (s, 3) float array_like
        Barycentric coordinates of the contact point (the patch centre).
    radius : float or (s,) array_like
        Patch radius ``a`` [m] per contact; 0 gives a point contact (the
        barycentric weights, bit for bit).
    normals : (s, 3) float array_like, optional
        Outward unit contact normals (the disc lies in the plane normal to
        it); default the contacted triangles' normals.
    profile : {"hertz", "uniform"}
        Pressure over the disc: ``sqrt(1 - r^2/a^2)`` or constant.
    resolution : float
        Quadrature points per local mesh size along a radius (plus 4). The
        default integrates the hat functions to ~1e-3 relative; the weights
        always sum to 1.
    Returns
    -------
    verts : (s, P) int ndarray
        Surface vertices carrying each contact's force (``P >= 3``; padding
        repeats the first vertex with weight 0).
    weights : (s, P) float ndarray
        Non-negative weights summing to 1 per contact.
    """
    if profile not in PATCH_PROFILES:
        raise ValueError(f"patch profile must be one of {PATCH_PROFILES}, got {profile!r}")
    T = np.asarray(gf.triangles)
    t = np.asarray(tri_idx, dtype=np.intp).reshape(-1)
    s = t.size
    b = np.asarray(bary, dtype=np.float64).reshape(s, 3)
    a = np.broadcast_to(np.asarray(radius, dtype=np.float64), (s,))
    if not np.all(np.isfinite(a)) or np.any(a < 0):
        raise ValueError("patch radius must be finite and non-negative")
    if normals is None:
        n = triangle_normals(gf.vertices, T[t])
    else:
        n = np.asarray(normals, dtype=np.float64).reshape(s, 3)
        n = n / np.where((ln := np.linalg.norm(n, axis=1, keepdims=True)) > 0, ln, 1.0)
    verts_list: list[np.ndarray] = [T[k] for k in t]
    w_list: list[np.ndarray] = [b[k] for k in range(s)]
    if np.any(a > 0):
        idx = triangle_index(gf)
        X = contact_points(gf.vertices, T, t, b)
        P = np.asarray(gf.vertices, dtype=np.float64)[T[t]]
        E = P - P[:, [2, 0, 1]]  # the edges (np.roll(P, 1, axis=1) without its overhead)
        h = np.sqrt(np.add.reduce(E * E, axis=2)).mean(axis=1)  # mean edge of the contact triangle
        for j in np.flatnonzero(a > 0):
            res = _one_patch(idx, X[j], n[j], float(a[j]), float(h[j]), profile, resolution)
            if res is not None:
                verts_list[j], w_list[j] = res
    Pm = max([3] + [v.size for v in verts_list])
    verts = np.empty((s, Pm), dtype=np.intp)
    w = np.zeros((s, Pm))
    for k in range(s):
        p = verts_list[k].size
        verts[k, :p] = verts_list[k]
        verts[k, p:] = verts_list[k][0]
        w[k, :p] = w_list[k]
    return verts, w
