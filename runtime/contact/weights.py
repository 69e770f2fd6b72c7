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

The contact normals are :mod:`hailstorm.runtime.contact.normals`'s; the radius and the offset
of a sphere's patch, :mod:`hailstorm.runtime.contact.sphere_patch`'s.
"""

from __future__ import annotations

import functools
import math
import weakref
from typing import Any

import numpy as np

from hailstorm.runtime.compiled import SampleGrid
from hailstorm.runtime.compiled.patches import disc_patch as one_patch_kernel
from hailstorm.runtime.bundle.compliance import ComplianceSource, unique_inverse
from hailstorm.runtime.contact.normals import triangle_normals

__all__ = [
    "PATCH_DROP",
    "PATCH_FACING",
    "PATCH_PROFILES",
    "TriangleIndex",
    "barycentric_matrix",
    "contact_points",
    "dense_B",
    "dense_Bs",
    "disc_rule",
    "disc_table",
    "interpolate",
    "locate",
    "pad",
    "patch_matrix",
    "patch_weights",
    "triangle_index",
    "vertex_forces",
]

#: Pressure profiles of a patch contact: Hertz ``sqrt(1 - r^2/a^2)`` or uniform.
PATCH_PROFILES = ("hertz", "uniform")
#: A surface triangle takes part in a patch if its normal makes less than
#: ~75 degrees with the contact normal (``n_t . n_k > PATCH_FACING``).
PATCH_FACING: float = 0.25
#: Weights below this fraction of a contact's largest weight are dropped.
PATCH_DROP: float = 1e-12


def contact_points(vertices: np.ndarray, triangles: np.ndarray, tri_idx: Any, bary: Any) -> np.ndarray:
    """Positions ``sum_a beta_a x_a`` of contacts given by triangle and barycentric coordinates, (s, 3)."""
    tri_idx = np.asarray(tri_idx, dtype=np.intp).reshape(-1)
    bary = np.asarray(bary, dtype=np.float64).reshape(tri_idx.size, 3)
    return np.einsum("ka,kad->kd", bary, np.asarray(vertices, dtype=np.float64)[np.asarray(triangles)[tri_idx]])


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
