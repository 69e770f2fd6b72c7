"""A contact across an edge of the faceted surface. Its normal (``Stones.cnormal``) is the
surface's read as a smooth one: the normals at its triangle's corners interpolated at the contact
point (:func:`hailstorm.runtime.contact.normals.corner_normals`,
:func:`hailstorm.runtime.compiled.narrow.contact_normal`), so that it turns continuously across an
edge instead of jumping from one face's normal to the next, and two contacts at one point have
one normal; a sharp edge (beyond ``CREASE_ANGLE``) keeps each side's. Its spring measures the
distance to the plane through its contact point at right angles to that normal: it opens at its
rest length and moves so that the spring never jumps shorter (``Stones.shift``,
:func:`hailstorm.runtime.compiled.narrow.free_phase`).

On the synthetic plate folded along ``x = 60 mm`` (``helpers.plate_gf(fold=...)``): a ridge
(``fold > 0``, the faces' normals ``(-/+ sin f, 0, cos f)`` left and right) or a valley
(``fold < 0``); 13 x 13 vertices 10 mm apart, E = 2 MPa, nu = 0.35, the ring clamped. A fold
of 0.2 rad (23 degrees) is within the crease angle (its vertices' normal is straight up), one of
0.6 rad (69 degrees) is sharp.
"""

from __future__ import annotations

import numpy as np
import pytest
from helpers import plate_gf

from hailstorm.runtime.contact.normals import CREASE_ANGLE, corner_normals
from hailstorm.runtime.storm.collide import Collision, sharp_features
from hailstorm.runtime.storm.driver import Storm
from hailstorm.runtime.storm.hail import Air
from hailstorm.runtime.storm.recording import StormStats
from hailstorm.runtime.storm.scene import Scene
from hailstorm.runtime.storm.seat import SeatState
from hailstorm.runtime.storm.stones import Stones

FOLD = 0.2  # [rad]: a smooth ridge (the faces' normals 23 degrees apart, within the crease angle)
RIDGE_X = 0.06
R = 0.005


def _collision(gf):
    sc = Scene.default()
    air = Air.of((0.0, 0.0, 0.0), False, sc.hail.cd, sc.hail.rho_air, sc.hail.density)  # no drag
    return Collision(gf, sc, air), sc


def _edge_point(gf, y=0.0011):
    """A point of the fold's line (x = 60 mm) at ``y``."""
    return np.array([RIDGE_X, y, 0.0])


def _normals(fold):
    s, c = np.sin(fold), np.cos(fold)
    return np.array([-s, 0.0, c]), np.array([s, 0.0, c])  # left (x < 60 mm), right


def _smooth_normal(gf, t, bary, side):
    """The contact normal at ``bary`` on triangle ``t`` of the ``side`` face, by hand: straight up
    at the fold's vertices, the face's normal at the others, interpolated and made unit."""
    on_fold = np.isclose(np.asarray(gf.vertices)[gf.triangles[t], 0], RIDGE_X)
    n = np.where(on_fold[:, None], [0.0, 0.0, 1.0], _normals(FOLD if gf.vertices[:, 2].min() < 0 else -FOLD)[side])
    m = np.asarray(bary) @ n
    return m / np.linalg.norm(m)


def _in_contact_on(gf, col, x, side, cpoint):
    """A stone centred at ``x`` in contact on the ``side`` face's triangle that holds ``cpoint``
    (its contact point there)."""
    X, T = np.asarray(gf.vertices), np.asarray(gf.triangles)
    n = col.index.normals
    st = Stones(density=917.0)
    ids = st.add(x[None], np.zeros((1, 3)), R)
    want = _normals(FOLD if gf.vertices[:, 2].min() < 0 else -FOLD)[side]
    for t in range(len(T)):
        P = X[T[t]]
        A = np.column_stack([P[1] - P[0], P[2] - P[0]])
        lam, *_ = np.linalg.lstsq(A, cpoint - P[0], rcond=None)
        b = np.array([1.0 - lam.sum(), lam[0], lam[1]])
        if np.all(b >= -1e-12) and np.allclose(b @ P, cpoint, atol=1e-12) and np.allclose(n[t], want, atol=1e-12):
            st.ctri[0], st.cbary[0], st.cnormal[0] = t, b, want
            return st, ids
    raise AssertionError("no such triangle")  # pragma: no cover


