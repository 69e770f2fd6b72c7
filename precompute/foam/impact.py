"""A rigid sphere striking the foam pad: the pad's mass, implicit Newmark, Newton per step.

A sphere of radius ``R`` and mass ``m`` touches the pad's top on the axis at ``t = 0`` with speed
``v`` (no gravity). The state is the pad's displacement ``u`` and the sphere's approach ``d``
(:class:`~hailstorm.precompute.foam.contact.SphereContact` with the approach as an unknown).
Newmark's average acceleration (``beta = 1/4``, ``gamma = 1/2``: implicit, unconditionally
stable for linear systems, no numerical damping) makes each step the minimisation of the
incremental potential

    ``E(u) + 2/dt^2 (u - u^)^T M (u - u^) + 2 m/dt^2 (d - d^)^2 + contact``,

``u^ = u_n + dt v_n + dt^2/4 a_n`` (and ``d^`` alike), whose stationarity is
``M a_{n+1} + f_int(u_{n+1}) + f_c = 0``, ``m d''_{n+1} = -F``. Each step is solved by Newton
with the energy line search (:func:`~hailstorm.precompute.foam.newton.minimise`) inside Uzawa
updates of the contact's multipliers (warm-started from the last step), until every touching
node's gap is within ``gap_tol`` of the largest approach so far, both ways (no penetration, no
force across an open gap).

``M`` is the pad's consistent mass (:meth:`~hailstorm.precompute.foam.pad.PadModel.mass`) without
the rows and columns of the top nodes under the sphere (``r < R``): Khenous, Laborde & Renard
(Eur. J. Mech. A/Solids 27 (2008) 918) -- with inertia on the contact nodes the semi-discrete
problem is ill-posed and Newmark creates or destroys energy at each node's touch and release
(the project's linear peer, :func:`hailstorm.runtime.inertia.pad.without_contact_mass`, does the
same). The mass removed is that of the top cells under the sphere.

* :func:`strike` -> :class:`FoamImpact` -- the force history, peak force, contact time,
  rebound speed, dent and the energy account.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from hailstorm.precompute.foam.contact import SphereContact
from hailstorm.precompute.foam.indent import FORCE_TOL, PENALTY, STEP_TOL
from hailstorm.precompute.foam.newton import minimise
from hailstorm.precompute.foam.pad import PadModel

__all__ = ["GAP_TOL", "FoamImpact", "strike"]

#: the contact's tolerance per step: every touching node's gap within this share of the largest approach so far
GAP_TOL = 1e-5


@dataclass
class FoamImpact:
    """One impact on the foam pad (:func:`strike`).

    Attributes
    ----------
    speed, mass, radius : float
        The sphere at impact [m/s], [kg], [m].
    density : float
        The pad's density in the run [kg/m^3] (0: the massless, quasi-static pad).
    dt : float
        [s]
    peak_force : float
        The largest contact force [N] (the parabola through the largest step and its neighbours).
    contact_time : float
        ``t = 0`` to release [s]: the release located in its step by Hertz's law near release
        (``F^(2/3)`` linear in time, carried from the last two touching steps).
    rebound_speed : float
        The sphere's speed away from the pad once released [m/s].
    max_approach : float
        [m]
    max_dent : float
        Largest downward displacement of the top at the axis [m].
    max_contact_radius : float
        Largest undeformed radius of a touching node [m].
    pad_energy : float
        The pad's strain plus kinetic energy at the end [J]: its residual vibration.
    energy_drift : float
        The largest ``|E_total(t) - m v^2 / 2|`` over the run [J] (strain, pad and sphere kinetic;
        zero for an exact integrator, the scheme's and the contact tolerance's error otherwise).
    steps, newton, uzawa : int
        Time steps, Newton iterations and multiplier updates over the run.
    history : (k, 5) ndarray
        Per step: time [s], force [N], approach [m], dent at the axis [m], contact radius [m].
    """

    speed: float
    mass: float
    radius: float
    density: float
    dt: float
    peak_force: float
    contact_time: float
    rebound_speed: float
    max_approach: float
    max_dent: float
    max_contact_radius: float
    pad_energy: float
    energy_drift: float
    steps: int
    newton: int
    uzawa: int
    history: np.ndarray = field(repr=False)

    @property
    def restitution(self) -> float:
        """Rebound over impact speed."""
        return self.rebound_speed / self.speed


def _peak(t: np.ndarray, f: np.ndarray) -> float:
    """The largest value of ``f`` from the parabola through its largest sample and neighbours."""
    k = int(np.argmax(f))
    if k == 0 or k == f.size - 1:
        return float(f[k])
    f0, f1, f2 = f[k - 1], f[k], f[k + 1]
    den = f0 - 2.0 * f1 + f2
    if not den < 0:
        return float(f1)
    return float(f1 - 0.125 * (f2 - f0) ** 2 / den)


def _release(t_last: float, before: float, last: float, dt: float) -> float:
    """The release's time: ``F^(2/3)`` carried linearly from the last two touching steps to zero (within a step)."""
    g0, g1 = before ** (2.0 / 3.0), last ** (2.0 / 3.0)
    if not g0 > g1:
        return t_last + 0.5 * dt
    return t_last + min(dt, dt * g1 / (g0 - g1))


