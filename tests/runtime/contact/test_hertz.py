"""Patch contacts against Hertz on a graded block that stands in for a half-space.

Reference: a rigid sphere of radius R pressed a depth delta into an elastic
half-space carries F = (4/3) E* sqrt(R) delta^(3/2) (Johnson, ch. 4).

The block (studies.hertz_study.block_bundle: halfspace_block's defaults, P1,
E = 2 MPa, nu = 0.35, R = 10 mm) and its measured force ratios F / F_Hertz at
delta/R = 0.01 / 0.02 / 0.04 (python -m studies.hertz_study):

=========  ========================  =======================================
fine size  press_spheres             the old block (50 mm, 30 % growth, 8 mm)
=========  ========================  =======================================
0.35 mm    1.136 / 1.092 / 1.070     1.170 / 1.134 / 1.128
0.25 mm    1.084 / 1.060 / 1.050
0.177 mm   1.054 / 1.041 / 1.038
=========  ========================  =======================================

The error under the load falls as h^p (p ~ 1.3, P1); what stays in the limit is the
far field and the clamp. On the 0.35 mm block at delta/R = 0.04 (a = 2 mm): the old block
1.128, clamped at 150 mm instead of 50 mm 1.101 (a Boussinesq estimate of the clamp:
0.75 a / H, 3 % at 50 mm), far-field elements growing 15 % per layer instead of 30 %
1.095, both 1.070, and a 300 mm block 1.064: the old block's Richardson limit (+2.5 /
+5.0 / +7.6 %) grew with the contact radius for that reason. The default-run tests use
the 0.35 mm block (15 % tolerance, and prescribing delta as the patch mean, the old
model, must be 30 % off); the slow tests refine twice and extrapolate.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("gmsh")

import hailstorm.runtime  # noqa: E402
from hailstorm.runtime.contact.hertz import hertz_force, hertz_impact, press_spheres, sphere_force  # noqa: E402
from hailstorm.runtime.contact.sphere_patch import sphere_offset, sphere_radius  # noqa: E402
from studies.hertz_study import (  # noqa: E402
    block_bundle, drop_stone, hertz_depth, origin_contact, rest_stone)

E, NU, R = 2.0e6, 0.35, 0.01
RATIOS = (0.01, 0.02, 0.04)


def _block_bundle(path, fine: float):
    return block_bundle(path, fine)


def _force_ratios(gf) -> tuple[np.ndarray, np.ndarray]:
    t, b = origin_contact(gf)
    new, old = [], []
    n = np.array([[0.0, 0.0, 1.0]])
    for rel in RATIOS:
        d = rel * R
        res = press_spheres(gf, [t], [b], [d], R)
        new.append(res.normal_force[0] / hertz_force(d, R, E, NU))
        sol = hailstorm.runtime.solve_contacts(gf, [t], [b], -d * n, mode="frictionless", normals=n,
                                     patch_radius=np.sqrt(R * d))
        old.append(-sol.forces[0, 2] / hertz_force(d, R, E, NU))
    return np.array(new), np.array(old)


@pytest.fixture(scope="module")
def coarse_block(tmp_path_factory):
    return _block_bundle(tmp_path_factory.mktemp("hs") / "block", 3.5e-4)


def test_sphere_offset_is_the_hertz_weighted_mean_of_the_paraboloid_for_small_contacts():
    # <r^2> under Hertz weights sqrt(1 - r^2/a^2) over a disc, by quadrature; a/R = 0.013, where the
    # sphere's offset is the paraboloid's to (a/R)^2 / 15 ~ 1e-5
    a, Rs = 1.3e-4, 0.01
    r = np.linspace(0.0, a, 200001)
    w = np.sqrt(np.clip(1 - (r / a) ** 2, 0, None)) * r
    trap = getattr(np, "trapezoid", None) or np.trapz
    mean_r2 = trap(w * r * r, r) / trap(w, r)
    assert sphere_offset(a, Rs) == pytest.approx(mean_r2 / (2 * Rs), rel=3e-5)
    assert sphere_offset(0.0, Rs) == 0.0
    x = np.array([0.1, 0.3])  # the series a^2 / (5 R) (1 + x^2 / 15 + ...)
    np.testing.assert_allclose(sphere_offset(x * Rs, Rs), x * x * Rs / 5 * (1 + x * x / 15), rtol=2e-3)
    # it grows with the patch up to its peak (0.149 R at a/R 0.910) and is held there beyond, where the
    # exact form would fall to 0 at 0.993 (a wider patch never has a smaller offset)
    x = np.linspace(0.01, 0.999, 400)
    o = sphere_offset(x * Rs, Rs)
    assert np.all(np.diff(o) >= 0.0)
    assert o.max() == pytest.approx(0.14886 * Rs, rel=1e-4) and o[-1] == o.max()


def test_the_sphere_law_against_sneddon_and_hertz():
    """sphere_force and sphere_radius against Sneddon's closed form written out here
    (F = E*/2 ((a^2 + R^2) ln((R + a)/(R - a)) - 2 a R), delta = a/2 ln((R + a)/(R - a))),
    Hertz's for small a/R, and the paraboloid's excess at large a/R (the reason for the law)."""
    e_star = E / (1 - NU**2)
    Rs = 0.005
    x = np.array([0.02, 0.1, 0.3, 0.5, 0.7, 0.9, 0.99])
    a = x * Rs
    L = np.log((Rs + a) / (Rs - a))
    F = e_star / 2 * ((a * a + Rs * Rs) * L - 2 * a * Rs)
    delta = a / 2 * L
    np.testing.assert_allclose(sphere_force(delta, Rs, E, NU), F, rtol=1e-9)
    np.testing.assert_allclose(sphere_radius(F, Rs, E, NU), a, rtol=1e-9)
    small = x <= 0.1
    np.testing.assert_allclose(sphere_force(delta[small], Rs, E, NU), hertz_force(delta[small], Rs, E, NU), rtol=4e-3)
    np.testing.assert_allclose(sphere_radius(F[small], Rs, E, NU),
                               hailstorm.runtime.hertz_radius(F[small], Rs, E, NU), rtol=2e-3)
    excess = hertz_force(delta, Rs, E, NU) / F - 1
    assert excess[3] == pytest.approx(0.028, abs=1e-3) and np.all(np.diff(excess) > 0)
    assert np.all(sphere_radius(1e3 * F, Rs, E, NU) < Rs)  # the sphere's radius never reaches R
    assert sphere_radius(0.0, Rs, E, NU) == 0.0


def test_press_spheres_matches_hertz_on_a_coarse_block(coarse_block):
    new, old = _force_ratios(coarse_block)
    assert np.all(np.abs(new - 1.0) < 0.15), new  # measured 1.136 / 1.092 / 1.070
    assert np.all(old > 1.3), old  # prescribing delta as the patch mean: the old, too-stiff model


def test_press_spheres_radius_is_consistent_with_its_force(coarse_block):
    t, b = origin_contact(coarse_block)
    res = press_spheres(coarse_block, [t], [b], [2e-4], R)
    a_of_f = sphere_radius(res.normal_force, R, E, NU)
    np.testing.assert_allclose(res.patch_radius, a_of_f, rtol=1e-5)
    assert res.patch_radius[0] == pytest.approx(np.sqrt(R * 2e-4), rel=0.1)  # near Hertz's sqrt(R delta)


def test_press_spheres_zero_depth_carries_no_force(coarse_block):
    t, b = origin_contact(coarse_block)
    res = press_spheres(coarse_block, [t, t], [b, b], [0.0, 1e-4], R)
    assert res.normal_force[0] == 0.0 and res.normal_force[1] > 0


@pytest.mark.parametrize("bad, match", [
    (dict(depths=[-1e-4]), "depths"),
    (dict(sphere_radii=0.0), "radii"),
    (dict(depths=[1e-4, 1e-4]), "shape"),
    (dict(barycentric=[[0.5, 0.5]]), "barycentric must have shape"),
])
def test_press_spheres_bad_input(coarse_block, bad, match):
    t, b = origin_contact(coarse_block)
    kw = dict(barycentric=[b], depths=[1e-4], sphere_radii=R) | bad
    with pytest.raises(ValueError, match=match):
        press_spheres(coarse_block, [t], **kw)


def test_smooth_normals_are_continuous_and_press_spheres_presses_along_them(seat_bundle):
    """On the 15 mm seat: a point on a smooth edge shared by two triangles (their facets 3-15 degrees
    apart, inside the crease) gets one normal from either; at a vertex of a smooth region it is the
    area-weighted vertex normal; on every triangle it is a unit vector within 45 degrees of the
    facet's; and ``press_spheres`` without normals presses along it."""
    from hailstorm.runtime.bundle.read import vertex_normals
    from hailstorm.runtime.contact.normals import corner_normals, smooth_normals, triangle_normals

    gf = hailstorm.runtime.load(seat_bundle)
    V, T = np.asarray(gf.vertices), np.asarray(gf.triangles)
    ok = np.flatnonzero(gf.contactable[T].all(axis=1))
    # an interior edge: two triangles sharing vertices (u, v)
    owner: dict[tuple[int, int], list[int]] = {}
    for t in ok:
        for a, b in ((0, 1), (1, 2), (2, 0)):
            owner.setdefault(tuple(sorted((int(T[t, a]), int(T[t, b])))), []).append(int(t))
    shared = [(e, ts) for e, ts in owner.items() if len(ts) == 2]
    fn = triangle_normals(V, T)
    def angle(ts):
        return np.degrees(np.arccos(np.clip(fn[ts[0]] @ fn[ts[1]], -1.0, 1.0)))

    CN = corner_normals(V, T)

    def one_reading(e, ts):  # both vertices read alike by both triangles (a smooth region)
        return all(np.array_equal(CN[ts[0]][T[ts[0]] == x][0], CN[ts[1]][T[ts[1]] == x][0]) for x in e)

    smooth = [(e, ts) for e, ts in shared if 3.0 < angle(ts) < 15.0 and one_reading(e, ts)]
    assert smooth  # the facets do differ on the seat's curved top
    (u, v), (t1, t2) = max(smooth, key=lambda item: angle(item[1]))
    bary = [np.where(T[t] == u, 0.3, 0.0) + np.where(T[t] == v, 0.7, 0.0) for t in (t1, t2)]
    n1, n2 = smooth_normals(V, T, np.array([t1, t2]), np.array(bary))
    np.testing.assert_allclose(n1, n2, rtol=0, atol=1e-14)
    corner = smooth_normals(V, T, np.array([t1]), (T[t1] == u).astype(float)[None])[0]
    np.testing.assert_allclose(corner, vertex_normals(V, T)[u], rtol=0, atol=1e-14)
    rng = np.random.default_rng(1)
    b = rng.dirichlet(np.ones(3), ok.size)
    n = smooth_normals(V, T, ok, b)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, rtol=1e-14)
    assert np.all(np.einsum("kd,kd->k", n, fn[ok]) > np.cos(np.radians(45)))
    default = press_spheres(gf, [t1], [bary[0]], [1e-3], 5e-3, rows=None)
    along = press_spheres(gf, [t1], [bary[0]], [1e-3], 5e-3, rows=None, normals=n1[None])
    assert default.normal_force[0] == along.normal_force[0]


