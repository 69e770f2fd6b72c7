"""The storm's collision part on its own (:class:`Collision`): the free part of a sub-step (closest
points, time of impact, contacts that open, hard walls), the penetration statistics, the broad
phase, free flight and retirement, against geometry worked out by hand on the flat plate and
against brute force over every triangle of the deformed surface (``tests/reference/collide_ref.py``).

On the synthetic plate (``helpers.plate_gf``: 13 x 13 vertices 10 mm apart at z = 0, normal +z,
E = 2 MPa, nu = 0.35, the boundary ring clamped). Grid cell (i, j) spans x in [0.01 i, 0.01 (i + 1)],
y in [0.01 j - 0.06, 0.01 (j + 1) - 0.06]; its lower triangle (vertices (i, j), (i + 1, j),
(i + 1, j + 1)) holds the points with x' >= y' (local coordinates in the cell), its upper one
(vertices (i, j), (i + 1, j + 1), (i, j + 1)) those with y' >= x'.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
from helpers import plate_gf
from reference.collide_ref import closest_brute

from hailstorm.runtime.storm.collide import Collision
from hailstorm.runtime.storm.hail import GRAVITY, Air
from hailstorm.runtime.storm.recording import StormStats
from hailstorm.runtime.storm.scene import Scene
from hailstorm.runtime.storm.seat import SeatState
from hailstorm.runtime.storm.stones import Stones

N = 13
H = 0.01  # grid spacing [m]
R = 0.003  # stone radius [m]
UP = np.array([0.0, 0.0, 1.0])
#: positions are ~0.1 m; every coordinate here is a handful of products and sums of such numbers
ATOL = 1e-15


@pytest.fixture(scope="module")
def gf():
    return plate_gf(N)


def cell(i, j, upper=0):
    """Triangle of grid cell (i, j) (two per cell, as plate_gf lists them)."""
    return 2 * (i * (N - 1) + j) + upper


def on_cell(i, j, xl, yl):
    """The plate point at local coordinates (xl, yl) in [0, 1]^2 of cell (i, j), its triangle and
    its barycentric coordinates on that triangle's (a, b, c), by hand."""
    x, y = H * (i + xl), H * (j + yl) - 0.06
    if xl >= yl:  # lower: a = (i, j), b = (i + 1, j), c = (i + 1, j + 1)
        t, bary = cell(i, j, 0), np.array([1.0 - xl, xl - yl, yl])
    else:  # upper: a = (i, j), c = (i + 1, j + 1), d = (i, j + 1)
        t, bary = cell(i, j, 1), np.array([1.0 - yl, xl, yl - xl])
    return np.array([x, y, 0.0]), t, bary


def make(gf, **scene):
    sc = Scene.default().with_(**scene) if scene else Scene.default()
    air = Air.of((0.0, 0.0, 0.0), False, sc.hail.cd, sc.hail.rho_air, sc.hail.density)  # no drag
    return Collision(gf, sc, air), sc


def stones_at(pos, vel, radius=R):
    st = Stones(density=917.0)
    ids = st.add(np.atleast_2d(pos), np.atleast_2d(vel), radius)
    return st, ids


def test_the_plate_geometry_by_hand(gf):
    """The oracle's premises: on_cell's triangle and barycentric coordinates reproduce the point,
    and the index's normals of the flat plate are +z."""
    col, _ = make(gf)
    X, T = np.asarray(gf.vertices), np.asarray(gf.triangles)
    for (i, j, xl, yl) in [(3, 4, 0.7, 0.2), (5, 5, 0.25, 0.6), (8, 2, 0.5, 0.5), (1, 9, 0.1, 0.9)]:
        p, t, b = on_cell(i, j, xl, yl)
        np.testing.assert_allclose(b @ X[T[t]], p, rtol=0, atol=ATOL)
        assert np.all(b >= 0) and b.sum() == pytest.approx(1.0, abs=1e-15)
    np.testing.assert_allclose(col.index.normals, np.tile(UP, (len(T), 1)), rtol=0, atol=1e-15)
    # soft: every triangle but the two all-clamped corner ones (a corner cell's triangle on the ring)
    all_fixed = np.asarray(gf.fixed)[T].all(axis=1)
    assert all_fixed.sum() == 2 and np.array_equal(col.soft, ~all_fixed)


