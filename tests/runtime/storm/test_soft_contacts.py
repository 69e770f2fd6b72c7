"""The storm's soft contacts on their own (:class:`SoftContacts`): Hertz's secant stiffness of a
patch contact against Hertz's force ``(4/3) E* sqrt(R) delta^(3/2)``, one contact sub-step of
stones in point contact against backward Euler written out with the capacitance by hand
(``1 / (G^T D G)``), unilateral release, the forces handed to the seat (``D B f`` by hand) and
the statistics of the sub-step.

On the synthetic plate (``helpers.plate_gf``: 13 x 13 vertices 10 mm apart at z = 0, normal +z,
E = 2 MPa, nu = 0.35, the boundary ring clamped).
"""

from __future__ import annotations

import dataclasses
import importlib

import numpy as np
import pytest
from helpers import plate_gf

from hailstorm.runtime.contact.hertz import sphere_force
from hailstorm.runtime.contact.near_field import near_field
from hailstorm.runtime.contact.normals import triangle_normals
from hailstorm.runtime.contact.sphere_patch import sphere_offset
from hailstorm.runtime.contact.weights import patch_weights
from hailstorm.runtime.storm.contact_set import ContactSets
from hailstorm.runtime.storm.hail import GRAVITY, Air
from hailstorm.runtime.storm.integrators import ContactIntegrator
from hailstorm.runtime.storm.patches import Patches
from hailstorm.runtime.storm.recording import StormStats
from hailstorm.runtime.storm.scene import Scene
from hailstorm.runtime.storm.seat import SeatState
from hailstorm.runtime.storm.soft_contacts import SoftContacts
from hailstorm.runtime.storm.stones import Stones

N = 13
UP = np.array([0.0, 0.0, 1.0])
G_VEC = np.array([0.0, 0.0, -GRAVITY])


def cell(i, j, upper=0):
    return 2 * (i * (N - 1) + j) + upper


@pytest.fixture(scope="module")
def gf():
    return plate_gf(N)


def make(gf, **scene):
    sc = Scene.default().with_(**scene)
    normals = triangle_normals(gf.vertices, gf.triangles)
    soft = np.ones(len(gf.triangles), dtype=bool)
    air = Air.of((0.0, 0.0, 0.0), False, sc.hail.cd, sc.hail.rho_air, sc.hail.density)  # no drag
    seat = SeatState(gf)
    patches = Patches(gf, sc.contact, sc.time, seat, normals, soft, air)
    sets = ContactSets(gf, sc.contact, normals, patches)
    integ = ContactIntegrator(sc.time, sc.contact)
    return SoftContacts(sc.contact, sc.time, sets, patches, integ, seat, air), seat, sc


def in_contact(gf, tris, bary, radius, ubar, vel):
    """Stones in contact on ``tris`` at ``bary``: centres ``radius + ubar`` above the contact points."""
    st = Stones(density=917.0)
    tris = np.asarray(tris)
    bary = np.asarray(bary, dtype=float)
    X = np.einsum("kj,kjd->kd", bary, gf.vertices[gf.triangles[tris]])
    ids = st.add(X + (np.asarray(radius) + np.asarray(ubar))[:, None] * UP, np.atleast_2d(vel), radius)
    st.ctri[ids] = tris
    st.cbary[ids] = bary
    st.cnormal[ids] = UP
    return st, ids, X


def dense_D(gf):
    allv = np.arange(gf.vertices.shape[0])
    return gf.compliance(allv, allv)


def B_of(gf, tris, bary):
    """B (3n, 3s): each contact's force on its triangle's vertices at the barycentric weights."""
    n = gf.vertices.shape[0]
    B = np.zeros((3 * n, 3 * len(tris)))
    for k, (t, b) in enumerate(zip(tris, bary)):
        for v, w in zip(gf.triangles[t], b):
            B[3 * v:3 * v + 3, 3 * k:3 * k + 3] += w * np.eye(3)
    return B