@pytest.mark.slow
def test_press_spheres_converges_to_hertz(tmp_path):
    """Three meshes; the Richardson limit of the force ratio is within 5 % of Hertz for
    delta/R = 0.01 to 0.04 (the issue's requirement).

    Measured limits at delta/R = 0.01 / 0.02 / 0.04: +1.3 / +1.3 / +2.0 % (the 0.177 mm block itself
    +5.4 / +4.1 / +3.8 %). On the old block (50 mm,
    clamped at 50 mm, 30 % growth to 8 mm) they were +2.5 / +5.0 / +7.6 %: the sequence
    refines only the elements under the load, so the limit kept the far field's and the
    clamp's stiffening, which grows with the contact radius (module docstring).
    """
    h = (3.5e-4, 2.5e-4, 1.77e-4)
    e = np.array([_force_ratios(_block_bundle(tmp_path / f"b{i}", hi))[0] - 1.0 for i, hi in enumerate(h)])
    assert np.all(np.abs(e[1]) < np.abs(e[0])) and np.all(np.abs(e[2]) < np.abs(e[1]))  # it converges
    q = (e[0] - e[1]) / (e[1] - e[2])  # ratio of successive differences (equal refinement steps)
    limit = e[2] - (e[1] - e[2]) / (q - 1.0)
    assert np.all(np.abs(limit) < 0.05), limit
    assert np.all(np.abs(e[2]) < 0.06), e[2]  # the finest block itself


