"""Stones that meet (``[hail] collisions``): the pair's impact against Hertz's closed form,
the storm's event against the analytic two-body solution, momentum, restitution."""

from __future__ import annotations

import numpy as np
import pytest

from hailstorm.runtime.storm.driver import Storm
from hailstorm.runtime.storm.hail import stone_mass
from hailstorm.runtime.storm.scene import Scene, SceneError
from hailstorm.runtime.storm.stone_collisions import (
    StoneCollisions,
    contact_modulus,
    hertz_impact,
    ice_moduli,
    integrated_impact,
)

E_ICE, NU_ICE = ice_moduli()
E_STAR = contact_modulus(E_ICE, NU_ICE)


def test_ice_moduli_are_the_isotropic_average():
    # an isotropic "crystal" (c11 = c33, c12 = c13, c44 = (c11 - c12) / 2) returns its own E and nu
    E, nu = 9.0e9, 0.3
    lam, mu = E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))
    got = ice_moduli((lam + 2 * mu, lam, lam, lam + 2 * mu, mu))
    assert got == pytest.approx((E, nu), rel=1e-12)
    # ice Ih's Hill average lies between its Reuss and Voigt bounds (a few per cent apart), and
    # within the range the glaciology literature quotes for polycrystalline ice (9-10 GPa, nu 0.31-0.34)
    assert 9.0e9 < E_ICE < 1.0e10 and 0.31 < NU_ICE < 0.34


@pytest.mark.parametrize("speed", [5.0, 10.0, 20.0])
@pytest.mark.parametrize("e", [1.0, 0.5, 0.0])
@pytest.mark.parametrize("r2", [0.005, 0.0025])
def test_integrated_impact_is_hertz(speed, e, r2):
    """The kernel integrates the contact (RK4, 200 steps a phase) and meets Hertz's closed form:
    the ODE is smooth but for delta^(3/2) at the touch, so 200 steps give ~1e-8 (2 % is the
    issue's target; 1e-6 leaves two decades for other BLAS-free float paths)."""
    m1, m2 = float(stone_mass(0.005)), float(stone_mass(r2))
    ref = hertz_impact(m1, m2, 0.005, r2, E_STAR, speed, e)
    out, duration, peak, dmax = integrated_impact(m1 * m2 / (m1 + m2), 0.005 * r2 / (0.005 + r2), E_STAR, speed, e, 200)
    assert peak == pytest.approx(ref.peak_force, rel=1e-6)
    assert dmax == pytest.approx(ref.delta_max, rel=1e-6)
    assert duration == pytest.approx(ref.duration, rel=1e-6)
    assert out == pytest.approx(e * speed, rel=1e-6, abs=1e-12)


def test_hertz_closed_form_against_textbook_figures():
    """Johnson (Contact Mechanics, 11.4): two equal spheres, ``t = 2.94 delta_max / v``,
    ``delta_max = (15 m v^2 / (16 E* R^1/2))^(2/5)`` with m, R the effective ones."""
    m = float(stone_mass(0.005))
    ref = hertz_impact(m, m, 0.005, 0.005, E_STAR, 10.0)
    delta = (15 * (m / 2) * 100.0 / (16 * E_STAR * np.sqrt(0.0025))) ** 0.4
    assert ref.delta_max == pytest.approx(delta, rel=1e-12)
    assert ref.duration == pytest.approx(2.9432 * delta / 10.0, rel=1e-4)
    # energy: the work of the Hertz force to delta_max is the pair's kinetic energy of approach
    assert 0.4 * ref.peak_force * ref.delta_max == pytest.approx(0.5 * (m / 2) * 100.0, rel=1e-12)


def _pair(dt, speed=10.0, e=0.5, r=(0.005, 0.004), offset=0.0, steps=40, gap=2.1e-3):
    """Two stones high above the plate, head on along x (``offset``: the impact parameter
    along y) at ``+-speed / 2``, no drag: (storm, ids, state before, records)."""
    from helpers import plate_gf

    gf = plate_gf()
    sc = Scene.from_flat(duration=1.0, stones=0, drag=False, dt=dt, restitution=e, collisions=True)
    st = Storm(gf, sc, spawn=False)
    z = 0.5  # far above the plate: no seat contact
    ids = st.add_stones([[0.06 - r[0] - gap, 0.0, z], [0.06 + r[1] + gap, offset, z]],
                        [[speed / 2, 0, 0], [-speed / 2, 0, 0]], np.array(r))
    before = (st.pos[ids].copy(), st.vel[ids].copy())
    recs = []
    orig = st.stone_collisions.resolve

    def spy(*a, **k):
        out = orig(*a, **k)
        recs.extend(out.tolist())
        return out

    st.stone_collisions.resolve = spy
    for _ in range(steps):
        st.step()
    return st, ids, before, np.array(recs)


