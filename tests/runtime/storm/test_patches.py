"""The storm's patch contacts on their own (:class:`Patches`): the radii against the Hertz radius of
the force they are given and the tolerance band, the weights against the contact API's
``patch_weights`` and their cache, the near-field blocks against :meth:`NearField.blocks`,
and the stiffness against ``1 / (g^T D g)`` written out on the bundle's D.

On the synthetic plate (``helpers.plate_gf``: 13 x 13 vertices 10 mm apart at z = 0, normal
+z, E = 2 MPa, nu = 0.35, the boundary ring clamped).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import plate_gf

from hailstorm.runtime.contact.near_field import near_field
from hailstorm.runtime.contact.normals import triangle_normals
from hailstorm.runtime.contact.sphere_patch import hertz_radius, impact_offset, impact_radius
from hailstorm.runtime.contact.weights import patch_weights
from hailstorm.runtime.storm.scene import Scene
from hailstorm.runtime.storm.hail import GRAVITY, Air
from hailstorm.runtime.storm.patches import Patches, peak_radius
from hailstorm.runtime.storm.recording import StormStats
from hailstorm.runtime.storm.seat import SeatState
from hailstorm.runtime.storm.stones import Stones

N = 13
YOUNG, POISSON = 2e6, 0.35  # plate_gf's material
UP = np.array([0.0, 0.0, 1.0])


def cell(i, j, upper=0):
    """Triangle of grid cell (i, j) (two per cell)."""
    return 2 * (i * (N - 1) + j) + upper


@pytest.fixture(scope="module")
def gf():
    return plate_gf(N)


def make_patches(gf, soft=None, **contact):
    sc = Scene.default()
    normals = triangle_normals(gf.vertices, gf.triangles)
    if soft is None:
        fixed = np.asarray(gf.fixed)
        tri = np.asarray(gf.triangles)
        soft = ((np.asarray(gf.contactable) | fixed)[tri].all(axis=1) & ~fixed[tri].all(axis=1))
    air = Air.of((0.0, 0.0, 0.0), False, sc.hail.cd, sc.hail.rho_air, sc.hail.density)  # no drag: f_eq = m g
    return Patches(gf, dataclasses.replace(sc.contact, **contact), sc.time, SeatState(gf), normals, soft, air)


def hertz(force, R, a_min):
    """The patch radius of a peak force: the sphere's impact patch (Hertz's radius for a << R), clipped to
    [a_min, R], at least a_min."""
    return np.maximum(impact_radius(force, R, YOUNG, POISSON, a_min=a_min, a_max=R), a_min)


def d_block(gf, verts):
    """D between the dofs of ``verts`` (rows) and their columns (clamped vertices: 0), by hand."""
    D = np.asarray(gf.D)
    k = len(verts)
    out = np.zeros((3 * k, 3 * k))
    for a, va in enumerate(verts):
        for b, vb in enumerate(verts):
            c = gf.column_of[vb]
            if c >= 0:
                out[3 * a:3 * a + 3, 3 * b:3 * b + 3] = D[3 * va:3 * va + 3, 3 * c:3 * c + 3]
    return out


def compliance_by_hand(gf, verts, w, n):
    """``g^T D g``, ``g = w kron n`` on ``verts``."""
    g = np.kron(w, n)
    return float(g @ d_block(gf, verts) @ g)


def k_by_hand(gf, t, n):
    """A triangle's point stiffness at its centroid, ``1 / (b^T D b)`` (0: no compliance)."""
    c = compliance_by_hand(gf, gf.triangles[t], np.full(3, 1.0 / 3.0), n)
    return 1.0 / c if c > 0 else 0.0


def dense(gf, verts, w):
    """Weights per surface vertex (padding and order do not matter)."""
    out = np.zeros(gf.vertices.shape[0])
    np.add.at(out, verts, w)
    return out


def stones_on(gf, tris, bary, radius, vel):
    st = Stones(density=917.0)
    X = np.einsum("ka,kad->kd", bary, gf.vertices[gf.triangles[tris]])
    ids = st.add(X + np.asarray(radius)[:, None] * UP, vel, radius)
    st.cbary[ids] = bary
    st.cnormal[ids] = UP  # (the plate's)
    return st, ids