# ----------------------------------------------------------------------------------------------
# the Hertz secant stiffness
# ----------------------------------------------------------------------------------------------
def halfspace_patch_bundle(gf, t, bary, a):
    """A copy of the plate whose compliance of the patch of radius ``a`` at (t, bary), as the mesh
    carries it (``w^T D w``), equals the half-space kernel's of the same hat loads (``w^T H w``):
    ``D + beta g g^T`` on the patch's normal dofs. With the half-space near field the contact's
    compliance is then exactly the Hertz disc's on a half-space, ``c(a) = 3 / (5 E* a)``."""
    n = np.array([UP])
    verts, w = patch_weights(gf, np.array([t]), np.array([bary]), np.array([a]), n)
    X = np.asarray(bary) @ gf.vertices[gf.triangles[t]]
    whw = near_field("halfspace", gf.young, gf.poisson).mesh_compliance(gf, verts, w, X[None], n)[0][0]
    D = np.array(gf.D)
    g_row, g_col = np.zeros(D.shape[0]), np.zeros(D.shape[1])
    for v, wv in zip(verts[0], w[0]):
        assert gf.column_of[v] >= 0
        g_row[3 * v + 2] += wv
        g_col[3 * gf.column_of[v] + 2] += wv
    beta = (whw - g_row @ D @ g_col) / ((g_row @ g_row) * (g_col @ g_col))
    return dataclasses.replace(gf, D=np.asfortranarray(D + beta * np.outer(g_row, g_col)))


@pytest.mark.parametrize("a, R", [(1e-3, 2e-3), (1.5e-3, 4e-3), (2e-3, 3e-3)])
def test_patch_force_is_the_spheres_at_the_patch_depth(gf, a, R, monkeypatch):
    """A stone of radius R at rest in a patch contact of radius a (the floor patch_min_radius: above
    the Hertz radius of the stone's expected force, so a is known) engaged with the sphere's offset
    o = sphere_offset(a, R), on a bundle whose patch compliance is the half-space's (near field
    "halfspace"): pressed to the sphere's depth of that patch, delta = (a/2) ln((R + a)/(R - a)), the
    seat force after one sub-step of 1 ns is the sphere's force (Sneddon; a/R 0.38-0.67 here, where
    Hertz's would be 1.5-4.5 % off); half way from o to delta half of it, at o none (the law is
    affine, ``F = (delta - o) / c``)."""
    t, bary = cell(6, 6), np.array([0.3, 0.3, 0.4])
    gfh = halfspace_patch_bundle(gf, t, bary, a)
    # a mesh that carries the half-space exactly has no hat-scale defect of its own (its D is made so)
    monkeypatch.setattr(importlib.import_module("hailstorm.runtime.contact.near_field"), "patch_defect",
                        lambda defect, verts, weights: (np.zeros(len(verts)), np.zeros(len(verts))))
    E, nu = gf.young, gf.poisson
    delta, o = a / 2 * np.log((R + a) / (R - a)), float(sphere_offset(a, R))
    F = float(sphere_force(delta, R, E, nu))
    L = np.log((R + a) / (R - a))
    assert F == pytest.approx(E / (1.0 - nu**2) / 2 * ((a * a + R * R) * L - 2 * a * R), rel=1e-10)
    for depth, want in ((delta, F), (0.5 * (o + delta), 0.5 * F), (o, 0.0)):
        sc_, seat, _ = make(gfh, patch="hertz", near_field="halfspace", patch_min_radius=a, integrator="implicit")
        st, ids, _ = in_contact(gfh, [t], [bary], np.array([R]), [-depth], np.zeros(3))
        st.offset[ids] = o
        stats = StormStats()
        sc_.advance(st, ids, ids, np.array([True]), 1e-9, stats)
        cc = sc_.current
        assert cc.patch_radius[0] == a and cc.offset[0] == o
        # the premise: the contact's compliance is the half-space Hertz disc's (a few sums: rounding)
        assert cc.capacitance.W[0, 0] == pytest.approx(3.0 * (1.0 - nu**2) / (5.0 * E * a), rel=1e-10)
        # one backward Euler sub-step of h = 1 ns moves the stone by ~(omega h)^2 ~ 1e-10 of its depth
        assert -sc_.lam[0] == pytest.approx(want, rel=1e-8, abs=1e-9 * F)
        if want > 0:
            ids_f, f = sc_.forces(st.ctri)
            assert ids_f.tolist() == [0]
            np.testing.assert_allclose(f, [[0.0, 0.0, -want]], rtol=1e-8, atol=1e-12 * want)
            assert stats.max_indentation_m == pytest.approx(depth, rel=1e-6)  # the stone's own depth
    # (the sphere's own law half way would give less: the affine law is its chord from o to delta)
    assert float(sphere_force(0.5 * (o + delta), R, E, nu)) < 0.5 * F