def test_boussinesq_point_load_on_the_block(coarse_block):
    """A unit normal point force on the block's top: u_z(r) = (1 - nu^2) F / (pi E r) + const
    over 3-30 mm (the constant: the finite, clamped block). Measured on the 0.35 mm block:
    coefficient 0.970 of Boussinesq's, bands 0.969 / 0.969 / 0.971, fit residual 1.0 %. The
    old block (50 mm, clamped at 50 mm, far field growing 30 % per element layer to 8 mm)
    gave 0.90: P1 elements at h ~ 0.3 r are 10 % stiff there, and that far field carried
    the force-indentation drift at large delta/R; the block now grows 15 % per layer
    (h ~ 0.15 r: P1's energy error ~ (h/r)^2 quarters) out to 150 mm."""
    gf = coarse_block
    V = np.asarray(gf.vertices)
    j = int(np.argmin(np.where(gf.contactable, np.linalg.norm(V, axis=1), np.inf)))
    uz = gf.compliance(np.arange(gf.n_vertices), [j])[:, 2].reshape(-1, 3)[:, 2]  # unit F_z at j
    r = np.linalg.norm(V[:, :2] - V[j, :2], axis=1)
    top = np.abs(V[:, 2]) < 1e-9
    m = top & (r >= 3e-3) & (r <= 30e-3)
    A = np.stack([1.0 / r[m], np.ones(m.sum())], axis=1)
    (c, off), *_ = np.linalg.lstsq(A, uz[m], rcond=None)
    c_b = (1 - NU**2) / (np.pi * E)
    assert 0.95 < c / c_b < 1.0, c / c_b  # P1 is stiff (never softer than the continuum); the old block: 0.90
    assert np.abs(A @ [c, off] - uz[m]).max() < 0.02 * np.abs(uz[m]).max()  # the 1/r shape
    bands = [np.median((uz[b] - off) * r[b]) / c_b for b in
             (top & (r >= lo) & (r < hi) for lo, hi in ((3e-3, 6e-3), (6e-3, 12e-3), (12e-3, 30e-3)))]
    assert max(bands) - min(bands) < 0.02, bands