def strike(model: PadModel, radius: float, mass: float, speed: float, dt: float, *, density: float | None = None,
           gap_tol: float = GAP_TOL, max_uzawa: int = 30, max_steps: int = 100_000) -> FoamImpact:
    """The sphere striking the pad on its axis (module notes).

    Parameters
    ----------
    model : PadModel
    radius, mass, speed : float
        The sphere [m], [kg] and its speed at touch [m/s] (> 0).
    dt : float
        Time step [s] (> 0): about a hundredth of the contact time is a good start.
    density : float, optional
        The pad's density [kg/m^3] (>= 0; default its foam's; 0: the massless pad).
    gap_tol : float
        The contact's tolerance (module notes).
    max_uzawa : int
        Multiplier updates allowed per step.
    max_steps : int
        Steps allowed before release.

    Returns
    -------
    FoamImpact

    Raises
    ------
    ValueError
        Non-positive radius, mass, speed or time step.
    hailstorm.precompute.foam.newton.NewtonError
        A step's Newton solve did not converge (e.g. the sphere crushing the pad through to its base).
    RuntimeError
        The multipliers did not converge, or no release within ``max_steps``.
    """
    import scipy.sparse as sp

    for name, value in (("radius", radius), ("mass", mass), ("speed", speed), ("dt", dt)):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"strike needs a positive {name}, got {value!r}")
    n, h = model.ndofs, model.pad.thickness
    E0 = model.pad.foam.young
    M = model.mass(density).tolil()
    under = model.top[model.top_r < radius]
    for dof in np.concatenate([2 * under, 2 * under + 1]):  # no inertia on the contact nodes (module notes)
        M[dof, :] = 0.0
        M[:, dof] = 0.0
    M = M.tocsr()
    rho = model.pad.foam.density if density is None else float(density)
    k_dof = n
    free = np.append(model.free, k_dof)
    eps = PENALTY * E0 * model.top_area / model.cell
    lam = np.zeros(model.top.size)
    c_dt = 4.0 / (dt * dt)
    x, v, a = np.zeros(n + 1), np.zeros(n + 1), np.zeros(n + 1)
    v[k_dof] = speed
    kinetic0 = 0.5 * mass * speed**2
    hist = [(0.0, 0.0, 0.0, 0.0, 0.0)]
    drift, d_top, newton, uzawa = 0.0, 0.0, 0, 0
    t, released_at, last_touch, before_last = 0.0, None, None, (0.0, 0.0)
    Mx = sp.block_diag([M, sp.csr_matrix([[mass]])], format="csr")
    for step in range(1, max_steps + 1):
        t = step * dt
        x_hat = x + dt * v + 0.25 * dt * dt * a
        guess = x_hat if np.isfinite(model.energy(x_hat[:n])) else x.copy()

        for k in range(1, max_uzawa + 1):
            c = SphereContact(model, radius, lam, eps, sphere_dof=k_dof)

            def value(y: np.ndarray, c: SphereContact = c, x_hat: np.ndarray = x_hat) -> float:
                e = model.energy(y[:n])
                dy = y - x_hat
                return e + 0.5 * c_dt * float(dy @ (Mx @ dy)) + c.value(y)

            def grad_hess(y: np.ndarray, c: SphereContact = c, x_hat: np.ndarray = x_hat) -> tuple[np.ndarray, object]:
                r, K = model.tangent(y[:n])
                g = np.append(r, 0.0) + c_dt * (Mx @ (y - x_hat))
                K = sp.block_diag([K, sp.csr_matrix((1, 1))], format="csr") + c_dt * Mx
                return c.add(y, g, K)

            guess, stats = minimise(value, grad_hess, guess, free, force_tol=FORCE_TOL * E0 * h * h,
                                    step_tol=STEP_TOL * h, energy_scale=kinetic0)
            newton += stats.iterations
            gap, _, _, tn = c.state(guess)
            lam = tn
            scale = gap_tol * max(d_top, float(guess[k_dof]), 1e-6 * h)
            if float(np.abs(gap[tn > 0]).max(initial=0.0)) <= scale:
                break
        else:
            raise RuntimeError(f"strike: the contact's multipliers did not converge in {max_uzawa} updates at "
                               f"t = {t:.4g} s")
        uzawa += k
        a_new = c_dt * (guess - x_hat)
        v = v + 0.5 * dt * (a + a_new)
        x, a = guess, a_new
        force = c.force(x)
        d_top = max(d_top, float(x[k_dof]))
        touching = tn > 0
        r_c = float(model.top_r[touching].max(initial=0.0))
        hist.append((t, force, float(x[k_dof]), float(-x[2 * model.top[0] + 1]), r_c))
        total = model.energy(x[:n]) + 0.5 * float(v @ (Mx @ v))
        drift = max(drift, abs(total - kinetic0))
        if force > 0:
            before_last, last_touch = (hist[-2][1], force), t
            released_at = None
        elif last_touch is not None and v[k_dof] < 0:
            if released_at is None:
                released_at = t
            if t - released_at >= 0.1 * last_touch:  # away, and no touch for a tenth of the contact
                break
    else:
        raise RuntimeError(f"strike: no release within {max_steps} steps of {dt:.3g} s")
    H = np.array(hist)
    pad_energy = model.energy(x[:n]) + 0.5 * float(v[:n] @ (M @ v[:n]))
    return FoamImpact(speed=float(speed), mass=float(mass), radius=float(radius), density=rho, dt=float(dt),
                      peak_force=_peak(H[:, 0], H[:, 1]), contact_time=_release(last_touch, *before_last, dt),
                      rebound_speed=float(-v[k_dof]), max_approach=float(H[:, 2].max()), max_dent=float(H[:, 3].max()),
                      max_contact_radius=float(H[:, 4].max()), pad_energy=float(pad_energy), energy_drift=float(drift),
                      steps=len(hist) - 1, newton=newton, uzawa=uzawa, history=H)