def test_hertz_radius_is_the_closed_form():
    """The oracle's oracle: ``a = (3 F R / (4 E*))^(1/3)`` (Johnson ch. 4), clipped."""
    F, R = np.array([0.01, 1.0, 50.0]), np.array([0.003, 0.005, 0.01])
    a = np.cbrt(3.0 * F * R * (1 - POISSON**2) / (4.0 * YOUNG))
    np.testing.assert_allclose(hertz_radius(F, R, YOUNG, POISSON), a, rtol=1e-14)
    # the sizing's radius is the sphere's impact patch: below Hertz's, by 2 (a/R)^2 / 21 for a << R
    # (the sphere's radius, 1 - 2 x^2 / 15 from q(x) = 4 x^3 / 3 (1 + 2 x^2 / 5 + ...), times the
    # patch's 1 + 4 x^2 / 105; both against Sneddon's closed form: test_hertz.py)
    got = hertz(F, R, 1e-3)
    assert got[0] == 1e-3 and np.all(got[1:] < a[1:])
    assert got[1] == pytest.approx(a[1] * (1 - 2 * (a[1] / R[1]) ** 2 / 21), rel=5e-4)  # a/R 0.24


# ----------------------------------------------------------------------------------------------
# radii
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("sticky", [False, True])
def test_radii_of_known_contacts_are_the_impact_patch_of_the_peak_force(gf, sticky):
    """Contacts of the current set (force ``F`` from ``lam``, stiffness ``k`` from the diagonal of its
    capacitance), sized for the first time: ``impact_radius(F_eq + sqrt((F - F_eq)^2 + k m v_n^2))``
    with ``F_eq = m g`` (no drag), clipped to [patch_min_radius, R], by hand."""
    p = make_patches(gf, mode="sticky" if sticky else "frictionless", patch_min_radius=1e-3)
    tris = np.array([cell(5, 5), cell(3, 7, 1), cell(8, 2), cell(6, 9, 1), cell(2, 2)])
    bary = np.array([[0.2, 0.3, 0.5], [1 / 3, 1 / 3, 1 / 3], [0.6, 0.2, 0.2], [0.1, 0.1, 0.8], [0.5, 0.25, 0.25]])
    R = np.array([0.003, 0.008, 0.0025, 0.012, 0.0008])
    vn = np.array([0.0, -1.5, 0.3, -4.0, -0.2])  # the normal is +z
    vel = np.column_stack([np.array([0.1, -0.2, 0.0, 0.3, 0.0]), np.zeros(5), vn])
    st, ids = stones_on(gf, tris, bary, R, vel)
    F = np.array([300.0, 0.02, 1e-4, 40.0, 0.5])  # at rest (a > R), light, below its weight, heavy, R < a_min
    k = np.array([2e3, 5e3, 1e3, 8e3, 4e3])
    # the set lists the stones in another order, with one more stone
    order = np.array([3, 0, 4, 1, 2])
    cs = np.concatenate([[77], ids[order]])
    if sticky:
        d = np.array([0.3, -0.4, -1.0])  # a sticky force with tangential parts: its normal part counts
        lam = np.concatenate([[0.0, 0.0, -1.0]] + [F[i] * d / abs(d[2]) for i in order])
        kd = np.concatenate([[1.0, 1.0, 1.0]] + [[9e9, 9e9, k[i]] for i in order])  # n n^T picks the z one
    else:
        lam = np.concatenate([[-1.0], -F[order]])
        kd = np.concatenate([[1.0], k[order]])
    m = st.mass[ids]
    f_eq = m * GRAVITY
    peak = f_eq + np.sqrt((F - f_eq) ** 2 + k * m * vn**2)
    want = hertz(peak, R, 1e-3)
    # floored, at the ceiling (the sphere's radius nears R under 300 N) and in between
    assert np.any(want == 1e-3) and np.any(np.isclose(want, R, rtol=1e-4)) and np.any((want > 1e-3) & (want < 0.99 * R))
    stats = StormStats()
    a = p.radii(st, ids, tris, cs, kd, lam, stats)
    np.testing.assert_allclose(a, want, rtol=1e-12)
    np.testing.assert_array_equal(st.crad[ids], a)
    assert stats.patch_resizes == 0 and stats.patch_weights_computed == 0  # first radii, known contacts
    assert stats.max_patch_radius_m == a.max()
    # a stone resting under its own weight: F = F_eq, v = 0 -> the patch of its weight
    st.vel[ids] = 0.0
    st.crad[ids] = 0.0
    lam_w = lam.copy()
    if sticky:
        lam_w[3:] = np.concatenate([f_eq[i] * d / abs(d[2]) for i in order])
    else:
        lam_w[1:] = -f_eq[order]
    np.testing.assert_allclose(p.radii(st, ids, tris, cs, kd, lam_w, StormStats()), hertz(f_eq, R, 1e-3),
                               rtol=1e-12)


