"""The storm's contact integrators on their own (:class:`ContactIntegrator`): one contact step of a
contact set against the closed-form harmonic oscillator (the exact integrator to rounding, backward
and symplectic Euler to their order, checked by halving the step), the exact integrator's dashpot
against the restitution it is meant to realise, a coupled pair against ``scipy.linalg.expm``, and
the sub-step size against its rules worked out by hand.

The contact sets are the storm's own (:meth:`ContactSets.build`, point contacts on the synthetic
plate of ``helpers.plate_gf``); the step works in constrained coordinates (``q`` the normal
coordinate of the stone's centre, ``a`` its anchor, ``ubar = q - a``), so one frictionless contact
with stiffness ``k = K[0, 0]`` and mass ``m`` is the oscillator ``m q'' = -k (q - a) + m g``,
``omega = sqrt(k / m)``, around ``q_eq = a + g / omega^2``.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import plate_gf
from scipy.linalg import expm

from hailstorm.runtime.contact.normals import triangle_normals
from hailstorm.runtime.storm.contact_set import ContactSets
from hailstorm.runtime.storm.hail import GRAVITY, Air
from hailstorm.runtime.storm.integrators import ContactIntegrator
from hailstorm.runtime.storm.patches import Patches
from hailstorm.runtime.storm.recording import StormStats
from hailstorm.runtime.storm.scene import Scene
from hailstorm.runtime.storm.seat import SeatState
from hailstorm.runtime.storm.stones import Stones

N = 13
UP = np.array([0.0, 0.0, 1.0])
ONE = np.ones(1)
G0 = np.arange(1)
NEVER = np.zeros(1, dtype=bool)


def cell(i, j, upper=0):
    return 2 * (i * (N - 1) + j) + upper


@pytest.fixture(scope="module")
def gf():
    return plate_gf(N)


def scene(**kw):
    """The default scene with point contacts; ``restitution = 1`` (no dashpot) and bilateral contact
    unless overridden, so that the contact step is the undamped linear oscillator."""
    base = dict(patch="none", restitution=1.0, unilateral=False)
    base.update(kw)
    return Scene.default().with_(**base)


def contact_set(gf, sc, tris=(cell(6, 6),), bary=((0.3, 0.3, 0.4),), stones=None, rest=0.003):
    """A fresh storm contact set of point contacts (its modes and dashpot are cached on it)."""
    normals = triangle_normals(gf.vertices, gf.triangles)
    air = Air.of((0.0, 0.0, 0.0), False, sc.hail.cd, sc.hail.rho_air, sc.hail.density)
    patches = Patches(gf, sc.contact, sc.time, SeatState(gf), normals, np.ones(len(gf.triangles), bool), air)
    sets = ContactSets(gf, sc.contact, normals, patches)
    tris = np.asarray(tris)
    s = tris.size
    stones = np.arange(s) if stones is None else np.asarray(stones)
    return sets.build(stones, tris, np.asarray(bary, dtype=float), normals[tris], (0,), np.full(s, rest), StormStats())


def integrator(sc, name):
    sc = sc.with_(integrator=name)
    return ContactIntegrator(sc.time, sc.contact)


def oscillator(q0, v0, a, g, om, t):
    """The closed form: ``q(t) = q_eq + (q0 - q_eq) cos(om t) + v0 / om sin(om t)``."""
    qe = a + g / om**2
    c, s = np.cos(om * t), np.sin(om * t)
    return qe + (q0 - qe) * c + v0 / om * s, -(q0 - qe) * om * s + v0 * c


A_ = 0.003  # the anchor (the stone's radius above the plate)
M = 1e-4  # the stone's mass [kg]
G_N = -GRAVITY  # gravity along the (upward) normal


def one_step(integ, cc, q0, v0, h, m=M, g=G_N):
    return integ.step(cc, np.array([q0]), np.array([v0]), np.array([A_]), np.array([m]), np.array([g]), h, G0, ONE,
                      NEVER)


# ----------------------------------------------------------------------------------------------
# exact
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("omega_h", [0.1, 1.0, 3.0, 10.0])
def test_exact_step_is_the_closed_form_oscillator(gf, omega_h):
    """One exact step of any length (omega h from 0.1 to 10: no stability or accuracy limit) is the
    closed form; its force on the stone, seat force, deepest ubar and peak seat force are the closed
    form's too."""
    sc = scene()
    cc = contact_set(gf, sc)
    k = cc.K[0, 0]
    om = np.sqrt(k / M)
    h = omega_h / om
    q0, v0 = A_ - 2e-4, -0.5
    res = one_step(integrator(sc, "exact"), cc, q0, v0, h)
    q, v = oscillator(q0, v0, A_, G_N, om, h)
    amp = np.hypot(q0 - (A_ + G_N / om**2), v0 / om)
    # cos / sin of an argument <= 10 and a few products: rounding ~1e-15 of the amplitude (0.2 mm)
    assert abs(res.q[0] - q) <= 1e-12 * amp and abs(res.v[0] - v) <= 1e-12 * om * amp
    assert res.active[0]
    # the force on the stone over the step (mean), the elastic force on the seat at its end
    assert res.force[0] == pytest.approx(M * ((v - v0) / h - G_N), rel=1e-9, abs=1e-12 * k * amp)
    assert res.seat_force[0] == pytest.approx(k * (q - A_), rel=1e-9, abs=1e-12 * k * amp)
    # the deepest instant: the trough of q_eq + amp cos(om t - phi), if the step reaches it, else an end
    phi = np.arctan2(v0 / om, q0 - (A_ + G_N / om**2))
    t_trough = ((phi + np.pi) % (2 * np.pi)) / om
    ends = [q0 - A_, q - A_]
    umin = min(ends + ([A_ + G_N / om**2 - amp - A_] if t_trough <= h else []))
    crest = (phi % (2 * np.pi)) / om
    umax = max(ends + ([G_N / om**2 + amp] if 0 < crest <= h else []))
    assert res.peak_ubar[0] == pytest.approx(umin, rel=1e-9, abs=1e-12 * amp)
    assert res.peak_seat_force[0] == pytest.approx(k * (umin if -umin >= umax else umax), rel=1e-9,
                                                   abs=1e-12 * k * amp)


