"""The storm's compiled kernels (broad phase, flight, closest points, retirement) against
plain statements of their algorithms (``tests/reference/``) and brute force."""

from __future__ import annotations

import numpy as np
import pytest

from hailstorm.runtime import compiled as C
from hailstorm.runtime.storm.collide import SurfaceIndex
from hailstorm.runtime.storm.hail import GRAVITY
from reference.collide_ref import closest_brute, closest_point_on_triangles
from reference.flight_ref import drag_ref, free_flight_ref, near_set_ref, retired_ref
from helpers import plate_gf


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
    from hailstorm.runtime.compiled.grid import nearest_sample

    V, T = _bumpy(gf)
    idx = SurfaceIndex(V, T)
    g = idx.grid
    rng = np.random.default_rng(1)
    P = rng.uniform(V.min(axis=0) - 0.05, V.max(axis=0) + 0.05, (500, 3))
    ref = np.linalg.norm(P[:, None, :] - idx.samples[None], axis=2).min(axis=1)
    got = np.array([nearest_sample(p, g.lo, g.h, g.dims, g.start, g.items, g.points) for p in P])
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


@pytest.mark.parametrize("fold", [0.2, 0.6])
def test_contact_normal_matches_reference(fold):
    """The compiled contact normal against the plain statement, for centres around every triangle
    of the folded plate (a smooth ridge at 0.2 rad, a sharp one at 0.6 rad, the sharp border):
    over faces, over edges and over corners, at random barycentric contact points."""
    from hailstorm.runtime.compiled.narrow import contact_normal
    from hailstorm.runtime.storm.collide import SurfaceIndex
    from reference.collide_ref import contact_normal_ref

    gf = plate_gf(fold=fold)
    ix = SurfaceIndex(gf.vertices, gf.triangles)
    X, T = ix.vertices, np.asarray(ix.triangles, dtype=np.int64)
    rng = np.random.default_rng(3)
    out, bt = np.empty(3), np.empty(3)
    kinds = set()
    for t in range(len(T)):
        for _ in range(4):
            bary = rng.dirichlet([1.0, 1.0, 1.0])
            spot = rng.dirichlet([0.3, 0.3, 0.3]) * 1.6 - 0.2  # inside or out past an edge or a corner
            p = spot @ X[T[t]] + 0.004 * ix.normals[t] + rng.normal(0.0, 0.002, 3)
            contact_normal(p, t, bary, X, T, ix.normals, ix.corner_normals, ix.sharp_edges, ix.sharp_vertices, bt, out)
            want = contact_normal_ref(p, t, bary, X, T, ix.normals, ix.corner_normals, ix.sharp_edges, ix.sharp_vertices)
            np.testing.assert_allclose(out, want, atol=1e-12)
            kinds.add("smooth" if np.allclose(want, bary @ ix.corner_normals[t] / np.linalg.norm(bary @ ix.corner_normals[t]))
                      else "edge")
    assert kinds == {"smooth", "edge"}  # (both rules met)


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


def test_sorted_ints_is_np_sort():
    """The kernels' integer sort (a heapsort that compiles in a fraction of numba's
    quicksort) gives np.sort's result: empty, one, duplicates, sorted, reversed, random."""
    from hailstorm.runtime.compiled.grid import sorted_ints

    rng = np.random.default_rng(10)
    cases = [np.zeros(0, np.int64), np.array([7]), np.arange(20), np.arange(20)[::-1].copy(),
             rng.integers(0, 5, 50), rng.integers(-10**9, 10**9, 1000)]
    for a in cases:
        a = np.ascontiguousarray(a, dtype=np.int64)
        b = a.copy()
        np.testing.assert_array_equal(sorted_ints(a), np.sort(a))
        np.testing.assert_array_equal(a, b)  # a copy: the input is not touched


def test_modal_damping_interpolation_is_np_interp():
    """The dashpot's table look-up (compiled scalar interpolation, numpy's rule) equals
    np.interp exactly (the same arithmetic, no BLAS) on the restitution table: inside, at its nodes, beyond both
    ends and on its flat (clipped) tail."""
    from hailstorm.runtime.compiled.modal import interp1
    from hailstorm.runtime.storm.hail import _X_GRID, _Z_GRID

    rng = np.random.default_rng(11)
    xs = np.concatenate([rng.uniform(-1.0, _X_GRID[-1] + 1.0, 2000), _X_GRID[::37], [_X_GRID[-1], 0.0, -0.0],
                         -np.log([0.5, 0.1, 0.9, 1e-300, 1.0])])
    got = np.array([interp1(float(x), _X_GRID, _Z_GRID) for x in xs])
    np.testing.assert_array_equal(got, np.interp(xs, _X_GRID, _Z_GRID))


