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

__all__ = ["GAP_TOL", "RELEASE_BISECTIONS", "FoamImpact", "strike"]

#: the contact's tolerance per step: every touching node's gap within this share of the largest approach so far
GAP_TOL = 1e-5
#: the release is located within the step that opened the contact by this many halvings of the step
RELEASE_BISECTIONS = 10


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
        ``t = 0`` to the last release [s]: located within the step that opened the contact by
        :data:`RELEASE_BISECTIONS` halvings of that step (re-solved from its start), so that it is
        the discrete trajectory's, not a step's multiple.
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


class _Stepper:
    """One Newmark step of the pad and the sphere (module notes); the state is ``(x, v, a)`` with ``x = [u, d]``."""

    def __init__(self, model: PadModel, radius: float, mass: float, density: float | None, gap_tol: float,
                 max_uzawa: int, energy_scale: float) -> None:
        import scipy.sparse as sp

        self.model, self.radius, self.gap_tol, self.max_uzawa = model, radius, gap_tol, max_uzawa
        self.n = n = model.ndofs
        M = model.mass(density).tolil()
        under = model.top[model.top_r < radius]
        for dof in np.concatenate([2 * under, 2 * under + 1]):  # no inertia on the contact nodes (module notes)
            M[dof, :] = 0.0
            M[:, dof] = 0.0
        self.M = M.tocsr()
        self.Mx = sp.block_diag([self.M, sp.csr_matrix([[mass]])], format="csr")
        self.free = np.append(model.free, n)
        E0, h = model.pad.foam.young, model.pad.thickness
        self.eps = PENALTY * E0 * model.top_area / model.cell
        self.force_tol, self.step_tol, self.energy_scale = FORCE_TOL * E0 * h * h, STEP_TOL * h, energy_scale

    def energy(self, x: np.ndarray, v: np.ndarray) -> float:
        """Strain plus kinetic energy of the pad and the sphere [J]."""
        return self.model.energy(x[: self.n]) + 0.5 * float(v @ (self.Mx @ v))

    def step(self, x: np.ndarray, v: np.ndarray, a: np.ndarray, lam: np.ndarray, dt: float, d_top: float
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, SphereContact, np.ndarray, int, int]:
        """The state after ``dt`` from ``(x, v, a)``; the last pass's contact term (its force is the one in
        equilibrium with the pad) and the updated multipliers; Newton iterations and Uzawa updates."""
        import scipy.sparse as sp

        model, n, Mx = self.model, self.n, self.Mx
        c_dt = 4.0 / (dt * dt)
        x_hat = x + dt * v + 0.25 * dt * dt * a
        guess = x_hat if np.isfinite(model.energy(x_hat[:n])) else x.copy()
        newton = 0
        for k in range(1, self.max_uzawa + 1):
            c = SphereContact(model, self.radius, lam, self.eps, sphere_dof=n)

            def value(y: np.ndarray, c: SphereContact = c) -> float:
                dy = y - x_hat
                return model.energy(y[:n]) + 0.5 * c_dt * float(dy @ (Mx @ dy)) + c.value(y)

            def grad_hess(y: np.ndarray, c: SphereContact = c) -> tuple[np.ndarray, object]:
                r, K = model.tangent(y[:n])
                g = np.append(r, 0.0) + c_dt * (Mx @ (y - x_hat))
                K = sp.block_diag([K, sp.csr_matrix((1, 1))], format="csr") + c_dt * Mx
                return c.add(y, g, K)

            guess, stats = minimise(value, grad_hess, guess, self.free, force_tol=self.force_tol,
                                    step_tol=self.step_tol, energy_scale=self.energy_scale)
            newton += stats.iterations
            gap, _, _, tn = c.state(guess)
            lam = tn
            scale = self.gap_tol * max(d_top, float(guess[n]), 1e-6 * model.pad.thickness)
            if float(np.abs(gap[tn > 0]).max(initial=0.0)) <= scale:
                break
        else:
            raise RuntimeError(f"strike: the contact's multipliers did not converge in {self.max_uzawa} updates")
        a_new = c_dt * (guess - x_hat)
        return guess, v + 0.5 * dt * (a + a_new), a_new, c, lam, newton, k


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
    for name, value in (("radius", radius), ("mass", mass), ("speed", speed), ("dt", dt)):
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"strike needs a positive {name}, got {value!r}")
    n = model.ndofs
    kinetic0 = 0.5 * mass * speed**2
    stepper = _Stepper(model, radius, mass, density, gap_tol, max_uzawa, kinetic0)
    rho = model.pad.foam.density if density is None else float(density)
    lam = np.zeros(model.top.size)
    x, v, a = np.zeros(n + 1), np.zeros(n + 1), np.zeros(n + 1)
    v[n] = speed
    hist = [(0.0, 0.0, 0.0, 0.0, 0.0)]
    drift, d_top, newton, uzawa = 0.0, 0.0, 0, 0
    released_at, release = None, None
    for step in range(1, max_steps + 1):
        t = step * dt
        prev = (x, v, a, lam)
        x, v, a, c, lam, it, k = stepper.step(x, v, a, lam, dt, d_top)
        newton, uzawa = newton + it, uzawa + k
        force = c.force(x)
        d_top = max(d_top, float(x[n]))
        r_c = float(model.top_r[lam > 0].max(initial=0.0))
        hist.append((t, force, float(x[n]), float(-x[2 * model.top[0] + 1]), r_c))
        drift = max(drift, abs(stepper.energy(x, v) - kinetic0))
        if force > 0:
            released_at = None
        elif hist[-2][1] > 0:  # released in this step: locate it by bisecting the step's length
            lo, hi = 0.0, dt
            for _ in range(RELEASE_BISECTIONS):
                mid = 0.5 * (lo + hi)
                xs, _, _, cs, _, it, k = stepper.step(*prev, mid, d_top)
                newton, uzawa = newton + it, uzawa + k
                lo, hi = (mid, hi) if cs.force(xs) > 0 else (lo, mid)
            release = t - dt + 0.5 * (lo + hi)
            released_at = t
        if released_at is not None and v[n] < 0 and t - released_at >= 0.1 * release:
            break  # away, and no touch for a tenth of the contact
    else:
        raise RuntimeError(f"strike: no release within {max_steps} steps of {dt:.3g} s")
    H = np.array(hist)
    pad_energy = model.energy(x[:n]) + 0.5 * float(v[:n] @ (stepper.M @ v[:n]))
    return FoamImpact(speed=float(speed), mass=float(mass), radius=float(radius), density=rho, dt=float(dt),
                      peak_force=_peak(H[:, 0], H[:, 1]), contact_time=float(release),
                      rebound_speed=float(-v[n]), max_approach=float(H[:, 2].max()), max_dent=float(H[:, 3].max()),
                      max_contact_radius=float(H[:, 4].max()), pad_energy=float(pad_energy), energy_drift=float(drift),
                      steps=len(hist) - 1, newton=newton, uzawa=uzawa, history=H)
