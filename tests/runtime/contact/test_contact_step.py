"""The contact step (the compiled kernels behind hail.contact_step) against independent
oracles: the matrix exponential of the state matrix (scipy) for critically damped,
repeated-eigenvalue and overdamped sets, the analytic bounce of one damped contact, and
the capacitance of a released subset."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla

from hailstorm.runtime import compiled as C
from hailstorm.runtime.storm.hail import contact_step, restitution_for_damping_ratio


@pytest.mark.parametrize("scale", [1e-6, 1e-2, 1.0, 5.0, 40.0, 300.0])
def test_expm_is_scipys(scale):
    """The compiled matrix exponential against scipy.linalg.expm: random (n, n) matrices
    whose 1-norm spans no scaling to seven squarings, and a critically damped state matrix
    (unit frequency: a double eigenvalue -1 with one eigenvector)."""
    from hailstorm.runtime.compiled.expm import expm

    rng = np.random.default_rng(int(round(np.log10(scale) * 10)) + 60)
    for n in (1, 2, 6):
        A = rng.normal(size=(n, n)) * scale / n
        ref = sla.expm(A)
        np.testing.assert_allclose(expm(A), ref, rtol=0, atol=1e-13 * max(1.0, scale) * np.abs(ref).max())
    A = np.array([[0.0, 1.0], [-1.0, -2.0]]) * scale
    ref = sla.expm(A)
    np.testing.assert_allclose(expm(A), ref, rtol=0, atol=1e-13 * max(1.0, scale) * np.abs(ref).max())


def _set(name):
    """(K, m, C, q, v, a, g) of a bilateral contact set with a dashpot acting both ways."""
    rng = np.random.default_rng(3)
    if name == "critical-one":  # one contact, zeta = 1: a double eigenvalue, one eigenvector
        K, m = np.array([[1e4]]), np.array([1e-3])
        Cm = np.array([[2.0 * np.sqrt(1e4 * 1e-3)]])
    elif name == "nearly-critical-one":  # zeta = 1 + 1e-9: cond(V) ~ 1e9
        K, m = np.array([[1e4]]), np.array([1e-3])
        Cm = np.array([[2.0 * (1.0 + 1e-9) * np.sqrt(1e4 * 1e-3)]])
    elif name == "overdamped-one":  # zeta = 2 (the scalar closed form hands it to the set's path)
        K, m = np.array([[1e4]]), np.array([1e-3])
        Cm = np.array([[4.0 * np.sqrt(1e4 * 1e-3)]])
    elif name == "repeated":  # two equal uncoupled contacts, both critically damped: eigenvalues of multiplicity 4
        K, m = np.diag([2e4, 2e4]), np.array([2e-3, 2e-3])
        Cm = np.diag([2.0 * np.sqrt(2e4 * 2e-3)] * 2)
    else:  # "coupled-critical": three coupled contacts, every normal mode critically damped
        A = rng.normal(size=(3, 3))
        W = (A @ A.T + 3 * np.eye(3)) * 1e-4
        K, m = np.linalg.inv(W), rng.uniform(5e-4, 2e-3, 3)
        om2, Phi = np.linalg.eigh(K / np.sqrt(np.outer(m, m)))
        P = Phi * np.sqrt(m)[:, None]
        Cm = (P * (2.0 * np.sqrt(om2))) @ P.T
        Cm = 0.5 * (Cm + Cm.T)
    n = m.size
    q = rng.normal(size=n) * 1e-4
    v = -rng.uniform(0.5, 1.5, n)
    a = rng.normal(size=n) * 1e-5
    g = np.full(n, -9.81)
    return K, m, Cm, q, v, a, g


@pytest.mark.parametrize("name", ["critical-one", "nearly-critical-one", "overdamped-one", "repeated",
                                  "coupled-critical"])
@pytest.mark.parametrize("omega_dt", [0.3, 3.0, 30.0])
def test_exact_step_of_a_defective_set_is_the_matrix_exponential(name, omega_dt):
    """Bilateral, dashpot acting both ways (no events): the exact step is
    ``z(dt) = expm(A dt) (z0 - z_eq) + z_eq`` of the state matrix ``A = [[0, I], [-M^-1 K, -M^-1 C]]``.
    Critically damped and repeated modes make the modal basis defective: the kernel itself
    covers them (its matrix exponential; it used to hand them to a numpy fallback)."""
    K, m, Cm, q, v, a, g = _set(name)
    n = m.size
    omega = np.sqrt(np.linalg.eigvalsh(K / np.sqrt(np.outer(m, m))).max())
    dt = omega_dt / omega
    A = np.block([[np.zeros((n, n)), np.eye(n)], [-K / m[:, None], -Cm / m[:, None]]])
    q_eq = a + np.linalg.solve(K, m * g)
    z = sla.expm(A * dt) @ np.concatenate([q - q_eq, v])
    q_ref, v_ref = z[:n] + q_eq, z[n:]
    W = np.linalg.inv(K)
    qn, vn, act, force, seat, peak, pub = C.exact_step(q, v, a, m, g, dt, K, W, Cm, False, np.arange(n),
                                                       np.ones(n), np.ones(n, dtype=bool), 1e10, 1e-10)[:7]
    assert act.all()
    np.testing.assert_allclose(qn, q_ref, rtol=1e-11, atol=1e-14 * np.abs(q).max())
    np.testing.assert_allclose(vn, v_ref, rtol=1e-11, atol=1e-11 * np.abs(v).max())
    np.testing.assert_allclose(seat, K @ (q_ref - a), rtol=1e-8, atol=1e-8 * np.abs(K @ (q - a)).max())
    np.testing.assert_allclose(force, m * ((v_ref - v) / dt - g), rtol=1e-8, atol=1e-8 * np.abs(m * v / dt).max())


def _closed_form_bounce(zeta, omega, v0):
    """Exit speed and deepest compression of one contact hit at ``v0`` (no gravity), the
    dashpot ``2 zeta omega m`` acting while it compresses: ``u(t)`` of the damped
    oscillator from ``u = 0, u' = -v0`` until ``u' = 0`` (under-, critically or over-damped),
    then the undamped spring returns the elastic energy: exit speed ``omega |u_max|``."""
    if zeta < 1.0:
        wd = omega * np.sqrt(1.0 - zeta * zeta)
        t1 = np.arctan2(wd, zeta * omega) / wd
        u = -(v0 / wd) * np.exp(-zeta * omega * t1) * np.sin(wd * t1)
    elif zeta == 1.0:
        t1 = 1.0 / omega
        u = -v0 * t1 * np.exp(-omega * t1)
    else:
        s = omega * np.sqrt(zeta * zeta - 1.0)
        r1, r2 = -zeta * omega + s, -zeta * omega - s  # u = -(v0 / 2s) (e^{r1 t} - e^{r2 t})
        t1 = np.log(r2 / r1) / (r1 - r2)
        u = -(v0 / (2.0 * s)) * (np.exp(r1 * t1) - np.exp(r2 * t1))
    return omega * abs(u), u


@pytest.mark.parametrize("zeta", [0.05, 0.4, 0.9, 1.0, 1.5, 3.0])
@pytest.mark.parametrize("omega_dt", [0.5, 8.0])
def test_one_contact_bounces_as_the_damped_oscillator(zeta, omega_dt):
    """One frictionless unilateral contact, compression-only dashpot: the exit speed, the
    deepest compression and the peak seat force over the contact are the damped
    oscillator's closed form (e = restitution_for_damping_ratio(zeta)), for any step,
    under-, critically (the defective basis) and over-damped (the scalar closed form's
    hand-over to the set's path), the kernel itself."""
    k, m, v0 = 1e4, 1e-3, 1.3
    omega = np.sqrt(k / m)
    v_out, u_max = _closed_form_bounce(zeta, omega, v0)
    assert v_out / v0 == pytest.approx(restitution_for_damping_ratio(zeta), rel=1e-6)
    dt = omega_dt / omega
    K, W, Cm = np.array([[k]]), np.array([[1.0 / k]]), np.array([[2.0 * zeta * omega * m]])
    q, v = np.zeros(1), np.array([-v0])
    peak, deepest = 0.0, 0.0
    for _ in range(200):
        qn, vn, act, force, seat, pk, pub = C.exact_step(q, v, np.zeros(1), np.array([m]), np.zeros(1), dt, K, W, Cm,
                                                         True, np.arange(1), np.ones(1), np.zeros(1, dtype=bool),
                                                         1e10, 1e-10)[:7]
        assert np.isfinite(qn).all() and np.isfinite(vn).all()
        q, v = qn, vn
        peak = max(peak, abs(pk[0]))
        deepest = min(deepest, pub[0])
        if not act[0]:
            break
    else:
        raise AssertionError("the contact never released")
    assert v[0] == pytest.approx(v_out, rel=1e-5)
    assert deepest == pytest.approx(u_max, rel=1e-6)
    assert peak == pytest.approx(k * abs(u_max), rel=1e-6)


def test_contact_step_with_k_alone_releases_with_the_subsets_compliance():
    """Given K alone, a released subset's capacitance is inv(W[a, a]) with W = K^-1 (the
    physically exact one: the released contact carries no force), whatever the integrator;
    K and W give the same step."""
    W = np.array([[1.0, 0.8], [0.8, 1.0]]) * 1e-4
    K = np.linalg.inv(W)
    m = np.array([1e-3, 1e-3])
    q = np.array([-1e-5, -1e-9])  # the coupling pulls the second contact
    for integrator in ("implicit", "symplectic", "exact"):
        dt = 1e-7
        res = contact_step(q, np.zeros(2), np.zeros(2), m, np.zeros(2), dt, K=K, integrator=integrator)
        assert res.active.tolist() == [True, False]
        assert res.seat_force[0] == pytest.approx(res.q[0] / W[0, 0], rel=1e-12)
        assert res.seat_force[1] == 0.0 and res.force[1] == 0.0
        by_w = contact_step(q, np.zeros(2), np.zeros(2), m, np.zeros(2), dt, W=W, integrator=integrator)
        np.testing.assert_allclose(by_w.q, res.q, rtol=1e-12, atol=1e-20)
        np.testing.assert_allclose(by_w.seat_force, res.seat_force, rtol=1e-10)


def test_contact_step_rejects_bad_arguments():
    """Shapes are checked before the kernels see them (a compiled kernel would read out of bounds)."""
    one = np.zeros(1)
    with pytest.raises(ValueError, match="integrator"):
        contact_step(one, one, one, one + 1e-3, one, 1e-4, K=np.eye(1), integrator="rk4")
    with pytest.raises(ValueError, match="K or"):
        contact_step(one, one, one, one + 1e-3, one, 1e-4)
    with pytest.raises(ValueError, match="mass"):
        contact_step(one, one, one, np.ones(2), one, 1e-4, K=np.eye(1))
    with pytest.raises(ValueError, match="K must be"):
        contact_step(np.zeros(2), np.zeros(2), np.zeros(2), np.ones(2), np.zeros(2), 1e-4, K=np.eye(3))