def test_corner_normals_are_the_mean_of_the_faces_within_the_crease():
    """Each triangle's corner normals: the area-weighted mean of the normals of the triangles
    around the vertex within the crease angle of its own, against a loop over every triangle;
    on the fold (23 degrees) straight up, and with a crease angle below the fold each side's own."""
    gf = plate_gf(fold=FOLD)
    X, T = np.asarray(gf.vertices), np.asarray(gf.triangles)
    fn = np.cross(X[T[:, 1]] - X[T[:, 0]], X[T[:, 2]] - X[T[:, 0]])
    area = 0.5 * np.linalg.norm(fn, axis=1)
    fn /= 2.0 * area[:, None]
    for crease, fold_normal in ((CREASE_ANGLE, None), (0.3, "own")):
        got = corner_normals(X, T, crease)
        for t in range(len(T)):
            for i in range(3):
                around = [f for f in range(len(T)) if T[t, i] in T[f] and fn[f] @ fn[t] >= np.cos(crease)]
                m = sum(area[f] * fn[f] for f in around)
                np.testing.assert_allclose(got[t, i], m / np.linalg.norm(m), atol=1e-14)
                if np.isclose(X[T[t, i], 0], RIDGE_X) and abs(X[T[t, i], 1]) < 0.05:  # on the fold, inside
                    want = fn[t] if fold_normal else [0.0, 0.0, 1.0]
                    np.testing.assert_allclose(got[t, i], want, atol=1e-14)


@pytest.mark.parametrize(("fold", "sharp"), [(FOLD, False), (0.6, True)])
def test_sharp_edges_are_the_creases_and_the_border(fold, sharp):
    """An edge is sharp where its two triangles' normals are more than the crease angle apart
    (the fold of 0.6 rad: 69 degrees; not that of 0.2 rad: 23) or it has one triangle (the
    plate's border); a sharp vertex ends a sharp edge."""
    gf = plate_gf(fold=fold)
    X, T = np.asarray(gf.vertices), np.asarray(gf.triangles)
    edge, vertex = sharp_features(X, T)
    lo, hi = X[:, :2].min(axis=0), X[:, :2].max(axis=0)
    border = np.isclose(X[:, :2], lo).any(axis=1) | np.isclose(X[:, :2], hi).any(axis=1)
    fold_line = np.isclose(X[:, 0], RIDGE_X)
    for t in range(len(T)):
        for k in range(3):
            u, v = T[t, k], T[t, (k + 1) % 3]
            on_border = border[u] and border[v] and (np.isclose(X[u, :2], X[v, :2]).any())
            on_fold = fold_line[u] and fold_line[v]
            assert edge[t, k] == (on_border or (sharp and on_fold)), (t, k)
    np.testing.assert_array_equal(vertex, border | (fold_line if sharp else False))


@pytest.mark.parametrize(("phi", "moves"), [(0.1, False), (0.3, False), (0.5, True), (0.7, True)])
def test_a_contact_crosses_a_ridge_where_its_closest_point_leaves_the_face(phi, moves):
    """A stone in contact on the ridge's left face, its contact point on the ridge (normal straight
    up), its centre turned by ``phi`` about the ridge from the left normal towards the right one. In
    the wedge (``phi`` in [0, 2 f], f = 0.2) its closest point is the ridge, on the left face
    still: the contact stays; past it the closest point is inside the right face and the contact
    moves there, its normal the smooth surface's there (by hand), and its anchor out by the shift
    that keeps the spring's length (by hand; 0 where the new plane's distance is the larger)."""
    gf = plate_gf(fold=FOLD)
    col, sc = _collision(gf)
    left, right = _normals(FOLD)
    up = np.array([0.0, 0.0, 1.0])
    e = _edge_point(gf)
    d = R - 2e-4
    toward = np.array([np.cos(FOLD), 0.0, np.sin(FOLD)])  # in the plane of the normals, at right angles to the left one
    x = e + d * (np.cos(phi) * left + np.sin(phi) * toward)
    assert np.dot(x - e, right) == pytest.approx(d * np.cos(2 * FOLD - phi), rel=1e-9)  # the premise
    st, ids = _in_contact_on(gf, col, x, 0, e)
    st.cnormal[0] = up
    before = up @ (x - e)
    t0 = int(st.ctri[0])
    col.free_phase(st, ids, sc.time.dt, SeatState(gf), StormStats())
    t = int(st.ctri[0])
    np.testing.assert_allclose(col.index.normals[t], right if moves else left, atol=1e-12)
    assert (t != t0) == moves
    if not moves:
        np.testing.assert_array_equal(st.cnormal[0], up)
        assert st.shift[0] == 0.0
        return
    n = _smooth_normal(gf, t, st.cbary[0], 1)
    np.testing.assert_allclose(st.cnormal[0], n, atol=1e-12)
    X = st.cbary[0] @ np.asarray(gf.vertices)[gf.triangles[t]]
    assert st.shift[0] == pytest.approx(max(before - n @ (x - X), 0.0), abs=1e-15)
    assert n @ (x - X) + st.shift[0] >= before - 1e-15  # the spring never shorter


