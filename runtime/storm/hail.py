"""Hailstones: size distribution, spawning, free flight and contact integrators.

Stones are rigid ice spheres. Everything here is vectorised numpy over stones
or contacts, except the contact step, a wrapper over the compiled kernels
(:mod:`hailstorm.runtime.compiled.integrators`, the one implementation, which the
storm calls too); nothing knows about the seat's mesh (see :mod:`hailstorm.runtime.storm.collide`
and :mod:`hailstorm.runtime.storm.driver`).

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

  stable only for ``omega dt < 2`` (``omega = sqrt(k/m)``);
* ``"exact"`` (the damped linear system solved in closed form)::

      z(t) = Re(V exp(Lambda t) V^-1 z0),   z = (q - q_eq, v),
      A = [[0, I], [-M^-1 K, -M^-1 C]] = V Lambda V^-1,   K (q_eq - a) = M g

  While the active set and the dashpot pattern do not change, the contact
  dynamics is linear with constant coefficients, so the modal solution is
  exact for any ``dt``: no numerical damping, no stability limit. The step
  is split at the instants the pattern changes (a contact reaches maximum
  compression: its dashpot switches off; a contact's normal force reaches
  zero: it is released), located on the exact trajectory (grid + bisection,
  relative accuracy ~1e-4 of the step). The external acceleration is
  constant over the step. It therefore realises the restitution of
  :func:`restitution_for_damping_ratio` at any ``omega dt``. Where the modal
  basis is (nearly) defective (critically damped modes) the step takes the
  matrix exponential ``z(t) = exp(A t) z0`` instead; one frictionless contact
  that is not overdamped, the scalar closed form.

The dashpot ``C`` acts in compression only (normal velocity < 0), so it never
pulls and a contact opens exactly when its spring relaxes; its size comes
from a target coefficient of restitution (:func:`damping_coefficients`).

Both support *unilateral* contact: a contact whose total force on the stone
would pull it towards the seat is released and the step is re-solved
(active set).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from hailstorm.runtime.compiled.exact import exact_step
from hailstorm.runtime.compiled.integrators import substep_contacts
from hailstorm.runtime.compiled.modal import explicit_modes_py as _explicit_modes
from hailstorm.runtime.compiled.modal import modal_damping_py as _modal_damping
from hailstorm.runtime.contact import policy

__all__ = [
    "GRAVITY",
    "Air",
    "RHO_AIR",
    "RHO_ICE",
    "ContactStep",
    "SizeDistribution",
    "contact_step",
    "damping_coefficients",
    "damping_ratio_for_restitution",
    "modal_damping",
    "drag_acceleration",
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

class Integrator(StrEnum):
    """The contacts' time integrator, resolved once from its name (``Integrator("exact")``).

    A string enum (it compares equal to, prints as and serialises to its name): what
    the choice means is read from its members, never from string tests.
    """

    #: backward Euler: unconditionally stable, its numerical damping compensated; peak forces
    #: first order in omega dt
    IMPLICIT = "implicit"
    #: symplectic Euler with an explicit dashpot: the modes a step can carry
    SYMPLECTIC = "symplectic"
    #: the closed form over the step (matrix exponential): the model's own peak force
    EXACT = "exact"

    @property
    def closed_form(self) -> bool:
        """The step is the linear system's closed form (no omega dt sub-steps, no stability limit)."""
        return self is Integrator.EXACT

    @property
    def backward_euler(self) -> bool:
        """Backward Euler, whose numerical damping the dashpot compensates."""
        return self is Integrator.IMPLICIT

    @property
    def explicit(self) -> bool:
        """Explicit (symplectic Euler): only the modes with omega dt below its limit are carried."""
        return self is Integrator.SYMPLECTIC

    @property
    def omega_dt_factor(self) -> float:
        """The share of the scene's omega dt target its sub-steps take (symplectic: half, its
        explicit dashpot's peak-force error being first order in omega dt)."""
        return 0.5 if self is Integrator.SYMPLECTIC else 1.0


#: the integrators' names
INTEGRATORS: tuple[str, ...] = tuple(Integrator)


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
    speed = np.sqrt(np.add.reduce(w * w, axis=1, keepdims=True))  # |w| (few numpy calls: called every step)
    coef = 3.0 * cd * rho_air / (8.0 * density * np.asarray(radius, dtype=np.float64))
    return -coef[:, None] * speed * w


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
            raise ValueError(f"r_max must be a finite radius >= r_min ({self.r_min}), got {self.r_max!r}")
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
_X_GRID = -np.log(np.clip(_E_GRID, 1e-300, 1.0))  # the look-up's abscissae (increasing), computed once
#: the restitution table of the dashpot, as the kernels take it: -log(e) (increasing) and the damping ratio
X_GRID, Z_GRID = _X_GRID, _Z_GRID