def _known(gf, ratio, vn, force=None, k=3e3, R=0.006):
    """One known contact (stiffness ``k``, force ``force``, default its weight) moving at ``vn``
    along the normal, its current radius ``ratio`` times its target radius (by hand); returns
    (patches, stones, ids, triangles, Kdiag, lam, target radius, oscillation amplitude)."""
    p = make_patches(gf, patch_min_radius=1e-4, patch_tolerance=0.2)
    t = np.array([cell(6, 6)])
    st, ids = stones_on(gf, t, np.array([[0.3, 0.3, 0.4]]), np.array([R]), np.array([[0.0, 0.0, vn]]))
    m = st.mass[0]
    f_eq = m * GRAVITY
    f = f_eq if force is None else force
    target = float(hertz(f_eq + np.sqrt((f - f_eq) ** 2 + k * m * vn**2), R, 1e-4))
    assert 1e-4 < target < R
    st.crad[0] = ratio * target
    amp = np.sqrt((f - f_eq) ** 2 / (k * m) + vn**2)
    return p, st, ids, t, np.array([k]), np.array([-f]), target, amp


@pytest.mark.parametrize(("ratio", "vn", "resized"), [
    (1.0 / 1.1, -1.0, False),  # the target 10 % above the radius: inside the band, kept
    (1.0 / 1.19, -1.0, False),
    (1.0 / 1.21, -1.0, True),  # 21 % above: re-sized
    (1.0 / 2.0, -1.0, True),
    (1.1, -1.0, False),  # below the radius, while moving: kept (re-weighting a rebound
    (1.5, -1.0, False),  # would change the stiffness its damping was tuned for: module notes)
    (1.05, 0.0, True),  # at rest: re-sized once 1 % off (REST_TOLERANCE), either way
    (1.0 / 1.05, 0.0, True),
    (1.005, 0.0, False),
    (1.0 / 1.005, 0.0, False),
])
def test_radius_band(gf, ratio, vn, resized):
    """A contact keeps its radius ``a`` while its target stays in the band up to ``a (1 + tol)``
    (tol = patch_tolerance = 0.2) and re-sizes to the target beyond it; to a target below ``a``
    only once it rests (amplitude below rest_speed), there once 1 % off."""
    p, st, ids, t, kd, lam, target, amp = _known(gf, ratio, vn, force=0.5 if vn else None)
    assert (amp < p.time.rest_speed) == (vn == 0.0)
    before = float(st.crad[0])
    stats = StormStats()
    a = p.radii(st, ids, t, ids, kd, lam, stats)
    assert a[0] == pytest.approx(target if resized else before, rel=1e-12)
    assert st.crad[0] == a[0]
    assert stats.patch_resizes == int(resized)
    assert stats.patch_weights_computed == 0  # a known contact's weights are not made here