def test_a_contact_moved_past_a_valley_keeps_its_distance():
    """A stone in contact on the valley's left face whose centre is over the right face (past both
    the bisector and the left triangle): the contact moves to the right face, whose plane through
    the new contact point is nearer, and the anchor moves out by the difference of the two
    distances (by hand), so the spring's length ``n . (x - X) + shift`` is the old one still."""
    gf = plate_gf(fold=-FOLD)
    col, sc = _collision(gf)
    left, right = _normals(-FOLD)
    e = _edge_point(gf)
    x = e + np.array([0.004, 0.0, 0.0]) + (R - 3e-4) * right  # over the right face, near its plane
    cpoint = e - np.array([0.001, 0.0, 0.0])
    cpoint[2] = -np.tan(-FOLD) * 0.001  # on the left face (z = -tan(fold) |x - 60 mm|)
    st, ids = _in_contact_on(gf, col, x, 0, cpoint)
    d_left = float(left @ (x - cpoint))
    col.free_phase(st, ids, sc.time.dt, SeatState(gf), StormStats())
    t = int(st.ctri[0])
    np.testing.assert_allclose(col.index.normals[t], right, atol=1e-12)
    n = _smooth_normal(gf, t, st.cbary[0], 1)
    np.testing.assert_allclose(st.cnormal[0], n, atol=1e-12)
    X = st.cbary[0] @ np.asarray(gf.vertices)[gf.triangles[t]]
    d_right = float(n @ (x - X))
    assert d_right < d_left - 1e-4  # the premise: a jump of more than 0.1 mm without the shift
    assert st.shift[0] == pytest.approx(d_left - d_right, rel=1e-9)
    assert d_right + st.shift[0] == pytest.approx(d_left, rel=1e-12)


def test_a_contact_that_opens_on_a_ridge_starts_at_its_rest_length():
    """A stone overlapping the ridge by 0.1 mm, its centre in the wedge: the contact opens at the
    ridge, its normal straight up (the smooth surface's there), the stone put out along it by the
    overlap, and its anchor out by the normal's tilt from the direction to the centre, so the
    spring starts at its rest length (no force)."""
    gf = plate_gf(fold=FOLD)
    col, sc = _collision(gf)
    left, right = _normals(FOLD)
    up = np.array([0.0, 0.0, 1.0])
    e = _edge_point(gf)
    u = left + 0.3 * right
    u /= np.linalg.norm(u)
    x0 = e + (R - 1e-4) * u
    st = Stones(density=917.0)
    ids = st.add(x0[None], np.array([[0.0, 0.0, -1.0]]), R)
    col.free_phase(st, ids, sc.time.dt, SeatState(gf), StormStats())
    t = int(st.ctri[0])
    assert t >= 0
    X = st.cbary[0] @ np.asarray(gf.vertices)[gf.triangles[t]]
    np.testing.assert_allclose(X, e, atol=1e-12)
    np.testing.assert_allclose(st.cnormal[0], up, atol=1e-12)
    np.testing.assert_allclose(st.pos[0], x0 + 1e-4 * up, atol=1e-15)
    assert st.shift[0] == pytest.approx((R - 1e-4) * (1.0 - u[2]), rel=1e-9)
    assert up @ (st.pos[0] - X) + st.shift[0] == pytest.approx(R, rel=1e-12)


def _drop(gf, dt, x0, vx, vz=-8.0, until=0.006):
    """A 5 mm stone from 30 mm up onto the folded plate (no drag, exact integrator, restitution
    0.5): (peak force, deepest indentation, speed after the bounce, its direction's angle from +z
    towards +x [rad])."""
    sc = Scene.from_flat(duration=0.05, stones=0, drag=False, dt=dt, integrator="exact", restitution=0.5)
    st = Storm(gf, sc, spawn=False)
    st.add_stones(np.array([x0, 0.001, R + 0.032]), [vx, 0.0, vz], R)
    for _ in range(int(round(until / dt))):
        st.step()
    v = st.vel[0]
    return np.array([st.stats["max_contact_force"], st.stats["max_indentation_m"], np.linalg.norm(v),
                     np.arctan2(v[0], v[2])])


