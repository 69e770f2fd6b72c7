"""Hail physics: size distribution, restitution model, contact integrators, a drop.

The seat is replaced by a synthetic flat plate (Boussinesq-like compliance) so
the tests run in well under a second each and do not need a bundle.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import plate_gf

from hailstorm.runtime.storm.hail import (
    GRAVITY,
    SizeDistribution,
    contact_step,
    damping_ratio_for_restitution,
    drag_acceleration,
    restitution_for_damping_ratio,
    stone_mass,
    terminal_velocity,
)


def test_plate_compliance_is_spd():
    gf = plate_gf()
    c = gf.contact_vertices
    Dcc = gf.compliance(c, c)
    assert np.allclose(Dcc, Dcc.T)
    assert np.linalg.eigvalsh(Dcc).min() > 0


def test_size_distribution_bounds_and_reproducible():
    d = SizeDistribution("exponential", 0.0025, 0.0125, 0.002)
    r1 = d.sample(np.random.default_rng(3), 5000)
    r2 = d.sample(np.random.default_rng(3), 5000)
    assert np.array_equal(r1, r2)
    assert r1.min() >= 0.0025 and r1.max() <= 0.0125
    assert abs(r1.mean() - d.mean()) < 1e-4
    assert np.median(r1) < 0.5 * (0.0025 + 0.0125)  # skewed to small stones
    with pytest.raises(ValueError):
        SizeDistribution("lognormal")
    with pytest.raises(ValueError):
        SizeDistribution("uniform", 0.01, 0.005)


def test_terminal_velocity_balances_drag():
    r = np.array([0.0025, 0.005, 0.0125])
    vt = terminal_velocity(r)
    assert 8 < vt[0] < 10 and 19 < vt[2] < 22  # ~9 m/s for 5 mm hail, ~20 m/s for 25 mm
    a = drag_acceleration(np.column_stack([0 * r, 0 * r, -vt]), r)
    assert np.allclose(a[:, 2], GRAVITY)
    assert np.isclose(stone_mass(0.005), 917 * 4 / 3 * np.pi * 0.005**3)


@pytest.mark.parametrize("e", [0.1, 0.5, 0.9])
def test_restitution_damping_round_trip(e):
    z = damping_ratio_for_restitution(e)
    assert np.isclose(restitution_for_damping_ratio(z), e, atol=1e-8)


def _bounce(e: float, integrator: str, omega_dt: float, k: float = 1e4, m: float = 1e-3, v0: float = 1.0) -> float:
    """Exit speed of one unilateral spring-dashpot impact (no gravity)."""
    from hailstorm.runtime.storm.hail import damping_coefficients

    omega = np.sqrt(k / m)
    dt = omega_dt / omega
    K = np.array([[k]])
    C = damping_coefficients(K, np.array([m]), e, dt=dt, integrator=integrator)
    q, v = np.zeros(1), np.array([-v0])
    for _ in range(10000):
        res = contact_step(q, v, np.zeros(1), np.array([m]), np.zeros(1), dt, K=K, damping=C, integrator=integrator)
        q, v = res.q, res.v
        if not res.active[0]:
            break
    return float(v[0] / v0)


@pytest.mark.parametrize("integrator", ["implicit", "symplectic", "exact"])
@pytest.mark.parametrize("e", [0.3, 0.7])
def test_integrators_realise_restitution(integrator, e):
    # at omega*dt = 0.05 the discrete restitution is within 0.06 of the target
    assert abs(_bounce(e, integrator, 0.05) - e) < 0.06


@pytest.mark.parametrize("e", [0.1, 0.5, 0.9])
@pytest.mark.parametrize("omega_dt", [0.3, 1.0, 2.0, 3.0, 10.0])
def test_exact_integrator_restitution_at_any_step(e, omega_dt):
    """The modal integrator locates maximum compression and release inside the step:
    the restitution is the model's at any omega*dt (backward Euler at omega*dt = 2
    gives 0.12 for a target of 0.5)."""
    assert abs(_bounce(e, "exact", omega_dt) - e) < 2e-3
    if omega_dt >= 1.0:
        assert _bounce(0.5, "implicit", omega_dt) < 0.3  # what the exact integrator fixes


def test_exact_coupled_contacts_match_a_fine_reference():
    """Two coupled contacts (general modal path, events per contact) against backward
    Euler at omega*dt ~ 1e-3: the exit velocities agree whatever the step."""
    W = np.array([[1.0, 0.4], [0.4, 1.5]]) * 1e-4
    K = np.linalg.inv(W)
    m = np.array([1e-3, 2e-3])
    g = np.array([-9.81, -9.81])
    from hailstorm.runtime.storm.hail import damping_coefficients

    def run(integrator, dt, T=0.004):
        q, v = np.zeros(2), np.array([-1.0, -0.6])
        C = damping_coefficients(K, m, 0.5, dt=dt, integrator=integrator)
        active = np.ones(2, bool)
        for _ in range(int(round(T / dt))):
            idx = np.flatnonzero(active)
            qn, vn = q.copy(), v.copy()
            fr = np.flatnonzero(~active)
            vn[fr] = v[fr] + dt * g[fr]
            qn[fr] = q[fr] + dt * vn[fr]
            if idx.size:
                res = contact_step(q[idx], v[idx], np.zeros(idx.size), m[idx], g[idx], dt, W=W[np.ix_(idx, idx)],
                                   damping=C[idx], integrator=integrator)
                qn[idx], vn[idx] = res.q, res.v
                active[idx[~res.active]] = False
            q, v = qn, vn
        assert not active.any()
        return v

    ref = run("implicit", 4e-7)
    for dt in (1e-4, 1e-3):
        assert np.allclose(run("exact", dt), ref, rtol=2e-3)
    assert not np.allclose(run("implicit", 1e-3), ref, rtol=0.1)  # the test can fail


def _oscillate(integrator: str, dt: float, k: float, m: float, steps: int = 400) -> float:
    """Max |q| of an undamped bilateral spring released from q = 1e-3."""
    q, v = np.array([1e-3]), np.zeros(1)
    K = np.array([[k]])
    peak = 0.0
    for _ in range(steps):
        res = contact_step(q, v, np.zeros(1), np.array([m]), np.zeros(1), dt, K=K, integrator=integrator,
                           unilateral=False)
        q, v = res.q, res.v
        peak = max(peak, float(abs(q[0])))
        if not np.isfinite(peak) or peak > 1.0:
            return np.inf
    return peak


def test_stability_limit_on_a_seat_contact():
    """Symplectic Euler diverges above dt = 2/omega and is bounded below it;
    backward Euler is bounded at 10x that. k is a real contact's capacitance."""
    from hailstorm.runtime.contact import capacitance

    gf = plate_gf()
    cap = capacitance(gf, np.array([100]), np.array([[0.2, 0.3, 0.5]]), mode="frictionless")
    k = float(cap.K[0, 0])
    m = float(stone_mass(0.005))
    omega = np.sqrt(k / m)
    limit = 2.0 / omega
    assert _oscillate("symplectic", 0.95 * limit, k, m) < 1e-2
    assert _oscillate("symplectic", 1.05 * limit, k, m) == np.inf
    peak = _oscillate("implicit", 10 * limit, k, m)
    assert peak <= 1e-3 + 1e-12
    # exact: bounded and undamped (no numerical dissipation) at 10x the limit
    peak = _oscillate("exact", 10 * limit, k, m)
    assert abs(peak - 1e-3) < 1e-6