# ----------------------------------------------------------------------------------------------
# a sub-step by hand
# ----------------------------------------------------------------------------------------------
def test_point_contact_sub_step_is_backward_euler_by_hand(gf):
    """A 5 mm stone arriving at 0.8 m/s (with a tangential 0.3 m/s) whose contact opened this
    sub-step, 10 um into the plate; restitution 1 (no dashpot), implicit: the normal velocity is
    backward Euler's with ``k = 1 / (G^T D G)`` by hand, the tangential one untouched (frictionless,
    no drag), the new position ``pos + h v+``; the seat force ``k (q+ - a)`` and the seat's
    displacement ``D B f`` by hand; the statistics count one impact."""
    sc_, seat, sc = make(gf, patch="none", restitution=1.0, integrator="implicit")
    t, bary, r = cell(5, 7, 1), np.array([0.2, 0.5, 0.3]), 0.005
    ub = -1e-5
    vel = np.array([0.3, 0.0, -0.8])
    st, ids, X = in_contact(gf, [t], [bary], np.array([r]), [ub], vel)
    pos0 = st.pos[0].copy()
    D = dense_D(gf)
    B = B_of(gf, [t], [bary])
    g = B @ UP
    k = 1.0 / (g @ D @ g)
    m = st.mass[0]
    h = 2e-6
    stats = StormStats()
    sc_.advance(st, ids, ids, np.array([False]), h, stats)  # the contact opened in this sub-step
    vn = (m * vel[2] + h * (m * -GRAVITY - k * ub)) / (m + h * h * k)
    want_v = np.array([vel[0], vel[1], vn])
    # a 1 x 1 backward Euler step and a compliance summed in another order: ~1e-15 relative
    np.testing.assert_allclose(st.vel[0], want_v, rtol=1e-12, atol=0)
    np.testing.assert_allclose(st.pos[0], pos0 + h * want_v, rtol=1e-14, atol=0)
    ub1 = ub + h * vn
    lam = k * ub1
    assert sc_.lam.shape == (1,)
    assert sc_.lam[0] == pytest.approx(lam, rel=1e-9)  # (q+ - a: a difference of ~5 mm numbers)
    ids_f, f = sc_.forces(st.ctri)
    assert ids_f.tolist() == [0]
    np.testing.assert_allclose(f, [lam * UP], rtol=1e-9, atol=1e-12 * abs(lam))
    assert seat.loaded
    u = (D @ B @ (lam * UP)).reshape(-1, 3)
    np.testing.assert_allclose(seat.u, u, rtol=1e-8, atol=1e-12 * np.abs(u).max())
    assert st.ctri[0] == t and st.hit[0]
    assert stats.impacts == 1 and stats.capacitance_rebuilds == 1
    assert stats.max_contact_force == pytest.approx(abs(lam), rel=1e-9)
    assert stats.max_indentation_m == pytest.approx(-ub1, rel=1e-9)
    assert stats.max_simultaneous_contacts == 1
    # the next sub-step continues the same contact: no new impact, the same set
    cc = sc_.current
    sc_.advance(st, ids, ids, np.array([True]), h, stats)
    assert stats.impacts == 1 and sc_.current is cc and stats.capacitance_rebuilds == 1