@pytest.mark.slow
def test_each_storm_kernel_compiles_once(tmp_path):
    """The warm-up calls every kernel with the loop's argument types: after a storm of
    each integrator and contact model, no kernel (nor a kernel it calls) holds a second
    type specialisation (each would be a second compile on a first run). In a fresh
    interpreter with an empty numba cache (a cold compile: slow), so that the kernels
    called from kernels are compiled, not loaded, and show their specialisations."""
    import os
    import subprocess
    import sys

    code = """
import numpy as np, sys
from numba.core.dispatcher import Dispatcher
sys.path.insert(0, sys.argv[1])
from helpers import plate_gf
from hailstorm.runtime import compiled
from hailstorm.runtime.storm.scene import Scene
from hailstorm.runtime.storm.run import run_storm
gf = plate_gf()
for integ in ("implicit", "exact", "symplectic"):
    for patch in ("hertz", "none"):
        run_storm(gf, Scene.from_flat(duration=0.03, stones=8, seed=3, spawn_height=0.02, r_min=0.003, r_max=0.006,
                            integrator=integ, patch=patch, collisions=patch == "none"), progress=False)
from hailstorm.runtime.compiled import exact, free_steps, stone_pairs
many = {}
for mod in (compiled.flight, compiled.narrow, compiled.patches, compiled.contacts, compiled.integrators,
            compiled.grid, compiled.modal, compiled.lapack, stone_pairs, free_steps, exact):
    for name in dir(mod):
        f = getattr(mod, name)
        if isinstance(f, Dispatcher) and len(f.signatures) > 1:
            many[mod.__name__ + "." + name] = [str(s) for s in f.signatures]
assert not many, many
"""
    from pathlib import Path

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    subprocess.run([sys.executable, "-c", code, str(Path(__file__).parents[2])], check=True, env=env)


@pytest.mark.parametrize("mode", ["frictionless", "sticky"])
def test_patch_radii_match_reference(gf, mode):
    """The compiled patch sizing gives the plain rule's radii and resizes, for new contacts
    (point stiffness, then the patch's own) and known ones (a previous contact set with
    forces, two of its radii out of date); the new contacts' weights are cached."""
    from hailstorm.runtime.storm.recording import StormStats
    from hailstorm.runtime.storm.scene import Scene
    from hailstorm.runtime.storm.driver import Storm
    from reference.patches_ref import patch_radii_ref

    sc = Scene.from_flat(duration=0.1, stones=0, r_min=0.003, r_max=0.008, mode=mode)
    st = Storm(gf, sc, spawn=False)
    rng = np.random.default_rng(6)
    tris = rng.choice(np.flatnonzero(st.soft), 6, replace=False)
    bary = rng.dirichlet([2.0, 2.0, 2.0], 6)
    X = np.einsum("kj,kjd->kd", bary, gf.vertices[gf.triangles[tris]])
    r = rng.uniform(0.003, 0.008, 6)
    ids = st.add_stones(X + r[:, None] * st.index.normals[tris], rng.normal(0.0, 2.0, (6, 3)), r)
    stones = st.stones
    stones.ctri[ids] = tris
    stones.cbary[ids] = bary
    # contact normals: the triangles', half of them turned by 0.2 rad (as on an edge's side)
    turn = np.where(np.arange(6) % 2 == 1, 0.2, 0.0)[:, None]
    side = np.cross(st.index.normals[tris], [0.6, 0.8, 0.0])
    cn = np.cos(turn) * st.index.normals[tris] + np.sin(turn) * side / np.linalg.norm(side, axis=1, keepdims=True)
    stones.cnormal[ids] = cn
    wind = np.asarray(sc.storm.wind, dtype=float)
    coef = 3.0 * sc.hail.cd * sc.hail.rho_air / (8.0 * sc.hail.density)
    accel = drag_ref(stones.vel[ids], stones.radius[ids], wind, coef) + [0.0, 0.0, -GRAVITY]

    def k_patch(i, t, a, n):
        verts, w = st.patches.weights(i, t, stones.cbary[i], a, n, StormStats())
        return st.patches.stiffness(verts, w, n)

    for known in (False, True):
        cs = K = None
        lam = np.zeros(0)
        if known:  # a previous set with the first four stones and some forces
            prev = st.contacts.sets.build(ids[:4], tris[:4], bary[:4].copy(), cn[:4].copy(), ("prev",),
                                          r[:4].copy(), StormStats(), stones.crad[ids[:4]])
            cs, K = prev.stones, prev.K
            lam = -rng.uniform(0.1, 20.0, 4 * (3 if mode == "sticky" else 1))
            stones.crad[ids[:2]] *= 0.5  # two known contacts whose radius is out of date
        crad0 = stones.crad.copy()
        a_ref, resized_ref = patch_radii_ref(ids, tris, stones.mass, stones.radius, stones.vel, accel, crad0,
                                             stones.cnormal, cs, K, lam, mode == "sticky", st.patches.k_tri,
                                             k_patch, gf.young, gf.poisson, sc.contact.patch_min_radius,
                                             sc.contact.patch_tolerance, sc.time.rest_speed)
        stats = StormStats()
        a = st.patches.radii(stones, ids, tris, cs, None if K is None else np.diag(K).copy(), lam, stats)
        np.testing.assert_allclose(a, a_ref, rtol=1e-12)
        np.testing.assert_allclose(stones.crad[ids], a_ref, rtol=1e-12)
        assert stats.patch_resizes == resized_ref >= (1 if known else 0)
        assert stats.patch_weights_computed == (2 if known else 6) and np.all(a > 0)