def test_active_set_releases_pulling_contact():
    # two coupled contacts, one pressed in, one barely touching: the coupling pulls the second
    W = np.array([[1.0, 0.8], [0.8, 1.0]]) * 1e-4
    m = np.array([1e-3, 1e-3])
    res = contact_step(np.array([-1e-5, -1e-9]), np.zeros(2), np.zeros(2), m, np.zeros(2), 1e-5, W=W)
    assert res.active.tolist() == [True, False]
    assert res.force[0] > 0 and res.force[1] == 0


def _drop(e: float, h0: float, r: float = 0.005, integrator: str = "implicit", t_end: float = 0.6):
    from hailstorm.runtime.storm.driver import Scene, Storm

    gf = plate_gf()
    sc = Scene.from_flat(duration=t_end, dt=5e-4, restitution=e, drag=False, integrator=integrator, stones=0)
    st = Storm(gf, sc, spawn=False)
    x0 = np.array([0.061, 0.003, r + h0])
    st.add_stones(x0, np.zeros(3), r)
    zs, ts = [], []
    while st.t < t_end - 1e-12:
        st.step()
        zs.append(st.pos[0, 2])
        ts.append(st.t)
    return st, np.array(ts), np.array(zs)


@pytest.mark.parametrize("integrator", ["implicit", "exact"])
def test_drop_rebound_bounded_by_restitution_and_rest_force(integrator):
    e, h0, r = 0.5, 0.02, 0.005
    st, t, z = _drop(e, h0, r, integrator=integrator)
    assert np.all(np.isfinite(z))
    # first contact, then the first apex after it
    i_hit = int(np.argmax(z < r + 1e-4))
    after = z[i_hit:]
    rising = np.flatnonzero(np.diff(after) > 0)
    assert rising.size
    i0 = rising[0]
    apex = after[i0:][: np.argmax(np.diff(after[i0:]) < 0) + 1].max()
    rebound = apex - r
    assert rebound <= e**2 * h0 * 1.1 + 1e-4
    assert rebound >= 0.3 * e**2 * h0  # it does bounce
    if integrator == "exact":
        assert rebound >= 0.85 * e**2 * h0  # the restitution is realised, not damped away
    # at rest: the contact force equals m g within 1%
    ids, f = st.contact_forces()
    assert ids.tolist() == [0]
    mg = float(st.mass[0]) * GRAVITY
    assert abs(np.linalg.norm(f[0]) - mg) < 0.01 * mg
    assert f[0, 2] < 0  # pushes the seat down
    assert abs(st.vel[0, 2]) < 1e-3