def test_exact_step_of_a_coupled_pair_is_the_matrix_exponential(gf):
    """Two stones on neighbouring triangles share a coupled 2 x 2 capacitance (the modal path of the
    exact step): the step is ``q_eq + expm(A h) z0`` with ``A = [[0, I], [-M^-1 K, 0]]`` and
    ``K (q_eq - a) = M g``, for steps from a fraction of a period to many."""
    sc = scene()
    cc = contact_set(gf, sc, tris=(cell(6, 6), cell(6, 7, 1)), bary=((0.3, 0.3, 0.4), (0.2, 0.5, 0.3)))
    K = cc.K
    assert abs(K[0, 1]) > 0.2 * np.sqrt(K[0, 0] * K[1, 1])  # the premise: coupled
    m = np.array([1e-4, 2.5e-4])
    a = np.full(2, A_)
    g = np.full(2, G_N)
    q0, v0 = a + np.array([-1e-4, 5e-5]), np.array([-0.3, 0.2])
    integ = integrator(sc, "exact")
    Am = np.block([[np.zeros((2, 2)), np.eye(2)], [-K / m[:, None], np.zeros((2, 2))]])
    qe = a + np.linalg.solve(K, m * g)
    om_max = np.sqrt(np.linalg.eigvals(K / m[:, None]).real.max())
    for h in (0.2 / om_max, 3.0 / om_max, 40.0 / om_max):
        res = integ.step(cc, q0, v0, a, m, g, h, np.arange(2), np.ones(2), np.zeros(2, dtype=bool))
        z = expm(Am * h) @ np.concatenate([q0 - qe, v0])
        scale = np.abs(np.concatenate([q0 - qe, v0 / om_max])).max()
        # a 4 x 4 eigen-decomposition (cond(V) ~ 1) against scipy's Pade: ~1e-14 of the state's size
        np.testing.assert_allclose(res.q, qe + z[:2], rtol=0, atol=1e-11 * scale)
        np.testing.assert_allclose(res.v, z[2:], rtol=0, atol=1e-11 * scale * om_max)
        assert res.active.all()