# --------------------------------------------------------------------------
# the storm's patch contacts: a stone at rest under gravity
# --------------------------------------------------------------------------
STONE = 0.02  # radius of the resting stone [m] (a = 1.26 mm under its weight: 3.6 fine elements)


def _storm_rest_depth(gf) -> tuple[float, float, float, float]:
    """A 20 mm stone let down onto the block's top by the storm (exact integrator, patch
    contacts): (depth of its lowest point, its contact force, m g, patch radius) once at rest."""
    return rest_stone(gf, STONE, steps=800, dt=5e-4)  # 0.4 s: the bounces die out and the stone rests


def _api_rest_depth(gf, force: float) -> float:
    """The depth at which :func:`press_spheres` carries ``force`` (bisection)."""
    t, b = origin_contact(gf)
    lo, hi = 1e-6, 1e-3
    for _ in range(50):
        d = 0.5 * (lo + hi)
        lo, hi = (d, hi) if press_spheres(gf, [t], [b], [d], STONE).normal_force[0] < force else (lo, d)
    return d


def _hertz_depth(force: float) -> float:
    return hertz_depth(force, STONE, E, NU)


def test_storm_stone_rests_at_the_hertz_depth(coarse_block):
    """Measured on the 0.35 / 0.25 / 0.177 mm blocks: depth / Hertz 0.930 / 0.956 / 0.970 (the
    slow test extrapolates; the old block 0.909 / 0.933 / 0.947), force / m g 1.0000. The old
    prescription (delta as the patch mean) rested at 0.69 on the old 0.35 mm block."""
    depth, force, mg, a = _storm_rest_depth(coarse_block)
    assert force == pytest.approx(mg, rel=1e-2)  # the seat carries the stone
    dH = _hertz_depth(mg)
    assert abs(depth / dH - 1.0) < 0.10, depth / dH  # the coarse block is ~7 % stiff (press_spheres too)
    assert depth == pytest.approx(_api_rest_depth(coarse_block, mg), rel=0.02)  # the storm and the API agree
    assert a == pytest.approx(sphere_radius(mg, STONE, E, NU), rel=0.02)  # radius from the weight (the patch's, a << R)