# ----------------------------------------------------------------------------------------------
# free phase on the undeformed plate
# ----------------------------------------------------------------------------------------------
def test_free_phase_above_touching_receding_and_penetrating_stones(gf):
    """Five stones over five known triangles, in one call: 2 mm above (beyond the query's reach,
    r + |v| h + 1 mm: free, its gap unknown), 0.5 mm above (slow: stays free, its gap and closest
    triangle recorded), 10 um above (inside the 1 % of its radius that opens a contact,
    approaching: the contact opens at the point below it, the stone put on the surface), 10 um above
    but moving away (stays free), 0.5 mm into the plate (opens, pushed back out). The step is not
    shortened (no stone is approaching from beyond the opening gap)."""
    col, sc = make(gf)
    seat = SeatState(gf)
    cases = [  # (cell, local xy, height of the centre above the plate, vz)
        ((2, 9), (0.4, 0.1), R + 2e-3, -0.1),
        ((3, 4), (0.7, 0.2), R + 5e-4, -0.1),
        ((5, 5), (0.25, 0.6), R + 1e-5, -1.0),
        ((8, 2), (0.5, 0.3), R + 1e-5, +1.0),
        ((7, 8), (0.2, 0.9), R - 5e-4, -1.0),
    ]
    feet = [on_cell(i, j, xl, yl) for (i, j), (xl, yl), _, _ in cases]
    pos = np.array([p + z * UP for (p, _, _), (_, _, z, _) in zip(feet, cases)])
    vel = np.array([[0.2, -0.1, vz] for *_, vz in cases])
    st, ids = stones_at(pos, vel)
    near = ids.copy()
    stats = StormStats()
    dt = sc.time.dt
    h = col.free_phase(st, near, dt, seat, stats)
    assert h == dt
    # the closest points, by hand: the foot of each centre (gap = height - r); none beyond the reach
    gaps = np.array([z for _, _, z, _ in cases]) - R
    gaps[0] = np.inf
    np.testing.assert_allclose(st.gap[ids], gaps, rtol=1e-9, atol=1e-15)  # (z - r: a difference of ~3 mm numbers)
    np.testing.assert_array_equal(st.near_tri[ids], [-1] + [t for _, t, _ in feet[1:]])
    # stones 0, 1 and 3 stay free, 2 and 4 open at their feet
    np.testing.assert_array_equal(st.ctri[ids], [-1, -1, feet[2][1], -1, feet[4][1]])
    for k in (2, 4):
        np.testing.assert_allclose(st.cbary[k], feet[k][2], rtol=0, atol=1e-12)  # projections of mm numbers
    # opened contacts: the centre put on the surface along the normal (z = r), x, y untouched
    want = pos.copy()
    want[[2, 4], 2] = R
    np.testing.assert_allclose(st.pos[ids], want, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(st.vel[ids], vel)  # the free phase moves no velocity of a soft contact
    assert stats.wall_contacts == 0


def test_free_phase_time_of_impact_by_hand(gf):
    """A stone 0.1 mm above the plate falling at 2 m/s under gravity (no drag): the sub-step ends
    when it reaches the plate, the root of ``gap = w t + g t^2 / 2``; the contact does not open yet."""
    col, sc = make(gf)
    p, t, _ = on_cell(6, 6, 0.4, 0.1)
    gap, w = 1e-4, 2.0
    st, ids = stones_at(p + (R + gap) * UP, [0.0, 0.0, -w])
    h = col.free_phase(st, ids, sc.time.dt, SeatState(gf), StormStats())
    t_hit = (-w + np.sqrt(w * w + 2.0 * GRAVITY * gap)) / GRAVITY  # positive root of g t^2 / 2 + w t - gap
    assert sc.time.dt / sc.time.max_substeps < t_hit < sc.time.dt  # the premise: neither floor nor full step
    assert h == pytest.approx(t_hit, rel=1e-9)  # (the kernel's rationalised root; sqrt rounding of a
    # difference of ~4 numbers: far below 1e-9)
    assert st.ctri[0] == -1 and st.near_tri[0] == t
    # the approach that would not reach the plate within the step leaves it whole
    st2, ids2 = stones_at(p + (R + gap) * UP, [0.0, 0.0, -0.1])
    assert col.free_phase(st2, ids2, sc.time.dt, SeatState(gf), StormStats()) == sc.time.dt


def test_free_phase_without_time_of_impact_opens_on_overlap_only(gf):
    """``adaptive = false``: no time of impact; a contact opens when the centre is closer than r
    (the stone pushed out by its overlap when approaching), not within the 1 % gap."""
    col, sc = make(gf, adaptive=False)
    p1, t1, b1 = on_cell(4, 6, 0.6, 0.3)
    p2, t2, _ = on_cell(6, 4, 0.3, 0.6)
    pos = np.array([p1 + (R - 2e-4) * UP, p2 + (R + 1e-5) * UP])
    st, ids = stones_at(pos, np.array([[0.0, 0.0, -1.0], [0.0, 0.0, -1.0]]))
    assert col.free_phase(st, ids, sc.time.dt, SeatState(gf), StormStats()) == sc.time.dt
    assert st.ctri[0] == t1 and st.ctri[1] == -1
    np.testing.assert_allclose(st.cbary[0], b1, rtol=0, atol=1e-12)
    np.testing.assert_allclose(st.pos[0], p1 + R * UP, rtol=0, atol=1e-15)
    np.testing.assert_allclose(st.pos[1], pos[1], rtol=0, atol=0)


def test_open_contact_keeps_its_point_until_the_stone_slides_off(gf):
    """A contact keeps its (triangle, beta) while the centre stays over the triangle; once it has
    slid off, the contact moves to the closest point of the undeformed surface (by hand)."""
    col, sc = make(gf)
    p, t, b = on_cell(5, 7, 0.7, 0.2)
    st, ids = stones_at(p + R * UP, [0.0, 0.0, 0.0])
    st.ctri[0], st.cbary[0], st.cnormal[0] = t, b, UP
    q, _, _ = on_cell(5, 7, 0.8, 0.3)  # moved within the triangle
    st.pos[0] = q + (R - 1e-4) * UP
    col.free_phase(st, ids, sc.time.dt, SeatState(gf), StormStats())
    assert st.ctri[0] == t
    np.testing.assert_array_equal(st.cbary[0], b)
    q2, t2, b2 = on_cell(5, 7, 0.3, 0.6)  # across the diagonal: the upper triangle
    assert t2 != t
    st.pos[0] = q2 + (R - 1e-4) * UP
    col.free_phase(st, ids, sc.time.dt, SeatState(gf), StormStats())
    assert st.ctri[0] == t2
    np.testing.assert_allclose(st.cbary[0], b2, rtol=0, atol=1e-12)


def test_hard_wall_bounces_with_the_restitution(gf):
    """A stone touching an all-clamped corner triangle: the contact does not stay open (a hard wall),
    its normal velocity is reversed times the restitution, the tangential one kept, one wall contact."""
    col, sc = make(gf, restitution=0.5)
    t = cell(0, 11, 1)
    assert np.asarray(gf.fixed)[gf.triangles[t]].all() and not col.soft[t]
    p = np.array([0.002, 0.057, 0.0])  # inside (x' = 0.2 <= y' = 0.7 in cell (0, 11))
    st, ids = stones_at(p + (R + 1e-5) * UP, [0.3, -0.2, -2.0])
    stats = StormStats()
    col.free_phase(st, ids, sc.time.dt, SeatState(gf), stats)
    assert st.ctri[0] == -1
    # (the wall's normal is the unit vector from the closest point, rounded to ~1e-17 m, to the centre
    # 3 mm away: its tangential part is ~1e-14, and so is the change of the tangential velocity)
    np.testing.assert_allclose(st.vel[0], [0.3, -0.2, 0.5 * 2.0], rtol=0, atol=1e-13)
    np.testing.assert_allclose(st.pos[0], p + R * UP, rtol=0, atol=1e-15)  # put on the wall
    assert stats.wall_contacts == 1


# ----------------------------------------------------------------------------------------------
# the deformed surface
# ----------------------------------------------------------------------------------------------
def point_load(gf, v, fz):
    """A seat loaded by a force ``fz`` along z at vertex ``v`` (a LoadedSet made by hand, as in
    test_seat.py) and its displacement field by hand, ``D[:, cols] f``."""
    cols = 3 * gf.column_of[v] + np.arange(3)
    G = np.array([[0.0], [0.0], [1.0]])
    rows = 3 * v + np.arange(3)
    cc = SimpleNamespace(stones=np.array([0]), G=G, cols=cols, DVV=np.asarray(gf.D)[np.ix_(rows, cols)] @ G)
    seat = SeatState(gf)
    seat.set_forces(cc, np.array([fz]))
    u = (np.asarray(gf.D)[:, cols] @ (G[:, 0] * fz)).reshape(-1, 3)
    return seat, u


@pytest.mark.parametrize("fz", [-20.0, 20.0])
def test_free_phase_against_the_deformed_surface(gf, fz):
    """A vertex pushed in (a 1 mm dent) or pulled out (a bump) by a 20 N load. A stone 10 um above
    the rest surface over the dent (it would open a contact there) finds the deformed surface ~1 mm
    lower and stays free; one 0.3 mm above the rest surface over the bump (free against the rest
    surface) overlaps the deformed one and opens a contact. Gap, triangle and barycentric
    coordinates are brute force over every triangle of the deformed surface X + u, u = D f by hand."""
    col, sc = make(gf)
    v = 6 * N + 6
    seat, u = point_load(gf, v, fz)
    np.testing.assert_allclose(seat.u, u, rtol=1e-12, atol=1e-18)
    assert abs(u[v, 2]) > 5e-4 and np.sign(u[v, 2]) == np.sign(fz)
    p, t0, _ = on_cell(5, 5, 0.8, 0.6)  # in a triangle of vertex (6, 6)
    assert v in gf.triangles[t0]
    z = R + (1e-5 if fz < 0 else 3e-4)
    pos = p + z * UP
    st, ids = stones_at(pos, [0.0, 0.0, -0.05])
    ref = closest_brute(pos[None], gf.vertices, gf.triangles, u=u)
    gap = ref.distance[0] - R
    if fz < 0:
        assert gap > 10 * Collision.TOI_TOL * R  # the premise: well clear of the dent
    else:
        assert gap < 0.0  # the premise: inside the bump
    h = col.free_phase(st, ids, sc.time.dt, seat, StormStats())
    assert h == sc.time.dt
    assert st.gap[0] == pytest.approx(gap, rel=1e-9)  # (brute force and the kernel: other sums, rounding)
    assert st.near_tri[0] == ref.triangle[0]
    if fz < 0:
        assert st.ctri[0] == -1
        np.testing.assert_array_equal(st.pos[0], pos)
    else:
        assert st.ctri[0] == ref.triangle[0]
        np.testing.assert_allclose(st.cbary[0], ref.bary[0], rtol=0, atol=1e-9)
        # put on the deformed surface along the contact's normal (the flat plate's, up) by the
        # overlap, its anchor out by the normal's tilt from the direction to the closest point
        # (on the bump's slope), so that the spring starts at its rest length R
        Y = gf.vertices + u
        c = ref.bary[0] @ Y[gf.triangles[ref.triangle[0]]]
        np.testing.assert_allclose(st.cnormal[0], UP, atol=1e-15)
        np.testing.assert_allclose(st.pos[0][:2], pos[:2], rtol=0, atol=ATOL)
        assert st.pos[0][2] - pos[2] == pytest.approx(-gap, rel=1e-9)
        assert st.shift[0] == pytest.approx(ref.distance[0] - (pos - c) @ UP, rel=1e-9)
        assert st.shift[0] > 1e-6  # (the premise: the bump's slope)
        assert (st.pos[0] - c) @ UP + st.shift[0] == pytest.approx(R, rel=1e-12)
    # the rest surface would have said otherwise
    rest = closest_brute(pos[None], gf.vertices, gf.triangles)
    assert (rest.distance[0] - R < Collision.TOI_TOL * R) == (fz < 0)


# ----------------------------------------------------------------------------------------------
# penetration statistics
# ----------------------------------------------------------------------------------------------
def test_penetration_statistics_by_hand(gf):
    """Three free stones (0.5 mm and 0.2 mm into the plate, one 0.5 mm above) and two in contact
    (0.3 mm and 0.1 mm into it; radii 3 and 5 mm): the largest overlaps, free and in contact,
    the relative one, and the sum and count of the overlaps in contact."""
    col, sc = make(gf)
    radii = np.array([R, R, R, 0.003, 0.005])
    depth = np.array([5e-4, 2e-4, -5e-4, 3e-4, 1e-4])  # overlap r - distance (negative: a gap)
    cells = [(3, 3), (4, 8), (8, 8), (6, 3), (9, 6)]
    feet = [on_cell(i, j, 0.6, 0.3) for i, j in cells]
    pos = np.array([p + (r - d) * UP for (p, _, _), r, d in zip(feet, radii, depth)])
    st, ids = stones_at(pos, np.zeros(3), radii)
    for k in (3, 4):
        st.ctri[k], st.cbary[k], st.cnormal[k] = feet[k][1], feet[k][2], UP
    stats = StormStats()
    col.penetration(st, ids, sc.time.dt, SeatState(gf), stats)
    tol = dict(rel=1e-9, abs=1e-15)  # r - (z - 0): a difference of mm numbers
    assert stats.max_penetration_m == pytest.approx(5e-4, **tol)
    assert stats.max_penetration_free_m == pytest.approx(5e-4, **tol)
    assert stats.max_penetration_contact_m == pytest.approx(3e-4, **tol)
    assert stats.max_penetration_contact_rel == pytest.approx(max(3e-4 / 0.003, 1e-4 / 0.005), **tol)
    assert stats.pen_contact_sum == pytest.approx(4e-4, **tol)
    assert stats.pen_contact_n == 2
    assert stats.mean_penetration_contact_m == pytest.approx(2e-4, **tol)
    # the statistics keep their maxima across calls: a smaller overlap changes no maximum
    st.pos[0, 2] = R - 1e-4
    col.penetration(st, ids, sc.time.dt, SeatState(gf), stats)
    assert stats.max_penetration_free_m == pytest.approx(5e-4, **tol)
    assert stats.pen_contact_n == 4 and stats.pen_contact_sum == pytest.approx(8e-4, **tol)


# ----------------------------------------------------------------------------------------------
# broad phase, flight, retirement
# ----------------------------------------------------------------------------------------------
def test_near_set_never_misses_a_stone_that_can_reach_the_plate(gf):
    """Stones at heights above the plate from 0.05 mm to 40 mm, falling at 5 m/s: every stone that
    can travel its gap within dt (gap <= |v| dt + g dt^2) is near; those farther than that plus the
    bound's slack (sample radius, the 1e-4 margins) are not; a stone in contact is near wherever
    it is. A far stone's budget stays a lower bound of its distance."""
    col, sc = make(gf)
    dt = sc.time.dt
    gaps = np.array([5e-5, 5e-4, 1e-3, 3e-3, 1e-2, 4e-2])
    feet = [on_cell(4 + k % 4, 3 + k, 0.5, 0.2)[0] for k in range(gaps.size)]
    pos = np.array([p + (R + g) * UP for p, g in zip(feet, gaps)])
    st, ids = stones_at(pos, [0.0, 0.0, -5.0])
    travel = 5.0 * dt + GRAVITY * dt * dt
    slack = col.index.sample_radius + 2e-4
    must = gaps <= travel
    cannot = gaps > travel + slack
    assert must.any() and cannot.any()
    near, far = col.near_set(st, ids, dt, 0.0)
    assert set(ids[must]) <= set(near.tolist())
    assert set(ids[cannot]) <= set(far.tolist())
    assert np.all(st.budget[far] <= gaps[far] - travel + 1e-15)  # spent by this step's travel
    # a stone in contact is near however far
    st2, ids2 = stones_at(pos[-1], [0.0, 0.0, 0.0])
    st2.ctri[0] = 0
    near2, far2 = col.near_set(st2, ids2, dt, 0.0)
    assert near2.tolist() == [0] and far2.size == 0


def test_fly_is_the_parabola_without_drag(gf):
    col, _ = make(gf)
    pos = np.array([[0.01, 0.02, 0.3], [0.05, -0.01, 0.2]])
    vel = np.array([[1.0, -2.0, -3.0], [0.0, 0.5, 4.0]])
    st, ids = stones_at(pos, vel)
    h = 7e-4
    col.fly(st, ids[:1], h)  # only the first
    g = np.array([0.0, 0.0, -GRAVITY])
    np.testing.assert_allclose(st.pos[0], pos[0] + h * vel[0] + 0.5 * h * h * g, rtol=1e-15, atol=0)
    np.testing.assert_allclose(st.vel[0], vel[0] + h * g, rtol=1e-15, atol=0)
    np.testing.assert_array_equal(st.pos[1], pos[1])
    np.testing.assert_array_equal(st.vel[1], vel[1])


def test_fly_with_drag_by_hand(gf):
    """Quadratic drag relative to the wind, ``-(3 C_d rho_air / (8 rho_ice r)) |v - w| (v - w)``, taken
    at the step's start (as the module states), with gravity."""
    sc = Scene.default()
    wind = np.array([2.0, -1.0, 0.0])
    air = Air.of(wind, True, sc.hail.cd, sc.hail.rho_air, sc.hail.density)
    col = Collision(gf, sc, air)
    pos, vel, r = np.array([0.01, 0.0, 0.2]), np.array([0.5, 1.0, -12.0]), 0.004
    st, ids = stones_at(pos, vel, r)
    h = 5e-4
    col.fly(st, ids, h)
    w = vel - wind
    a = np.array([0.0, 0.0, -GRAVITY]) - 3.0 * sc.hail.cd * sc.hail.rho_air / (8.0 * sc.hail.density * r) \
        * np.linalg.norm(w) * w
    np.testing.assert_allclose(st.vel[0], vel + h * a, rtol=1e-14, atol=0)
    np.testing.assert_allclose(st.pos[0], pos + h * vel + 0.5 * h * h * a, rtol=1e-14, atol=0)


def test_retired_by_hand(gf):
    """Below the plate by more than the margin, or beyond the footprint grown by 2 margin + r while
    below the top: retired; above the top or inside the footprint: kept."""
    col, sc = make(gf, margin=0.01)
    m = 0.01
    lo, hi = col.lo, col.hi
    np.testing.assert_allclose(lo, [0.0, -0.06, 0.0], rtol=0, atol=1e-17)  # linspace's ends, +- rounding
    np.testing.assert_allclose(hi, [0.12, 0.06, 0.0], rtol=0, atol=1e-17)
    pos = np.array([
        [0.05, 0.0, -m - 1e-4],  # below by more than the margin: retired
        [0.05, 0.0, -m + 1e-4],  # within the margin: kept
        [hi[0] + 2 * m + R + 1e-4, 0.0, -1e-3],  # beyond the footprint, below the top: retired
        [hi[0] + 2 * m + R - 1e-4, 0.0, -1e-3],  # inside the grown footprint: kept
        [0.05, lo[1] - 2 * m - R - 1e-4, 0.01],  # beyond it, but above the top: kept (still falling)
    ])
    st, ids = stones_at(pos, np.zeros(3))
    np.testing.assert_array_equal(col.retired(st, ids), [0, 2])
    np.testing.assert_array_equal(col.retired(st, ids[1:]), [2])
