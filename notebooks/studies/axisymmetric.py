"""The foam pad as an axisymmetric finite-element problem: its mesh, matrices and a sphere pressed into it.

The pad of :mod:`hailstorm.studies.dynamic_study` (a disc of foam on a rigid base, the
impact on its axis) and the references built on it:

* :func:`axisymmetric_matrices` -- stiffness and mass of axisymmetric linear elasticity
  (scikit-fem, the weak forms weighted by ``2 pi r``);
* :func:`pad_mesh` -- the disc's graded (r, z) mesh, clamped underneath, and its matrices;
* :func:`contact_lcp` -- the unilateral contact of a rigid sphere with the top nodes;
* :func:`press_disc` -- a rigid sphere (or Hertz's paraboloid) pressed to a depth into a
  disc, statically: the converged force of a block's own geometry (its depth, its clamp),
  against which Hertz's half-space and the Green's-function contacts are measured
  (:func:`hailstorm.studies.resolution_study.block_table`); checked against Segedin's
  sphere on a half-space (tests/studies/test_axisymmetric.py).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hailstorm.runtime.contact.layer_solve import graded
from hailstorm.runtime.storm.limits import PAD_DENSITY

__all__ = ["FOAM_DENSITY", "DiscPress", "Pad", "PadMesh", "axisymmetric_matrices", "contact_lcp", "pad_mesh",
           "press_disc", "without_contact_mass"]

#: foam density [kg/m^3]: flexible polyurethane foams ~20-100 (Gibson & Ashby, Cellular Solids, 2nd ed.);
#: the scene's default ``[validity] pad_density``
FOAM_DENSITY = PAD_DENSITY


@dataclass(frozen=True)
class Pad:
    """A disc-shaped foam pad on a rigid base.

    Attributes
    ----------
    young, poisson : float
        The foam [Pa], [-].
    density : float
        [kg/m^3] (> 0).
    thickness, radius : float
        The disc [m].
    """

    young: float = 2.0e6
    poisson: float = 0.35
    density: float = FOAM_DENSITY
    thickness: float = 0.015
    radius: float = 0.06

    def __post_init__(self) -> None:
        for name in ("young", "density", "thickness", "radius"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"pad {name} must be a positive number, got {v!r}")
        if not (-1.0 < self.poisson < 0.5):
            raise ValueError(f"pad poisson must be in (-1, 0.5), got {self.poisson!r}")

    @property
    def wave_speeds(self) -> tuple[float, float]:
        """Dilatational and shear wave speeds [m/s]."""
        E, nu, rho = self.young, self.poisson, self.density
        return (math.sqrt(E * (1 - nu) / ((1 + nu) * (1 - 2 * nu) * rho)), math.sqrt(E / (2 * (1 + nu) * rho)))


@dataclass
class PadMesh:
    """The pad's (r, z) mesh and its matrices (:func:`pad_mesh`).

    Attributes
    ----------
    pad : Pad
    r, z : (nr,), (nz,) ndarray
        Grid lines [m] (z = 0 the clamped base, z = thickness the top).
    K, M : scipy.sparse matrix
        Stiffness and mass on the free dofs (``2 pi r``-weighted) [N/m], [kg].
    free : (f,) int ndarray
        Free dofs of the vector P1 basis.
    top_r : (t,) ndarray
        Radii of the top nodes [m], ascending.
    top_uz : (t,) int ndarray
        Their u_z dofs, as indices into ``free``.
    cell : float
        Cell size at the axis under the contact [m].
    """

    pad: Pad
    r: np.ndarray
    z: np.ndarray
    K: Any
    M: Any
    free: np.ndarray
    top_r: np.ndarray
    top_uz: np.ndarray
    cell: float


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


def pad_mesh(pad: Pad, cell: float, extent: float, growth: float = 1.15) -> PadMesh:
    """The pad's graded (r, z) mesh and matrices: cells of ``cell`` within ``extent`` of the
    contact (radially from the axis, downwards from the top), growing by ``growth`` beyond.

    Parameters
    ----------
    pad : Pad
    cell : float
        Cell size under the contact [m] (> 0).
    extent : float
        Reach of the fine cells [m].
    growth : float
        Ratio of neighbouring cells beyond it (> 1).
    """
    from skfem import MeshTri

    if not (cell > 0 and extent > 0 and growth > 1):
        raise ValueError(f"pad_mesh needs cell > 0, extent > 0, growth > 1, got {cell!r}, {extent!r}, {growth!r}")
    r = graded(pad.radius, cell, extent, growth)
    depth = graded(pad.thickness, cell, extent, growth)
    z = np.sort(pad.thickness - depth)
    z[0] = 0.0
    mesh = MeshTri.init_tensor(r, z)
    K, M, basis = axisymmetric_matrices(mesh, pad.young, pad.poisson, pad.density)
    x = mesh.p
    nd = basis.nodal_dofs  # (2, nodes): u_r, u_z dofs
    tol = 1e-12 * pad.thickness
    fixed = np.concatenate([nd[:, x[1] < tol].ravel(), nd[0, x[0] < tol]])
    free = np.setdiff1d(np.arange(basis.N), fixed)
    top = np.flatnonzero(x[1] > pad.thickness - tol)
    top = top[np.argsort(x[0, top])]
    pos = np.full(basis.N, -1)
    pos[free] = np.arange(free.size)
    return PadMesh(pad=pad, r=r, z=z, K=K[free][:, free].tocsc(), M=M[free][:, free].tocsc(), free=free,
                   top_r=x[0, top], top_uz=pos[nd[1, top]], cell=float(r[1] - r[0]))


def contact_lcp(S: np.ndarray, q: np.ndarray, active: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``lam >= 0``, ``w = S lam + q >= 0``, ``lam . w = 0`` for SPD ``S`` (active set from
    ``active``; an exact non-negative least squares if it cycles). Returns lam and the active set."""
    p = q.size
    tol = 1e-12 * max(float(np.abs(q).max(initial=0.0)), 1e-300)
    A = active.copy()
    for _ in range(4 * p + 10):
        lam = np.zeros(p)
        if A.any():
            lam[A] = np.linalg.solve(S[np.ix_(A, A)], -q[A])
        neg = A & (lam < -tol)
        if neg.any():
            A &= ~neg
            continue
        w = S @ lam + q
        viol = ~A & (w < -tol)
        if not viol.any():
            return np.clip(lam, 0.0, None), A
        A |= viol
    from scipy.linalg import cholesky, solve_triangular
    from scipy.optimize import nnls

    L = cholesky(S, lower=True)
    lam, _ = nnls(L.T, -solve_triangular(L, q, lower=True))
    return lam, lam > 0


def without_contact_mass(M: Any, dofs: np.ndarray) -> Any:
    """The mass matrix with the rows and columns of the contact dofs removed (zeroed).

    Khenous, Laborde & Renard, Mass redistribution method for finite element contact
    problems in elastodynamics, Eur. J. Mech. A/Solids 27 (2008) 918-932: without
    inertia on the contact nodes' normal dofs the semi-discrete problem is well posed
    and the Newmark average-acceleration scheme no longer creates energy at the
    contact's onset and release (measured here: restitution 1.15 at 30 m/s with the
    consistent mass, <= 1 without it). The mass removed is that of the top layer of
    cells under the sphere, ~``rho pi R^2 cell / 2``: below 0.1 % of the stone's.
    """
    from scipy.sparse import diags

    keep = np.ones(M.shape[0])
    keep[dofs] = 0.0
    P = diags(keep)
    return (P @ M @ P).tocsc()


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
