"""The local pad of one impact: a disc of foam on a rigid base, axisymmetric about the impact.

* :class:`Pad` -- its material, density and size;
* :func:`pad_mesh` -> :class:`PadMesh` -- its graded (r, z) P1 mesh, stiffness and mass
  (:func:`hailstorm.runtime.contact.layer_solve.axisymmetric_p1`, numpy and scipy alone);
* :func:`contact_lcp` -- the unilateral contact of a rigid sphere with the top nodes;
* :func:`without_contact_mass` -- the mass matrix without the contact nodes' inertia.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hailstorm.runtime.contact.layer_solve import axisymmetric_p1, graded

__all__ = ["PAD_DENSITY", "Pad", "PadMesh", "contact_lcp", "pad_mesh", "without_contact_mass"]

#: the default pad foam's density [kg/m^3]: flexible polyurethane foams span about 20-100
#: (Gibson & Ashby, *Cellular Solids*, 2nd ed. 1997); the scene's ``[validity] pad_density``
PAD_DENSITY = 70.0


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
    density: float = PAD_DENSITY
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


def pad_mesh(pad: Pad, cell: float, extent: float, growth: float = 1.15) -> PadMesh:
    """The pad's graded (r, z) mesh and matrices: cells of ``cell`` within ``extent`` of the
    contact (radially from the axis, downwards from the top), growing by ``growth`` beyond.
    Clamped underneath, ``u_r = 0`` on the axis, the rim free.

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
    if not (cell > 0 and extent > 0 and growth > 1):
        raise ValueError(f"pad_mesh needs cell > 0, extent > 0, growth > 1, got {cell!r}, {extent!r}, {growth!r}")
    r = graded(pad.radius, cell, extent, growth)
    z = np.sort(pad.thickness - graded(pad.thickness, cell, extent, growth))
    z[0] = 0.0
    K, M, nodes = axisymmetric_p1(r, z, pad.poisson, pad.density)
    nr = r.size
    fixed = np.concatenate([np.arange(2 * nr), 2 * np.flatnonzero(nodes[:, 0] == 0.0)])  # the base, u_r on the axis
    free = np.setdiff1d(np.arange(K.shape[0]), fixed)
    pos = np.full(K.shape[0], -1)
    pos[free] = np.arange(free.size)
    top = (z.size - 1) * nr + np.arange(nr)  # ascending r
    K = (K * pad.young)[free][:, free].tocsc()
    return PadMesh(pad=pad, r=r, z=z, K=K, M=M[free][:, free].tocsc(), free=free, top_r=r.copy(),
                   top_uz=pos[2 * top + 1], cell=float(r[1] - r[0]))


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
    contact's onset and release (measured: restitution 1.15 at 30 m/s with the
    consistent mass, <= 1 without it). The mass removed is that of the top layer of
    cells under the sphere, ~``rho pi R^2 cell / 2``: below 0.1 % of the stone's.
    """
    from scipy.sparse import diags

    keep = np.ones(M.shape[0])
    keep[dofs] = 0.0
    P = diags(keep)
    return (P @ M @ P).tocsc()