def test_exact_dashpot_realises_the_restitution_of_one_impact(gf):
    """restitution = 0.5, unilateral: a stone arriving at 1 m/s (no gravity, so that the restitution is
    the model's alone) goes through one whole impact inside one long exact step: its dashpot (cached
    on the set) has the damping ratio whose closed-form restitution ``exp(-zeta w t1)`` is 0.5; the
    damped compression to ``t1``, the undamped rebound over a quarter period and the free flight after
    release are the closed forms by hand."""
    sc = scene(restitution=0.5, unilateral=True)
    cc = contact_set(gf, sc)
    integ = integrator(sc, "exact")
    k = cc.K[0, 0]
    om = np.sqrt(k / M)
    mq = np.array([M])
    C = integ.exact_damping(cc, mq)
    assert integ.exact_damping(cc, mq) is C  # cached with the set
    heavier = integ.exact_damping(cc, 4.0 * mq)  # other masses (same shape): modes and dashpot anew
    assert heavier is not C and heavier[0, 0] == pytest.approx(2.0 * C[0, 0], rel=1e-4)  # c ~ sqrt(k m)
    C = integ.exact_damping(cc, mq)
    zeta = C[0, 0] / (2.0 * M * om)
    wd = np.sqrt(1.0 - zeta**2)
    t1 = np.arctan2(wd, zeta) / (wd * om)  # the first zero of the compression's velocity
    e = np.exp(-zeta * om * t1)
    assert e == pytest.approx(0.5, rel=1e-4)  # the dashpot's table look-up (relative accuracy ~1e-5)
    v0 = 1.0
    depth = v0 / om * e  # the deepest compression: (v0 / wd) e^{-zeta w t1} sin(wd w t1), sin = wd
    t_contact = t1 + np.pi / (2.0 * om)
    h = 10.0 / om
    res = integ.step(cc, np.array([A_]), np.array([-v0]), np.array([A_]), mq, np.zeros(1), h, G0, ONE, NEVER)
    assert not res.active[0] and res.force[0] == 0.0 and res.seat_force[0] == 0.0  # released
    # (closed forms of a few exponentials and trigonometric functions: ~1e-15 relative)
    assert res.v[0] == pytest.approx(e * v0, rel=1e-12)
    assert res.q[0] == pytest.approx(A_ + e * v0 * (h - t_contact), rel=1e-12)
    assert res.peak_ubar[0] == pytest.approx(-depth, rel=1e-12)
    assert res.peak_seat_force[0] == pytest.approx(-k * depth, rel=1e-12)


# ----------------------------------------------------------------------------------------------
# implicit and symplectic
# ----------------------------------------------------------------------------------------------
def test_one_sub_step_is_the_integrators_formula(gf):
    """Backward Euler ``(m + h^2 k) v+ = m v + h (m g - k ubar)`` and symplectic Euler
    ``v+ = v + h (g - k_h ubar / m)`` with the stiffness the explicit step carries,
    ``k_h = k / sqrt(1 + (omega h)^4)``; ``q+ = q + h v+`` for both; the seat force ``k (q+ - a)``
    with the step's stiffness."""
    sc = scene()
    q0, v0 = A_ - 3e-5, -0.7
    for omega_h in (0.05, 0.5, 2.5):
        cc = contact_set(gf, sc)
        k = cc.K[0, 0]
        om = np.sqrt(k / M)
        h = omega_h / om
        u = q0 - A_
        res = one_step(integrator(sc, "implicit"), cc, q0, v0, h)
        v = (M * v0 + h * (M * G_N - k * u)) / (M + h * h * k)
        # a 1 x 1 solve and a few products: ~1e-16 relative; 1e-12 leaves room for the order of sums
        assert res.v[0] == pytest.approx(v, rel=1e-12)
        assert res.q[0] == pytest.approx(q0 + h * v, rel=1e-14)
        assert res.seat_force[0] == pytest.approx(k * (q0 + h * v - A_), rel=1e-9)  # (q+ - a: cancellation)
        cc = contact_set(gf, sc)
        res = one_step(integrator(sc, "symplectic"), cc, q0, v0, h)
        kh = k / np.sqrt(1.0 + omega_h**4)
        v = v0 + h * (G_N - kh * u / M)
        assert res.v[0] == pytest.approx(v, rel=1e-12)
        assert res.q[0] == pytest.approx(q0 + h * v, rel=1e-14)
        assert res.seat_force[0] == pytest.approx(kh * (q0 + h * v - A_), rel=1e-9)