@pytest.mark.parametrize("dt", [5e-4, 5e-5])
def test_head_on_pair_in_the_storm(dt):
    st, ids, (p0, v0), rec = _pair(dt, steps=int(round(2e-3 / dt)))
    assert st.stats["stone_collisions"] == 1 and rec.shape == (1, 8)
    m = st.mass[ids]
    # momentum (x: the line of centres; gravity acts along z on both alike)
    px0, px1 = (m * v0[:, 0]).sum(), (m * st.vel[ids, 0]).sum()
    assert abs(px1 - px0) <= 1e-12 * (m * np.abs(v0[:, 0])).sum()
    # restitution as set
    assert (st.vel[ids[1], 0] - st.vel[ids[0], 0]) / 10.0 == pytest.approx(0.5, rel=1e-6)
    # the force the storm records is the pair's Hertz peak
    ref = hertz_impact(m[0], m[1], 0.005, 0.004, E_STAR, 10.0, 0.5)
    assert st.stats["max_stone_collision_force_N"] == pytest.approx(ref.peak_force, rel=1e-6)
    assert rec[0, 5] == pytest.approx(ref.duration, rel=1e-6)
    # positions: the impulsive two-body solution (touch at t_c = 2 gap / v, then the new velocities)
    tc = 2 * 2.1e-3 / 10.0
    t = st.t
    x_touch = p0[:, 0] + v0[:, 0] * tc
    expect = x_touch + st.vel[ids, 0] * (t - tc)
    assert st.pos[ids, 0] == pytest.approx(expect, abs=1e-12)
    assert rec[0, 2] + (np.floor(tc / dt)) * dt == pytest.approx(tc, abs=1e-12)


def test_same_answer_at_two_time_steps():
    a, ia, _, _ = _pair(5e-4, steps=4)
    b, ib, _, _ = _pair(5e-5, steps=40)
    assert a.t == pytest.approx(b.t)
    assert a.pos[ia] == pytest.approx(b.pos[ib], abs=1e-12)
    assert a.vel[ia] == pytest.approx(b.vel[ib], abs=1e-12)


def test_oblique_pair_exchanges_the_normal_component_only():
    r, b = (0.005, 0.004), 0.005  # impact parameter b < R1 + R2
    st, ids, (p0, v0), rec = _pair(5e-5, r=r, offset=b, steps=40)
    assert rec.shape[0] == 1
    # at the touch the line of centres is n = (sqrt(s^2 - b^2), b) / s
    s = r[0] + r[1]
    n = np.array([np.sqrt(s * s - b * b), b, 0.0]) / s
    dv = st.vel[ids] - v0
    dv[:, 2] = 0.0  # (gravity)
    for k in range(2):
        assert np.linalg.norm(np.cross(dv[k], n)) <= 1e-9 * np.linalg.norm(dv[k])
    # the approach speed along n is what the impact saw: 10 n_x
    assert rec[0, 3] == pytest.approx(10.0 * n[0], rel=1e-9)
    m = st.mass[ids]
    assert np.abs((m[:, None] * dv).sum(axis=0)).max() <= 1e-12 * m.sum() * 10.0


def test_collisions_are_off_by_default_and_checked():
    assert Scene.default().hail.collisions is False
    from helpers import plate_gf

    sc = Scene.from_flat(duration=1.0, stones=0, drag=False)
    storm = Storm(plate_gf(), sc, spawn=False)
    ids = storm.add_stones([[0.05, 0.0, 0.5], [0.07, 0.0, 0.5]], [[5, 0, 0], [-5, 0, 0]], np.array([0.005, 0.005]))
    for _ in range(10):
        storm.step()
    assert storm.stone_collisions is None and storm.stats["stone_collisions"] == 0
    assert storm.pos[ids[0], 0] > storm.pos[ids[1], 0]  # passed through each other
    with pytest.raises(SceneError, match="collisions"):
        Scene.from_dict({"hail": {"collisions": "yes"}})


def test_a_crowd_keeps_its_momentum_and_separates():
    """Twenty stones thrown at one point: chains of collisions within a step, in time order;
    the total momentum (less gravity's, common to all) is kept, and no pair that met overlaps
    at the end by more than the straight-path approximation of a chain allows."""
    from helpers import plate_gf

    rng = np.random.default_rng(3)
    sc = Scene.from_flat(duration=1.0, stones=0, drag=False, dt=2e-4, restitution=0.5, collisions=True)
    st = Storm(plate_gf(), sc, spawn=False)
    k = 20
    d = rng.normal(size=(k, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    r = rng.uniform(0.003, 0.006, k)
    pos = np.array([0.06, 0.0, 0.6]) + 0.04 * d
    ids = st.add_stones(pos, -8.0 * d, r)
    m = st.mass[ids]
    p_before = (m[:, None] * st.vel[ids]).sum(axis=0)
    n_steps = 60
    for _ in range(n_steps):
        st.step()
    assert st.stats["stone_collisions"] >= 5
    p_after = (m[:, None] * st.vel[ids]).sum(axis=0)
    p_after[2] += m.sum() * 9.81 * st.t
    assert np.abs(p_after - p_before).max() <= 1e-12 * (m * 8.0).sum()
    x = st.pos[ids]
    gap = np.linalg.norm(x[:, None] - x[None], axis=2) - (r[:, None] + r[None])
    np.fill_diagonal(gap, np.inf)
    assert gap.min() > -0.05 * r.min()


def test_warm_up_and_empty():
    c = StoneCollisions(0.5)
    from hailstorm.runtime.storm.stones import Stones

    s = Stones(917.0)
    c.warm_up(s)
    assert c.e_star == pytest.approx(E_STAR)
