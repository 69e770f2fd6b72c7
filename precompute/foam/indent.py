"""A rigid sphere pressed into the foam pad: frictionless unilateral contact, force against approach.

The sphere (radius ``R``) touches the undeformed top at the axis at approach 0; at approach
``d`` its centre is at ``z = h + R - d``. Contact is node-to-sphere on the top surface's nodes
(the sphere's exact surface, in the deformed configuration: gap ``g = |x - c| - R``, normal
``(x - c) / |x - c|``), frictionless, enforced by an **augmented Lagrangian** (Uzawa): for fixed
nodal multipliers ``lam`` Newton (:func:`~hailstorm.precompute.foam.newton.minimise`) minimises

    ``E(u) + sum_i (<lam_i - eps_i g_i>_+^2 - lam_i^2) / (2 eps_i)``,

then ``lam_i <- <lam_i - eps_i g_i>_+``, until the deepest penetration is within
:data:`PENETRATION_TOL` of the approach. ``eps_i = PENALTY E0 a_i / cell`` (``a_i`` the node's ring
area). The force on the sphere is ``sum_i lam_i (-n_z)``; the multipliers are ring forces (the
model integrates over ``2 pi r``).

* :func:`press` -- the quasi-static force-approach curve over given approaches;
* :class:`IndentPoint` -- one approach's force, contact radius, dent and solver counts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hailstorm.precompute.foam.contact import SphereContact
from hailstorm.precompute.foam.newton import minimise
from hailstorm.precompute.foam.pad import PadModel

__all__ = ["PENALTY", "PENETRATION_TOL", "IndentPoint", "press"]

#: the augmented Lagrangian's penalty in units of ``E0 / cell`` per unit ring area
PENALTY = 100.0
#: the contact's tolerance: deepest penetration over the approach
PENETRATION_TOL = 1e-5
#: Newton's tolerances: residual over ``E0 h^2`` and step over ``h``
FORCE_TOL, STEP_TOL = 1e-11, 1e-10


@dataclass
class IndentPoint:
    """The pad under the sphere at one approach (:func:`press`).

    Attributes
    ----------
    approach : float
        ``d`` [m].
    force : float
        The contact force on the sphere [N] (upwards).
    contact_radius : float
        Largest undeformed radius of a touching node [m].
    dent : float
        Downward displacement of the top at the axis [m].
    penetration : float
        Deepest penetration left [m] (``<= PENETRATION_TOL d``).
    newton : int
        Newton iterations over all of the point's Uzawa passes.
    uzawa : int
        Multiplier updates.
    """

    approach: float
    force: float
    contact_radius: float
    dent: float
    penetration: float
    newton: int
    uzawa: int


def press(model: PadModel, radius: float, approaches: np.ndarray, *, max_uzawa: int = 30
          ) -> tuple[list[IndentPoint], np.ndarray]:
    """Press a rigid sphere into ``model``'s pad through ``approaches`` (ascending, the load steps).

    Parameters
    ----------
    model : PadModel
    radius : float
        The sphere's ``R`` [m] (> 0).
    approaches : array_like
        Approaches [m], ascending and > 0: each is one load step, solved from the previous one.
    max_uzawa : int
        Multiplier updates allowed per step.

    Returns
    -------
    points : list of IndentPoint
    u : ndarray
        The displacement at the last approach [m].

    Raises
    ------
    ValueError
        ``radius <= 0`` or approaches not ascending and positive.
    hailstorm.precompute.foam.newton.NewtonError
        A step's Newton solve did not converge.
    RuntimeError
        The multipliers did not converge in ``max_uzawa`` updates.
    """
    d_all = np.asarray(approaches, dtype=np.float64)
    if not radius > 0:
        raise ValueError(f"press needs a sphere radius > 0, got {radius!r}")
    if d_all.ndim != 1 or d_all.size == 0 or not (d_all[0] > 0 and np.all(np.diff(d_all) > 0)):
        raise ValueError("press needs ascending positive approaches")
    pad, foam = model.pad, model.pad.foam
    E0, h = foam.young, pad.thickness
    eps = PENALTY * E0 * model.top_area / model.cell
    lam = np.zeros(model.top.size)
    u = u_prev = np.zeros(model.ndofs)
    d_prev = d_pp = 0.0
    out = []
    for d in d_all:
        guess = u + (u - u_prev) * ((d - d_prev) / (d_prev - d_pp)) if d_prev > 0 else u  # linear predictor
        if model.energy(guess) == np.inf:
            guess = u
        newton = 0
        for k in range(1, max_uzawa + 1):
            c = SphereContact(model, radius, lam, eps, approach=float(d))

            def value(v: np.ndarray, c: SphereContact = c) -> float:
                return model.energy(v) + c.value(v)

            def grad_hess(v: np.ndarray, c: SphereContact = c) -> tuple[np.ndarray, object]:
                r, K = model.tangent(v)
                return c.add(v, r, K)

            guess, stats = minimise(value, grad_hess, guess, model.free, force_tol=FORCE_TOL * E0 * h * h,
                                    step_tol=STEP_TOL * h)
            newton += stats.iterations
            gap, n, _, t = c.state(guess)
            pen = float(np.maximum(-gap[t > 0], 0.0).max(initial=0.0))
            lam = t
            if pen <= PENETRATION_TOL * d:
                break
        else:
            raise RuntimeError(f"press: the contact's multipliers did not converge in {max_uzawa} updates at approach "
                               f"{d:.4g} m (penetration {pen:.3g} m)")
        u_prev, u, d_pp, d_prev = u, guess, d_prev, d
        touching = t > 0
        out.append(IndentPoint(approach=float(d), force=float((t * -n[1]).sum()),
                               contact_radius=float(model.top_r[touching].max(initial=0.0)),
                               dent=float(-u[2 * model.top[0] + 1]), penetration=pen, newton=newton, uzawa=k))
    return out, u