def damping_ratio_for_restitution(e: np.ndarray | float) -> np.ndarray | float:
    """Inverse of :func:`restitution_for_damping_ratio` (vectorised table look-up,
    relative accuracy ~1e-5)."""
    ea = np.asarray(e, dtype=np.float64)
    if np.any((ea < 0) | (ea > 1)):
        raise ValueError(f"restitution must lie in [0, 1], got {e!r}")
    z = np.interp(-np.log(np.clip(ea, 1e-300, 1.0)), _X_GRID, _Z_GRID)
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

    For ``"exact"`` (and without ``dt``) the dashpot is the model's: the exact
    integrator realises exactly :func:`restitution_for_damping_ratio` (for a
    single contact; coupled contacts use the diagonal of ``K``).
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
    if Integrator(integrator).backward_euler and dt is not None:
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
    peak_seat_force : (m,) ndarray
        The elastic seat force at the instant inside the step when the
        contact's force was largest (zero for a contact that carried none).
        ``"exact"`` finds it on the closed-form trajectory, so a contact that
        opens and is released within one step still shows its peak;
        ``"implicit"``/``"symplectic"`` only know the step's end
        (``seat_force``).
    peak_ubar : (m,) ndarray
        ``q - a`` at the contact's deepest instant inside the step (the most
        negative normal component; where the contact carried no force, ``q+ - a``).
    """

    q: np.ndarray
    v: np.ndarray
    active: np.ndarray
    force: np.ndarray
    seat_force: np.ndarray
    peak_seat_force: np.ndarray
    peak_ubar: np.ndarray


def contact_modes(K: np.ndarray, mass: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Normal modes of a contact set: ``M^-1/2 K M^-1/2 = Phi diag(omega^2) Phi^T``.

    Parameters
    ----------
    K : (m, m) ndarray
        Capacitance (symmetric positive semi-definite; the pseudo-inverse of
        coincident contacts has zero modes).
    mass : (m,) ndarray

    Returns
    -------
    omega2 : (m,) ndarray
        Squared modal frequencies, clipped at zero.
    Phi : (m, m) ndarray
        Orthonormal mode shapes (columns).
    sqm : (m,) ndarray
        ``sqrt(mass)``.
    """
    K = np.asarray(K, dtype=np.float64)
    sqm = np.sqrt(np.asarray(mass, dtype=np.float64))
    if K.size == 0:
        return np.zeros(0), np.zeros((0, 0)), sqm
    Kt = K / sqm[:, None] / sqm[None, :]
    om2, Phi = np.linalg.eigh(0.5 * (Kt + Kt.T))
    return np.clip(om2, 0.0, None), np.ascontiguousarray(Phi), sqm


