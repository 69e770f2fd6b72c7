"""The storm's compiled kernels (broad phase, flight, closest points, retirement) against
plain statements of their algorithms (``tests/reference/``) and brute force."""

from __future__ import annotations

import numpy as np
import pytest

from hailstorm.runtime import compiled as C
from hailstorm.runtime.collide import SurfaceIndex
from hailstorm.runtime.hail import GRAVITY
from reference.collide_ref import closest_brute, closest_point_on_triangles
from reference.flight_ref import drag_ref, free_flight_ref, near_set_ref, retired_ref
from test_hail import plate_gf


@pytest.fixture(scope="module")
def gf():
    return plate_gf()


def _bumpy(gf):
    """A lifted, bumpy copy of the plate (no two triangles coplanar)."""
    V = gf.vertices.copy()
    V[:, 2] = 0.01 * np.sin(40 * V[:, 0]) * np.cos(30 * V[:, 1])
    return V, np.asarray(gf.triangles)


def test_closest_point_oracle_against_dense_sampling():
    """The oracle itself: Ericson's closest point is no farther than any of 4000 samples
    of the triangle (random triangles and points)."""
    rng = np.random.default_rng(0)
    A, B, Cc, P = (rng.normal(size=(300, 3)) for _ in range(4))
    cp, bc = closest_point_on_triangles(P, A, B, Cc)
    assert np.all(bc >= 0) and np.allclose(bc.sum(axis=1), 1.0)
    uv = rng.random((4000, 2))
    uv = np.where(uv.sum(axis=1, keepdims=True) > 1, 1 - uv, uv)
    for i in range(300):
        S = A[i] + uv[:, :1] * (B[i] - A[i]) + uv[:, 1:] * (Cc[i] - A[i])
        assert np.linalg.norm(cp[i] - P[i]) <= np.linalg.norm(S - P[i], axis=1).min() + 1e-12


def test_samples_cover_every_triangle(gf):
    """Every point of a triangle lies within sample_radius of one of its samples."""
    V, T = _bumpy(gf)
    idx = SurfaceIndex(V, T)
    rng = np.random.default_rng(9)
    for t in rng.choice(len(T), 40, replace=False):
        uv = rng.dirichlet([1.0, 1.0, 1.0], 200)
        P = uv @ V[T[t]]
        S = idx.samples[idx.sample_tri == t]
        assert np.linalg.norm(P[:, None] - S[None], axis=2).min(axis=1).max() <= idx.sample_radius * (1 + 1e-12)


def test_nearest_sample_is_exact(gf):
    """The grid's nearest-sample search equals brute force over all samples, inside and far outside the grid."""
    from hailstorm.runtime.compiled.grid import _nearest_sample

    V, T = _bumpy(gf)
    idx = SurfaceIndex(V, T)
    g = idx.grid
    rng = np.random.default_rng(1)
    P = rng.uniform(V.min(axis=0) - 0.05, V.max(axis=0) + 0.05, (500, 3))
    ref = np.linalg.norm(P[:, None, :] - idx.samples[None], axis=2).min(axis=1)
    got = np.array([_nearest_sample(p, g.lo, g.h, g.dims, g.start, g.items, g.points) for p in P])
    np.testing.assert_allclose(got, ref, rtol=1e-14, atol=1e-15)


