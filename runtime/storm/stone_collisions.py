"""Stones that meet: collisions between hailstones (``[hail] collisions = true``).

Two stones that touch while approaching collide as two elastic ice spheres: Hertz's law in
compression, and an unloading law that returns the scene's restitution ``e``
(``[contact] restitution``), frictionless (along the line of centres). A hailstone
collision lasts tens of microseconds (:func:`hertz_impact`: 28 us for two 5 mm stones
meeting at 10 m/s), far less than a storm step, so it is resolved inside the step as an
isolated two-body impact at its time of impact (the compiled kernels of
:mod:`hailstorm.runtime.compiled.stone_pairs` integrate it through the contact): the
seat's force on a stone in contact with it is not felt during those microseconds (its
impulse over them is below 1e-3 of the collision's for a resting stone), and a stone in a
seat contact keeps it, with its new velocity.

The ice is isotropic polycrystalline ice: the Voigt-Reuss-Hill average of the single
crystal's elastic constants at -16 degC measured by Brillouin spectroscopy (Gammon, Kiefte,
Clouter & Denner, "Elastic constants of artificial and natural ice samples by Brillouin
spectroscopy", J. Glaciology 29(103), 433-460, 1983): :func:`ice_moduli`, E = 9.20 GPa,
nu = 0.328.

Limits (what this does not model): friction between stones and their spin (issue #47's
Coulomb contact), stones resting on each other (a persistent contact: each approach is an
impact), and a third stone meeting a pair within its contact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from hailstorm.runtime.compiled.stone_pairs import candidate_pairs, collide_pairs
from hailstorm.runtime.compiled.stone_pairs import hertz_impact as integrated_impact

if TYPE_CHECKING:  # annotations only
    from hailstorm.runtime.storm.recording import StormStats
    from hailstorm.runtime.storm.stones import Stones

__all__ = ["ICE_CONSTANTS", "PairImpact", "StoneCollisions", "contact_modulus", "hertz_impact", "ice_moduli",
           "integrated_impact"]

#: single-crystal ice Ih at -16 degC, c11, c12, c13, c33, c44 [Pa] (Gammon et al. 1983)
ICE_CONSTANTS: tuple[float, float, float, float, float] = (13.929e9, 7.082e9, 5.765e9, 15.010e9, 3.014e9)
#: RK4 steps per phase of a collision (compression, restitution): 1e-9 relative on its figures
STEPS_PER_PHASE = 200
#: the most collisions resolved in one storm step
MAX_PER_STEP = 1000


def ice_moduli(constants: tuple[float, float, float, float, float] = ICE_CONSTANTS) -> tuple[float, float]:
    """Young's modulus [Pa] and Poisson's ratio of isotropic polycrystalline ice: the
    Voigt-Reuss-Hill average of a hexagonal crystal's ``c11, c12, c13, c33, c44``."""
    c11, c12, c13, c33, c44 = constants
    C = np.zeros((6, 6))
    C[0, 0] = C[1, 1] = c11
    C[2, 2] = c33
    C[0, 1] = C[1, 0] = c12
    C[0, 2] = C[2, 0] = C[1, 2] = C[2, 1] = c13
    C[3, 3] = C[4, 4] = c44
    C[5, 5] = 0.5 * (c11 - c12)
    S = np.linalg.inv(C)
    d, o, s = np.trace(C[:3, :3]), C[0, 1] + C[1, 2] + C[0, 2], np.trace(C[3:, 3:])
    k_v, g_v = (d + 2.0 * o) / 9.0, (d - o + 3.0 * s) / 15.0
    ds, os_, ss = np.trace(S[:3, :3]), S[0, 1] + S[1, 2] + S[0, 2], np.trace(S[3:, 3:])
    k_r, g_r = 1.0 / (ds + 2.0 * os_), 15.0 / (4.0 * ds - 4.0 * os_ + 3.0 * ss)
    k, g = 0.5 * (k_v + k_r), 0.5 * (g_v + g_r)
    return float(9.0 * k * g / (3.0 * k + g)), float((3.0 * k - 2.0 * g) / (2.0 * (3.0 * k + g)))


def contact_modulus(young: float, poisson: float) -> float:
    """``E*`` of two spheres of one material: ``E / (2 (1 - nu^2))`` [Pa]."""
    return young / (2.0 * (1.0 - poisson * poisson))