def modal_damping(
    K: np.ndarray,
    mass: np.ndarray,
    restitution: float,
    *,
    dt: float | None = None,
    integrator: Integrator = "implicit",
) -> np.ndarray:
    """The contact set's dashpot, per normal mode: ``C = M^1/2 Phi diag(2 zeta_j omega_j) Phi^T M^1/2``.

    Every mode of ``M^-1/2 K M^-1/2`` (:func:`contact_modes`) is damped to the
    target restitution, as :func:`damping_coefficients` damps a single contact
    (with ``dt``, for ``"implicit"``, backward Euler's numerical damping of the
    mode compensated; for ``"symplectic"`` the modes the step can carry,
    see the storm). Zero modes (coincident contacts: the split of their common
    force is free) get none. For uncoupled contacts ``C`` is the diagonal of
    :func:`damping_coefficients`; for coupled ones (two stones on one spot) the
    diagonal dashpot would damp the mode they share by the wrong ratio.

    Returns
    -------
    (m, m) ndarray
        Symmetric positive semi-definite dashpot [N s/m] (:func:`contact_step`'s ``damping``).
    """
    om2, Phi, sqm = contact_modes(K, mass)
    kind = Integrator(integrator)
    if kind.explicit and dt is not None:
        om2 = _explicit_modes(om2, float(dt))
    return _modal_damping(om2, Phi, sqm, float(restitution), 0.0 if dt is None else float(dt),
                          kind.backward_euler and dt is not None, _X_GRID, _Z_GRID)


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
    always_damped: np.ndarray | None = None,
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
        Capacitance of the full set. Give ``K``, ``W`` or both (the storm gives
        both). The capacitance of an active subset ``a`` (after releases) is
        ``inv(W[a, a])``, the physically exact one: the released contacts carry
        no force, so the others see the compliance of their own subset. With
        ``K`` alone, ``W`` is its inverse under the contact core's policy
        (:func:`hailstorm.runtime.contact.policy.spd_inverse`: the pseudo-inverse
        of a singular ``K``); with ``W`` alone, ``K = spd_inverse(W)``.
    W : (m, m) ndarray, optional
        Contact compliance ``K^-1``.
    damping : (m,) ndarray, float or (m, m) ndarray
        Contact damping ``C`` [N s/m]: diagonal, or a symmetric matrix
        (:func:`modal_damping`); the dashpot of a contact that is not
        compressing is off (its rows and columns).
    integrator : {"implicit", "symplectic", "exact"}
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
    always_damped : (m,) bool ndarray, optional
        ``"exact"`` only: components whose dashpot acts in both directions
        (resting contacts: no switching events, the oscillation decays).

    Returns
    -------
    ContactStep

    Raises
    ------
    ValueError
        An unknown integrator, neither ``K`` nor ``W``, or arrays whose shapes do not match.

    Notes
    -----
    A thin wrapper over the one implementation, the compiled kernels
    :func:`hailstorm.runtime.compiled.exact_step` (``"exact"``) and
    :func:`hailstorm.runtime.compiled.substep_contacts` (``"implicit"``,
    ``"symplectic"``), with the contact core's condition policy
    (:data:`~hailstorm.runtime.contact.policy.COND_LIMIT`,
    :data:`~hailstorm.runtime.contact.policy.PINV_RCOND`) for the subsets'
    inverses: the storm's contact step, the studies' and the tests' are one.
    The first call of a process loads (the first after an install compiles)
    the kernel.
    """
    q = np.ascontiguousarray(q, dtype=np.float64)
    v = np.ascontiguousarray(v, dtype=np.float64)
    a = np.ascontiguousarray(anchor, dtype=np.float64)
    m = np.ascontiguousarray(mass, dtype=np.float64)
    g = np.ascontiguousarray(accel, dtype=np.float64)
    n = q.size
    if integrator not in INTEGRATORS:
        raise ValueError(f"integrator must be one of {', '.join(INTEGRATORS)}, got {integrator!r}")
    if K is None and W is None:
        raise ValueError("give the capacitance K or the contact compliance W")
    if q.ndim != 1:
        raise ValueError(f"q must be one-dimensional, got shape {q.shape}")
    for name, x in (("v", v), ("anchor", a), ("mass", m), ("accel", g)):
        if x.shape != q.shape:
            raise ValueError(f"{name} must have the shape of q, {q.shape}, got {x.shape}")
    C = np.asarray(damping, dtype=np.float64)
    C = np.diag(np.broadcast_to(C, (n,))) if C.ndim < 2 else np.ascontiguousarray(C)  # a diagonal dashpot
    K = policy.spd_inverse(W) if K is None else np.ascontiguousarray(K, dtype=np.float64)
    W = policy.spd_inverse(K) if W is None else np.ascontiguousarray(W, dtype=np.float64)
    for name, x in (("K", K), ("W", W), ("damping", C)):
        if x.shape != (n, n):
            raise ValueError(f"{name} must be ({n}, {n}), got {x.shape}")
    grp = np.arange(n, dtype=np.int64) if group is None else np.ascontiguousarray(group, dtype=np.int64)
    wts = np.ones(n) if normal_of is None else np.ascontiguousarray(normal_of, dtype=np.float64)
    lim, rcond = float(policy.COND_LIMIT), float(policy.PINV_RCOND)
    kind = Integrator(integrator)
    if kind.closed_form:
        always = np.zeros(n, dtype=bool) if always_damped is None else np.ascontiguousarray(always_damped, dtype=bool)
        qn, vn, act, force, seat, peak, pub = exact_step(q, v, a, m, g, float(dt), K, W, C, bool(unilateral), grp,
                                                         wts, always, lim, rcond)
        return ContactStep(q=qn, v=vn, active=act, force=force, seat_force=seat, peak_seat_force=peak,
                           peak_ubar=pub)
    qn, vn, act, force, seat = substep_contacts(q, v, a, m, g, float(dt), K, W, C, kind.backward_euler,
                                                bool(unilateral), grp, wts, lim, rcond)
    return ContactStep(q=qn, v=vn, active=act, force=force, seat_force=seat, peak_seat_force=seat.copy(),
                       peak_ubar=qn - a)


@dataclass(frozen=True)
class Air:
    """What acts on a flying stone besides gravity: the wind and quadratic drag, as the
    compiled kernels take them (``drag_coef = 3 C_d rho_air / (8 rho_ice)``, 0 without
    drag: the acceleration is ``-(drag_coef / r) |v - wind| (v - wind)``)."""

    wind: np.ndarray
    drag_coef: float

    @classmethod
    def of(cls, wind: object, drag: bool, cd: float, rho_air: float, density: float) -> "Air":
        """From a scene's ``wind``, ``drag``, ``cd``, ``rho_air`` and ``density``."""
        coef = 3.0 * cd * rho_air / (8.0 * density) if drag else 0.0
        return cls(wind=np.asarray(wind, dtype=np.float64), drag_coef=coef)