@pytest.mark.parametrize("deformed", [False, True])
def test_closest_points_match_brute_force(gf, deformed):
    """The compiled closest points of the (locally deformed) surface equal brute force over
    all triangles of the deformed surface: hits, distances, points (the triangle may differ
    only where two triangles share the closest point: a tie)."""
    V, T = _bumpy(gf)
    idx = SurfaceIndex(V, T)
    rng = np.random.default_rng(2)
    Q = rng.uniform(V.min(axis=0) - 0.01, V.max(axis=0) + 0.01, (400, 3))
    reach = rng.uniform(0.001, 0.03, 400)
    D = np.asfortranarray(gf.D)
    cols = np.array([3 * 40 + 2, 3 * 41 + 2, 3 * 60 + 0])
    fv = np.array([-20.0, -15.0, 7.0])
    u = (D[:, cols] @ fv).reshape(-1, 3)
    kw = {}
    if deformed:
        md = 1.5 * float(np.linalg.norm(u, axis=1).max())
        assert md > 1e-3  # the deformation moves the surface by more than the rounding
        kw = dict(D=D, cols=cols, forces=fv, max_displacement=md)
    ref = closest_brute(Q, V, T, reach, u=u if deformed else None)
    tri, bary, point, dist = C.closest_points(idx.grid, idx.sample_radius, idx.vertices, idx.triangles, Q, reach,
                                              **kw)
    hit = ref.triangle >= 0
    assert 50 < hit.sum() < 350  # hits and misses
    np.testing.assert_array_equal(tri >= 0, hit)
    np.testing.assert_allclose(dist[hit], ref.distance[hit], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(point[hit], ref.point[hit], atol=1e-12)
    assert np.all(np.isinf(dist[~hit])) and np.all(np.isnan(point[~hit]))
    assert np.mean(tri[hit] == ref.triangle[hit]) > 0.95
    np.testing.assert_allclose(bary[hit].sum(axis=1), 1.0, rtol=1e-14)
    # the barycentric coordinates reproduce the point on the (deformed) triangle they name
    X = V + (u if deformed else 0.0)
    np.testing.assert_allclose(np.einsum("kj,kjd->kd", bary[hit], X[T[tri[hit]]]), point[hit], atol=1e-12)


def _stones(idx, rng, n=300):
    lo, hi = idx.bbox
    pos = rng.uniform(lo - 0.03, hi + np.array([0.03, 0.03, 0.08]), (n, 3))
    return pos, rng.normal(0.0, 5.0, (n, 3)), rng.uniform(0.003, 0.008, n)


def test_near_set_matches_reference(gf):
    """The compiled broad phase decides near/far and updates the budgets as the plain
    rule does (with a brute-force nearest sample), stones in contact included."""
    idx = SurfaceIndex(gf.vertices, gf.triangles)
    rng = np.random.default_rng(3)
    pos, vel, r = _stones(idx, rng)
    n = r.size
    ctri = np.where(rng.random(n) < 0.05, 0, -1).astype(np.int64)  # a few stones in contact
    b0, u0 = rng.uniform(-0.01, 0.05, n), rng.uniform(0.0, 0.002, n)
    live = np.arange(n)
    for dt in (5e-4, 5e-3):
        b, bu = b0.copy(), u0.copy()
        ref = near_set_ref(live, pos, vel, r, ctri, b, bu, 1.5e-3, dt, idx.samples, idx.sample_radius, idx.bbox)
        b1, bu1 = b0.copy(), u0.copy()
        got = C.near_set(idx.grid, idx.sample_radius, idx.bbox, live, pos, vel, r, ctri, b1, bu1, 1.5e-3, dt,
                         GRAVITY)
        np.testing.assert_array_equal(got, ref)
        np.testing.assert_allclose(b1, b, rtol=1e-13, atol=1e-15)
        np.testing.assert_array_equal(bu1, bu)
        assert 0 < got.sum() < n


@pytest.mark.parametrize("drag_coef", [0.0, 3.0 * 0.6 * 1.2 / (8.0 * 917.0)])
def test_flight_matches_reference(drag_coef):
    """Free flight: the kernel's update equals the constant-acceleration step with drag
    taken at the start of the step; without drag it is the exact parabola."""
    rng = np.random.default_rng(4)
    n = 50
    pos, vel = rng.normal(size=(n, 3)), rng.normal(0.0, 8.0, (n, 3))
    r = rng.uniform(0.002, 0.01, n)
    wind = np.array([1.0, -2.0, 0.5])
    idx = np.flatnonzero(rng.random(n) < 0.7)
    h = 3e-4
    ref_p, ref_v = free_flight_ref(pos[idx], vel[idx], h, accel=drag_ref(vel[idx], r[idx], wind, drag_coef))
    p, v = pos.copy(), vel.copy()
    C.flight(idx, p, v, r, h, GRAVITY, wind, drag_coef)
    np.testing.assert_allclose(p[idx], ref_p, rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(v[idx], ref_v, rtol=1e-14, atol=1e-14)
    rest = np.setdiff1d(np.arange(n), idx)
    np.testing.assert_array_equal(p[rest], pos[rest])
    if drag_coef == 0.0:  # the analytic parabola
        np.testing.assert_allclose(p[idx], pos[idx] + h * vel[idx] - [0, 0, 0.5 * GRAVITY * h * h], atol=1e-15)


def test_retired_matches_reference(gf):
    idx = SurfaceIndex(gf.vertices, gf.triangles)
    rng = np.random.default_rng(5)
    pos, _, r = _stones(idx, rng, 500)
    pos[:, 2] -= 0.05  # some below the seat
    live = np.flatnonzero(rng.random(500) < 0.8)
    lo, hi = idx.bbox
    got = C.retired(live, pos, r, lo, hi, 0.01)
    np.testing.assert_array_equal(got, retired_ref(live, pos, r, lo, hi, 0.01))
    assert 0 < got.sum() < live.size
