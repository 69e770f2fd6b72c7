"""The foam pad as an axisymmetric finite-element problem: references on scikit-fem, and a sphere pressed into it.

The pad of :mod:`studies.dynamic_study` (a disc of foam on a rigid base, the
impact on its axis; :class:`hailstorm.runtime.inertia.pad.Pad`, its mesh
:func:`hailstorm.runtime.inertia.pad.pad_mesh`) and the references built on it:

* :func:`axisymmetric_matrices` -- stiffness and mass of axisymmetric linear elasticity
  on scikit-fem's forms (the weak forms weighted by ``2 pi r``): the independent assembly
  the runtime's numpy one (:func:`hailstorm.runtime.contact.layer_solve.axisymmetric_p1`) is held to;
* :func:`press_disc` -- a rigid sphere (or Hertz's paraboloid) pressed to a depth into a
  disc, statically: the converged force of a block's own geometry (its depth, its clamp),
  against which Hertz's half-space and the Green's-function contacts are measured
  (:func:`studies.resolution_study.block_table`); checked against Segedin's
  sphere on a half-space (tests/studies/test_axisymmetric.py).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hailstorm.runtime.inertia.pad import Pad, contact_lcp, pad_mesh
from hailstorm.runtime.storm.limits import PAD_DENSITY

__all__ = ["FOAM_DENSITY", "DiscPress", "axisymmetric_matrices", "press_disc"]

#: foam density [kg/m^3]: flexible polyurethane foams ~20-100 (Gibson & Ashby, Cellular Solids, 2nd ed.);
#: the scene's default ``[validity] pad_density``
FOAM_DENSITY = PAD_DENSITY


def axisymmetric_matrices(mesh: Any, young: float, poisson: float, density: float) -> tuple[Any, Any, Any]:
    """Stiffness and mass of axisymmetric linear elasticity on an (r, z) triangle mesh.

    With ``u = (u_r, u_z)``: strains ``e_rr = du_r/dr``, ``e_zz = du_z/dz``,
    ``e_tt = u_r / r``, ``e_rz = (du_r/dz + du_z/dr) / 2``; the energy density
    ``lambda tr(e)^2 / 2 + mu e:e`` and the kinetic energy ``rho |u'|^2 / 2``,
    both integrated over ``2 pi r dr dz`` (scikit-fem ``BilinearForm``; the
    quadrature points are inside the triangles, never on the axis).

    Returns
    -------
    K, M : scipy.sparse.csr_matrix
        On every dof of the vector P1 basis [N/m], [kg].
    basis : skfem.Basis
    """
    from skfem import Basis, BilinearForm, ElementTriP1, ElementVector, asm
    from skfem.helpers import dot, grad

    lam = young * poisson / ((1 + poisson) * (1 - 2 * poisson))
    mu = young / (2 * (1 + poisson))
    basis = Basis(mesh, ElementVector(ElementTriP1()), intorder=3)

    def strains(u: Any, r: np.ndarray) -> tuple[Any, Any, Any, Any]:
        g = grad(u)
        return g[0, 0], g[1, 1], u[0] / r, 0.5 * (g[0, 1] + g[1, 0])

    @BilinearForm
    def stiffness(u: Any, v: Any, w: Any) -> Any:
        r = w.x[0]
        a, b = strains(u, r), strains(v, r)
        tr_u, tr_v = a[0] + a[1] + a[2], b[0] + b[1] + b[2]
        return 2 * np.pi * r * (lam * tr_u * tr_v + 2 * mu * (a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + 2 * a[3] * b[3]))

    @BilinearForm
    def mass(u: Any, v: Any, w: Any) -> Any:
        return 2 * np.pi * w.x[0] * density * dot(u, v)

    return asm(stiffness, basis).tocsr(), asm(mass, basis).tocsr(), basis


@dataclass(frozen=True)
class DiscPress:
    """A rigid sphere pressed into a disc (:func:`press_disc`).

    Attributes
    ----------
    force : float
        The sphere's force [N].
    contact_radius : float
        Radius of the outermost touching node [m].
    dofs : int
        Free dofs of the mesh.
    """

    force: float
    contact_radius: float
    dofs: int


@functools.lru_cache(maxsize=2)
def _top_compliance(pad: Pad, radius: float, depth: float, cells_per_radius: float,
                    growth: float) -> tuple[np.ndarray, np.ndarray, int]:
    """:func:`press_disc`'s static compliance among its candidate top nodes, their radii and the mesh's
    free dofs (kept for the last two presses: the sphere and the paraboloid share one mesh and factor)."""
    from scipy.sparse.linalg import splu

    a = math.sqrt(radius * depth)
    mesh = pad_mesh(pad, cell=a / cells_per_radius, extent=1.5 * a, growth=growth)
    cand = np.flatnonzero(mesh.top_r < min(0.999 * radius, 2.0 * a))
    C, r = mesh.top_uz[cand], mesh.top_r[cand]
    n = mesh.K.shape[0]
    E = np.zeros((n, C.size))
    E[C, np.arange(C.size)] = 1.0
    S = splu(mesh.K.tocsc()).solve(E)[C]
    S.flags.writeable = False
    r.flags.writeable = False
    return S, r, n


def press_disc(pad: Pad, radius: float, depth: float, *, profile: str = "sphere", cells_per_radius: float = 32.0,
               growth: float = 1.04) -> DiscPress:
    """A rigid frictionless sphere of ``radius`` pressed ``depth`` into the pad's top on its axis, statically.

    The indenter's profile at each top node's undeformed radius (small displacements):
    ``"sphere"``, ``R - sqrt(R^2 - r^2)``, or ``"paraboloid"``, ``r^2 / 2R`` (Hertz's). Unilateral on
    the nodes within ``min(0.999 R, 2 a_H)`` (``a_H = sqrt(R depth)``, Hertz's contact radius) by
    :func:`contact_lcp` on the static compliance; cells of ``a_H / cells_per_radius`` within ``1.5 a_H``
    of the axis and below the top, growing by ``growth`` beyond (:func:`pad_mesh`).

    Measured (``a_H`` = 0.5-2 mm): against Segedin's sphere on a half-space (a disc 4 m deep) the
    force is +0.37 / +0.15 / +0.08 % high at ``growth`` 1.15 / 1.08 / 1.04 (the coarse far cells'
    stiffness, about linear in ``growth - 1``); 32 / 64 / 96 cells per radius move it by
    0.05 / 0.01 % (a/R 0.2) and 0.08 / 0.02 % (a/R 0.4). The defaults are within about 0.15 %.

    Returns
    -------
    DiscPress

    Raises
    ------
    ValueError
        Non-positive radius, depth or resolution; an unknown profile; a contact that reaches the
        last candidate node.
    """
    if not (radius > 0 and depth > 0 and cells_per_radius > 0):
        raise ValueError(f"press_disc needs radius, depth, cells_per_radius > 0, got {radius!r}, {depth!r}, "
                         f"{cells_per_radius!r}")
    if profile not in ("sphere", "paraboloid"):
        raise ValueError(f"press_disc: profile must be 'sphere' or 'paraboloid', got {profile!r}")
    S, r, n = _top_compliance(pad, radius, depth, float(cells_per_radius), float(growth))
    phi = radius - np.sqrt(radius * radius - r * r) if profile == "sphere" else r * r / (2.0 * radius)
    lam, _ = contact_lcp(S, phi - depth, np.zeros(r.size, dtype=bool))
    touching = np.flatnonzero(lam > 0)
    if touching.size and touching[-1] == r.size - 1:
        raise ValueError(f"press_disc: the contact reaches the last candidate node at r = {r[-1] * 1e3:.3g} mm "
                         f"(sphere radius {radius * 1e3:.3g} mm, depth {depth * 1e3:.3g} mm)")
    return DiscPress(force=float(lam.sum()), contact_radius=float(r[touching[-1]]) if touching.size else 0.0, dofs=n)