@pytest.mark.parametrize("tol", [0.2, 0.01])
def test_new_contact_is_sized_with_the_triangle_then_its_patch(gf, tol):
    """A contact not in the set (``F = 0``): first radius ``a0`` from the triangle's point stiffness
    (``1 / (b^T D b)``, ``b`` = the centroid's weights times the normal), then ``a1`` from the
    stiffness of the patch of radius ``a0`` (its ``patch_weights``); ``a1`` is taken when outside
    the band of ``a0`` (here 2 % off: kept at tol = 0.2, taken at 0.01). Everything by hand; the
    weights at ``a0`` go to the cache."""
    p = make_patches(gf, patch_min_radius=1e-3, patch_tolerance=tol)
    tris = np.array([cell(6, 6), cell(4, 5, 1), cell(7, 3)])
    bary = np.array([[0.2, 0.3, 0.5], [1 / 3, 1 / 3, 1 / 3], [0.7, 0.2, 0.1]])
    R = np.array([0.01, 0.006, 0.012])
    vn = np.array([-12.0, -0.5, -25.0])
    st, ids = stones_on(gf, tris, bary, R, np.column_stack([np.zeros((3, 2)), vn]))
    m, f_eq = st.mass[ids], st.mass[ids] * GRAVITY
    k_tri = np.array([k_by_hand(gf, t, UP) for t in tris])
    a0 = hertz(f_eq + np.sqrt(f_eq**2 + k_tri * m * vn**2), R, 1e-3)
    v0, w0 = patch_weights(gf, tris, bary, a0, np.tile(UP, (3, 1)))
    k_patch = np.array([1.0 / compliance_by_hand(gf, v0[i], w0[i], UP) for i in range(3)])
    a1 = hertz(f_eq + np.sqrt(f_eq**2 + k_patch * m * vn**2), R, 1e-3)
    want = np.where((a1 > (1 + tol) * a0) | ((1 + tol) * a1 < a0), a1, a0)
    assert np.all(a0 > 1e-3)  # real patches
    # the second one lies within its triangle: the same stiffness by two sums (b^T D b against the
    # patch's weights), equal to rounding (a 3 x 3 block of a well-conditioned D: 1e-12 is ample)
    assert a1[1] == pytest.approx(a0[1], rel=1e-12)
    assert np.count_nonzero(want != a0) == (2 if tol < 0.1 else 0)
    stats = StormStats()
    a = p.radii(st, ids, tris, None, None, np.zeros(0), stats)
    np.testing.assert_allclose(a, want, rtol=1e-9)  # cube roots of stiffnesses summed in another order
    np.testing.assert_array_equal(st.crad[ids], a)
    assert stats.patch_weights_computed == 3 and stats.patch_resizes == 0
    # the weights at the kernel's first radius are cached: asking for the kept radii computes
    # nothing, the re-sized ones (tol 0.01) are computed at their new radius. The radii asked are
    # the kernel's own (the cache is keyed on the radius it computed, not on a by-hand copy of it)
    kept = 3 if tol > 0.1 else 1
    stats2 = StormStats()
    verts, w = p.weights(ids, tris, bary, a, np.tile(UP, (3, 1)), stats2)
    assert stats2.patch_weights_reused == kept and stats2.patch_weights_computed == 3 - kept
    va, wa = patch_weights(gf, tris, bary, a, np.tile(UP, (3, 1)))
    for i in range(3):
        np.testing.assert_allclose(dense(gf, verts[i], w[i]), dense(gf, va[i], wa[i]), rtol=1e-12, atol=1e-15)


