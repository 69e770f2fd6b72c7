"""The storm's stones on their own: :class:`Stones` (growable per-stone arrays, retirement)
and :class:`SpawnPlan` (the scene's random stones, drawn up front), against the scene's
numbers and the stone physics written out by hand."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hailstorm.runtime.storm.scene import Scene
from hailstorm.runtime.storm.hail import terminal_velocity
from hailstorm.runtime.storm.stones import SpawnPlan, Stones

#: a seat's bounding box (any box: the plan only reads lo and hi)
LO = np.array([-0.10, -0.05, 0.02])
HI = np.array([0.12, 0.07, 0.09])


def _sections(**storm):
    sc = Scene.default()
    return dataclasses.replace(sc.storm, **storm), sc.hail


def _plan(seed=0, **storm):
    st, hail = _sections(**storm)
    return SpawnPlan(st, hail, LO, HI, np.random.default_rng(seed)), st, hail


def _ks(u):
    """Kolmogorov-Smirnov distance of samples ``u`` (already mapped through their CDF) from U(0, 1)."""
    u = np.sort(u)
    n = u.size
    return max(np.max(np.arange(1, n + 1) / n - u), np.max(u - np.arange(n) / n))


# ----------------------------------------------------------------------------------------------
# SpawnPlan
# ----------------------------------------------------------------------------------------------
def test_plan_is_reproducible_from_the_seed_and_differs_with_another():
    a, _, _ = _plan(seed=7, rate=400.0, duration=0.3)
    b, _, _ = _plan(seed=7, rate=400.0, duration=0.3)
    c, _, _ = _plan(seed=8, rate=400.0, duration=0.3)
    assert a.rows.shape == b.rows.shape and np.array_equal(a.rows, b.rows)  # same generator stream, same draws
    assert a.rows.shape[1] == 8
    assert a.rows.shape != c.rows.shape or not np.array_equal(a.rows, c.rows)
    n = min(len(a.rows), len(c.rows))
    assert n > 0 and not np.allclose(a.rows[:n], c.rows[:n])


def test_plan_with_a_count_spawns_exactly_that_many_over_the_duration():
    plan, st, _ = _plan(seed=3, stones=57, duration=0.25, rate=1e6)  # the count overrides the rate
    t = plan.rows[:, 0]
    assert t.size == 57
    assert np.all(np.diff(t) >= 0.0)  # sorted spawn times
    assert t.min() >= 0.0 and t.max() < st.duration


def test_plan_count_follows_the_rate_times_the_duration():
    """Poisson(rate * duration) over many seeds: the mean count within 5 standard errors of
    rate * duration, the spread that of a Poisson law (variance = mean, within 30 %)."""
    rate, duration, seeds = 150.0, 0.2, 300
    counts = np.array([len(_plan(seed=s, rate=rate, duration=duration)[0].rows) for s in range(seeds)])
    mu = rate * duration
    assert abs(counts.mean() - mu) < 5.0 * np.sqrt(mu / seeds)
    assert 0.7 * mu < counts.var(ddof=1) < 1.3 * mu  # var of the sample variance ~ 2 mu^2 / seeds: ~8 % sd


def test_plan_spawn_times_are_uniform_over_the_duration():
    """The pooled spawn times fill [0, duration) uniformly (Kolmogorov-Smirnov distance
    below 1.63 / sqrt(n): the 1 % level)."""
    u = np.concatenate([_plan(seed=s, stones=200, duration=0.4)[0].rows[:, 0] for s in range(10)]) / 0.4
    assert u.min() >= 0.0 and u.max() < 1.0
    assert _ks(u) < 1.63 / np.sqrt(u.size)


@pytest.mark.parametrize("wind", [(0.0, 0.0, 0.0), (3.0, -2.0, 0.0)])
def test_plan_positions_velocities_and_radii_follow_the_scene(wind):
    """Every stone: a radius in [r_min, r_max]; spawned spawn_height + r above the seat's top; at
    terminal speed downwards with the wind's horizontal velocity; where it would reach the
    seat's mid-height, falling at terminal speed with the wind, inside the box grown by the margin."""
    plan, st, hail = _plan(seed=11, stones=400, wind=wind, margin=0.015, spawn_height=0.07)
    xy, z, vel, r = plan.rows[:, 1:3], plan.rows[:, 3], plan.rows[:, 4:7], plan.rows[:, 7]
    dist = hail.size_distribution()
    assert np.all(r >= dist.r_min) and np.all(r <= dist.r_max)
    assert np.ptp(r) > 0.0  # the default distribution is not fixed
    np.testing.assert_allclose(z, HI[2] + 0.07 + r, rtol=0, atol=1e-15)
    vt = terminal_velocity(r, cd=hail.cd, rho_air=hail.rho_air, density=hail.density)
    np.testing.assert_allclose(vel[:, 2], -vt, rtol=1e-14)
    np.testing.assert_array_equal(vel[:, :2], np.broadcast_to(np.asarray(wind)[:2], (r.size, 2)))
    # the landing point (at the box's mid-height, the fall at terminal speed): inside box + margin
    land = xy + np.asarray(wind)[None, :2] * ((z - 0.5 * (LO[2] + HI[2])) / vt)[:, None]
    lo, hi = LO[:2] - 0.015, HI[:2] + 0.015
    eps = 1e-12
    assert np.all(land >= lo - eps) and np.all(land <= hi + eps)
    # and they fill it: the extremes within 5 % of its width of the edges (400 uniform draws)
    width = hi - lo
    assert np.all(land.min(axis=0) < lo + 0.05 * width) and np.all(land.max(axis=0) > hi - 0.05 * width)
    if any(wind):
        assert not np.all((xy >= lo) & (xy <= hi))  # spawned upwind, some outside the footprint


