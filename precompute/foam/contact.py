"""The rigid sphere's frictionless contact with the pad's top: the augmented-Lagrangian term.

:class:`SphereContact` is the term ``sum_i (<lam_i - eps_i g_i>_+^2 - lam_i^2) / (2 eps_i)`` of
one Uzawa pass (fixed multipliers ``lam``), node-to-sphere on the top surface's nodes in the
deformed configuration: gap ``g = |x - c| - R``, normal ``n = (x - c) / |x - c|``, centre
``c = (0, h + R - d)`` at approach ``d``. The approach is either fixed (a quasi-static press,
:mod:`~hailstorm.precompute.foam.indent`) or an unknown of its own, the last entry of the state
vector (an impact, :mod:`~hailstorm.precompute.foam.impact`): then ``g`` depends on ``u_z + d``
alone in ``z`` and the sphere's row of the gradient is the contact force ``F = sum t (-n_z)``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hailstorm.precompute.foam.pad import PadModel

__all__ = ["SphereContact"]


class SphereContact:
    """The augmented-Lagrangian contact term of one Uzawa pass (module notes).

    Parameters
    ----------
    model : PadModel
    radius : float
        The sphere's ``R`` [m].
    lam, eps : ndarray
        Multipliers [N] (ring forces) and penalties [N/m] of the top nodes, (t,).
    approach : float, optional
        A fixed approach [m]; None: the approach is the state's entry ``sphere_dof``.
    sphere_dof : int, optional
        The state's entry of the approach (needed when ``approach`` is None).
    """

    def __init__(self, model: PadModel, radius: float, lam: np.ndarray, eps: np.ndarray, *,
                 approach: float | None = None, sphere_dof: int | None = None) -> None:
        if (approach is None) == (sphere_dof is None):
            raise ValueError("SphereContact needs exactly one of approach and sphere_dof")
        self.model, self.radius, self.lam, self.eps = model, float(radius), lam, eps
        self.approach, self.sphere_dof = approach, sphere_dof
        self.ir, self.iz = 2 * model.top, 2 * model.top + 1

    def _approach(self, x: np.ndarray) -> float:
        return float(self.approach) if self.sphere_dof is None else float(x[self.sphere_dof])

    def state(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Gap [m], normal (2, t), distance to the centre [m] and ``t = <lam - eps g>_+`` [N] of each top node."""
        cz = self.model.pad.thickness + self.radius - self._approach(x)
        xr = self.model.top_r + x[self.ir]
        xz = self.model.pad.thickness + x[self.iz] - cz
        rho = np.hypot(xr, xz)
        g = rho - self.radius
        return g, np.stack([xr, xz]) / rho, rho, np.maximum(self.lam - self.eps * g, 0.0)

    def force(self, x: np.ndarray) -> float:
        """The contact force on the sphere, upwards [N]."""
        _, n, _, t = self.state(x)
        return float((t * -n[1]).sum())

    def value(self, x: np.ndarray) -> float:
        """The term's value [J]."""
        _, _, _, t = self.state(x)
        return float(((t * t - self.lam * self.lam) / (2.0 * self.eps)).sum())

    def add(self, x: np.ndarray, g: np.ndarray, K: Any) -> tuple[np.ndarray, Any]:
        """``g`` and ``K`` (a scipy sparse matrix of ``x``'s size) plus the term's gradient and Hessian."""
        import scipy.sparse as sp

        _, n, rho, t = self.state(x)
        g = g.copy()
        np.add.at(g, self.ir, -t * n[0])
        np.add.at(g, self.iz, -t * n[1])
        on = (t > 0).astype(float)
        blocks = [[self.eps * on * n[a] * n[b] - t * ((a == b) - n[a] * n[b]) / rho for b in range(2)]
                  for a in range(2)]
        idx = [self.ir, self.iz]
        pairs = [(a, b) for a in range(2) for b in range(2)]
        if self.sphere_dof is not None:  # d enters as u_z of every node: its rows and columns are the z ones
            g[self.sphere_dof] += float((-t * n[1]).sum())
            k = np.full(t.size, self.sphere_dof)
            idx.append(k)
            zz = blocks[1][1]
            blocks = [[blocks[0][0], blocks[0][1], blocks[0][1]], [blocks[1][0], zz, zz], [blocks[1][0], zz, zz]]
            pairs = [(a, b) for a in range(3) for b in range(3)]
        rows = np.concatenate([idx[a] for a, b in pairs])
        cols = np.concatenate([idx[b] for a, b in pairs])
        vals = np.concatenate([blocks[a][b] for a, b in pairs])
        return g, K + sp.coo_matrix((vals, (rows, cols)), shape=K.shape).tocsr()