def test_peak_radius_on_a_half_space_is_the_spheres_impact():
    """No body term (``b = 0``) and no weight: ``k = a / d``, ``d = 3 / (5 E*)`` (Hertz's disc), and the
    linear oscillator's peak force is ``sqrt(k m v^2)``. A stone whose energy ``m v^2 / 2`` is the
    sphere's work ``W = E* R^3 w(x)`` to ``x = a / R`` (Sneddon's law integrated by adaptive
    quadrature, tests/reference/sphere_ref.py) gets the patch ``R 3 q(x)^2 / (10 w(x))``, whose
    oscillator then peaks at the sphere's own force ``E* R^2 q(x)`` and, with
    :func:`impact_offset`, depth ``R x atanh x`` (Hertz's ``a^(5/2) = (3 R / (4 E*)) sqrt(m v^2 / d)``
    for small ``x``; a patch of the sphere's own radius ``x R`` would peak 0.6 / 1.9 % low at that
    energy, ``x`` 0.5 / 0.8). With a weight and a body term the result is a fixed point of its own map (to the
    iteration's 1e-12); the floor, the approach to the ceiling and a point contact (start 0) are
    kept."""
    from reference.sphere_ref import impact_patch_ref, q_ref, w_ref

    e_star = YOUNG / (1.0 - POISSON**2)
    d = 3.0 / (5.0 * e_star)
    R = np.array([0.0025, 0.005, 0.0125, 0.004, 0.003, 0.01])
    x = np.array([0.02, 0.5, 0.8])
    q = np.array([q_ref(v) for v in x])
    w = np.array([w_ref(v) for v in x])
    mv2 = np.array([0.0, 0.0, 0.0, 1e-16, 5.0, 0.2])
    mv2[:3] = 2.0 * e_star * R[:3] ** 3 * w
    f_eq = np.zeros(6)
    start = np.full(6, 1e-3)
    start[5] = 0.0
    a = peak_radius(np.zeros(6), d, start, f_eq, mv2, R, e_star, 1e-5)
    np.testing.assert_allclose(a[:3], [impact_patch_ref(v) * r for v, r in zip(x, R[:3])], rtol=1e-9)
    F = np.sqrt(a[:3] / d * mv2[:3])  # the oscillator's peak force and depth
    np.testing.assert_allclose(F, e_star * R[:3] ** 2 * q, rtol=1e-9)
    depth = impact_offset(a[:3], R[:3]) + d / a[:3] * F
    np.testing.assert_allclose(depth, R[:3] * x * np.arctanh(x), rtol=1e-9)
    soft = np.sqrt(5.0 * e_star * x * R[:3] / 3.0 * mv2[:3]) / F - 1.0  # the sphere's own radius instead
    assert -0.021 < soft[2] < -0.018 and -0.007 < soft[1] < -0.005 and abs(soft[0]) < 1e-4
    hertz_closed = (3.0 * R / (4.0 * e_star) * np.sqrt(mv2 / d)) ** 0.4
    assert a[0] == pytest.approx(hertz_closed[0], rel=1e-3)  # Hertz's where a << R
    assert a[1] < 0.99 * hertz_closed[1]  # the paraboloid's radius is too large at a/R 0.5
    assert a[3] == 1e-5 and hertz_closed[3] < 1e-5  # the floor
    assert 0.95 * R[4] < a[4] <= R[4] and hertz_closed[4] > R[4]  # the patch nears R, never past it
    assert a[5] == 0.0  # a point contact stays one
    # a weight and a body term (softer, and stiffer than the half-space): a fixed point of the map
    b = np.array([2e-4, -1e-5, 5e-5])
    fe = np.array([0.002, 0.05, 0.5])
    mv2 = np.array([0.01, 0.1, 2.0])
    a = peak_radius(b, d, np.full(3, 2e-3), fe, mv2, R[:3], e_star, 1e-4)
    k = 1.0 / (b + d / a)
    F = fe + np.sqrt(fe**2 + k * mv2)
    np.testing.assert_allclose(a, np.clip(impact_radius(F, R[:3], YOUNG, POISSON), 1e-4, R[:3]), rtol=1e-10)
    a_free = peak_radius(np.zeros(1), d, np.full(1, 2e-3), np.zeros(1), mv2[:1], R[:1], e_star, 1e-4)
    assert a[0] < a_free[0]  # a softer body: a smaller peak force, a smaller patch


@pytest.mark.parametrize("vn", [-3.0, -12.0])
def test_first_touch_radius_is_the_fixed_point_of_its_mesh(gf, vn):
    """With the near field the first-touch radius solves ``a = a_i(F_peak(k(a)))``,
    ``1 / k(a) = w^T D w + c(a) - w^T H w`` with the body's part ``w^T D w - w^T H w`` of the patch
    at the first radius ``a0`` (by hand: ``patch_weights``, ``g^T D g``, ``NearField.blocks``). Held
    to the fixed point with the whole model re-evaluated at every radius (the weights and both
    sums at each iterate) within 0.5 % (measured here: 0.17 % at most, against 3-47 % for ``a0``):
    the body's part is smooth in ``a``. (In a 2 000-stone storm on the default seat the largest of
    1 064 first touches was 1.7 % of the radius, the median 0.1 %.)"""
    p = make_patches(gf, patch_min_radius=1e-4)
    nf = near_field("halfspace", gf.young, gf.poisson)
    tris = np.array([cell(6, 6), cell(4, 5, 1), cell(7, 3)])
    bary = np.array([[0.2, 0.3, 0.5], [1 / 3, 1 / 3, 1 / 3], [0.9, 0.05, 0.05]])
    R = np.array([0.0025, 0.005, 0.0125])
    st, ids = stones_on(gf, tris, bary, R, np.column_stack([np.zeros((3, 2)), np.full(3, vn)]))
    m, f_eq = st.mass[ids], st.mass[ids] * GRAVITY
    normals = np.tile(UP, (3, 1))
    X = np.einsum("ka,kad->kd", bary, gf.vertices[gf.triangles[tris]])
    e_star = YOUNG / (1.0 - POISSON**2)

    def model_compliance(a):
        v, w = patch_weights(gf, tris, bary, a, normals)
        dw = np.array([compliance_by_hand(gf, v[i], w[i], UP) for i in range(3)])
        return dw + nf.blocks(gf, a, v, w, X, normals, False)[:, 0, 0]

    a0 = p.radii(st, ids, tris, None, None, np.zeros(0), StormStats()).copy()
    st.crad[ids] = 0.0
    got = p.first_touch(st, ids, tris, nf, StormStats())
    np.testing.assert_array_equal(st.crad[ids], got)
    d = float(nf.compliance(np.ones(1))[0][0])
    body = model_compliance(a0) - d / a0
    np.testing.assert_allclose(got, peak_radius(body, d, a0, f_eq, m * vn**2, R, e_star, 1e-4), rtol=1e-9)
    full = a0.copy()
    for _ in range(30):
        k = 1.0 / model_compliance(full)
        full = hertz(f_eq + np.sqrt(f_eq**2 + k * m * vn**2), R, 1e-4)
    assert np.all((full > 1e-4) & (full < R))
    assert np.max(np.abs(a0 / full - 1)) > 0.05  # the first radius alone is off
    np.testing.assert_allclose(got, full, rtol=5e-3)