def test_a_landing_across_a_ridge_turns_with_the_landing_point():
    """Stones falling straight at 8 m/s onto the ridge, their centres 0-3 mm beside it. In the
    wedge (``R sin f`` = 0.99 mm each side) their contact point is the ridge and they bounce
    straight up; beyond it the contact point leaves the ridge and the rebound turns with the
    smooth surface's normal, continuously (measured: 0, -0.3, -3.6, -7.0 degrees at 0.95, 1.05, 2
    and 3 mm), and the peak force with it; mirror-symmetric. Before the contact normal the rebound
    jumped from one face's direction to the other's between 0.05 mm left and right of the ridge,
    which side the time of impact decided: the default storm's peak forces changed by up to 40 %
    per impact between dt 0.5 and 0.1 ms."""
    gf = plate_gf(fold=FOLD)
    dx = np.array([-3.0, -2.0, -1.05, -0.95, -0.05, 0.0, 0.05, 3.0]) * 1e-3
    runs = np.array([_drop(gf, 5e-4, RIDGE_X + d, 0.0) for d in dx])
    angle = runs[:, 3]
    np.testing.assert_allclose(angle[3:7], 0.0, atol=1e-9)  # in the wedge: straight up
    assert angle[0] < angle[1] < angle[2] < 0.0  # turning beyond it
    assert angle[2] > -0.02 and angle[0] > -0.2  # continuously (the face's normal is 0.2 rad)
    np.testing.assert_allclose(runs[3:7, :3], np.tile(runs[5, :3], (4, 1)), rtol=1e-3)
    np.testing.assert_allclose(runs[2, :3], runs[3, :3], rtol=2e-3)
    # mirror images (but for the triangulation's diagonals, which all run one way: the plate is 2 %
    # stiffer 3 mm right of the ridge than left of it)
    np.testing.assert_allclose(runs[7, 2], runs[0, 2], rtol=1e-3)
    np.testing.assert_allclose(runs[7, :2], runs[0, :2], rtol=0.03)
    assert angle[7] == pytest.approx(-angle[0], rel=0.01)


def test_a_landing_across_a_sharp_ridge_turns_over_the_edge():
    """The same across a ridge folded by 69 degrees, beyond the crease angle: the faces keep their
    own normals up to the edge, and a stone whose centre lies over the edge (its wedge, ``R sin f``
    = 2.8 mm each side) touches it as an edge, its normal the direction from the edge to the
    centre, so the rebound turns continuously over the wedge from one face's to the other's
    (measured: -88.4, -86.5, -66.3, -34.5, -1.8, 0 degrees at 3, 2.7, 2, 1, 0.05, 0 mm);
    mirror-symmetric."""
    gf = plate_gf(fold=0.6)
    dx = np.array([-4.0, -3.0, -2.7, -2.0, -1.0, -0.05, 0.0, 2.0]) * 1e-3
    runs = np.array([_drop(gf, 5e-4, RIDGE_X + d, 0.0) for d in dx])
    angle = runs[:, 3]
    assert angle[0] == pytest.approx(angle[1], abs=1e-3)  # on the face
    assert np.all(np.diff(angle[1:7]) > 0.0)  # turning over the edge
    assert abs(angle[6]) < 1e-9 and abs(angle[5]) < 0.05  # straight up on the edge, nearly beside it
    # no jump: the rebound turns at most ~3 times as fast as the normal (1 / R per metre; measured
    # 620 rad/m), where a jump from face to face over 0.1 mm is 17 000
    assert np.max(np.abs(np.diff(angle[1:7]) / np.diff(dx[1:7]))) < 4.0 / R
    np.testing.assert_allclose(runs[7, 2], runs[3, 2], rtol=1e-3)  # mirror images
    assert angle[7] == pytest.approx(-angle[3], rel=0.01)


@pytest.mark.parametrize(("x0", "vx"), [(0.0595, 0.0), (0.0515, 2.0), (0.0505, 2.0)])
def test_a_landing_on_a_ridge_is_the_same_at_any_dt(x0, vx):
    """A stone that touches the ridge (its centre in the wedge: falling straight, or at 2 m/s
    across it, landing in the wedge or at its edge) bounces the same at dt 0.5 ms as at 0.02 ms:
    peak force, indentation and rebound speed within 0.5 % (measured within 0.03 %), the rebound's
    direction within 3 mrad (measured: 2 mrad across the sharp ridge, 1 % of its 0.18 rad; within
    0.01 mrad on the smooth one), on the smooth and on the sharp ridge. A stone sliding across the
    ridge leaves its contact a little inside its contact surface (the contact kept its tangent plane
    while the stone slid): it is put back on it, not given a new contact (which at dt 0.02 ms cost
    the 0.0505 and 0.0515 landings 1 % of their rebound speed, and nothing at 0.5 ms). Measured on
    a 0.3 rad ridge before the anchor's shift: +55 % and +59 % in force, and 42 % and 27 % more
    rebound speed than beside the ridge, from a spring that opened compressed by the plane's tilt."""
    for fold in (FOLD, 0.6):
        gf = plate_gf(fold=fold)
        on = _drop(gf, 5e-4, x0, vx)
        fine = _drop(gf, 2e-5, x0, vx)
        np.testing.assert_allclose(fine[:3], on[:3], rtol=5e-3)
        assert fine[3] == pytest.approx(on[3], abs=3e-3)
        assert on[2] < np.hypot(vx, 8.0)
