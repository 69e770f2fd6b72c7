"""Plain numpy statements of :mod:`hailstorm.runtime.compiled.near_field` (the tests hold the kernels to them)."""

from __future__ import annotations

import numpy as np


def hat_potential_ref(points: np.ndarray, corners: np.ndarray) -> np.ndarray:
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


def hat_halfspace_block_ref(vertices: np.ndarray, triangles: np.ndarray, areas: np.ndarray,
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
    I = hat_potential_ref(plane(X[v]), plane(X[T]))  # (P, m, 3)
    # column j collects I[:, t, c] over the (t, c) where corner c of t is vertex j
    col = np.searchsorted(v, T)  # position of each corner in v (v sorted)
    hit = (col < v.size) & (v[np.minimum(col, v.size - 1)] == T)
    H = np.zeros((v.size, v.size))
    for c in range(3):
        m = hit[:, c]
        np.add.at(H.T, col[m, c], I[:, m, c].T)
    return H / np.asarray(areas, dtype=np.float64)[v][None, :]


def hat_points_ref(X: np.ndarray, T: np.ndarray, v: int, k: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Vertex ``v``'s hat traction ``phi_v / a_v`` as a point cloud: each fan triangle cut into
    ``k^2`` similar subtriangles, a point at each one's centroid carrying ``phi_v`` there times its area,
    normalised to 1 (the midpoint rule; plain loops)."""
    pts, mass = [], []
    for t in T:
        if v not in t:
            continue
        c = list(t).index(v)
        P = X[t]
        area = 0.5 * np.linalg.norm(np.cross(P[1] - P[0], P[2] - P[0])) / k**2
        for a in range(k):
            for b in range(k - a):
                for lam in (((a + 1 / 3) / k, (b + 1 / 3) / k), ((a + 2 / 3) / k, (b + 2 / 3) / k)):
                    if lam[0] + lam[1] > 1.0:
                        continue
                    bary = np.array([1.0 - lam[0] - lam[1], lam[0], lam[1]])
                    pts.append(bary @ P)
                    mass.append(bary[c] * area)
    mass = np.array(mass)
    return np.array(pts), mass / mass.sum()


def layer_sum_ref(kernel, X: np.ndarray, T: np.ndarray, verts: np.ndarray, weights: np.ndarray,
                  thickness: np.ndarray, k: int = 8) -> np.ndarray:
    """The plain statement of :func:`hailstorm.runtime.compiled.near_field.layer_sum`: per patch,
    ``sum_ab w_a w_b int phi_b / a_b g(|x_a - y| / h)`` over :func:`hat_points_ref` clouds, ``g`` the
    kernel's own numpy rule (``LayerKernel.__call__``)."""
    out = np.zeros(len(verts))
    for s, (vs, ws, h) in enumerate(zip(verts, weights, thickness)):
        for va, wa in zip(vs, ws):
            for vb, wb in zip(vs, ws):
                if wa <= 0 or wb <= 0:
                    continue
                out[s] += wa * wb * _pair_ref(kernel, X, T, int(va), int(vb), h, k)
    return out


def disc_ref(kernel, alpha: float, n: int = 120) -> float:
    """``<p, g p>`` of a unit Hertz disc of radius ``alpha`` thicknesses on a plain square grid of
    ``n x n`` cells over the unit disc (the midpoint rule)."""
    x = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    P = np.stack(np.meshgrid(x, x), -1).reshape(-1, 2)
    r2 = (P**2).sum(1)
    inside = r2 < 1.0
    P, p = P[inside], np.sqrt(1.0 - r2[inside])
    p = p / p.sum()
    total = 0.0
    for i in range(P.shape[0]):
        total += p[i] * float(p @ kernel(alpha * np.linalg.norm(P - P[i], axis=1)))
    return total


def _pair_ref(kernel, X: np.ndarray, T: np.ndarray, a: int, b: int, h: float, k: int = 8) -> float:
    """``int phi_b / a_b g(|x_a - y| / h)``: one pair of :func:`layer_sum_ref`."""
    y, m = hat_points_ref(X, T, b, k)
    return float(m @ kernel(np.linalg.norm(X[a] - y, axis=1) / h))


def hat_defect_ref(gf, young: float, poisson: float, reach: float = 3.0, min_neighbours: int = 6,
                   layer=None) -> dict[tuple[int, int], tuple[float, float]]:
    """The plain statement of :func:`hailstorm.runtime.contact.hat_defect.hat_defect`: per contactable
    vertex, loops over its neighbours (every vertex tested by distance), D's 3 x 3 blocks one pair at
    a time, ``H`` from :func:`hat_halfspace_block_ref`, ``numpy.linalg.lstsq`` for the fit over the
    pairs beyond the first ring. With ``layer`` (a ``(kernel, thickness)`` pair: the layer kernel and
    the thickness under each vertex), the layer's regular part (:func:`_pair_ref` at the vertex's
    thickness) comes off the normal pairs and diagonal too.

    Returns ``{(i, j): (delta_n, delta_t)}`` for the near pairs (``j = i`` and the edge neighbours)."""
    X = np.asarray(gf.vertices, dtype=np.float64)
    T = np.asarray(gf.triangles)
    n = X.shape[0]
    ptr = np.zeros(n + 1, dtype=np.int64)
    owner = [[] for _ in range(n)]
    for k, t in enumerate(T):
        for v in t:
            owner[v].append(k)
    ptr[1:] = np.cumsum([len(o) for o in owner])
    fan = (ptr, np.array([k for o in owner for k in o], dtype=np.int64))
    edges = {tuple(sorted((int(t[a]), int(t[b])))) for t in T for a, b in ((0, 1), (1, 2), (2, 0))}
    lengths = [[] for _ in range(n)]
    for i, j in edges:
        L = float(np.linalg.norm(X[i] - X[j]))
        lengths[i].append(L)
        lengths[j].append(L)
    # area-weighted vertex normals
    N = np.zeros((n, 3))
    for t in T:
        N[t] += np.cross(X[t[1]] - X[t[0]], X[t[2]] - X[t[0]])
    N /= np.maximum(np.linalg.norm(N, axis=1, keepdims=True), 1e-300)
    k_n = (1.0 - poisson**2) / (np.pi * young)
    k_t = k_n * (2.0 - poisson) / (2.0 * (1.0 - poisson))
    soft = np.flatnonzero(gf.contactable)
    out: dict[tuple[int, int], tuple[float, float]] = {}

    def parts(B, nv):
        bn = nv @ B @ nv
        return bn, 0.5 * (np.trace(B) - bn)

    for i in soft:
        nv = N[i]

        def reg(a: int, b: int) -> float:  # the layer's regular part, R_ab, at i's thickness [m/N]
            if layer is None or not np.isfinite(layer[1][i]):
                return 0.0
            h = layer[1][i]
            return _pair_ref(layer[0], X, T, a, b, h) / (young * h)

        def g(j: int) -> tuple[float, float]:  # D - K for the pair (i, j), normal and tangential
            B = 0.5 * (gf.compliance([i], [j]) + gf.compliance([j], [i]).T)
            v = np.array(sorted({i, j}))
            H = hat_halfspace_block_ref(X, T, gf.areas, fan, v, X[i], nv)
            h_ij = H[0, 0] if j == i else 0.5 * (H[0, 1] + H[1, 0])
            dn, dt = parts(B, nv)
            return dn - k_n * h_ij - 0.5 * (reg(i, j) + reg(j, i)), dt - k_t * h_ij

        ring = [j for j in soft if tuple(sorted((int(i), int(j)))) in edges]
        far = [j for j in soft if j != i and j not in ring
               and np.linalg.norm(X[j] - X[i]) <= reach * np.mean(lengths[i])]
        if len(far) < min_neighbours:
            continue
        r2 = np.array([float(np.sum((X[j] - X[i]) ** 2)) for j in far])
        gf_far = np.array([g(j) for j in far])
        A = np.column_stack([np.ones_like(r2), r2])
        cn = np.linalg.lstsq(A, gf_far[:, 0], rcond=None)[0]
        ct = np.linalg.lstsq(A, gf_far[:, 1], rcond=None)[0]
        for j in [i, *ring]:
            rr = float(np.sum((X[j] - X[i]) ** 2))
            gn, gt = g(j)
            out[(int(i), int(j))] = (gn - cn[0] - cn[1] * rr, gt - ct[0] - ct[1] * rr)
    return out


def patch_defect_ref(near: dict[tuple[int, int], tuple[float, float]], verts: np.ndarray,
                     weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The plain statement of :func:`hailstorm.runtime.contact.hat_defect.patch_defect`: per patch,
    ``-sum w_i w_j delta_ij`` over its ordered vertex pairs that are near pairs (``near`` as
    :func:`hat_defect_ref` returns it)."""
    en, et = np.zeros(len(verts)), np.zeros(len(verts))
    for k, (vk, wk) in enumerate(zip(verts, weights)):
        w = {int(v): float(x) for v, x in zip(vk, wk) if x > 0}
        for i, wi in w.items():
            for j, wj in w.items():
                if (i, j) in near:
                    en[k] -= wi * wj * near[(i, j)][0]
                    et[k] -= wi * wj * near[(i, j)][1]
    return en, et