# ----------------------------------------------------------------------------------------------
# weights, their cache, forget
# ----------------------------------------------------------------------------------------------
TRIS = np.array([cell(6, 6), cell(3, 4, 1), cell(9, 8), cell(1, 1)])
BARY = np.array([[0.2, 0.3, 0.5], [1 / 3, 1 / 3, 1 / 3], [0.05, 0.9, 0.05], [0.4, 0.4, 0.2]])
RADII = np.array([0.004, 0.0, 0.025, 0.012])  # sub-element, a point contact, several elements, at the ring
IDS = np.array([3, 8, 1, 20])


def test_weights_are_the_contact_apis_patch_weights(gf):
    p = make_patches(gf)
    normals = np.tile(UP, (4, 1))
    stats = StormStats()
    verts, w = p.weights(IDS, TRIS, BARY, RADII, normals, stats)
    want_v, want_w = patch_weights(gf, TRIS, BARY, RADII, normals)
    assert verts.shape == w.shape and verts.shape[0] == 4 and verts.shape[1] >= 3
    for i in range(4):
        got, want = dense(gf, verts[i], w[i]), dense(gf, want_v[i], want_w[i])
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
        assert got.sum() == pytest.approx(1.0, rel=1e-12) and np.all(w[i] >= 0.0)
        assert np.all(np.isin(verts[i], want_v[i]))  # the padding repeats a carrying vertex
    np.testing.assert_array_equal(dense(gf, verts[1], w[1])[gf.triangles[TRIS[1]]], BARY[1])  # a = 0: the point
    assert np.count_nonzero(w[2]) > 20  # the wide patch spreads over many vertices
    assert stats.patch_weights_computed == 4 and stats.patch_weights_reused == 0


def test_weights_are_reused_from_the_cache_until_the_key_changes(gf):
    p = make_patches(gf)
    normals = np.tile(UP, (4, 1))
    stats = StormStats()
    first = p.weights(IDS, TRIS, BARY, RADII, normals, stats)
    again = p.weights(IDS, TRIS, BARY, RADII, normals, stats)
    assert (stats.patch_weights_computed, stats.patch_weights_reused) == (4, 4)
    for x, y in zip(first, again):
        np.testing.assert_array_equal(x, y)
    # a subset, in another order: reused
    p.weights(IDS[[2, 0]], TRIS[[2, 0]], BARY[[2, 0]], RADII[[2, 0]], normals[:2], stats)
    assert (stats.patch_weights_computed, stats.patch_weights_reused) == (4, 6)
    # one radius, one beta, one triangle changed: those three computed, the fourth reused
    r2, b2, t2 = RADII.copy(), BARY.copy(), TRIS.copy()
    r2[0] *= 1.3
    b2[2] = [0.1, 0.8, 0.1]
    t2[3] = cell(1, 1, 1)
    v2, w2 = p.weights(IDS, t2, b2, r2, normals, stats)
    assert (stats.patch_weights_computed, stats.patch_weights_reused) == (7, 7)
    want_v, want_w = patch_weights(gf, t2, b2, r2, normals)
    for i in range(4):
        np.testing.assert_allclose(dense(gf, v2[i], w2[i]), dense(gf, want_v[i], want_w[i]), rtol=1e-12, atol=1e-15)
    # the cache now holds the new keys
    p.weights(IDS, t2, b2, r2, normals, stats)
    assert (stats.patch_weights_computed, stats.patch_weights_reused) == (7, 11)
    # forget: the stones' cached weights are dropped (others kept; unknown ids are fine)
    p.forget([IDS[0], IDS[3], 999])
    p.weights(IDS, t2, b2, r2, normals, stats)
    assert (stats.patch_weights_computed, stats.patch_weights_reused) == (9, 13)
    # the same stone id on another contact (a new stone after forget): computed
    p.forget(IDS.tolist())
    p.weights(IDS, TRIS, BARY, RADII, normals, stats)
    assert (stats.patch_weights_computed, stats.patch_weights_reused) == (13, 13)


