"""Newton's method with a backtracking line search on a potential, for the foam pad.

:func:`minimise` finds a stationary point of ``Pi(u)`` on the free dofs from its value, gradient
and Hessian (``Pi`` is the pad's stored energy plus the contact's augmented-Lagrangian term:
a potential, so an Armijo line search on ``Pi`` is the natural globalisation, and a trial step
that inverts an element, ``Pi = inf``, is simply halved). Near convergence a full step that
leaves ``Pi`` unchanged to :data:`ROUNDOFF` is taken.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = ["NewtonError", "NewtonStats", "minimise"]

#: a full Newton step that raises ``Pi`` by less than this share of ``|Pi|`` is taken: near the
#: solution the energy (a sum over the whole pad) cannot resolve the step's change, and the
#: contact's kinks (a node entering or leaving) make it not quite quadratic
ROUNDOFF = 1e-8


class NewtonError(RuntimeError):
    """Newton's method did not converge (the message has the iteration count and residual)."""


@dataclass
class NewtonStats:
    """What one :func:`minimise` call took.

    Attributes
    ----------
    iterations : int
    residual : float
        The final ``max |dPi/du|`` on the free dofs [N].
    halvings : int
        Line-search halvings over all iterations.
    """

    iterations: int
    residual: float
    halvings: int


def minimise(value: Callable[[np.ndarray], float], grad_hess: Callable[[np.ndarray], tuple[np.ndarray, Any]],
             u: np.ndarray, free: np.ndarray, *, force_tol: float, step_tol: float, max_iter: int = 60,
             energy_scale: float = 0.0) -> tuple[np.ndarray, NewtonStats]:
    """Newton on ``Pi`` over ``free`` dofs from ``u`` (fixed dofs kept).

    Converged when ``max |grad| <= force_tol`` [N] and the last step's ``max |du| <= step_tol`` [m].
    ``energy_scale`` [J]: the size of ``Pi``'s parts where ``Pi`` itself is a small difference of
    them (an impact step's inertia and contact terms): a full step that raises ``Pi`` by less than
    :data:`ROUNDOFF` of ``max(|Pi|, energy_scale)`` is taken.

    Raises
    ------
    NewtonError
        Not converged in ``max_iter`` iterations, or no descent found along a Newton step.
    """
    from scipy.sparse.linalg import spsolve

    u = u.copy()
    halvings, step = 0, np.inf
    Pi = value(u)
    for it in range(max_iter + 1):
        g, H = grad_hess(u)
        gf = g[free]
        res = float(np.abs(gf).max(initial=0.0))
        if res <= force_tol and step <= step_tol:
            return u, NewtonStats(iterations=it, residual=res, halvings=halvings)
        if it == max_iter:
            break
        du = np.zeros_like(u)
        du[free] = -spsolve(H[free][:, free].tocsc(), gf)
        slope = float(gf @ du[free])
        if not slope < 0:  # not a descent direction (an indefinite tangent): a scaled gradient step
            du[free] = -gf * (np.abs(du[free]).max() / max(res, 1e-300))
            slope = float(gf @ du[free])
        s = 1.0
        while True:
            trial = value(u + s * du)
            if trial <= Pi + 1e-4 * s * slope:
                break
            if s == 1.0 and trial - Pi <= ROUNDOFF * max(abs(Pi), energy_scale):
                break  # an energy change the line search cannot judge: the full Newton step
            s *= 0.5
            halvings += 1
            if s < 1e-10:
                raise NewtonError(f"no descent along the Newton step at iteration {it + 1} (|grad| {res:.3g} N)")
        u = u + s * du
        Pi = trial
        step = s * float(np.abs(du).max())
    raise NewtonError(f"Newton did not converge in {max_iter} iterations (|grad| {res:.3g} N, last step {step:.3g} m)")