@pytest.mark.slow
def test_storm_rest_depth_converges_to_hertz(tmp_path):
    """Three blocks; the Richardson limit of the storm's rest depth is within 5 % of Hertz
    (measured: 0.986; the old block 0.967)."""
    h = (3.5e-4, 2.5e-4, 1.77e-4)
    r = []
    for i, hi in enumerate(h):
        depth, _, mg, _ = _storm_rest_depth(_block_bundle(tmp_path / f"b{i}", hi))
        r.append(depth / _hertz_depth(mg) - 1.0)
    e = np.array(r)
    assert abs(e[1]) < abs(e[0]) and abs(e[2]) < abs(e[1])
    q = (e[0] - e[1]) / (e[1] - e[2])
    limit = e[2] - (e[1] - e[2]) / (q - 1.0)
    assert abs(limit) < 0.05, limit


def test_the_patch_law_is_the_spheres_at_its_radius_on_a_half_space():
    """On an ideal half-space a Hertz-pressure patch of radius a has the weighted-mean
    compliance c = 0.6 / (E* a) (the Hertz disc's, halfspace_patch_compliance) and the sphere's
    offset o (sphere_offset): the affine law F = (delta - o) / c carries the sphere's force at
    the sphere's depth for any a/R (Sneddon), Hertz's at Hertz's depth a^2 / R as a/R -> 0."""
    from hailstorm.runtime.contact.near_field import halfspace_patch_compliance

    x = np.array([0.01, 0.1, 0.3, 0.6, 0.9])
    Rs = np.array([0.005, 0.01, 0.02, 0.0125, 0.0025])
    a = x * Rs
    c, _ = halfspace_patch_compliance(a, E, NU)
    np.testing.assert_allclose(c, 0.6 * (1 - NU**2) / (E * a), rtol=1e-12)
    depth = a / 2 * np.log((Rs + a) / (Rs - a))  # the sphere's depth at contact radius a
    np.testing.assert_allclose((depth - sphere_offset(a, Rs)) / c, sphere_force(depth, Rs, E, NU), rtol=1e-9)
    hertz = (a * a / Rs - sphere_offset(a, Rs)) / c / hertz_force(a * a / Rs, Rs, E, NU)
    assert hertz[0] == pytest.approx(1.0, abs=1e-4)  # Hertz's where Hertz holds


