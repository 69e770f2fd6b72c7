"""The seat surface's outward normals: a triangle's own, and the smooth normal read across its facets.

Part of the contact core (:mod:`hailstorm.runtime.contact`). :func:`triangle_normals` gives the
facets' unit normals (the default contact normals of point and patch contacts,
:mod:`hailstorm.runtime.contact.weights`); :func:`corner_normals` the surface's normal at each
triangle's corners, read as a smooth surface but at its sharp edges (beyond :data:`CREASE_ANGLE`),
and :func:`smooth_normals` those interpolated at points on the surface (the storm's and the
spheres' reading of the surface).
"""

from __future__ import annotations

import math

import numpy as np

from hailstorm.runtime.bundle.read import vertex_normals

__all__ = ["CREASE_ANGLE", "corner_normals", "smooth_normals", "triangle_normals"]


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