@pytest.mark.parametrize("kind", ["exponential", "uniform", "fixed"])
def test_plan_radii_follow_the_size_distribution(kind):
    """The radii lie in [r_min, r_max] and follow the scene's law, written out here: the truncated
    exponential ``(1 - exp(-(r - r_min) / scale)) / (1 - exp(-(r_max - r_min) / scale))``, the uniform,
    or r_min for all (KS distance below the 1 % level, 1.63 / sqrt(n))."""
    st, hail = _sections(stones=1500)
    hail = dataclasses.replace(hail, distribution=kind, r_min=0.003, r_max=0.011, scale=0.0025)
    r = SpawnPlan(st, hail, LO, HI, np.random.default_rng(21)).rows[:, 7]
    assert r.size == 1500 and np.all(r >= 0.003) and np.all(r <= 0.011)
    if kind == "fixed":
        np.testing.assert_array_equal(r, 0.003)
        return
    if kind == "uniform":
        u = (r - 0.003) / 0.008
    else:
        u = -np.expm1(-(r - 0.003) / 0.0025) / -np.expm1(-0.008 / 0.0025)
    assert _ks(u) < 1.63 / np.sqrt(r.size)


def test_plan_without_stones():
    for plan in (_plan(stones=0)[0], _plan(rate=0.0)[0]):
        assert plan.rows.shape == (0, 8)
        assert plan.due(1e9) is None


def test_plan_due_hands_out_each_stone_once_in_time_order():
    plan, st, _ = _plan(seed=5, stones=120, duration=0.2)
    edges = np.linspace(0.0, st.duration, 37)[1:]
    got, prev = [], 0.0
    for t_end in edges:
        rows = plan.due(float(t_end))
        if rows is not None:
            assert rows.shape[0] > 0
            assert np.all(rows[:, 0] < t_end) and np.all(rows[:, 0] >= prev)
            got.append(rows)
        prev = t_end
    assert plan.due(float(st.duration) * 2) is None  # all handed out
    np.testing.assert_array_equal(np.concatenate(got), plan.rows)
    assert plan.due(0.0) is None


def test_empty_plan_has_no_stones():
    plan = SpawnPlan.empty()
    assert plan.rows.shape == (0, 8)
    assert plan.due(1e9) is None


