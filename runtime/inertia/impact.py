"""One stone's impact on the local pad, with the pad's mass and without: the dynamic peer.

A rigid frictionless ice sphere hits a :class:`~hailstorm.runtime.inertia.pad.Pad` on its
axis (:func:`simulate_impact`): Newmark's average acceleration (``beta = 1/4``,
``gamma = 1/2``; unconditionally stable, no numerical damping) on the pad's P1 mesh,
unilateral node-to-sphere contact solved exactly each step (the sphere's exact profile
``phi(r) = R - sqrt(R^2 - r^2)`` at the nodes' undeformed radii; active set on the Schur
complement of the step's effective stiffness, the sphere's own Newmark equation included),
no mass on the contact nodes' normal dofs (:func:`~hailstorm.runtime.inertia.pad.without_contact_mass`).
*Dynamic*: the pad with its mass, so elastic waves carry energy away from the contact;
*quasi-static*: the same pad without mass (its static response: the Green's-function
assumption). No gravity: the difference is the pad's inertia alone.

:mod:`studies.dynamic_study` holds it to Hertz's impact and to the storm, and
charts where the two agree; :mod:`hailstorm.runtime.inertia.factors` runs it for every
impact of a storm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hailstorm.runtime.contact.hertz import HertzImpact, hertz_impact
from hailstorm.runtime.inertia.pad import Pad, PadMesh, contact_lcp, pad_mesh, without_contact_mass

__all__ = ["CELLS_PER_RADIUS", "ICE_DENSITY", "MIN_CELLS_PER_RADIUS", "MIN_STEPS_PER_CONTACT", "PAD_RADIUS",
           "STEPS_PER_CONTACT", "ImpactResult", "PeerResolutionError", "check_density", "hertz_estimate",
           "impact_inertia", "impact_mesh", "simulate_impact"]

#: ice density [kg/m^3] (the default scene's ``[hail] density``)
ICE_DENSITY = 917.0
#: the least steps per contact duration and cells per contact radius a run accepts
MIN_STEPS_PER_CONTACT, MIN_CELLS_PER_RADIUS = 20, 4.0


#: the local pad's radius [m]: about the half-width of a saddle's rear (at least 4 thicknesses)
PAD_RADIUS = 0.06
#: the default resolution of the local pad (cells per Hertz contact radius, steps per Hertz contact time)
CELLS_PER_RADIUS, STEPS_PER_CONTACT = 8.0, 100


class PeerResolutionError(ValueError):
    """A peer run asked on a mesh or a time step too coarse for its impact (the message has the numbers)."""


def check_density(name: str, value: float) -> float:
    """``value`` as a float, or ValueError naming ``name`` unless it is finite and positive [kg/m^3]."""
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{name} density must be positive, got {value!r} kg/m^3")
    return v


def hertz_estimate(pad: Pad, radius: float, speed: float, ice_density: float = ICE_DENSITY) -> HertzImpact:
    """Hertz's quasi-static impact of the stone on a half-space of the pad's material (no gravity)."""
    m = check_density("ice", ice_density) * 4.0 / 3.0 * math.pi * radius**3
    return hertz_impact(m, speed, radius, pad.young, pad.poisson)


@dataclass
class ImpactResult:
    """One impact of the peer (:func:`simulate_impact`).

    Attributes
    ----------
    dynamic : bool
        The pad had its mass (False: quasi-static).
    speed : float
        Impact speed [m/s].
    peak_force : float
        [N]
    duration : float
        First touch (t = 0) to the last release [s] (the release located inside its step by
        Hertz's law from the last two touching steps).
    rebound_speed : float
        The sphere's speed away from the pad after the contact [m/s].
    max_dent : float
        Largest downward displacement of the pad's top at the impact point [m].
    max_contact_radius : float
        Largest radius of the touching nodes [m].
    dt : float
    steps : int
    history : (k, 4) ndarray
        Per step: time [s], contact force [N], sphere penetration x [m], dent at the axis [m].
    modes : int or None
        The pad's dynamics cut to this many modes (:mod:`studies.pad_modes`); None: all.
    """

    dynamic: bool
    speed: float
    peak_force: float
    duration: float
    rebound_speed: float
    max_dent: float
    max_contact_radius: float
    dt: float
    steps: int
    history: np.ndarray = field(repr=False)
    modes: int | None = None

    @property
    def restitution(self) -> float:
        """Rebound over impact speed."""
        return self.rebound_speed / self.speed


def _check_resolution(cell: float, a: float, dt: float, duration: float, what: str) -> None:
    if cell > a / MIN_CELLS_PER_RADIUS:
        raise PeerResolutionError(
            f"the peer's mesh is too coarse for this impact ({what}): cells of {cell * 1e3:.3g} mm under a contact "
            f"radius of {a * 1e3:.3g} mm ({a / cell:.3g} cells per radius; at least {MIN_CELLS_PER_RADIUS:g}, "
            f"cells <= {a / MIN_CELLS_PER_RADIUS * 1e3:.3g} mm)")
    if dt > duration / MIN_STEPS_PER_CONTACT:
        raise PeerResolutionError(
            f"the peer's time step is too coarse for this impact ({what}): dt = {dt:.3g} s over a contact of "
            f"{duration:.3g} s ({duration / dt:.3g} steps; at least {MIN_STEPS_PER_CONTACT}, dt <= "
            f"{duration / MIN_STEPS_PER_CONTACT:.3g} s)")


def _release_lag(before: float, last: float, dt: float) -> float:
    """The release's time after the last touching step: ``F^(2/3)`` (Hertz's law, linear in the
    approach near release) carried linearly from the last two touching steps to zero, within one
    step (half a step where the force did not fall). A continuous measure of the contact time,
    where the last touching step alone would move it by a step between two nearby impacts."""
    g0, g1 = before ** (2.0 / 3.0), last ** (2.0 / 3.0)
    if not g0 > g1:
        return 0.5 * dt
    return min(dt, dt * g1 / (g0 - g1))


def simulate_impact(mesh: PadMesh, radius: float, speed: float, *, dynamic: bool = True, dt: float | None = None,
                    steps_per_contact: int = 200, ice_density: float = ICE_DENSITY,
                    beta: float = 0.25, gamma: float = 0.5, modes: Any = None) -> ImpactResult:
    """A rigid ice sphere hitting the pad at ``speed`` along its axis (Newmark, unilateral contact).

    Parameters
    ----------
    mesh : PadMesh
    radius : float
        Sphere radius R [m].
    speed : float
        Impact speed [m/s] (> 0).
    dynamic : bool
        With the pad's mass (False: the quasi-static pad, massless).
    dt : float, optional
        Time step [s] (default: Hertz's contact duration over ``steps_per_contact``).
    steps_per_contact : int
    ice_density : float
        [kg/m^3] (> 0).
    beta, gamma : float
        Newmark's parameters (default: average acceleration).
    modes : object, optional
        The pad's dynamics in these modes only, the rest quasi-static (the mode-acceleration
        form; the same Newmark rule per mode: with every mode of the massless-contact pad it
        is the full peer). Needs ``dynamic``. Any object with ``shapes`` (free dofs x k,
        mass-normalised), ``omega2`` (k,) [1/s^2] and ``count``, such as
        :class:`studies.pad_modes.PadModes`.

    Returns
    -------
    ImpactResult

    Raises
    ------
    ValueError
        Non-positive density, radius or speed.
    PeerResolutionError
        Fewer than :data:`MIN_STEPS_PER_CONTACT` steps per contact duration or fewer
        than :data:`MIN_CELLS_PER_RADIUS` cells per contact radius (Hertz's estimates
        before the run, the measured ones after).
    """
    rho_ice = check_density("ice", ice_density)
    if not (radius > 0 and speed > 0):
        raise ValueError(f"the sphere needs radius > 0 and speed > 0, got {radius!r}, {speed!r}")
    pad = mesh.pad
    m = rho_ice * 4.0 / 3.0 * math.pi * radius**3
    ref = hertz_impact(m, speed, radius, pad.young, pad.poisson)
    a_ref = math.sqrt(radius * ref.max_depth)
    dt = ref.duration / steps_per_contact if dt is None else float(dt)
    _check_resolution(mesh.cell, a_ref, dt, ref.duration, "Hertz's estimate")
    cand = np.flatnonzero(mesh.top_r < 0.999 * radius)
    r_c = mesh.top_r[cand]
    phi = radius - np.sqrt(radius**2 - r_c**2)
    C = mesh.top_uz[cand]  # u_z dofs of the candidate nodes (indices into the free dofs)
    if modes is not None and not dynamic:
        raise ValueError("simulate_impact: modes need dynamic=True")
    body = _PadResponse(mesh, C, dt, dynamic=dynamic, modes=modes, beta=beta, gamma=gamma)
    c = beta * dt * dt / m
    S = body.S_pad + c  # ... + c 1 1^T: the sphere's own Newmark equation
    x, xv, xa = 0.0, float(speed), 0.0
    active = np.zeros(C.size, dtype=bool)
    centre = mesh.top_uz[0]
    hist, t, last_touch, max_r = [], 0.0, -1.0, 0.0
    F_prev, release = 0.0, (0.0, 0.0)  # the force one step back; the last two forces of the last touch
    t_end = 4.0 * ref.duration
    while t < t_end:
        t += dt
        x_hat = x + dt * xv + (0.5 - beta) * dt * dt * xa
        u_free_C = body.free()
        q = phi - x_hat - u_free_C
        lam, active = contact_lcp(S, q, active)
        F = float(lam.sum())
        x_new = x_hat - c * F
        xa_new = -F / m
        body.respond(lam, centre)
        xv = xv + dt * ((1 - gamma) * xa + gamma * xa_new)
        x, xa = x_new, xa_new
        hist.append((t, F, x, -body.u[centre]))
        if F > 0:
            last_touch, release = t, (F_prev, F)
            max_r = max(max_r, float(r_c[lam > 0].max()))
        elif last_touch > 0 and t > last_touch + 0.5 * ref.duration and xv < 0:
            break  # released, moving away, and no touch for half a contact time
        if t >= t_end and last_touch > t - 0.5 * ref.duration:
            t_end += ref.duration  # still touching: go on
        F_prev = F
    H = np.array(hist)
    duration = last_touch + _release_lag(*release, dt) if last_touch > 0 else 0.0
    res = ImpactResult(dynamic=dynamic, speed=float(speed), peak_force=float(H[:, 1].max()), duration=duration,
                       rebound_speed=float(-xv), max_dent=float(H[:, 3].max()), max_contact_radius=max_r, dt=dt,
                       steps=len(hist), history=H, modes=modes.count if body.modal else None)
    _check_resolution(mesh.cell, max_r if max_r > 0 else a_ref, dt, max(duration, dt), "as measured")
    return res


class _PadResponse:
    """The pad's side of :func:`simulate_impact`'s Newmark step at the candidate contact dofs ``C``.

    One of three forms: every dof with its mass (``dynamic`` without ``modes``; no mass on ``C``,
    :func:`~hailstorm.runtime.inertia.pad.without_contact_mass`), the retained ``modes`` over the
    static response (the mode-acceleration form), or the static response alone
    (``dynamic=False``). Each step, :meth:`free` predicts the displacement of ``C`` without
    contact forces, then :meth:`respond` takes the step's forces and advances the state.

    Parameters
    ----------
    mesh : PadMesh
    C : (k,) int ndarray
        The candidate nodes' ``u_z`` dofs (indices into the free dofs).
    dt : float
        Time step [s].
    dynamic : bool
    modes : object or None
        As :func:`simulate_impact`'s.
    beta, gamma : float
        Newmark's parameters.

    Attributes
    ----------
    S_pad : (k, k) ndarray
        The step's compliance of ``C``: the displacement of ``C`` per unit forces on ``C`` within
        a step (``C K_eff^-1 C^T``, less the retained modes' lagging share in the modal form).
    u : (n,) ndarray
        The pad's displacement on the free dofs (in the modal form only the axis dof is kept).
    modal, full : bool
        The modal form; Newmark on every dof.
    """

    def __init__(self, mesh: PadMesh, C: np.ndarray, dt: float, *, dynamic: bool, modes: Any, beta: float,
                 gamma: float) -> None:
        from scipy.sparse.linalg import splu

        self.C, self.dt, self.beta, self.gamma = C, dt, beta, gamma
        self.modal = modal = modes is not None
        self.full = full = dynamic and not modal  # Newmark on every dof
        M = without_contact_mass(mesh.M, C) if full else None
        K_eff = mesh.K + M / (beta * dt * dt) if full else mesh.K
        # symmetric: a minimum-degree order of A^T + A (a third fewer factor entries than COLAMD's here)
        self.lu = splu(K_eff.tocsc(), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
        self.M = M
        n = K_eff.shape[0]
        E = np.zeros((n, C.size))
        E[C, np.arange(C.size)] = 1.0
        self.G = self.lu.solve(E)  # K_eff^-1 C^T
        S_pad = self.G[C]  # C K_eff^-1 C^T
        if modal:  # the retained modes' share of the static compliance, as far as a step lets them move
            self.PC, self.w2 = modes.shapes[C], modes.omega2
            self.lag = 1.0 / (1.0 + beta * dt * dt * self.w2)
            S_pad = S_pad - (self.PC * (self.lag / self.w2)) @ self.PC.T
            self.eta, self.eta_v, self.eta_a = np.zeros(self.w2.size), np.zeros(self.w2.size), np.zeros(self.w2.size)
        self.S_pad = S_pad
        self.u, self.v, self.acc = np.zeros(n), np.zeros(n), np.zeros(n)

    def free(self) -> np.ndarray:
        """The predicted displacement of ``C`` at the end of the next step without contact forces (k,) [m]."""
        dt, beta = self.dt, self.beta
        if self.full:
            self.u_hat = self.u + dt * self.v + (0.5 - beta) * dt * dt * self.acc
            self.u_free = self.lu.solve(self.M @ self.u_hat) / (beta * dt * dt)
            self.u_free_C = self.u_free[self.C]
        elif self.modal:
            self.eta_hat = self.eta + dt * self.eta_v + (0.5 - beta) * dt * dt * self.eta_a
            self.u_free_C = self.PC @ (self.eta_hat * self.lag)
        else:
            self.u_free_C = np.zeros(self.C.size)
        return self.u_free_C

    def respond(self, lam: np.ndarray, centre: int) -> None:
        """End the step :meth:`free` began under the contact forces ``lam`` (k,) [N] on ``C``: the
        new displacement ``u`` (in the modal form, at the axis dof ``centre`` alone, the first
        candidate's) and the dynamic state."""
        dt, beta, gamma = self.dt, self.beta, self.gamma
        if self.modal:  # the contact nodes alone: the dent at the axis is the first candidate's
            f_m = -(self.PC.T @ lam)
            eta_new = (self.eta_hat + beta * dt * dt * f_m) * self.lag
            eta_a_new = f_m - self.w2 * eta_new
            self.eta_v = self.eta_v + dt * ((1 - gamma) * self.eta_a + gamma * eta_a_new)
            self.eta, self.eta_a = eta_new, eta_a_new
            self.u[centre] = self.u_free_C[0] - self.S_pad[0] @ lam
        else:
            u_new = (self.u_free if self.full else 0.0) - self.G @ lam
            if self.full:
                acc_new = (u_new - self.u_hat) / (beta * dt * dt)
                self.v = self.v + dt * ((1 - gamma) * self.acc + gamma * acc_new)
                self.acc = acc_new
            self.u = u_new


def impact_mesh(pad: Pad, radius: float, speed: float, cells_per_radius: float = 8.0,
                ice_density: float = ICE_DENSITY) -> PadMesh:
    """The peer's mesh for one impact: fine cells of Hertz's contact radius over ``cells_per_radius``
    within 1.5 contact radii of the impact (growing by 1.15 beyond)."""
    a = math.sqrt(radius * hertz_estimate(pad, radius, speed, ice_density).max_depth)
    return pad_mesh(pad, cell=a / cells_per_radius, extent=1.5 * a)


def impact_inertia(radius: float, mass: float, speed: float, thickness: float, young: float, poisson: float,
                   density: float, *, pad_radius: float = PAD_RADIUS, cells_per_radius: float = CELLS_PER_RADIUS,
                   steps_per_contact: int = STEPS_PER_CONTACT) -> tuple[float, float, float, float]:
    """One impact's inertia factors (module docstring): peak force, contact time, rebound
    speed and largest dent of the dynamic peer over the quasi-static one.

    Parameters
    ----------
    radius, mass : float
        The stone [m], [kg] (> 0).
    speed : float
        Its normal speed at onset [m/s] (> 0).
    thickness : float
        The local pad's thickness [m] (> 0).
    young, poisson : float
        The pad's material [Pa], [-].
    density : float
        The pad foam's density [kg/m^3] (> 0).
    pad_radius : float
        The local pad's radius [m] (raised to 4 thicknesses).
    cells_per_radius, steps_per_contact
        The peer's resolution (doubled, up to twice, where the measured contact is narrower
        than the peer accepts).

    Returns
    -------
    tuple of float
        (force, duration, restitution, dent) factors.
    """
    if not (radius > 0 and mass > 0 and speed > 0 and thickness > 0):
        raise ValueError(f"impact_inertia needs radius, mass, speed and thickness > 0, got {radius!r}, {mass!r}, "
                         f"{speed!r}, {thickness!r}")
    stone = check_density("stone", mass / (4.0 / 3.0 * math.pi * radius**3))
    pad = Pad(young=float(young), poisson=float(poisson), density=check_density("pad", density),
              thickness=float(thickness), radius=max(float(pad_radius), 4.0 * float(thickness)))
    cells = float(cells_per_radius)
    for attempt in range(3):
        mesh = impact_mesh(pad, radius, speed, cells, stone)
        try:
            dyn = simulate_impact(mesh, radius, speed, dynamic=True, steps_per_contact=steps_per_contact,
                                  ice_density=stone)
            qs = simulate_impact(mesh, radius, speed, dynamic=False, steps_per_contact=steps_per_contact,
                                 ice_density=stone)
        except PeerResolutionError:
            if attempt == 2:
                raise
            cells *= 2.0
            continue
        return (dyn.peak_force / qs.peak_force, dyn.duration / qs.duration, dyn.rebound_speed / qs.rebound_speed,
                dyn.max_dent / qs.max_dent)
    raise AssertionError("unreachable")