def test_slow_contact_is_no_impact(gf):
    """A contact that opens at 1 cm/s (below rest_speed, 5 cm/s) marks the stone as having hit the seat
    but is no impact."""
    sc_, _, sc = make(gf, patch="none")
    assert sc.time.rest_speed == 0.05
    st, ids, _ = in_contact(gf, [cell(6, 6)], [[0.3, 0.3, 0.4]], np.array([0.004]), [0.0], [0.0, 0.0, -0.01])
    stats = StormStats()
    sc_.advance(st, ids, ids, np.array([False]), 1e-5, stats)
    assert stats.impacts == 0 and st.hit[0]


def test_sticky_contact_sub_step_by_hand(gf):
    """A sticky point contact (three multipliers: the stone's centre is held in all directions), moving
    obliquely: ``(M + h^2 K) v+ = M v + h (M g - K ubar)`` with K the inverse of the 3 x 3 ``B^T D B``
    by hand, ``ubar = c - (X + r n)``; the forces on the seat are the multipliers ``K (q+ - a)``."""
    sc_, seat, sc = make(gf, patch="none", restitution=1.0, integrator="implicit", mode="sticky")
    t, bary, r = cell(6, 5), np.array([0.5, 0.25, 0.25]), 0.004
    vel = np.array([0.2, -0.1, -0.5])
    st, ids, X = in_contact(gf, [t], [bary], np.array([r]), [-2e-5], vel)
    st.pos[0, :2] += [3e-6, -1e-6]  # (a tangential offset too)
    c0 = st.pos[0].copy()
    D = dense_D(gf)
    B = B_of(gf, [t], [bary])
    W = B.T @ D @ B
    K = np.linalg.inv(W)  # cond(W) ~ 1: the inverse to ~1e-16 relative
    m = st.mass[0]
    h = 1e-6
    ub = c0 - (X[0] + r * UP)
    sc_.advance(st, ids, ids, np.array([True]), h, StormStats())
    v1 = np.linalg.solve(m * np.eye(3) + h * h * K, m * vel + h * (m * G_VEC - K @ ub))
    np.testing.assert_allclose(st.vel[0], v1, rtol=1e-10, atol=1e-12 * np.abs(v1).max())
    np.testing.assert_allclose(st.pos[0], c0 + h * v1, rtol=1e-14, atol=0)
    lam = K @ (ub + h * v1)
    np.testing.assert_allclose(sc_.lam, lam, rtol=1e-8, atol=1e-10 * np.abs(lam).max())
    ids_f, f = sc_.forces(st.ctri)
    np.testing.assert_allclose(f, lam[None], rtol=1e-8, atol=1e-10 * np.abs(lam).max())
    u = (D @ B @ lam).reshape(-1, 3)
    np.testing.assert_allclose(seat.u, u, rtol=1e-7, atol=1e-10 * np.abs(u).max())


# ----------------------------------------------------------------------------------------------
# release
# ----------------------------------------------------------------------------------------------
def test_a_pulling_contact_is_released_and_the_seat_unloaded(gf):
    """Two stones in one set: one pressed in and approaching, the other 20 um out of the plate and
    leaving (its contact would pull): the second is released (free flight under gravity, by hand),
    the first keeps its contact and alone loads the seat; then ``release`` drops the set."""
    sc_, seat, sc = make(gf, patch="none", restitution=1.0, integrator="implicit")
    tris = [cell(3, 4), cell(8, 8, 1)]
    bary = [[0.3, 0.3, 0.4], [0.2, 0.3, 0.5]]
    r = np.array([0.004, 0.004])
    st, ids, _ = in_contact(gf, tris, bary, r, [-1e-5, 2e-5], np.array([[0.0, 0.0, -0.3], [0.1, 0.0, 0.5]]))
    p1, v1 = st.pos[1].copy(), st.vel[1].copy()
    h = 1e-6
    sc_.advance(st, ids, ids, np.array([True, True]), h, StormStats())
    assert st.ctri[0] == tris[0] and st.ctri[1] == -1
    assert sc_.lam[1] == 0.0 and sc_.lam[0] < 0.0
    np.testing.assert_allclose(st.vel[1], v1 + h * G_VEC, rtol=1e-15, atol=0)
    np.testing.assert_allclose(st.pos[1], p1 + h * (v1 + h * G_VEC), rtol=1e-15, atol=0)
    ids_f, f = sc_.forces(st.ctri)
    assert ids_f.tolist() == [0]
    np.testing.assert_allclose(f, [sc_.lam[0] * UP], rtol=1e-15)
    D = dense_D(gf)
    u = (D @ B_of(gf, tris[:1], bary[:1]) @ (sc_.lam[0] * UP)).reshape(-1, 3)
    np.testing.assert_allclose(seat.u, u, rtol=1e-8, atol=1e-12 * np.abs(u).max())
    sc_.release()
    assert sc_.current is None and sc_.lam.size == 0 and not seat.loaded
    got_ids, got_f = sc_.forces(st.ctri)
    assert got_ids.size == 0 and got_f.shape == (0, 3)
    np.testing.assert_array_equal(seat.u, np.zeros_like(u))