@pytest.mark.parametrize("name, v_sign", [("implicit", 1.0), ("symplectic", -1.0)])
def test_local_error_is_second_order(gf, name, v_sign):
    """One sub-step against the closed form, halving omega h from 0.01 to 0.00125: the errors fall by
    4 each time (a first-order method's local error, O(h^2)) and their leading terms are the Taylor
    expansions' by hand, ``h^2 a0 / 2`` for q (both) and ``-+ omega^2 v0 h^2 / 2`` for v
    (backward / symplectic Euler), ``a0 = g - omega^2 ubar0``."""
    sc = scene()
    integ = integrator(sc, name)
    q0, v0 = A_ - 2e-5, -0.5
    errs, lead = [], []
    for omega_h in (0.01, 0.005, 0.0025, 0.00125):
        cc = contact_set(gf, sc)
        om = np.sqrt(cc.K[0, 0] / M)
        h = omega_h / om
        res = one_step(integ, cc, q0, v0, h)
        q, v = oscillator(q0, v0, A_, G_N, om, h)
        errs.append((res.q[0] - q, res.v[0] - v))
        a0 = G_N - om**2 * (q0 - A_)
        lead.append((h * h * a0 / 2.0, v_sign * (-(om**2) * v0) * h * h / 2.0))
    errs, lead = np.array(errs), np.array(lead)
    # the next terms are O(omega h (1 + omega |ubar0| / |v0|)) ~ 2.4 omega h relative: <= 2.4 % here
    np.testing.assert_allclose(errs[:-1] / errs[1:], 4.0, rtol=0.05)
    np.testing.assert_allclose(errs / lead, 1.0, rtol=0.05)
    # the errors are far above the rounding (positions ~3e-3 m: ~1e-18)
    assert np.abs(errs[:, 0]).min() > 1e6 * 3e-3 * np.finfo(float).eps


@pytest.mark.parametrize("name", ["implicit", "symplectic"])
def test_global_error_is_first_order(gf, name):
    """Over one radian of the oscillation (T = 1 / omega) in 100, 200 and 400 sub-steps: the error at T
    halves with the step (first order)."""
    sc = scene()
    integ = integrator(sc, name)
    q0, v0 = A_ - 2e-5, -0.5
    errs = []
    for n in (100, 200, 400):
        cc = contact_set(gf, sc)
        om = np.sqrt(cc.K[0, 0] / M)
        T = 1.0 / om
        h = T / n
        q, v = np.array([q0]), np.array([v0])
        for _ in range(n):
            res = integ.step(cc, q, v, np.array([A_]), np.array([M]), np.array([G_N]), h, G0, ONE, NEVER)
            q, v = res.q, res.v
        qc, vc = oscillator(q0, v0, A_, G_N, om, T)
        errs.append((q[0] - qc, v[0] - vc))
    errs = np.array(errs)
    # O(h) error with an O(h^2) remainder: at omega h <= 0.01 the ratio is within ~6 % of 2
    np.testing.assert_allclose(errs[:-1] / errs[1:], 2.0, rtol=0.08)