def test_weights_of_no_contacts_are_empty(gf):
    p = make_patches(gf)
    e = np.zeros(0, dtype=np.intp)
    want_v, want_w = patch_weights(gf, e, np.zeros((0, 3)), np.zeros(0))
    verts, w = p.weights(e, e, np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)), StormStats())
    assert verts.shape == want_v.shape == (0, 3) and w.shape == want_w.shape == (0, 3)


# ----------------------------------------------------------------------------------------------
# near-field blocks
# ----------------------------------------------------------------------------------------------
class CountingNear:
    """A :class:`NearField` that counts the contacts it is asked for."""

    def __init__(self, near):
        self.near, self.asked = near, []

    def blocks(self, gf, radius, *args):
        self.asked.append(len(radius))
        return self.near.blocks(gf, radius, *args)


@pytest.mark.parametrize("sticky", [False, True])
def test_near_blocks_are_the_near_fields_and_cached_per_stone(gf, sticky):
    p = make_patches(gf, mode="sticky" if sticky else "frictionless")
    nf = near_field("halfspace", gf.young, gf.poisson)
    near = CountingNear(nf)
    normals = np.tile(UP, (4, 1))
    verts, w = p.weights(IDS, TRIS, BARY, RADII, normals, StormStats())
    X = np.einsum("ka,kad->kd", BARY, gf.vertices[gf.triangles[TRIS]])
    got = p.near_blocks(near, IDS, TRIS, BARY, RADII, verts, w, X, normals)
    want = nf.blocks(gf, RADII, verts, w, X, normals, sticky)
    assert got.shape == (4, 3, 3) if sticky else got.shape == (4, 1, 1)
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=0.0)
    assert not got[1].any() and np.all(np.abs(got[[0, 2, 3]]).max(axis=(1, 2)) > 0)  # a = 0: no correction
    assert near.asked == [4]  # the new ones in one call
    # cached per stone: again, or a subset in another order, asks nothing
    np.testing.assert_array_equal(p.near_blocks(near, IDS, TRIS, BARY, RADII, verts, w, X, normals), got)
    sub = [3, 1]
    np.testing.assert_array_equal(p.near_blocks(near, IDS[sub], TRIS[sub], BARY[sub], RADII[sub], verts[sub], w[sub],
                                                X[sub], normals[sub]), got[sub])
    assert near.asked == [4]
    # one radius changed: that stone alone is asked for, and its block is the near field's at it
    r2 = RADII.copy()
    r2[2] *= 0.7
    v2, w2 = p.weights(IDS, TRIS, BARY, r2, normals, StormStats())
    got2 = p.near_blocks(near, IDS, TRIS, BARY, r2, v2, w2, X, normals)
    assert near.asked == [4, 1]
    np.testing.assert_allclose(got2, nf.blocks(gf, r2, v2, w2, X, normals, sticky), rtol=1e-13, atol=0.0)
    # forget drops them
    p.forget([IDS[0]])
    p.near_blocks(near, IDS, TRIS, BARY, r2, v2, w2, X, normals)
    assert near.asked == [4, 1, 1]