# ----------------------------------------------------------------------------------------------
# the engagement: the dead zone of the patch law
# ----------------------------------------------------------------------------------------------
def test_a_stone_flies_through_its_dead_zone_then_engages_with_no_force(gf):
    """A 5 mm stone falling at 2 m/s onto the plate (exact integrator, restitution 1, no drag),
    stepped by hand: at its first touch its patch is sized and its offset o fixed
    (a^2 / (5 R) as far as the mesh follows the sphere, ``ContactSets.offsets``), its contact
    closes again and the sub-step ends where it reaches its contact surface, o deeper
    (gravity's 2 g o / v^2 ~ 1e-3 aside); there the contact opens (``F = k (delta - o)``: no
    force yet), carries force below it, and once the sphere is clear of the
    plate again the engagement is over (offset 0) and the rebound is the impact speed."""
    from hailstorm.runtime import Storm

    sc = Scene.from_flat(duration=0.05, stones=0, drag=False, integrator="exact", restitution=1.0, dt=1e-4)
    st = Storm(gf, sc, spawn=False)
    R, v0 = 0.005, 2.0
    x = gf.vertices[gf.triangles[cell(6, 6)]].mean(axis=0)
    st.add_stones((x + [0.0, 0.0, R + 1e-6])[None, :], np.array([[0.0, 0.0, -v0]]), np.array([R]))
    stones = st.stones
    near = np.array([0])
    seen = []
    for _ in range(200):
        was_open = stones.ctri[near] >= 0
        h = st.collision.free_phase(stones, near, 1e-4, st.seat, st.stats)
        opened = (stones.ctri[near] >= 0) & ~was_open
        off0 = float(stones.offset[0])
        if opened.any():
            h = st.contacts.engage(stones, near[opened], h, st.stats)
        if off0 == 0.0 and stones.offset[0] > 0.0:  # the first touch
            o = float(stones.offset[0])
            assert stones.ctri[0] == -1  # not in contact yet
            assert 0 < o <= stones.crad[0] ** 2 / (5 * R) * (1 + 1e-12)
            assert h * v0 == pytest.approx(o, rel=2e-3)  # the sub-step ends at the contact surface
            depth0 = -float(stones.pos[0, 2] - R)
            seen.append("touch")
        if stones.ctri[0] >= 0:
            if "engaged" not in seen and "touch" in seen:
                seen.append("engaged")  # on its contact surface: o below the plate, the spring at rest
                assert -float(stones.pos[0, 2] - R) == pytest.approx(depth0 + o, rel=0.02)
            st.contacts.advance(stones, near, near, was_open, h, st.stats)
            if abs(st.contacts.lam[0]) > 0 and "force" not in seen:
                seen.append("force")
                assert st.stats.max_indentation_m > o  # the stone's own depth: its offset and more
        else:
            st.contacts.release()
            st.collision.fly(stones, near, h)
        if "force" in seen and stones.ctri[0] < 0 and stones.offset[0] == 0.0 and stones.vel[0, 2] > 0:
            break
    assert seen[:3] == ["touch", "engaged", "force"], seen
    assert stones.offset[0] == 0.0 and stones.pos[0, 2] > R  # clear of the plate: the engagement is over
    assert stones.vel[0, 2] == pytest.approx(v0, rel=2e-3)  # restitution 1 (gravity over the contact aside)