def test_symplectic_step_stays_bounded_beyond_the_explicit_limit(gf):
    """At omega h = 5, far beyond symplectic Euler's limit omega h < 2, the step carries the softened
    mode (omega_h' h <= 1) and the oscillation stays bounded over 300 sub-steps, while plain
    symplectic Euler with the set's own stiffness, written out here, grows without bound."""
    sc = scene()
    cc = contact_set(gf, sc)
    k = cc.K[0, 0]
    om = np.sqrt(k / M)
    h = 5.0 / om
    integ = integrator(sc, "symplectic")
    qe = A_ + G_N / om**2
    q, v = np.array([qe - 1e-5]), np.array([0.0])
    qp, vp = q[0], v[0]
    worst, plain = 0.0, 0.0
    for _ in range(300):
        res = integ.step(cc, q, v, np.array([A_]), np.array([M]), np.array([G_N]), h, G0, ONE, NEVER)
        q, v = res.q, res.v
        worst = max(worst, abs(q[0] - qe))
    for _ in range(30):  # (plain: its amplification is ~23 per step; 30 steps stay far from overflow)
        vp = vp + h * (G_N - k * (qp - A_) / M)
        qp = qp + h * vp
        plain = max(plain, abs(qp - qe))
    # the softened step conserves a modified energy: |q - q_eq| stays within 1 / sqrt(1 - (w'h / 2)^2)
    # (<= 1.16 at w'h <= 1) of the start; about the start's equilibrium with k_h (offset g / w_h'^2)
    kh = k / np.sqrt(1.0 + 5.0**4)
    offset = abs(G_N * M / kh - G_N * M / k)
    assert worst <= 1.2 * (1e-5 + offset) + offset
    assert plain > 1e3 * 1e-5


# ----------------------------------------------------------------------------------------------
# the sub-step size
# ----------------------------------------------------------------------------------------------
def stones_for(gf, cc, ubar, vn, radius=0.006):
    """Stones 0..s-1 in the set ``cc`` (its contacts on their triangles), at ``ubar`` with normal
    velocity ``vn``; their own gap set far (the approach rule is tested apart)."""
    st = Stones(density=917.0)
    s = cc.stones.size
    ids = st.add(cc.X + (cc.rest + np.asarray(ubar))[:, None] * cc.normals, np.asarray(vn)[:, None] * cc.normals,
                 radius)
    st.ctri[ids] = cc.tris
    st.cbary[ids] = cc.bary
    st.cnormal[ids] = cc.normals
    st.near_tri[ids] = cc.tris
    st.gap[ids] = 1.0
    assert np.array_equal(ids, cc.stones) and s == ids.size
    return st, ids


def test_substep_size_of_a_moving_contact(gf):
    """A contact moving at 1 m/s: implicit sub-steps resolve omega h = omega_dt, symplectic half that;
    both far inside the explicit stability limit omega h < 2; exact and non-adaptive take what is left."""
    sc = scene(omega_dt=0.2)
    cc = contact_set(gf, sc, rest=0.006)  # (a 6 mm stone: its omega_dt sub-step lies above the floor)
    st, ids = stones_for(gf, cc, [0.0], [-1.0])
    om = np.sqrt(cc.Kdiag[0] / st.mass[0])
    h_left = sc.time.dt
    g = np.array([0.0, 0.0, -GRAVITY])
    k_tri = np.zeros(len(gf.triangles))
    h_imp = integrator(sc, "implicit").substep_size(st, ids, h_left, cc, k_tri, g)
    h_sym = integrator(sc, "symplectic").substep_size(st, ids, h_left, cc, k_tri, g)
    assert sc.time.dt / sc.time.max_substeps < 0.1 / om < h_left  # the premise: neither floor nor cap
    assert h_imp == pytest.approx(0.2 / om, rel=1e-14)
    assert h_sym == pytest.approx(0.1 / om, rel=1e-14)
    assert h_sym * om < 2.0 and h_imp * om < 2.0
    assert integrator(sc, "exact").substep_size(st, ids, h_left, cc, k_tri, g) == h_left
    assert integrator(scene(adaptive=False), "implicit").substep_size(st, ids, h_left, cc, k_tri, g) == h_left
    # no triangle stiffness given: the integrator sizes nothing
    assert integrator(sc, "implicit").substep_size(st, ids, h_left, cc, None, g) == h_left