def test_the_impact_patch_meets_the_spheres_impact():
    """The storm's impact law on an ideal half-space (affine_oscillator: k = 5 E* a / 3) with the
    patch of its own peak force (the fixed point a = impact_radius(F_max), F_max = v sqrt(k m)) and
    o = impact_offset(a, R), against the sphere's impact, m delta'' = -F(delta) with Sneddon's F
    integrated here to its energy balance: the same peak force and depth at every a/R, to the
    solvers' 1e-7 (measured: 3e-15; a/R 0.19, and the terminal speeds' 0.62 and 0.80). The patch of
    the sphere's own radius and sphere_offset (the static press's law) is a touch soft there: F_max
    1.1 and 2.2 % low, delta_max 0.7 and 1.5 % (measured; Hertz's paraboloid in its place: +2.7 ...
    +5.4 % and -1.3 ... -2.5 %)."""
    from scipy.integrate import quad
    from scipy.optimize import brentq
    from hailstorm.runtime.contact.sphere_patch import impact_offset, impact_radius
    from studies.hertz_study import affine_oscillator

    e_star = E / (1 - NU**2)
    for Rs, v, soft in ((0.005, 0.4, (0.0, 2e-3)), (0.0025, 9.1, (0.009, 0.013)), (0.0125, 20.4, (0.019, 0.024))):
        m = 917.0 * 4.0 / 3.0 * np.pi * Rs**3
        work = lambda d: quad(lambda t: float(sphere_force(t, Rs, E, NU)), 0.0, d, epsabs=0.0,  # noqa: E731
                              epsrel=1e-12)[0]
        d_max = brentq(lambda d: work(d) - 0.5 * m * v * v, 1e-9, 5 * Rs, xtol=1e-15)
        f_max = float(sphere_force(d_max, Rs, E, NU))
        for size, offset in ((impact_radius, impact_offset), (sphere_radius, sphere_offset)):
            a = 0.5 * Rs
            for _ in range(200):
                a = float(size(v * np.sqrt(5.0 / 3.0 * e_star * a * m), Rs, E, NU))
            got = affine_oscillator(m, v, 5.0 / 3.0 * e_star * a, float(offset(a, Rs)), gravity=0.0)
            if size is impact_radius:
                assert got.max_force == pytest.approx(f_max, rel=1e-7)
                assert got.max_depth == pytest.approx(d_max, rel=1e-7)
            else:  # the static patch: soft by what the impact patch mends
                assert soft[0] <= 1.0 - got.max_force / f_max <= soft[1]
                assert 0.0 <= 1.0 - got.max_depth / d_max <= soft[1]


def test_the_impact_patch_kernels_against_their_reference():
    """sphere_w, impact_patch_x and impact_offset_of_patch (compiled: Gauss-Legendre in atanh,
    Newton) against adaptive quadrature and bracketing of Sneddon's closed form
    (tests/reference/sphere_ref.py); Hertz's limits (w = 8 x^5 / 15, i(x) = x (1 + 4 x^2 / 105),
    o = a^2 / (5 R)); the offset grows with the patch at every size (no peak, unlike the static
    sphere_offset); the public faces' clipping and errors."""
    from reference.sphere_ref import impact_offset_ref, impact_patch_ref, w_ref
    from hailstorm.runtime.compiled.sphere import impact_offset_of_patch, impact_patch_x, sphere_w
    from hailstorm.runtime.contact.sphere_patch import impact_offset, impact_radius

    for x in (0.02, 0.1, 0.3, 0.5, 0.7, 0.8, 0.9, 0.99, 0.999):
        assert sphere_w(x) == pytest.approx(w_ref(x), rel=1e-10)
        assert impact_patch_x(x) == pytest.approx(impact_patch_ref(x), rel=1e-10)
        p = impact_patch_x(x)
        assert impact_offset_of_patch(p) == pytest.approx(impact_offset_ref(p, 1.0), rel=1e-9)
    for x in (1e-9, 1e-6, 1e-3, 0.01):  # Hertz's limits (the closed forms lose eps / x^2 here: not compared)
        assert sphere_w(x) == pytest.approx(8.0 * x**5 / 15.0, rel=max(2e-12, x * x))
        assert impact_patch_x(x) == pytest.approx(x * (1.0 + 4.0 * x * x / 105.0), rel=max(1e-14, x**4))
        assert impact_offset_of_patch(x) == pytest.approx(0.2 * x * x, rel=max(1e-14, 0.2 * x * x))
    assert sphere_w(0.0) == 0.0 and impact_patch_x(0.0) == 0.0 and impact_offset_of_patch(0.0) == 0.0
    Rs = 0.005
    o = impact_offset(np.linspace(0.0, Rs, 300), Rs)
    assert o[0] == 0.0 and np.all(np.diff(o) > 0)
    assert sphere_offset(0.8 * Rs, Rs) < impact_offset(0.8 * Rs, Rs)  # (the patch lies wider than the contact)
    F = np.array([0.0, 1e-3, 1.0, 50.0, 1e5])
    a = impact_radius(F, Rs, E, NU)
    x = sphere_radius(F, Rs, E, NU) / Rs
    np.testing.assert_allclose(a[1:4], [impact_patch_ref(v) * Rs for v in x[1:4]], rtol=1e-10)
    assert a[0] == 0.0 and a[4] > Rs  # past the cap of the storm's patches (R), which the caller applies
    assert impact_radius(1.0, Rs, E, NU, a_min=4e-3, a_max=4.5e-3) == 4e-3
    with pytest.raises(ValueError, match="impact_radius needs"):
        impact_radius(1.0, -Rs, E, NU)


