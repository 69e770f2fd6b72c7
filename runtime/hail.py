"""Hailstones: size distribution, spawning, free flight and contact integrators.

Stones are rigid ice spheres. Everything here is vectorised numpy over stones
or contacts; nothing knows about the seat's mesh (see :mod:`hailstorm.runtime.collide`
and :mod:`hailstorm.runtime.storm`).

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
  :func:`restitution_for_damping_ratio` at any ``omega dt``.

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

from hailstorm.runtime.compiled.modal import equilibrium_py as _equilibrium
from hailstorm.runtime.compiled.modal import explicit_modes_py as _explicit_modes
from hailstorm.runtime.compiled.modal import modal_damping_py as _modal_damping
from hailstorm.runtime.compiled.modal import scalar_exact_py as _scalar_exact

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

Integrator = Literal["implicit", "symplectic", "exact"]
INTEGRATORS: tuple[str, ...] = ("implicit", "symplectic", "exact")


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


def _inv_spd(W: np.ndarray) -> np.ndarray:
    """Inverse of a small symmetric positive (semi-)definite matrix: the contact API's
    policy (:func:`hailstorm.runtime.contact.policy.spd_inverse`; the pseudo-inverse when
    ``W`` is ill conditioned, e.g. coincident contacts)."""
    from hailstorm.runtime.contact.policy import spd_inverse  # (import cycle: it imports hailstorm.runtime.compiled)

    return spd_inverse(W)


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
    if integrator == "symplectic" and dt is not None:
        om2 = _explicit_modes(om2, float(dt))
    return _modal_damping(om2, Phi, sqm, float(restitution), 0.0 if dt is None else float(dt),
                          integrator == "implicit" and dt is not None, _X_GRID, _Z_GRID)


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
        Capacitance of the full set. Give either ``K`` or ``W``. With ``W``
        (the contact compliance), the capacitance of an active subset is
        ``inv(W[a, a])`` (exact); with ``K`` alone, subsets use ``K[a, a]``
        (exact only when nothing is released).
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
    """
    q = np.asarray(q, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    a = np.asarray(anchor, dtype=np.float64)
    m = np.asarray(mass, dtype=np.float64)
    g = np.asarray(accel, dtype=np.float64)
    n = q.size
    C = np.asarray(damping, dtype=np.float64)
    if C.ndim < 2:  # a diagonal dashpot
        C = np.diag(np.broadcast_to(C, (n,)))
    if K is None and W is None:
        raise ValueError("give the capacitance K or the contact compliance W")
    if integrator not in INTEGRATORS:
        raise ValueError(f"integrator must be one of {', '.join(INTEGRATORS)}, got {integrator!r}")
    group = np.arange(n) if group is None else np.asarray(group)
    wts = np.ones(n) if normal_of is None else np.asarray(normal_of, dtype=np.float64)
    if integrator == "exact":
        return _exact_step(q, v, np.asarray(anchor, dtype=np.float64), m, g, float(dt), K, W, C, unilateral,
                           group, wts, always_damped)
    # the dashpot acts in compression only (normal velocity of the contact < 0)
    vn_g = np.zeros(group.max() + 1 if n else 0)
    np.add.at(vn_g, group, wts * v)
    on = vn_g[group] < 0.0
    C = C * (on[:, None] & on[None, :])
    active = np.ones(n, dtype=bool)
    ubar = q - a
    if K is None:
        assert W is not None  # checked above: K or W is given
        K_full = _inv_spd(W)
    else:
        K_full = np.asarray(K, dtype=np.float64)
    while True:
        idx = np.flatnonzero(active)
        if W is not None and idx.size < n:
            Ka = _inv_spd(W[np.ix_(idx, idx)])
        else:
            Ka = K_full[np.ix_(idx, idx)]
        v_new = v + dt * g  # free motion of released components
        if idx.size:
            ma, ua, va, ga, ca = m[idx], ubar[idx], v[idx], g[idx], C[np.ix_(idx, idx)]
            if integrator == "implicit":
                A = dt * dt * Ka + dt * ca
                A[np.diag_indices_from(A)] += ma
                rhs = ma * va + dt * (ma * ga - Ka @ ua)
                v_new[idx] = np.linalg.solve(A, rhs)
            else:
                f = -(Ka @ ua) - ca @ va
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
    return ContactStep(q=q_new, v=v_new, active=active, force=force, seat_force=seat, peak_seat_force=seat.copy(),
                       peak_ubar=q_new - a)


# --------------------------------------------------------------------------
# the exact (modal) integrator
# --------------------------------------------------------------------------
_GRID = 32  # samples per bracket when locating an event
_REFINE = 2  # bracket refinements: event time to dt / 32**(_REFINE + 1)
_MAX_SEGMENTS = 12


class _Modal:
    """Closed-form solution of ``M y'' + C y' + K y = 0``, ``z = (y, y')``."""

    __slots__ = ("lam", "V", "Vi", "A", "n", "real")

    def __init__(self, K: np.ndarray, m: np.ndarray, c: np.ndarray) -> None:
        n = m.size
        A = np.zeros((2 * n, 2 * n))
        A[:n, n:] = np.eye(n)
        A[n:, :n] = -K / m[:, None]
        A[n:, n:] = -c / m[:, None]  # (n, n) dashpot
        self.n, self.A = n, A
        lam, V = np.linalg.eig(A)
        self.lam, self.V = lam, V
        try:
            Vi = np.linalg.inv(V)
            ok = np.isfinite(Vi).all() and np.abs(V).max() * np.abs(Vi).max() < 1e7
        except np.linalg.LinAlgError:
            ok = False
        self.Vi = Vi if ok else None  # None: (nearly) defective, use expm

    def at(self, z0: np.ndarray, t: np.ndarray) -> np.ndarray:
        """States (2n, len(t)) at times ``t`` from ``z0``."""
        if self.Vi is not None:
            c = self.Vi @ z0
            return (self.V @ (np.exp(np.multiply.outer(self.lam, t)) * c[:, None])).real
        from scipy.linalg import expm

        return np.stack([expm(self.A * ti) @ z0 for ti in np.atleast_1d(t)], axis=1)


def _exact_step(q, v, a, m, g, dt, K, W, C, unilateral, group, wts, always_damped) -> ContactStep:
    n = q.size
    if n == 1 and group[0] == 0 and wts[0] == 1.0:
        k = float((_inv_spd(W) if K is None else np.asarray(K, dtype=np.float64))[0, 0])
        al = bool(always_damped[0]) if always_damped is not None else False
        qn, vn, act, ok, umin, umax = _scalar_exact(float(q[0]), float(v[0]), float(a[0]), float(m[0]),
                                                    float(g[0]), dt, k, float(np.asarray(C)[0, 0]), unilateral, al)
        if ok:
            force = m * ((vn - v) / dt - g) if act else np.zeros(1)
            seat = np.array([k * (qn - a[0])]) if act else np.zeros(1)
            peak = np.array([k * (umin if -umin >= umax else umax)])
            return ContactStep(q=np.array([qn]), v=np.array([vn]), active=np.array([act]), force=force,
                               seat_force=seat, peak_seat_force=peak, peak_ubar=np.array([umin]))
    ng = int(group.max()) + 1 if n else 0
    K_full = _inv_spd(W) if K is None else np.asarray(K, dtype=np.float64)
    Cn = np.asarray(C, dtype=np.float64).copy()  # nominal dashpot (m, m)

    def dashpot(idx: np.ndarray) -> np.ndarray:  # of the components idx: on while compressing (or always)
        on = (damp_g[group] | always)[idx]
        return Cn[np.ix_(idx, idx)] * (on[:, None] & on[None, :])
    always = np.zeros(n, bool) if always_damped is None else np.asarray(always_damped, bool)
    v0 = v
    q, v = q.copy(), v.copy()
    active = np.ones(n, dtype=bool)

    ident = ng == n and np.array_equal(group, np.arange(n)) and np.all(wts == 1.0)

    def gsum(x: np.ndarray) -> np.ndarray:  # (n, ...) -> (ng, ...) normal sums per group
        if ident:
            return x
        out = np.zeros((ng,) + x.shape[1:])
        np.add.at(out, group, wts.reshape((-1,) + (1,) * (x.ndim - 1)) * x)
        return out

    def vn_of(vv):
        return gsum(vv)

    # dashpot on at the start where the contact is compressing (or always for resting ones)
    damp_g = vn_of(v) < 0.0
    t = 0.0
    Ka = K_full
    # peaks inside the step, per contact group: the largest |elastic seat force| (squared) and the
    # most negative normal q - a, with the components at those instants, over the closed-form
    # states the event search evaluates (its samples and the located events)
    pk2 = np.zeros(ng)
    pk_f = np.zeros(n)
    dmin = np.full(ng, np.inf)
    dmin_u = q - a

    def track(comp: np.ndarray, Ka_: np.ndarray, ub: np.ndarray) -> None:
        """Update the peaks from states of the active components ``comp`` (ub: their q - a, (na, T))."""
        F = Ka_ @ ub
        gc = group[comp]
        mag2 = np.zeros((ng, ub.shape[1]))
        np.add.at(mag2, gc, F * F)
        un = np.full((ng, ub.shape[1]), np.inf)
        un[gc] = 0.0
        np.add.at(un, gc, wts[comp][:, None] * ub)
        cb = np.argmax(mag2, axis=1)
        best = mag2[np.arange(ng), cb]
        up = best > pk2
        if up.any():
            pk2[up] = best[up]
            sel = up[gc]
            pk_f[comp[sel]] = F[sel, cb[gc[sel]]]
        cd = np.argmin(un, axis=1)
        deep = un[np.arange(ng), cd]
        dn = deep < dmin
        if dn.any():
            dmin[dn] = deep[dn]
            sel = dn[gc]
            dmin_u[comp[sel]] = ub[sel, cd[gc[sel]]]
    for _seg in range(_MAX_SEGMENTS):
        # unilateral: release contacts that pull now and do not approach (active-set iteration)
        while True:
            idx = np.flatnonzero(active)
            if W is not None and idx.size < n:
                Ka = _inv_spd(W[np.ix_(idx, idx)])
            else:
                Ka = K_full[np.ix_(idx, idx)]
            if not unilateral or idx.size == 0:
                break
            ce = dashpot(idx)
            f = np.zeros(n)
            f[idx] = -(Ka @ (q[idx] - a[idx])) - ce @ v[idx]
            fn = gsum(f)
            vn = vn_of(v)
            pull = (fn < 0.0) & (vn >= 0.0) & np.bincount(group, active, minlength=ng).astype(bool)
            if not pull.any():
                break
            active &= ~pull[group]
        if _seg == 0 and active.any():
            ia = np.flatnonzero(active)
            track(ia, Ka, (q[ia] - a[ia])[:, None])
        h = dt - t
        if h <= 1e-12 * dt:
            break
        idx = np.flatnonzero(active)
        free = np.flatnonzero(~active)
        if idx.size == 0:
            q[free] += h * v[free] + 0.5 * h * h * g[free]
            v[free] += h * g[free]
            t = dt
            break
        ma, ga, aa = m[idx], g[idx], a[idx]
        ce = dashpot(idx)
        q_eq = aa + _equilibrium(Ka, ma * ga)
        modal = _Modal(Ka, ma, ce)
        z0 = np.concatenate([q[idx] - q_eq, v[idx]])
        na = idx.size
        gi = group[idx]
        wi = wts[idx]
        # event functions on the group level, evaluated on times tau (columns)
        sw_on = np.zeros(ng, bool)
        sw_on[gi] = True

        switchable = sw_on & np.bincount(gi, (np.diag(Cn)[idx] > 0) & ~always[idx], minlength=ng).astype(bool)
        off_mask = (switchable & damp_g)[:, None]
        on_mask = (switchable & ~damp_g)[:, None]
        ident_a = ident and na == n
        off_eq = (q_eq - aa)[:, None]

        def gsum_a(x: np.ndarray) -> np.ndarray:
            if ident_a:
                return x
            out = np.zeros((ng, x.shape[1]))
            np.add.at(out, gi, wi[:, None] * x)
            return out

        def events(tau: np.ndarray):
            Z = modal.at(z0, tau)
            y, vv = Z[:na], Z[na:]
            vng = gsum_a(vv)
            fng = gsum_a(-(Ka @ (y + off_eq)) - ce @ vv)
            ev = np.zeros((ng, tau.size), bool)
            ev |= off_mask & (vng >= 0.0)  # maximum compression: dashpot off
            ev |= on_mask & (vng < 0.0)  # compresses again: dashpot on
            if unilateral:
                ev |= sw_on[:, None] & (fng < 0.0) & (vng >= 0.0)  # released
            return Z, ev

        lo, hi = 0.0, h
        tau = h * np.arange(1, _GRID + 1) / _GRID
        Z, ev = events(tau)
        anyev = ev.any(axis=0)
        if not anyev.any():
            t_e, ze, evg = h, Z[:, -1], None
            track(idx, Ka, Z[:na] + off_eq)
        else:
            j = int(np.argmax(anyev))
            lo, hi = (tau[j - 1] if j else 0.0), tau[j]
            ze, evg = Z[:, j], ev[:, j]
            track(idx, Ka, Z[:na, :j + 1] + off_eq)  # the states up to the event (after it: another pattern)
            for _ in range(_REFINE):
                tau = lo + (hi - lo) * np.arange(1, _GRID + 1) / _GRID
                Z, ev = events(tau)
                anyev = ev.any(axis=0)
                j = int(np.argmax(anyev))  # the bracket's right end has an event
                lo, hi = (tau[j - 1] if j else lo), tau[j]
                ze, evg = Z[:, j], ev[:, j]
                track(idx, Ka, Z[:na, :j + 1] + off_eq)
            t_e = hi
        # advance to t_e
        q[idx] = ze[:na] + q_eq
        v[idx] = ze[na:]
        if free.size:
            q[free] += t_e * v[free] + 0.5 * t_e * t_e * g[free]
            v[free] += t_e * g[free]
        t += t_e
        if evg is None:
            break
        vng = vn_of(v)
        ea = evg & sw_on
        f = np.zeros(n)
        f[idx] = -(Ka @ (q[idx] - aa)) - ce @ v[idx]
        fng = gsum(f)
        rel = ea & (fng < 0.0) & (vng >= 0.0) if unilateral else np.zeros(ng, bool)
        damp_g = np.where(ea & ~rel, vng < 0.0, damp_g)
        if rel.any():
            active &= ~rel[group]
    else:
        # too many events in one step: finish it with the pattern frozen (rare)
        h = dt - t
        if h > 0:
            idx = np.flatnonzero(active)
            free = np.flatnonzero(~active)
            if idx.size:
                # (the last segment may have released contacts: the capacitance of those left)
                Ka = _inv_spd(W[np.ix_(idx, idx)]) if W is not None and idx.size < n else K_full[np.ix_(idx, idx)]
                ce = dashpot(idx)
                q_eq = a[idx] + _equilibrium(Ka, m[idx] * g[idx])
                ze = _Modal(Ka, m[idx], ce).at(np.concatenate([q[idx] - q_eq, v[idx]]), np.array([h]))[:, 0]
                q[idx], v[idx] = ze[:idx.size] + q_eq, ze[idx.size:]
                track(idx, Ka, (q[idx] - a[idx])[:, None])
            q[free] += h * v[free] + 0.5 * h * h * g[free]
            v[free] += h * g[free]
    force = np.where(active, m * ((v - v0) / dt - g), 0.0)
    seat = np.zeros(n)
    idx = np.flatnonzero(active)
    if idx.size:
        if Ka.shape[0] != idx.size:  # released at the last event
            Ka = _inv_spd(W[np.ix_(idx, idx)]) if W is not None and idx.size < n else K_full[np.ix_(idx, idx)]
        seat[idx] = Ka @ (q[idx] - a[idx])
    untouched = ~np.isfinite(dmin)[group]
    dmin_u[untouched] = (q - a)[untouched]
    return ContactStep(q=q, v=v, active=active, force=force, seat_force=seat, peak_seat_force=pk_f,
                       peak_ubar=dmin_u)


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
