"""A layer on a rigid base under a point force: the axisymmetric solve behind the layer kernel.

Part of the contact core (:mod:`hailstorm.runtime.contact`), for
:mod:`hailstorm.runtime.contact.layer_kernel`. By dimensional analysis a point force
``P`` on a layer of thickness ``h`` and modulus ``E``, bonded to a rigid base, gives
``u_z = P / (E h) f(r / h)``, one curve per Poisson ratio: :func:`layer_point_response`
computes it on a unit layer with P1 triangles on a graded (r, z) grid, in numpy and
scipy alone (the runtime stage loads no finite-element library; the tests hold it to
scikit-fem's assembly of the same problem, ``tests/reference/layer_ref.py``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["DUNAVANT6", "DUNAVANT6_W", "LAYER_MESH", "axisymmetric_p1", "graded", "layer_point_response"]

#: Dunavant's 6-point rule on a triangle, exact for degree 4 (barycentric, weights sum to 1)
_A, _B = 0.445948490915965, 0.091576213509771
DUNAVANT6 = np.array([[_A, _A, 1 - 2 * _A], [_A, 1 - 2 * _A, _A], [1 - 2 * _A, _A, _A],
                      [_B, _B, 1 - 2 * _B], [_B, 1 - 2 * _B, _B], [1 - 2 * _B, _B, _B]])
DUNAVANT6_W = np.array([0.223381589678011] * 3 + [0.109951743655322] * 3)


def graded(length: float, fine: float, extent: float, growth: float) -> np.ndarray:
    """Grid lines ``0 .. length``: cells of ``fine`` up to ``extent``, then growing by ``growth``."""
    extent = min(extent, length)
    n = max(1, int(math.ceil(extent / fine)))
    pts = list(np.linspace(0.0, n * fine, n + 1))
    h = fine
    while pts[-1] < length:
        h *= growth
        pts.append(pts[-1] + h)
    out = np.array(pts)
    if out.size > 2 and length - out[-2] < 0.5 * (out[-2] - out[-3]):
        out = np.delete(out, -2)  # no sliver at the end
    out[-1] = length
    return out[out <= length]


def axisymmetric_p1(r: np.ndarray, z: np.ndarray, poisson: float,
                    density: float | None = None) -> tuple[Any, Any, np.ndarray]:
    """P1 stiffness (``E = 1``) and mass of axisymmetric elasticity on the tensor grid ``r x z``.

    The grid's rectangles are cut into triangles along the diagonal of increasing ``r`` and
    ``z``; dofs ``(u_r, u_z)`` per node (node ``k = i_z * len(r) + i_r``, dof ``2 k + c``);
    integrated with Dunavant's 6-point rule over ``2 pi r dA`` (never on the axis; the mass's
    integrand is a cubic, integrated exactly). The tests hold both to scikit-fem's assembly
    (``tests/reference/layer_ref.py``).

    Parameters
    ----------
    r, z : ndarray
        Grid lines [m], ascending (``r[0] = 0``: the axis).
    poisson : float
    density : float, optional
        [kg/m^3]; None: no mass matrix.

    Returns
    -------
    K : scipy.sparse.csc_matrix
        Stiffness for ``E = 1`` (scale by Young's modulus) [m].
    M : scipy.sparse.csc_matrix or None
        Consistent mass [kg].
    nodes : (N, 2) ndarray
        The nodes' (r, z).
    """
    import scipy.sparse as sp

    nr = r.size
    R, Z = np.meshgrid(r, z)
    nodes = np.column_stack([R.ravel(), Z.ravel()])
    k = (np.arange(z.size - 1)[:, None] * nr + np.arange(nr - 1)[None, :]).ravel()
    tri = np.concatenate([np.column_stack([k, k + 1, k + nr + 1]), np.column_stack([k, k + nr + 1, k + nr])])
    P = nodes[tri]  # (m, 3, 2)
    J = np.stack([P[:, 1] - P[:, 0], P[:, 2] - P[:, 0]], axis=2)  # columns: edges (m, 2, 2)
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    inv = np.stack([np.stack([J[:, 1, 1], -J[:, 0, 1]], 1), np.stack([-J[:, 1, 0], J[:, 0, 0]], 1)], 1) / det[:, None, None]
    dref = np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]])  # d lambda_c / d(xi, eta)
    grad = np.einsum("cx,mxy->mcy", dref, inv)  # (m, 3, [d/dr, d/dz])
    lam = DUNAVANT6  # (q, 3) barycentric of the quadrature points
    rq = np.einsum("qc,mc->mq", lam, P[:, :, 0])
    B = np.zeros((tri.shape[0], lam.shape[0], 4, 6))  # strains e_rr, e_zz, e_tt, g_rz per dof (u_r, u_z) x 3
    B[:, :, 0, 0::2] = grad[:, None, :, 0]
    B[:, :, 1, 1::2] = grad[:, None, :, 1]
    B[:, :, 2, 0::2] = lam[None, :, :] / rq[:, :, None]
    B[:, :, 3, 0::2] = grad[:, None, :, 1]
    B[:, :, 3, 1::2] = grad[:, None, :, 0]
    lame, mu = poisson / ((1 + poisson) * (1 - 2 * poisson)), 1.0 / (2 * (1 + poisson))
    C = np.diag([2 * mu, 2 * mu, 2 * mu, mu])
    C[:3, :3] += lame
    w = DUNAVANT6_W[None, :] * 0.5 * np.abs(det)[:, None] * 2.0 * np.pi * rq  # (m, q)
    m, q = B.shape[:2]
    CB = np.matmul(C, B)  # (m, q, 4, 6): the stresses of each dof's strains
    BW = (B * w[:, :, None, None]).reshape(m, 4 * q, 6)
    Ke = np.matmul(BW.transpose(0, 2, 1), CB.reshape(m, 4 * q, 6))  # sum over the points and the strains
    dofs = np.stack([2 * tri, 2 * tri + 1], axis=2).reshape(-1, 6)
    rows = np.repeat(dofs, 6, axis=1).ravel()
    cols = np.tile(dofs, (1, 6)).ravel()
    shape = (2 * nodes.shape[0],) * 2
    K = sp.csc_matrix((Ke.ravel(), (rows, cols)), shape=shape)
    if density is None:
        return K, None, nodes
    NN = np.einsum("mq,qa,qb->mab", w * float(density), lam, lam)  # (m, 3, 3) per component
    Me = np.zeros((tri.shape[0], 6, 6))
    Me[:, 0::2, 0::2] = NN
    Me[:, 1::2, 1::2] = NN
    return K, sp.csc_matrix((Me.ravel(), (rows, cols)), shape=shape), nodes


#: the default mesh of :func:`layer_point_response` (in thicknesses)
LAYER_MESH = {"cell": 0.004, "extent": 0.15, "growth": 1.04, "radius": 12.0}


def layer_point_response(poisson: float, *, cell: float = LAYER_MESH["cell"], extent: float = LAYER_MESH["extent"],
                         growth: float = LAYER_MESH["growth"], radius: float = LAYER_MESH["radius"]
                         ) -> tuple[np.ndarray, np.ndarray]:
    """The top surface's ``u_z`` under a unit point force on the axis of a unit layer.

    A layer of thickness 1 and Young's modulus 1 (``u`` scales as ``P / (E h)``), Poisson
    ratio ``poisson``, clamped underneath (its rigid base), free on top and at its rim
    ``radius`` thicknesses out (the response has decayed there: a layer on a rigid base
    carries a point force within a few thicknesses); P1 triangles of ``cell`` within
    ``extent`` of the load, growing by ``growth`` beyond. The defaults give about 31 000
    dofs, a second's work. The finite elements cannot carry the point force's own ``1/r``
    singularity within a few dozen cells of it (:func:`layer_kernel` reads the response beyond).

    Returns
    -------
    r, uz : ndarray
        The top nodes' radii (ascending, in thicknesses) and their ``u_z`` (positive into the
        layer, ``E h u_z / P``).

    Raises
    ------
    ValueError
        ``poisson`` outside (-1, 0.5).
    """
    from scipy.sparse.linalg import splu

    if not (-1.0 < poisson < 0.5):
        raise ValueError(f"layer_point_response needs -1 < poisson < 0.5, got {poisson!r}")
    r = graded(radius, cell, extent, growth)
    z = np.sort(1.0 - graded(1.0, cell, extent, growth))
    z[0] = 0.0
    K, _, nodes = axisymmetric_p1(r, z, float(poisson))
    nr = r.size
    fixed = np.concatenate([np.arange(2 * nr), 2 * np.flatnonzero(nodes[:, 0] == 0.0)])  # the base, u_r on the axis
    free = np.setdiff1d(np.arange(K.shape[0]), fixed)
    top = (z.size - 1) * nr + np.arange(nr)  # ascending r
    f = np.zeros(K.shape[0])
    f[2 * top[0] + 1] = -1.0  # a unit force pressing down (-z) on the axis
    u = np.zeros(K.shape[0])
    u[free] = splu(K[free][:, free].tocsc()).solve(f[free])
    return r, -u[2 * top + 1]