# ----------------------------------------------------------------------------------------------
# Stones
# ----------------------------------------------------------------------------------------------
def test_add_returns_ids_in_spawn_order_and_the_initial_state():
    st = Stones(density=900.0)
    assert len(st) == 0 and st.live().size == 0
    pos = np.array([[0.0, 0.0, 0.1], [0.01, 0.02, 0.2]])
    ids = st.add(pos, np.array([0.0, 0.0, -9.0]), np.array([0.003, 0.006]))
    np.testing.assert_array_equal(ids, [0, 1])
    ids2 = st.add(np.array([0.5, 0.5, 0.5]), np.array([[1.0, 2.0, 3.0]]), 0.004)
    np.testing.assert_array_equal(ids2, [2])
    assert len(st) == 3
    np.testing.assert_array_equal(st.pos, [[0.0, 0.0, 0.1], [0.01, 0.02, 0.2], [0.5, 0.5, 0.5]])
    np.testing.assert_array_equal(st.vel, [[0, 0, -9.0], [0, 0, -9.0], [1.0, 2.0, 3.0]])
    np.testing.assert_array_equal(st.radius, [0.003, 0.006, 0.004])
    np.testing.assert_allclose(st.mass, 900.0 * 4.0 / 3.0 * np.pi * st.radius**3, rtol=1e-15)
    assert st.alive.all() and not st.hit.any()
    np.testing.assert_array_equal(st.ctri, -1)
    np.testing.assert_array_equal(st.near_tri, -1)
    assert np.all(np.isinf(st.gap)) and not st.crad.any() and not st.budget.any() and not st.cbary.any()
    np.testing.assert_array_equal(st.live(), [0, 1, 2])


def _snapshot(st: Stones) -> dict:
    names = ("pos", "vel", "radius", "mass", "alive", "ctri", "cbary", "gap", "hit", "near_tri", "crad", "budget",
             "bud_u")
    return {k: getattr(st, k).copy() for k in names}


def test_growth_keeps_every_stones_state():
    """Spawning past the buffers' capacity (64, doubling) keeps the earlier stones' state, including
    what the storm wrote into the arrays in place."""
    rng = np.random.default_rng(0)
    st = Stones(density=917.0)
    for k in (1, 40, 30, 100, 7, 300):
        n = len(st)
        st.ctri[:] = np.arange(n) % 5 - 1  # state the storm writes in place
        st.gap[:] = np.arange(n) * 1e-3
        st.crad[:] = 1e-3
        before = _snapshot(st)
        ids = st.add(rng.random((k, 3)), rng.random((k, 3)), 0.002 + 0.01 * rng.random(k))
        np.testing.assert_array_equal(ids, np.arange(n, n + k))
        for name, old in before.items():
            np.testing.assert_array_equal(getattr(st, name)[:n], old, err_msg=name)
        assert st.live().size == n + k
    assert len(st) == 478


def test_retire_removes_exactly_the_given_ids_and_keeps_the_rest():
    rng = np.random.default_rng(1)
    st = Stones(density=917.0)
    st.add(rng.random((90, 3)), rng.random((90, 3)), 0.002 + 0.01 * rng.random(90))
    st.ctri[:] = rng.integers(-1, 50, 90)
    st.cbary[:] = rng.random((90, 3))
    st.hit[::3] = True
    st.crad[:] = rng.random(90)
    assert st.live().size == 90  # cached before the retirement
    gone = np.array([0, 5, 17, 18, 89, 42])
    before = _snapshot(st)
    st.retire(gone)
    keep = np.setdiff1d(np.arange(90), gone)
    np.testing.assert_array_equal(st.live(), keep)  # the cache was invalidated
    assert not st.alive[gone].any() and st.alive[keep].all()
    np.testing.assert_array_equal(st.ctri[gone], -1)  # retired stones leave their contact
    for name, old in before.items():
        np.testing.assert_array_equal(getattr(st, name)[keep], old[keep], err_msg=name)
    for name in ("pos", "vel", "radius", "mass"):  # the retired keep their record (ids are row numbers)
        np.testing.assert_array_equal(getattr(st, name)[gone], before[name][gone], err_msg=name)
    # retiring again, or nothing, changes nothing; new stones are alive and get fresh ids
    st.retire(gone)
    st.retire(np.zeros(0, dtype=np.intp))
    np.testing.assert_array_equal(st.live(), keep)
    ids = st.add(np.zeros((2, 3)), np.zeros(3), 0.003)
    np.testing.assert_array_equal(ids, [90, 91])
    np.testing.assert_array_equal(st.live(), np.concatenate([keep, [90, 91]]))
