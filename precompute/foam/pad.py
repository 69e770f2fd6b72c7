"""The nonlinear local pad: a disc of foam on a rigid base, axisymmetric, total Lagrangian.

* :class:`FoamPad` -- the foam, thickness and radius;
* :class:`PadModel` -- its (r, z) mesh (scikit-fem's :class:`~skfem.MeshTri` on graded grid lines,
  P1 or P2 vector elements) and the energy, residual and exact tangent of a displacement
  (``u_r, u_z``; ``F = [[1 + u_r,r, u_r,z, 0], [u_z,r, 1 + u_z,z, 0], [0, 0, 1 + u_r / r]]``,
  integrated over ``2 pi r dr dz``: total, not per radian). Base bonded (``u = 0`` at ``z = 0``),
  ``u_r = 0`` on the axis, rim and top free; its consistent mass by :meth:`PadModel.mass`.

The kinematic operator is built once from scikit-fem's basis (total Lagrangian: the reference
configuration does not move); each Newton step evaluates the foam at every quadrature point
(:mod:`~hailstorm.precompute.foam.constitutive`) and assembles with one einsum and one COO sum.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hailstorm.precompute.foam.constitutive import energy_density, first_piola, piola_tangent
from hailstorm.precompute.foam.material import Hyperfoam

__all__ = ["FoamPad", "PadModel", "graded_lines"]

#: the five non-zero components of ``F`` and ``P`` in axisymmetry: rr, rz, zr, zz, theta-theta
_COMP = ((0, 0), (0, 1), (1, 0), (1, 1), (2, 2))


@dataclass(frozen=True)
class FoamPad:
    """A disc of foam bonded to a rigid base.

    Attributes
    ----------
    foam : Hyperfoam
    thickness : float
        ``h`` [m] (> 0).
    radius : float
        [m] (> 0; a few thicknesses: the layer carries a load within a few ``h``).
    """

    foam: Hyperfoam
    thickness: float
    radius: float

    def __post_init__(self) -> None:
        for name in ("thickness", "radius"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"foam pad {name} must be a positive number, got {v!r}")


def graded_lines(length: float, fine: float, extent: float, growth: float) -> np.ndarray:
    """Grid lines ``0 .. length``: cells of ``fine`` up to ``extent``, then growing by ``growth``
    (:func:`hailstorm.runtime.contact.layer_solve.graded`)."""
    from hailstorm.runtime.contact.layer_solve import graded

    if not (fine > 0 and extent > 0 and growth >= 1.0 and length > 0):
        raise ValueError(f"graded_lines needs length, fine, extent > 0 and growth >= 1, got {length!r}, {fine!r}, "
                         f"{extent!r}, {growth!r}")
    return graded(length, fine, extent, growth)


class PadModel:
    """A :class:`FoamPad` meshed on grid lines ``r x z`` (module notes).

    Parameters
    ----------
    pad : FoamPad
    r, z : ndarray
        Grid lines [m], ascending, ``r[0] = 0``, ``r[-1] = pad.radius``, ``z[0] = 0``, ``z[-1] = pad.thickness``.
    order : {1, 2}
        Lagrange order of the triangles.
    bonded : bool
        The base holds ``u_r`` too (True: bonded, the pad's case); False: a frictionless base
        (``u_z = 0`` only), for homogeneous tests.

    Attributes
    ----------
    basis : skfem.Basis
    free : (f,) int ndarray
        The unconstrained dofs.
    top : (t,) int ndarray
        Scalar node index of the top surface's nodes, by ascending ``r``; their dofs are ``2 top`` (u_r), ``2 top + 1`` (u_z).
    top_r : (t,) ndarray
        Their radii [m].
    top_area : (t,) ndarray
        The ring a top node stands for [m^2]: ``int 2 pi r`` of the P1 hat on the top nodes (positive
        on the axis too, where a P2 corner's own weight is 0).
    cell : float
        The smallest cell's size [m].
    """

    def __init__(self, pad: FoamPad, r: np.ndarray, z: np.ndarray, order: int = 2, *, bonded: bool = True) -> None:
        from skfem import Basis, ElementTriP1, ElementTriP2, ElementVector, MeshTri

        r, z = np.asarray(r, dtype=np.float64), np.asarray(z, dtype=np.float64)
        if order not in (1, 2):
            raise ValueError(f"order must be 1 or 2, got {order!r}")
        if not (r[0] == 0.0 and np.all(np.diff(r) > 0) and z[0] == 0.0 and np.all(np.diff(z) > 0)):
            raise ValueError("grid lines must ascend from 0")
        if not (math.isclose(r[-1], pad.radius) and math.isclose(z[-1], pad.thickness)):
            raise ValueError(f"grid lines end at ({r[-1]!r}, {z[-1]!r}), not the pad's ({pad.radius!r}, {pad.thickness!r})")
        self.pad, self.order = pad, order
        self.mesh = MeshTri.init_tensor(r, z)
        scalar = ElementTriP2() if order == 2 else ElementTriP1()
        self.basis = Basis(self.mesh, ElementVector(scalar), intorder=2 * order + 1)
        b = self.basis
        rq = np.asarray(b.global_coordinates())[0]
        self.dx = b.dx * 2.0 * np.pi * rq  # (nel, nqp)
        nloc = len(b.basis)
        B = np.zeros((nloc, 5) + rq.shape)
        for i in range(nloc):
            phi = b.basis[i][0]
            B[i, 0], B[i, 1], B[i, 2], B[i, 3] = phi.grad[0, 0], phi.grad[0, 1], phi.grad[1, 0], phi.grad[1, 1]
            B[i, 4] = np.asarray(phi)[0] / rq
        self.B = B
        self.edofs = b.element_dofs  # (nloc, nel)
        loc = b.doflocs
        h = pad.thickness
        fixed = np.flatnonzero(np.isclose(loc[1], 0.0))  # the base: both components (bonded) or u_z
        if not bonded:
            fixed = fixed[fixed % 2 == 1]
        axis = np.flatnonzero(np.isclose(loc[0], 0.0))
        fixed = np.union1d(fixed, axis[axis % 2 == 0])  # u_r on the axis
        self.free = np.setdiff1d(np.arange(b.N), fixed)
        nodes = np.flatnonzero(np.isclose(loc[1, 0::2], h))
        nodes = nodes[np.argsort(loc[0, 2 * nodes])]
        self.top = nodes
        self.top_r = loc[0, 2 * nodes].copy()
        rt = self.top_r
        left = np.concatenate([[0.0], np.diff(rt) * (rt[:-1] + 2.0 * rt[1:])]) / 6.0
        right = np.concatenate([np.diff(rt) * (2.0 * rt[:-1] + rt[1:]), [0.0]]) / 6.0
        self.top_area = 2.0 * np.pi * (left + right)
        self.cell = float(min(r[1] - r[0], z[-1] - z[-2]))

    def mass(self, density: float | None = None) -> Any:
        """The consistent mass matrix ``int rho phi_i . phi_j 2 pi r dr dz`` [kg], scipy CSR.

        ``density`` [kg/m^3] (>= 0; default the foam's): 0 gives the massless (quasi-static) pad."""
        from skfem import BilinearForm
        from skfem.helpers import dot

        rho = self.pad.foam.density if density is None else float(density)
        if not (math.isfinite(rho) and rho >= 0):
            raise ValueError(f"pad density must be finite and >= 0, got {density!r}")

        @BilinearForm
        def form(u: Any, v: Any, w: Any) -> Any:
            return rho * dot(u, v) * 2.0 * np.pi * w.x[0]

        return form.assemble(self.basis).tocsr()

    @property
    def ndofs(self) -> int:
        """Number of dofs (free and fixed)."""
        return int(self.basis.N)

    def gradient(self, u: np.ndarray) -> np.ndarray:
        """``F`` at every quadrature point, (nel, nqp, 3, 3)."""
        F5 = np.einsum("ikeq,ie->keq", self.B, u[self.edofs])
        F = np.zeros(F5.shape[1:] + (3, 3))
        for k, (i, j) in enumerate(_COMP):
            F[..., i, j] = F5[k] + (1.0 if i == j else 0.0)
        return F

    def energy(self, u: np.ndarray) -> float:
        """Stored energy [J] (``inf`` if any ``det F <= 0``)."""
        with np.errstate(invalid="ignore", over="ignore"):
            return float((self.dx * energy_density(self.pad.foam, self.gradient(u))).sum())

    def residual(self, u: np.ndarray) -> np.ndarray:
        """Internal force ``dE/du`` [N], (ndofs,)."""
        P = first_piola(self.pad.foam, self.gradient(u))
        P5 = np.stack([P[..., i, j] for i, j in _COMP])
        Re = np.einsum("ikeq,keq,eq->ie", self.B, P5, self.dx)
        return np.bincount(self.edofs.ravel(), Re.ravel(), minlength=self.ndofs)

    def tangent(self, u: np.ndarray) -> tuple[np.ndarray, Any]:
        """(:meth:`residual`, the stiffness ``d^2E/du^2`` as scipy CSR) [N], [N/m]."""
        import scipy.sparse as sp

        F = self.gradient(u)
        foam = self.pad.foam
        E = np.zeros((5,) + F.shape)
        for k, (i, j) in enumerate(_COMP):
            E[k, ..., i, j] = 1.0
        dP = piola_tangent(foam, F, E)  # (5, nel, nqp, 3, 3)
        A = np.stack([np.stack([dP[l][..., i, j] for l in range(5)]) for i, j in _COMP])  # (5, 5, nel, nqp)
        P = first_piola(foam, F)
        P5 = np.stack([P[..., i, j] for i, j in _COMP])
        Re = np.einsum("ikeq,keq,eq->ie", self.B, P5, self.dx)
        BA = np.einsum("ikeq,kleq,eq->ileq", self.B, A, self.dx)
        Ke = np.einsum("ileq,jleq->ije", BA, self.B)
        rows = np.broadcast_to(self.edofs[:, None, :], Ke.shape).ravel()
        cols = np.broadcast_to(self.edofs[None, :, :], Ke.shape).ravel()
        K = sp.coo_matrix((Ke.ravel(), (rows, cols)), shape=(self.ndofs,) * 2).tocsr()
        return np.bincount(self.edofs.ravel(), Re.ravel(), minlength=self.ndofs), K
