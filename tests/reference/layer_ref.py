"""The plain statement of the layer's point response, on scikit-fem's assembly."""

from __future__ import annotations

import numpy as np


def layer_point_response_ref(poisson: float, *, cell: float = 0.004, extent: float = 0.15, growth: float = 1.04,
                             radius: float = 12.0) -> tuple[np.ndarray, np.ndarray]:
    """:func:`hailstorm.runtime.contact.layer_kernel.layer_point_response` with the studies' axisymmetric
    matrices (:func:`studies.axisymmetric.axisymmetric_matrices`, scikit-fem's forms and
    quadrature) on the same grid lines."""
    from scipy.sparse.linalg import splu
    from skfem import MeshTri

    from hailstorm.runtime.contact.layer_solve import graded
    from studies.axisymmetric import axisymmetric_matrices

    r = graded(radius, cell, extent, growth)
    z = np.sort(1.0 - graded(1.0, cell, extent, growth))
    z[0] = 0.0
    mesh = MeshTri.init_tensor(r, z)
    K, _, basis = axisymmetric_matrices(mesh, 1.0, poisson, 1.0)
    x, nd = mesh.p, basis.nodal_dofs
    fixed = np.concatenate([nd[:, x[1] < 1e-12].ravel(), nd[0, x[0] < 1e-12]])
    free = np.setdiff1d(np.arange(basis.N), fixed)
    top = np.flatnonzero(x[1] > 1.0 - 1e-12)
    top = top[np.argsort(x[0, top])]
    f = np.zeros(basis.N)
    f[nd[1, top[0]]] = -1.0
    u = np.zeros(basis.N)
    u[free] = splu(K[free][:, free].tocsc()).solve(f[free])
    return x[0, top], -u[nd[1, top]]
