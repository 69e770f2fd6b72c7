"""A rigid sphere on a massless pad: the quasi-static contact law integrated as a 1-DOF oscillator.

With the pad's inertia negligible, the impact of a sphere of mass ``m`` at speed ``v`` is
``m d'' = -F(d)`` for the pad's quasi-static law ``F(d)`` (force against approach,
:func:`~hailstorm.precompute.foam.indent.press`): the largest approach solves
``int_0^dmax F = m v^2 / 2``, the peak force is ``F(dmax)`` and, the law being elastic, the
rebound speed is ``v``. :func:`oscillator` integrates it from a tabulated law (monotone cubic,
PCHIP, through ``(0, 0)``), the reference of the dynamic solve
(:func:`~hailstorm.precompute.foam.impact.strike`) in its quasi-static limit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["OscillatorImpact", "oscillator"]


@dataclass(frozen=True)
class OscillatorImpact:
    """The 1-DOF impact of :func:`oscillator`.

    Attributes
    ----------
    peak_force : float
        [N]
    contact_time : float
        [s]
    max_approach : float
        [m]
    """

    peak_force: float
    contact_time: float
    max_approach: float


def oscillator(approaches: np.ndarray, forces: np.ndarray, mass: float, speed: float, *, rtol: float = 1e-10
               ) -> OscillatorImpact:
    """Integrate ``m d'' = -F(d)``, ``d(0) = 0``, ``d'(0) = speed``, until ``d`` returns to 0.

    Parameters
    ----------
    approaches, forces : array_like
        The tabulated law ``F(d)`` [m], [N]: ascending positive approaches, their forces (> 0).
        ``(0, 0)`` is added. It must reach past the largest approach.
    mass, speed : float
        The sphere [kg], [m/s] (> 0).
    rtol : float
        The integrator's relative tolerance.

    Returns
    -------
    OscillatorImpact

    Raises
    ------
    ValueError
        Bad input, or the table ends before the sphere stops.
    """
    from scipy.integrate import solve_ivp
    from scipy.interpolate import PchipInterpolator

    d = np.concatenate([[0.0], np.asarray(approaches, dtype=np.float64)])
    f = np.concatenate([[0.0], np.asarray(forces, dtype=np.float64)])
    if not (mass > 0 and speed > 0):
        raise ValueError(f"oscillator needs mass and speed > 0, got {mass!r}, {speed!r}")
    if d.size < 3 or np.any(np.diff(d) <= 0) or np.any(f[1:] <= 0):
        raise ValueError("oscillator needs ascending positive approaches with positive forces")
    law = PchipInterpolator(d, f)
    work = law.antiderivative()
    kinetic = 0.5 * mass * speed**2
    if work(d[-1]) < kinetic:
        raise ValueError(f"the law's table ends at approach {d[-1]:.4g} m with work {float(work(d[-1])):.4g} J, "
                         f"below the sphere's kinetic energy {kinetic:.4g} J")

    def rhs(_: float, y: np.ndarray) -> list[float]:
        return [y[1], -float(law(min(max(y[0], 0.0), d[-1]))) / mass]

    def back(_: float, y: np.ndarray) -> float:
        return y[0]

    back.terminal, back.direction = True, -1.0
    from scipy.optimize import brentq

    d_max = float(brentq(lambda x: float(work(x)) - kinetic, 0.0, d[-1], xtol=1e-15 * d[-1], rtol=1e-15))
    t_scale = d_max / speed
    sol = solve_ivp(rhs, (0.0, 1e3 * t_scale), [0.0, float(speed)], rtol=rtol, atol=1e-12 * d_max,
                    events=back, first_step=1e-6 * t_scale)
    if not sol.t_events[0].size:
        raise ValueError("oscillator: the sphere did not come back")
    return OscillatorImpact(peak_force=float(law(d_max)), contact_time=float(sol.t_events[0][0]), max_approach=d_max)