@dataclass(frozen=True)
class PairImpact:
    """A two-sphere impact's figures (:func:`hertz_impact`; the kernel's are the same keys)."""

    #: largest overlap [m]
    delta_max: float
    #: largest contact force [N]
    peak_force: float
    #: contact time [s]
    duration: float
    #: separation speed [m/s]
    speed_out: float


#: ``int_0^1 dx / sqrt(1 - x^(5/2))``: the compression's duration in units of ``delta_max / v``
_HALF = 0.4 * math.gamma(0.4) * math.gamma(0.5) / math.gamma(0.9)


def hertz_impact(m1: float, m2: float, r1: float, r2: float, e_star: float, speed: float,
                 restitution: float = 1.0) -> PairImpact:
    """Hertz's impact of two elastic spheres in closed form (Johnson, Contact Mechanics, 11.4),
    with the restitution of the module's unloading law.

    ``delta_max = (15 m v^2 / (16 E* sqrt(R)))^(2/5)``, ``F_max = 4/3 E* sqrt(R) delta_max^(3/2)``
    (``m``, ``R`` the effective mass and radius); the compression lasts
    ``1.4716 delta_max / v``, the restitution ``e`` times that (its law is the compression's
    with stiffness ``k / e^3`` started at ``e v``), so the contact time is
    ``(1 + e) 1.4716 delta_max / v`` (Hertz's ``2.9432 delta_max / v`` for ``e = 1``).
    """
    m = m1 * m2 / (m1 + m2)
    r = r1 * r2 / (r1 + r2)
    delta = (15.0 * m * speed * speed / (16.0 * e_star * math.sqrt(r))) ** 0.4
    peak = 4.0 / 3.0 * e_star * math.sqrt(r) * delta**1.5
    return PairImpact(delta_max=delta, peak_force=peak, duration=(1.0 + restitution) * _HALF * delta / speed,
                      speed_out=restitution * speed)


class StoneCollisions:
    """The storm's stone-on-stone collisions (module docstring).

    Parameters
    ----------
    restitution : float
        The pairs' coefficient of restitution.
    young, poisson : float, optional
        The ice's moduli (default: :func:`ice_moduli`).
    """

    def __init__(self, restitution: float, young: float | None = None, poisson: float | None = None) -> None:
        e_ice, nu_ice = ice_moduli()
        self.young = float(e_ice if young is None else young)
        self.poisson = float(nu_ice if poisson is None else poisson)
        self.e_star = contact_modulus(self.young, self.poisson)
        self.restitution = float(restitution)

    def resolve(self, stones: Stones, live: np.ndarray, pos0: np.ndarray, dt: float, stats: StormStats) -> np.ndarray:
        """Resolve the collisions among the ``live`` stones in the step that moved them from
        ``pos0`` to ``stones.pos``, in place; returns the impacts' records
        (:func:`hailstorm.runtime.compiled.stone_pairs.collide_pairs`). A flying stone that
        collided has its distance to the seat re-measured in the next step."""
        if live.size < 2:
            return np.zeros((0, 8))
        pairs = candidate_pairs(live, pos0, stones.pos, stones.radius, 0.5)
        if pairs.shape[0] == 0:
            return np.zeros((0, 8))
        rec = collide_pairs(pairs, pos0, stones.pos, stones.vel, stones.radius, stones.mass, float(dt), self.e_star,
                            self.restitution, STEPS_PER_PHASE, MAX_PER_STEP)
        if rec.shape[0]:
            ids = np.unique(rec[:, :2].astype(np.intp))
            free = ids[stones.ctri[ids] < 0]
            stones.budget[free] = -np.inf  # moved off its path: the broad phase measures it again
            stones.gap[free] = np.inf
            stats.stone_collisions += int(rec.shape[0])
            stats.max_stone_collision_force_N = max(stats.max_stone_collision_force_N, float(rec[:, 6].max()))
        return rec

    def warm_up(self, stones: Stones) -> None:
        """Load (or compile) the kernels with the storm loop's argument types."""
        none = np.zeros(0, dtype=np.intp)
        pairs = candidate_pairs(none, stones.pos, stones.pos, stones.radius, 0.5)
        collide_pairs(pairs, stones.pos, stones.pos.copy(), stones.vel.copy(), stones.radius, stones.mass, 1e-4,
                      self.e_star, self.restitution, STEPS_PER_PHASE, MAX_PER_STEP)
