"""Hailstones: size distribution, spawning, free flight and contact integrators.

Stones are rigid ice spheres. Everything here is vectorised numpy over stones
or contacts; nothing knows about the seat's mesh (see :mod:`runtime.collide`
and :mod:`runtime.storm`).

Contact dynamics in *constrained coordinates*
---------------------------------------------
A storm step with ``s`` contacts works in ``m`` constrained components ``q``
(``m = s`` for frictionless contacts: ``q_k = n_k . c_k``, the normal
coordinate of stone centre ``c_k``; ``m = 3s`` for sticky contacts:
``q = c``). Each component has an *anchor* ``a`` (where the prescribed
contact displacement ``ubar = q - a`` vanishes), a mass ``M`` (diagonal), an
external acceleration ``g`` and a diagonal contact damping ``C``. The stones
feel ``-K (q - a) - C v`` where ``K`` is the capacitance (effective contact
stiffness) of the contact set. :func:`contact_step` advances ``(q, v)`` by one
step with either

* ``"implicit"`` (backward Euler, the default)::

      (M + dt C + dt^2 K) v+ = M v + dt (M g - K (q - a)),   q+ = q + dt v+

  unconditionally stable; at rest it reproduces the static equilibrium
  ``K (q - a) = M g`` exactly, whatever ``dt``;
* ``"symplectic"`` (symplectic Euler)::

      v+ = v + dt (g - M^-1 (K (q - a) + C v)),   q+ = q + dt v+

  stable only for ``omega dt < 2`` (``omega = sqrt(k/m)``).

The dashpot ``C`` acts in compression only (normal velocity < 0), so it never
pulls and a contact opens exactly when its spring relaxes; its size comes
from a target coefficient of restitution (:func:`damping_coefficients`).

Both support *unilateral* contact: a contact whose total force on the stone
would pull it towards the seat is released and the step is re-solved
(active set).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

__all__ = [
    "GRAVITY",
    "RHO_AIR",
    "RHO_ICE",
    "ContactStep",
    "SizeDistribution",
    "contact_step",
    "damping_coefficients",
    "damping_ratio_for_restitution",
    "drag_acceleration",
    "free_flight",
    "restitution_for_damping_ratio",
    "stone_mass",
    "terminal_velocity",
]

#: Density of hail ice [kg/m^3].
RHO_ICE: float = 917.0
#: Density of air [kg/m^3].
RHO_AIR: float = 1.2
#: Gravitational acceleration [m/s^2] (along -z).
GRAVITY: float = 9.81

Integrator = Literal["implicit", "symplectic"]


def stone_mass(radius: np.ndarray | float, density: float = RHO_ICE) -> np.ndarray:
    """Mass of ice spheres [kg]."""
    r = np.asarray(radius, dtype=np.float64)
    return density * (4.0 / 3.0) * np.pi * r**3


def terminal_velocity(
    radius: np.ndarray | float,
    *,
    cd: float = 0.6,
    rho_air: float = RHO_AIR,
    density: float = RHO_ICE,
    g: float = GRAVITY,
) -> np.ndarray:
    """Terminal fall speed ``sqrt(8 r g rho_ice / (3 C_d rho_air))`` [m/s]."""
    r = np.asarray(radius, dtype=np.float64)
    return np.sqrt(8.0 * r * g * density / (3.0 * cd * rho_air))


def drag_acceleration(
    vel: np.ndarray,
    radius: np.ndarray,
    *,
    wind: np.ndarray | None = None,
    cd: float = 0.6,
    rho_air: float = RHO_AIR,
    density: float = RHO_ICE,
) -> np.ndarray:
    """Quadratic air drag on spheres, ``-(3 C_d rho_air / (8 r rho)) |w| w`` with ``w = v - wind``.

    Parameters
    ----------
    vel : (k, 3) ndarray
    radius : (k,) ndarray
    wind : (3,) ndarray, optional

    Returns
    -------
    (k, 3) ndarray
        Acceleration [m/s^2]. Balances gravity at the terminal velocity.
    """
    w = vel if wind is None else vel - np.asarray(wind, dtype=np.float64)
    speed = np.linalg.norm(w, axis=1, keepdims=True)
    coef = 3.0 * cd * rho_air / (8.0 * density * np.asarray(radius, dtype=np.float64))
    return -coef[:, None] * speed * w


def free_flight(
    pos: np.ndarray,
    vel: np.ndarray,
    dt: float,
    *,
    accel: np.ndarray | None = None,
    g: float = GRAVITY,
) -> tuple[np.ndarray, np.ndarray]:
    """Advance stones in free flight by ``dt``.

    Exact for gravity alone (constant acceleration); an extra acceleration
    (drag) is taken as constant over the step.

    Returns
    -------
    pos, vel : (k, 3) ndarray
        New arrays (inputs are not modified).
    """
    a = np.zeros_like(vel)
    a[:, 2] -= g
    if accel is not None:
        a = a + accel
    return pos + dt * vel + 0.5 * dt * dt * a, vel + dt * a


@dataclass(frozen=True)
class SizeDistribution:
    """Hailstone radius distribution.

    Attributes
    ----------
    kind : {"exponential", "uniform", "fixed"}
        ``"exponential"``: Marshall–Palmer-like ``N(r) ~ exp(-(r - r_min)/scale)``
        truncated to ``[r_min, r_max]``; ``"uniform"`` on ``[r_min, r_max]``;
        ``"fixed"``: every stone has ``r_min``.
    r_min, r_max : float
        Radius bounds [m].
    scale : float
        e-folding radius of the exponential [m].
    """

    kind: str = "exponential"
    r_min: float = 0.0025
    r_max: float = 0.0125
    scale: float = 0.002

    def __post_init__(self) -> None:
        if self.kind not in ("exponential", "uniform", "fixed"):
            raise ValueError(f"size distribution kind must be 'exponential', 'uniform' or 'fixed', got {self.kind!r}")
        if not (np.isfinite(self.r_min) and self.r_min > 0):
            raise ValueError(f"r_min must be a positive radius in metres, got {self.r_min!r}")
        if self.kind != "fixed" and not (np.isfinite(self.r_max) and self.r_max >= self.r_min):
            raise ValueError(f"r_max must be >= r_min ({self.r_min}), got {self.r_max!r}")
        if self.kind == "exponential" and not (np.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"scale must be positive, got {self.scale!r}")

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """Draw ``n`` radii [m]."""
        if self.kind == "fixed":
            return np.full(n, float(self.r_min))
        u = rng.random(n)
        if self.kind == "uniform":
            return self.r_min + u * (self.r_max - self.r_min)
        span = self.r_max - self.r_min
        cdf_max = -np.expm1(-span / self.scale)
        return self.r_min - self.scale * np.log1p(-u * cdf_max)

    def mean(self) -> float:
        """Mean radius [m] (numerically, for the exponential)."""
        if self.kind == "fixed":
            return float(self.r_min)
        if self.kind == "uniform":
            return 0.5 * (self.r_min + self.r_max)
        span = self.r_max - self.r_min
        x = np.linspace(0.0, span, 2001)
        w = np.exp(-x / self.scale)
        return float(self.r_min + np.trapezoid(x * w, x) / np.trapezoid(w, x))


# --------------------------------------------------------------------------
# restitution <-> damping
# --------------------------------------------------------------------------
def restitution_for_damping_ratio(zeta: np.ndarray | float) -> np.ndarray | float:
    """Coefficient of restitution of the contact model for damping ratio ``zeta``.

    The contact is a linear spring with a dashpot that acts during
    *compression only* (``v_n < 0``): the dashpot never pulls, the stone
    leaves exactly when the spring is relaxed (``ubar = 0``, so it does not
    sit inside the seat when the seat springs back), and the restitution
    is the ratio of the elastic energy at maximum compression to the impact
    energy: ``e = exp(-zeta t1)`` with ``t1 = atan(w_d / zeta) / w_d``,
    ``w_d = sqrt(1 - zeta^2)`` (unit frequency; continued analytically
    through critical damping).
    """
    z = np.asarray(zeta, dtype=np.float64)
    wd = np.sqrt((1.0 - z * z).astype(np.complex128))
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = np.where(np.abs(wd) > 1e-8, (np.arctan(wd / np.where(z > 0, z, 1e-300)) / np.where(np.abs(wd) > 1e-8, wd, 1.0)).real, 1.0)
    e = np.where(z > 0, np.exp(-z * t1), 1.0)
    return float(e) if e.ndim == 0 else e


_Z_GRID = np.concatenate([[0.0], np.logspace(-6, 3, 4000)])
_E_GRID = restitution_for_damping_ratio(_Z_GRID)  # decreasing from 1


def damping_ratio_for_restitution(e: np.ndarray | float) -> np.ndarray | float:
    """Inverse of :func:`restitution_for_damping_ratio` (vectorised table look-up,
    relative accuracy ~1e-5)."""
    ea = np.asarray(e, dtype=np.float64)
    if np.any((ea < 0) | (ea > 1)):
        raise ValueError(f"restitution must lie in [0, 1], got {e!r}")
    z = np.interp(-np.log(np.clip(ea, 1e-300, 1.0)), -np.log(np.clip(_E_GRID, 1e-300, 1.0)), _Z_GRID)
    return float(z) if z.ndim == 0 else z


def damping_coefficients(
    K: np.ndarray,
    mass: np.ndarray,
    restitution: float,
    *,
    dt: float | None = None,
    integrator: Integrator = "implicit",
) -> np.ndarray:
    """Diagonal compression damping ``c_i = 2 zeta_i sqrt(K_ii m_i)`` realising a restitution.

    For the implicit integrator the numerical damping of backward Euler (an
    effective damping ratio ``zeta_num ~ omega dt / 2`` throughout the contact)
    is compensated: the physical dashpot is chosen so that the *total*
    restitution stays close to the target while ``omega dt`` is small
    (it cannot go below zero: at large ``omega dt`` backward Euler alone is
    more dissipative than the target).
    """
    k = np.clip(np.diag(np.asarray(K)), 0.0, None)
    m = np.asarray(mass, dtype=np.float64)
    omega = np.sqrt(k / m)
    e = np.full_like(omega, float(restitution))
    zn = np.zeros_like(omega)
    if integrator == "implicit" and dt is not None:
        zn = 0.5 * omega * dt
        e = np.minimum(e / np.exp(-zn * np.pi / 2.0), 1.0)  # restitution phase loses exp(-zn pi/2)
    z = np.clip(damping_ratio_for_restitution(e) - zn, 0.0, None)
    return 2.0 * z * np.sqrt(k * m)


# --------------------------------------------------------------------------
# the contact step
# --------------------------------------------------------------------------
@dataclass
class ContactStep:
    """Result of :func:`contact_step`.

    Attributes
    ----------
    q, v : (m,) ndarray
        New constrained coordinates and velocities.
    active : (m,) bool ndarray
        Components whose contact stayed closed (unilateral active set).
    force : (m,) ndarray
        Contact force on the stones (elastic + damping) over the step; zero
        where released.
    seat_force : (m,) ndarray
        Elastic force on the seat ``K_active (q+ - a)`` (a push has the sign
        of ``q - a < 0``), the one that deforms the seat; zero where released.
    """

    q: np.ndarray
    v: np.ndarray
    active: np.ndarray
    force: np.ndarray
    seat_force: np.ndarray


def _inv_spd(W: np.ndarray) -> np.ndarray:
    """Inverse of a small symmetric positive (semi-)definite matrix."""
    if W.size == 0:
        return np.zeros_like(W)
    try:
        c = np.linalg.cholesky(0.5 * (W + W.T))
        ci = np.linalg.inv(c)
        return ci.T @ ci
    except np.linalg.LinAlgError:
        return np.linalg.pinv(W, rcond=1e-10, hermitian=True)


def contact_step(
    q: np.ndarray,
    v: np.ndarray,
    anchor: np.ndarray,
    mass: np.ndarray,
    accel: np.ndarray,
    dt: float,
    *,
    K: np.ndarray | None = None,
    W: np.ndarray | None = None,
    damping: np.ndarray | float = 0.0,
    integrator: Integrator = "implicit",
    unilateral: bool = True,
    group: np.ndarray | None = None,
    normal_of: np.ndarray | None = None,
) -> ContactStep:
    """Advance stones in contact by one step (constrained coordinates).

    Parameters
    ----------
    q, v, anchor, mass, accel : (m,) ndarray
        Constrained coordinates, velocities, anchors (``ubar = q - anchor``),
        masses and external accelerations (gravity, drag) per component.
    dt : float
        Time step [s].
    K : (m, m) ndarray, optional
        Capacitance of the full set. Give either ``K`` or ``W``. With ``W``
        (the contact compliance), the capacitance of an active subset is
        ``inv(W[a, a])`` (exact); with ``K`` alone, subsets use ``K[a, a]``
        (exact only when nothing is released).
    W : (m, m) ndarray, optional
        Contact compliance ``K^-1``.
    damping : (m,) ndarray or float
        Diagonal contact damping ``C`` [N s/m].
    integrator : {"implicit", "symplectic"}
    unilateral : bool
        Release contacts whose force on the stone would pull it in.
    group : (m,) int ndarray, optional
        Contact index of each component (sticky contacts have 3 components
        per contact; all are released together). Default: one per component.
    normal_of : (m,) ndarray, optional
        Weights ``w`` such that the *normal* force of contact ``g`` is
        ``sum over its components i of w_i force_i`` (sticky contacts: the
        components of the contact normal; frictionless: 1, the default). Used
        for the unilateral test and to apply the dashpot in compression only.

    Returns
    -------
    ContactStep
    """
    q = np.asarray(q, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    a = np.asarray(anchor, dtype=np.float64)
    m = np.asarray(mass, dtype=np.float64)
    g = np.asarray(accel, dtype=np.float64)
    n = q.size
    C = np.broadcast_to(np.asarray(damping, dtype=np.float64), (n,))
    if K is None and W is None:
        raise ValueError("give the capacitance K or the contact compliance W")
    if integrator not in ("implicit", "symplectic"):
        raise ValueError(f"integrator must be 'implicit' or 'symplectic', got {integrator!r}")
    group = np.arange(n) if group is None else np.asarray(group)
    wts = np.ones(n) if normal_of is None else np.asarray(normal_of, dtype=np.float64)
    # the dashpot acts in compression only (normal velocity of the contact < 0)
    vn_g = np.zeros(group.max() + 1 if n else 0)
    np.add.at(vn_g, group, wts * v)
    C = np.where(vn_g[group] < 0.0, C, 0.0)
    active = np.ones(n, dtype=bool)
    ubar = q - a
    K_full = _inv_spd(W) if K is None else np.asarray(K, dtype=np.float64)
    while True:
        idx = np.flatnonzero(active)
        if W is not None and idx.size < n:
            Ka = _inv_spd(W[np.ix_(idx, idx)])
        else:
            Ka = K_full[np.ix_(idx, idx)]
        v_new = v + dt * g  # free motion of released components
        if idx.size:
            ma, ua, va, ga, ca = m[idx], ubar[idx], v[idx], g[idx], C[idx]
            if integrator == "implicit":
                A = dt * dt * Ka
                A[np.diag_indices_from(A)] += ma + dt * ca
                rhs = ma * va + dt * (ma * ga - Ka @ ua)
                v_new[idx] = np.linalg.solve(A, rhs)
            else:
                f = -(Ka @ ua) - ca * va
                v_new[idx] = va + dt * (ga + f / ma)
        force = np.zeros(n)
        force[idx] = m[idx] * ((v_new[idx] - v[idx]) / dt - g[idx])
        if not unilateral or idx.size == 0:
            break
        # normal force per contact group (positive = pushes the stone out)
        fn = np.zeros(group.max() + 1)
        np.add.at(fn, group, wts * force)
        pulling = active & (fn[group] < 0.0)
        if not pulling.any():
            break
        active &= ~pulling
    q_new = q + dt * v_new
    seat = np.zeros(n)
    idx = np.flatnonzero(active)
    if idx.size:
        if W is not None and idx.size < n:
            Ka = _inv_spd(W[np.ix_(idx, idx)])
        else:
            Ka = K_full[np.ix_(idx, idx)]
        seat[idx] = Ka @ (q_new[idx] - a[idx])
    force[~active] = 0.0
    return ContactStep(q=q_new, v=v_new, active=active, force=force, seat_force=seat)