def test_substep_size_of_a_resting_contact(gf):
    """A contact at rest at its equilibrium (ubar = m g_n / k, v = 0): backward Euler is exact there and
    takes the whole step; symplectic Euler is limited by every contact (stability), to omega h = 0.1."""
    sc = scene()
    cc = contact_set(gf, sc, rest=0.006)
    m = 917.0 * 4.0 / 3.0 * np.pi * 0.006**3
    st, ids = stones_for(gf, cc, [-GRAVITY * m / cc.Kdiag[0]], [0.0])
    om = np.sqrt(cc.Kdiag[0] / st.mass[0])
    g = np.array([0.0, 0.0, -GRAVITY])
    k_tri = np.zeros(len(gf.triangles))
    h_left = sc.time.dt
    assert sc.time.dt / sc.time.max_substeps < 0.1 / om and 0.2 / om < h_left  # neither floor nor cap
    assert integrator(sc, "implicit").substep_size(st, ids, h_left, cc, k_tri, g) == h_left
    assert integrator(sc, "symplectic").substep_size(st, ids, h_left, cc, k_tri, g) == pytest.approx(0.1 / om,
                                                                                                    rel=1e-14)
    # moving just above rest_speed (0.05 m/s) is moving again
    st.vel[0] = -0.06 * UP
    assert integrator(sc, "implicit").substep_size(st, ids, h_left, cc, k_tri, g) == pytest.approx(0.2 / om,
                                                                                                  rel=1e-14)


def test_substep_size_of_an_approaching_stone(gf):
    """A free stone 0.5 mm above triangle t, approaching at 2 m/s: its travel per sub-step is at most
    approach_fraction radii, and an impact about to start is resolved to omega_dt with
    omega = 1.5 sqrt(k_t / m) (k_t the triangle's stiffness); a stone whose gap it cannot cross
    within what is left does not limit; the floor is dt / max_substeps."""
    sc = scene(approach_fraction=0.1, omega_dt=0.2)
    integ = integrator(sc, "implicit")
    t = cell(5, 5)
    r = 0.003
    st = Stones(density=917.0)
    ids = st.add(np.array([[0.055, -0.005, r + 5e-4], [0.07, 0.01, r + 0.02]]), np.array([0.0, 0.0, -2.0]), r)
    st.gap[ids] = [5e-4, 0.02]
    st.near_tri[ids] = t
    m = st.mass[0]
    g = np.array([0.0, 0.0, -GRAVITY])
    h_left = sc.time.dt
    approach = 0.1 * r / 2.0
    for k in (1e1, 1e3, 1e4, 1e6, 1e9):
        k_tri = np.zeros(len(gf.triangles))
        k_tri[t] = k
        want = max(min(h_left, approach, 0.2 / (1.5 * np.sqrt(k / m))), h_left / sc.time.max_substeps)
        assert integ.substep_size(st, ids, h_left, None, k_tri, g) == pytest.approx(want, rel=1e-14)
    # the approach and the omega limits and the floor each bind once over these stiffnesses
    hs = {k: integ.substep_size(st, ids, h_left, None, np.where(np.arange(len(gf.triangles)) == t, k, 0.0), g)
          for k in (1e1, 1e4, 1e9)}
    assert hs[1e1] == pytest.approx(approach, rel=1e-14)
    assert hs[1e9] == h_left / sc.time.max_substeps
    assert h_left / sc.time.max_substeps < hs[1e4] < approach
    # the far stone alone does not limit
    assert integ.substep_size(st, ids[1:], h_left, None, np.full(len(gf.triangles), 1e9), g) == h_left