# ----------------------------------------------------------------------------------------------
# stiffness
# ----------------------------------------------------------------------------------------------
def test_stiffness_is_one_over_the_patch_compliance_by_hand(gf):
    p = make_patches(gf)
    tilt = np.array([0.3, -0.2, 0.9])
    normals = np.vstack([UP, UP, tilt / np.linalg.norm(tilt), UP])
    verts, w = p.weights(IDS, TRIS, BARY, RADII, normals, StormStats())
    k = p.stiffness(verts, w, normals)
    want = np.array([1.0 / compliance_by_hand(gf, verts[i], w[i], normals[i]) for i in range(4)])
    np.testing.assert_allclose(k, want, rtol=1e-12)
    assert k[2] > k[0]  # a wider patch is stiffer (k ~ 2 E* a on a half-space)
    # a patch on clamped vertices only is hard: 0
    ring = np.array([[0, 1, 2]])
    assert p.stiffness(ring, np.array([[0.2, 0.5, 0.3]]), UP[None]).tolist() == [0.0]


def test_triangle_stiffness_by_hand(gf):
    """``1 / (b^T D_tt b)`` at each soft triangle's centroid; 0 on hard triangles and for -1."""
    soft = np.ones(len(gf.triangles), dtype=bool)
    soft[[cell(5, 5), cell(0, 11, 1)]] = False  # a triangle marked hard, and the corner (all clamped)
    p = make_patches(gf, soft=soft)
    tris = np.array([cell(6, 6), cell(5, 5), cell(2, 9, 1), cell(0, 0), cell(0, 11, 1), -1])
    normals = triangle_normals(gf.vertices, gf.triangles)
    want = np.array([k_by_hand(gf, t, normals[t]) if t >= 0 and soft[t] else 0.0 for t in tris])
    assert np.all(gf.fixed[gf.triangles[cell(0, 11, 1)]])
    got = p.triangle_stiffness(tris)
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert got[0] > 0 and got[3] > 0 and got[1] == 0.0 and got[5] == 0.0
    every = np.array([k_by_hand(gf, t, normals[t]) for t in range(len(gf.triangles))])
    np.testing.assert_allclose(p.k_tri, np.where(soft, every, 0.0), rtol=1e-12)


def test_on_a_bundle_from_disk(box_bundle):
    """The FEM box as loaded from disk: patches at its top's edge (the side faces, at 90 degrees,
    take no part) and in its middle: weights = ``patch_weights``, stiffness = ``1 / (g^T D g)`` and
    the triangles' stiffness = ``1 / (b^T D b)``, by hand on its D."""
    from hailstorm.runtime.bundle.read import load

    gf = load(box_bundle)
    p = make_patches(gf)
    X, T = np.asarray(gf.vertices), np.asarray(gf.triangles)
    normals = triangle_normals(X, T)
    c = X[T].mean(axis=1)
    top = np.flatnonzero(np.isclose(X[T][:, :, 2], X[:, 2].max()).all(axis=1))
    edge = top[np.argmax(c[top, 0])]  # next to the edge x = max
    middle = top[np.argmin(np.linalg.norm(c[top, :2] - X[:, :2].mean(axis=0), axis=1))]
    tris = np.array([edge, middle, middle])
    bary = np.array([[0.2, 0.3, 0.5], [0.3, 0.3, 0.4], [0.3, 0.3, 0.4]])
    radii = np.array([0.03, 0.015, 0.0])
    n = normals[tris]
    verts, w = p.weights(np.array([0, 1, 2]), tris, bary, radii, n, StormStats())
    want_v, want_w = patch_weights(gf, tris, bary, radii, n)
    for i in range(3):
        np.testing.assert_allclose(dense(gf, verts[i], w[i]), dense(gf, want_v[i], want_w[i]), rtol=1e-12, atol=1e-15)
    on = verts[0][w[0] > 0]
    assert np.allclose(X[on, 2], X[:, 2].max())  # the edge patch stays on the top
    assert np.count_nonzero(w[1]) > 3
    k = p.stiffness(verts, w, n)
    want = np.array([1.0 / compliance_by_hand(gf, verts[i], w[i], n[i]) for i in range(3)])
    np.testing.assert_allclose(k, want, rtol=1e-10)
    assert k[1] > k[2] > 0.0  # the patch is stiffer than the point
    kt = p.triangle_stiffness(tris[:2])
    np.testing.assert_allclose(kt, [k_by_hand(gf, t, normals[t]) for t in tris[:2]], rtol=1e-10)