# --------------------------------------------------------------------------
# the storm's contacts against Hertz's impact theory
# --------------------------------------------------------------------------
def test_hertz_impact_matches_the_equation_of_motion():
    """hertz_impact against an independent integration of m delta'' = m g - K delta^(3/2)
    (K = (4/3) E* sqrt(R), delta(0) = 0, delta'(0) = v) until release; without gravity
    the closed form (15 m v^2 / (16 E* sqrt(R)))^(2/5) and t_c = 2.9432 delta_max / v."""
    from scipy.integrate import solve_ivp

    m, v, Rs = 3.84e-3, 0.4, 0.01
    K = 4.0 / 3.0 * E / (1 - NU**2) * np.sqrt(Rs)
    for g in (0.0, 9.81):
        def rhs(t, y):
            return [y[1], g - K / m * max(y[0], 0.0) ** 1.5]
        out = lambda t, y: y[0] + 1e-12 * (t == 0)  # noqa: E731  (release: delta back to 0)
        out.terminal, out.direction = True, -1
        sol = solve_ivp(rhs, (0.0, 1.0), [0.0, v], events=out, rtol=1e-11, atol=1e-15, max_step=1e-5)
        ref = hertz_impact(m, v, Rs, E, NU, gravity=g)
        assert ref.max_depth == pytest.approx(sol.y[0].max(), rel=1e-6)
        assert ref.max_force == pytest.approx(K * sol.y[0].max() ** 1.5, rel=1e-6)
        assert ref.duration == pytest.approx(sol.t_events[0][0], rel=1e-6)
    e_star = E / (1 - NU**2)
    d0 = (15 * m * v * v / (16 * e_star * np.sqrt(Rs))) ** 0.4
    h0 = hertz_impact(m, v, Rs, E, NU)
    assert h0.max_depth == pytest.approx(d0, rel=1e-12)
    assert h0.duration == pytest.approx(2.9432 * d0 / v, rel=1e-4)
    with pytest.raises(ValueError, match="speed"):
        hertz_impact(m, 0.0, Rs, E, NU)


def test_sphere_impact_matches_the_equation_of_motion():
    """sphere_impact against an independent integration of m delta'' = m g - F(delta), F Sneddon's
    closed form written here (x from delta = (a/2) ln((R + a)/(R - a)) by bisection), until release;
    at a/R ~ 0.2 within 0.3 % of Hertz's impact, at a/R ~ 0.8 its peak force well below it."""
    from scipy.integrate import solve_ivp
    from hailstorm.runtime.contact.hertz import sphere_impact

    e_star = E / (1 - NU**2)

    def force(d, Rs):
        lo, hi = 0.0, 1.0 - 1e-15
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if mid / 2 * np.log((1 + mid) / (1 - mid)) * Rs < d else (lo, mid)
        a = 0.5 * (lo + hi) * Rs
        L = np.log((Rs + a) / (Rs - a))
        return e_star / 2 * ((a * a + Rs * Rs) * L - 2 * a * Rs)

    for Rs, v, g in ((0.005, 0.4, 9.81), (0.0125, 20.4, 0.0), (0.0025, 9.1, 9.81)):
        m = 917.0 * 4.0 / 3.0 * np.pi * Rs**3

        def rhs(t, y):
            return [y[1], g - force(max(y[0], 0.0), Rs) / m]
        out = lambda t, y: y[0] + 1e-15 * (t == 0)  # noqa: E731  (release: delta back to 0)
        out.terminal, out.direction = True, -1
        h = hertz_impact(m, v, Rs, E, NU, gravity=g)
        sol = solve_ivp(rhs, (0.0, 4 * h.duration), [0.0, v], events=out, rtol=1e-10, atol=1e-14,
                        max_step=h.duration / 400)
        ref = sphere_impact(m, v, Rs, E, NU, gravity=g)
        assert ref.max_depth == pytest.approx(sol.y[0].max(), rel=1e-5)
        assert ref.max_force == pytest.approx(force(sol.y[0].max(), Rs), rel=1e-5)
        assert ref.duration == pytest.approx(sol.t_events[0][0], rel=1e-5)
        if Rs == 0.005:
            assert ref.max_force == pytest.approx(h.max_force, rel=3e-3)
        if Rs == 0.0125:
            assert ref.max_force < 0.96 * h.max_force  # a/R ~ 0.8: the paraboloid is too stiff
    with pytest.raises(ValueError, match="speed"):
        sphere_impact(1e-3, 0.0, 0.005, E, NU)
    with pytest.raises(ValueError, match="deeper than a/R 0.999"):
        sphere_impact(1.0, 1e4, 0.005, E, NU)


def test_storm_drop_against_hertz_impact(coarse_block):
    """A 10 mm stone dropped at 0.4 m/s on the block (exact integrator, patch contacts,
    restitution 1): peak indentation, peak force and contact duration against Hertz's
    quasi-static impact (with gravity: 370.5 um, 2.168 N, 2.701 ms).

    The storm's patch keeps one radius a through an impact (sized for its expected peak
    force) and its law is affine, F = k (delta - o), o = impact_offset(a, R) (~ a^2 / (5 R) here,
    a/R ~ 0.2): on an ideal half-space Hertz's delta_max and F_max within 0.1 %, and 0.990 of t_c
    (tests above). The block is a few % stiff at the patch's radius (press_spheres: +7 % at
    a = 2 mm; F_max goes as k^(1/2), the spring's share of delta_max and t_c as k^(-1/2)), so
    the storm is held to the law at its own radius and offset with the block's Hertz disc
    (4 %) and to Hertz (6 %). The exact integrator has no step error in a linear spring;
    the peak is sampled at steps of dt = 20 us over t_c = 2.7 ms: < 1e-3."""
    dr = drop_stone(coarse_block, stone_radius=0.01, speed=0.4, dt=2e-5)
    s, h, law = dr.storm, dr.hertz, dr.affine
    assert dr.rebound == pytest.approx(1.0, abs=2e-3)  # restitution 1: no energy lost
    from hailstorm.runtime.contact.sphere_patch import impact_offset

    assert dr.offset == pytest.approx(impact_offset(dr.patch_radius, 0.01), rel=0.05)  # the patch resolves the sphere
    for got, want in ((s.max_depth, law.max_depth), (s.max_force, law.max_force), (s.duration, law.duration)):
        assert got == pytest.approx(want, rel=0.04)
    for got, want in ((s.max_depth, h.max_depth), (s.max_force, h.max_force), (s.duration, h.duration)):
        assert got == pytest.approx(want, rel=0.06)
    assert dr.patch_radius == pytest.approx(np.sqrt(0.01 * h.max_depth), rel=0.1)  # near Hertz's sqrt(R delta_max)


def test_press_spheres_settles_where_the_plain_update_cycles(seat_bundle):
    """Deep 12.5 mm stones on the 15 mm seat: the plain fixed-point update a <- sphere_radius(F(a))
    cycled at 7 of these 60 places (50 iterations, RuntimeError); bracketing and bisection settle
    every one, at a radius consistent with its force to within the jump of F(a) where the patch's
    vertex set changes (measured below 0.4 %)."""
    gf = hailstorm.runtime.load(seat_bundle)
    rng = np.random.default_rng(0)
    ok = np.flatnonzero(gf.contactable[gf.triangles].all(axis=1))
    tri, bary = rng.choice(ok, size=60, replace=False), rng.dirichlet(np.ones(3), size=60)
    for i in range(60):
        res = press_spheres(gf, tri[i:i + 1], bary[i:i + 1], [10.573e-3], 12.5e-3, rows=None)
        a_of_f = sphere_radius(res.normal_force, 12.5e-3, gf.young, gf.poisson)
        np.testing.assert_allclose(res.patch_radius, a_of_f, rtol=1e-2)
