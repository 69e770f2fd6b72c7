"""The storm's contact set on its own (:class:`ContactSets` / :class:`ContactSet`): a set's W is
``G^T D G`` written out on the dense D of the bundle (``gf.compliance``), its K inverts W, patch
contacts are anchored the sphere's offset deep (worked out by hand from the module's statement), the
seat's view of the set (``G``, ``cols``, ``DVV``) is the same D, and the storm builds a set once
and reuses it while the set does not change.

On the synthetic plate (``helpers.plate_gf``: 13 x 13 vertices 10 mm apart at z = 0, normal +z,
E = 2 MPa, nu = 0.35, the boundary ring clamped).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from helpers import plate_gf

from hailstorm.runtime.contact import Capacitance
from hailstorm.runtime.contact.near_field import near_field
from hailstorm.runtime.contact.normals import triangle_normals
from hailstorm.runtime.contact.weights import patch_weights
from hailstorm.runtime.storm.contact_set import ContactSets
from hailstorm.runtime.storm.hail import Air
from hailstorm.runtime.storm.integrators import ContactIntegrator
from hailstorm.runtime.storm.patches import Patches
from hailstorm.runtime.storm.recording import StormStats
from hailstorm.runtime.storm.scene import Scene
from hailstorm.runtime.storm.seat import SeatState
from hailstorm.runtime.storm.soft_contacts import SoftContacts
from hailstorm.runtime.storm.stones import Stones

N = 13
UP = np.array([0.0, 0.0, 1.0])
UP3 = np.tile(UP, (3, 1))  # the flat plate's normals at three contacts


def cell(i, j, upper=0):
    return 2 * (i * (N - 1) + j) + upper


#: three contacts: triangles, barycentric coordinates, normals (one tilted), stone radii
TRIS = np.array([cell(4, 4), cell(5, 6, 1), cell(8, 7)])
BARY = np.array([[0.2, 0.3, 0.5], [1 / 3, 1 / 3, 1 / 3], [0.6, 0.1, 0.3]])
TILT = np.array([0.3, -0.2, 0.9]) / np.linalg.norm([0.3, -0.2, 0.9])
NORMALS = np.vstack([UP, TILT, UP])
RADII = np.array([0.004, 0.006, 0.003])
STONES = np.array([7, 2, 11])


@pytest.fixture(scope="module")
def gf():
    return plate_gf(N)


@pytest.fixture(scope="module")
def dense_D(gf):
    """The whole surface's compliance (3n, 3n) from the bundle's own block reader (clamped columns 0)."""
    allv = np.arange(gf.vertices.shape[0])
    return gf.compliance(allv, allv)


def make_sets(gf, normals=None, **contact):
    sc = Scene.default()
    contact_s = dataclasses.replace(sc.contact, **contact)
    if normals is None:
        normals = triangle_normals(gf.vertices, gf.triangles)
    soft = np.ones(len(gf.triangles), dtype=bool)
    air = Air.of((0.0, 0.0, 0.0), False, sc.hail.cd, sc.hail.rho_air, sc.hail.density)
    patches = Patches(gf, contact_s, sc.time, SeatState(gf), normals, soft, air)
    return ContactSets(gf, contact_s, normals, patches), patches, contact_s


def tri_normals_with(gf, tris, normals):
    """The triangles' normals with those of ``tris`` replaced (the set takes its normals from them)."""
    out = triangle_normals(gf.vertices, gf.triangles).copy()
    out[tris] = normals
    return out


def B_dense(n, verts, weights):
    """B (3n, 3s): contact k's force spread over ``verts[k]`` with ``weights[k]`` (identity blocks)."""
    s = len(verts)
    B = np.zeros((3 * n, 3 * s))
    for k in range(s):
        for v, w in zip(verts[k], weights[k]):
            B[3 * v:3 * v + 3, 3 * k:3 * k + 3] += w * np.eye(3)
    return B


def G_dense(B, normals, sticky):
    """G: B itself (sticky) or B's columns along each contact's normal (frictionless)."""
    if sticky:
        return B
    s = normals.shape[0]
    return np.einsum("rkj,kj->rk", B.reshape(B.shape[0], s, 3), normals)


# ----------------------------------------------------------------------------------------------
# point contacts: W = G^T D G, K = W^-1
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("sticky", [False, True])
def test_point_set_W_is_GtDG_and_K_its_inverse(gf, dense_D, sticky):
    """Point contacts: the set's W equals ``G^T D G`` (G the barycentric weights, along the normals
    for frictionless contacts) on the dense D, both the set's and its capacitance's; K W = I; the
    set records what it was given; the seat's view (``D[:, cols] G`` and ``DVV``) is ``D G``."""
    normals = tri_normals_with(gf, TRIS, NORMALS)
    sets, _, _ = make_sets(gf, normals, patch="none", mode="sticky" if sticky else "frictionless")
    stats = StormStats()
    key = (("a", 1),)
    cc = sets.build(STONES, TRIS, BARY, NORMALS, key, RADII, stats)
    n = gf.vertices.shape[0]
    B = B_dense(n, gf.triangles[TRIS], BARY)
    G = G_dense(B, NORMALS, sticky)
    W = G.T @ dense_D @ G
    m = (3 if sticky else 1) * TRIS.size
    assert W.shape == (m, m) and np.all(np.linalg.eigvalsh(W) > 0)
    # sums of a few dozen products of O(1e-5) numbers, summed in another order: rounding ~1e-16 relative
    np.testing.assert_allclose(cc.W, W, rtol=1e-12, atol=1e-14 * np.abs(W).max())
    assert isinstance(cc.capacitance, Capacitance)
    np.testing.assert_allclose(cc.capacitance.W, W, rtol=1e-12, atol=1e-14 * np.abs(W).max())
    # K inverts W: W is well conditioned (cond ~ 10), so K W = I to ~cond * eps
    assert np.linalg.cond(W) < 100
    np.testing.assert_allclose(cc.K @ W, np.eye(m), rtol=0, atol=1e-12)
    np.testing.assert_allclose(cc.K, cc.K.T, rtol=0, atol=1e-12 * np.abs(cc.K).max())
    np.testing.assert_array_equal(cc.Kdiag, np.diag(cc.K))
    assert cc.Kdiag.flags.c_contiguous and cc.Kdiag.flags.writeable
    # what the set records
    assert cc.key == key
    np.testing.assert_array_equal(cc.stones, STONES)
    np.testing.assert_array_equal(cc.tris, TRIS)
    np.testing.assert_array_equal(cc.bary, BARY)
    np.testing.assert_array_equal(cc.rest, RADII)
    np.testing.assert_array_equal(cc.normals, NORMALS)
    np.testing.assert_array_equal(cc.patch_radius, np.zeros(3))
    X = np.einsum("kj,kjd->kd", BARY, gf.vertices[gf.triangles[TRIS]])
    np.testing.assert_allclose(cc.X, X, rtol=0, atol=1e-17)  # three products of cm numbers
    assert stats.capacitance_rebuilds == 1
    # the seat's view: forces at the loaded columns per unit multiplier, and the displacement
    # of the loaded vertices, both D G
    DG = dense_D @ G
    np.testing.assert_allclose(np.asarray(gf.D)[:, cc.cols] @ cc.G, DG, rtol=1e-12, atol=1e-14 * np.abs(DG).max())
    V = np.unique(gf.triangles[TRIS])
    rows = (3 * V[:, None] + np.arange(3)).ravel()
    np.testing.assert_allclose(cc.DVV, DG[rows], rtol=1e-12, atol=1e-14 * np.abs(DG).max())


def test_W_changes_with_the_set(gf, dense_D):
    """A set of two of the three contacts is the 2 x 2 block of the three's W (nothing cached across
    sets), and moving a contact to another point changes its row of W as G^T D G says."""
    sets, _, _ = make_sets(gf, patch="none")
    full = sets.build(STONES, TRIS, BARY, UP3, (1,), RADII, StormStats())
    sub = sets.build(STONES[[2, 0]], TRIS[[2, 0]], BARY[[2, 0]], UP3[[2, 0]], (2,), RADII[[2, 0]], StormStats())
    np.testing.assert_allclose(sub.W, full.W[np.ix_([2, 0], [2, 0])], rtol=1e-12)
    bary2 = BARY.copy()
    bary2[1] = [0.8, 0.1, 0.1]
    moved = sets.build(STONES, TRIS, bary2, UP3, (3,), RADII, StormStats())
    n = gf.vertices.shape[0]
    G = G_dense(B_dense(n, gf.triangles[TRIS], bary2), np.tile(UP, (3, 1)), False)
    np.testing.assert_allclose(moved.W, G.T @ dense_D @ G, rtol=1e-12)
    assert abs(moved.W[1, 1] - full.W[1, 1]) > 1e-3 * full.W[1, 1]  # the premise: it moved


# ----------------------------------------------------------------------------------------------
# patch contacts: the sphere's offset
# ----------------------------------------------------------------------------------------------
def sphere_offset(gf, verts, w, X, normals, a, R, resolved):
    """The sphere's offset over an impact patch by hand (the module's statement): the sphere's own,
    ``delta - 2 W / F`` of the sphere whose impact patch has radius ``a`` (tests/reference/sphere_ref.py),
    on a disc the near field resolves; as the mesh follows it, times ``min(1, (2 a^2 / 5) / m2)``,
    ``m2`` the weights' tangential second moment about the contact point; 0 for a point contact."""
    from reference.sphere_ref import impact_offset_ref

    o = np.array([impact_offset_ref(ak, Rk) if ak > 0 else 0.0 for ak, Rk in zip(a, R)])
    if not resolved:
        m2 = np.empty(a.size)
        for k in range(a.size):
            rho = gf.vertices[verts[k]] - X[k]
            rho -= np.outer(rho @ normals[k], normals[k])
            m2[k] = np.sum(w[k] * np.sum(rho * rho, axis=1))
        o = o * np.where(a > 0, np.minimum(1.0, 0.4 * a * a / np.where(m2 > 0, m2, 1.0)), 0.0)
    return o


@pytest.mark.parametrize("near", ["none", "halfspace"])
def test_patch_set_is_the_capacitance_with_the_sphere_offset(gf, dense_D, near):
    """Patch contacts (radii 2.5, 4 and 6 mm: within a triangle and across several): the set's W
    is ``G^T D G`` with the contact API's patch weights (plus, with the half-space near field, its
    per-contact diagonal correction ``c(a) - w^T H w``), unscaled; K W = I; the offsets
    (:meth:`ContactSets.offsets`) are the sphere's worked out by hand, and a set built with them
    anchors each contact that far below its stone's radius (``rest = R - o``): on a resolved
    half-space patch its law ``F = (delta - o) / W_kk`` meets the sphere's impact peak."""
    a = np.array([0.0025, 0.004, 0.006])
    radii = np.array([0.004, 0.006, 0.009])  # a/R 0.62-0.67: where the sphere's offset is not Hertz's
    sets, patches, contact = make_sets(gf, patch="hertz", near_field=near)
    normals = np.tile(UP, (3, 1))
    stats = StormStats()
    X = np.einsum("kj,kjd->kd", BARY, gf.vertices[gf.triangles[TRIS]])
    verts, w = patches.weights(STONES, TRIS, BARY, a, normals, stats)
    o = sets.offsets(verts.astype(np.int64), w, X, normals, a, radii)
    np.testing.assert_allclose(o, sphere_offset(gf, verts, w, X, normals, a, radii, near == "halfspace"),
                               rtol=1e-10)
    assert np.all(o > 0) and np.all(o <= sphere_offset(gf, verts, w, X, normals, a, radii, True) * (1 + 1e-12))
    cc = sets.build(STONES, TRIS, BARY, UP3, (1,), radii, stats, a, o)
    np.testing.assert_array_equal(cc.patch_radius, a)
    np.testing.assert_array_equal(cc.offset, o)
    np.testing.assert_allclose(cc.rest, radii - o, rtol=1e-15)
    # the weights are the contact API's (padding aside)
    want_v, want_w = patch_weights(gf, TRIS, BARY, a, normals)
    n = gf.vertices.shape[0]
    for k in range(3):
        got, want = np.zeros(n), np.zeros(n)
        np.add.at(got, cc.verts[k], cc.weights[k])
        np.add.at(want, want_v[k], want_w[k])
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
    assert np.count_nonzero(cc.weights[2]) > 3  # the widest one spreads over several vertices
    G = G_dense(B_dense(n, cc.verts, cc.weights), normals, False)
    W_cap = G.T @ dense_D @ G
    if near == "halfspace":
        nf = near_field("halfspace", gf.young, gf.poisson)
        c_a = 3.0 * (1.0 - gf.poisson**2) / (5.0 * gf.young * a)  # Johnson 3.41: the Hertz disc's mean
        whw = nf.mesh_compliance(gf, cc.verts, cc.weights, X, normals)[0]
        e_w = nf.mesh_defect(gf, cc.verts, cc.weights)[0]  # D's own hat-scale error (module hat_defect)
        W_cap[np.diag_indices(3)] += c_a - whw + e_w
    scale = max(np.abs(W_cap).max(), 1e-300)
    np.testing.assert_allclose(cc.capacitance.W, W_cap, rtol=1e-12, atol=1e-14 * scale)
    np.testing.assert_allclose(cc.W, W_cap, rtol=1e-12, atol=1e-14 * scale)
    K_cap = np.linalg.inv(W_cap)  # cond(W) ~ 10: the inverse to ~1e-15 relative
    np.testing.assert_allclose(cc.K, K_cap, rtol=1e-10, atol=1e-12 * np.abs(K_cap).max())
    np.testing.assert_allclose(cc.K @ cc.W, np.eye(3), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(cc.Kdiag, np.diag(cc.K))
    assert stats.capacitance_rebuilds == 1
    # without an offset (a set built before any engagement) the anchors are the stones' radii
    plain = sets.build(STONES, TRIS, BARY, UP3, (2,), radii, stats, a)
    np.testing.assert_array_equal(plain.rest, radii)


def test_a_point_contact_in_a_patch_set_has_no_offset(gf, dense_D):
    """Radius 0 in a set of patches: a point contact (its barycentric weights), offset 0 (no
    sphere profile over a point), its W the capacitance's."""
    a = np.array([0.004, 0.0, 0.006])
    radii = np.array([0.008, 0.006, 0.009])  # patches within their stones (a < R)
    sets, patches, _ = make_sets(gf, patch="hertz", near_field="none")
    normals = np.tile(UP, (3, 1))
    stats = StormStats()
    verts, w = patches.weights(STONES, TRIS, BARY, a, normals, stats)
    X = np.einsum("kj,kjd->kd", BARY, gf.vertices[gf.triangles[TRIS]])
    o = sets.offsets(verts.astype(np.int64), w, X, normals, a, radii)
    assert o[1] == 0.0 and np.all(o[[0, 2]] > 0)
    cc = sets.build(STONES, TRIS, BARY, UP3, (1,), radii, stats, a, o)
    w1 = np.zeros(gf.vertices.shape[0])
    np.add.at(w1, cc.verts[1], cc.weights[1])
    np.testing.assert_allclose(w1[gf.triangles[TRIS[1]]], BARY[1], rtol=1e-15)
    assert np.isclose(w1.sum(), 1.0, rtol=1e-15)
    np.testing.assert_array_equal(cc.W, cc.capacitance.W)
    assert cc.rest[1] == radii[1]


# ----------------------------------------------------------------------------------------------
# built once, reused while the set does not change
# ----------------------------------------------------------------------------------------------
def soft_contacts(gf, **scene):
    sc = Scene.default().with_(**scene)
    normals = triangle_normals(gf.vertices, gf.triangles)
    soft = np.ones(len(gf.triangles), dtype=bool)
    air = Air.of((0.0, 0.0, 0.0), False, sc.hail.cd, sc.hail.rho_air, sc.hail.density)
    seat = SeatState(gf)
    patches = Patches(gf, sc.contact, sc.time, seat, normals, soft, air)
    sets = ContactSets(gf, sc.contact, normals, patches)
    integ = ContactIntegrator(sc.time, sc.contact)
    return SoftContacts(sc.contact, sc.time, sets, patches, integ, seat, air), sc


def resting_stones(gf, tris, bary, radius, depth=2e-5):
    """Stones whose contacts on ``tris`` at ``bary`` are open, ``depth`` into the plate, at rest."""
    st = Stones(density=917.0)
    X = np.einsum("kj,kjd->kd", bary, gf.vertices[gf.triangles[tris]])
    ids = st.add(X + (np.asarray(radius) - depth)[:, None] * UP, np.zeros(3), radius)
    st.ctri[ids] = tris
    st.cbary[ids] = bary
    st.cnormal[ids] = UP
    return st, ids


@pytest.mark.parametrize("patch", ["none", "hertz"])
def test_set_is_built_once_and_reused_while_unchanged(gf, patch):
    """Sub-steps of two stones resting in contact: the set is built at the first and reused (the same
    object, no rebuild counted) while its (stone, triangle[, radius]) stay; a third stone joining
    builds a new set of three, with W = G^T D G again; the first two leaving it builds one of one."""
    # (patches: a floor of 3 mm, above the Hertz radius of any force here (< 1 mm), so that the
    # radii stay put and only a change of the stones or triangles changes the set)
    sc_, sc = soft_contacts(gf, patch=patch, integrator="implicit", patch_min_radius=0.003)
    tris = np.array([cell(4, 4), cell(7, 6, 1), cell(6, 2)])
    bary = np.array([[0.3, 0.3, 0.4], [0.25, 0.5, 0.25], [0.4, 0.2, 0.4]])
    st, ids = resting_stones(gf, tris, bary, np.array([0.004, 0.005, 0.004]))
    stats = StormStats()
    two = ids[:2]
    h = 1e-5
    sc_.advance(st, two, two, np.array([True, True]), h, stats)
    first = sc_.current
    assert first is not None and stats.capacitance_rebuilds == 1
    np.testing.assert_array_equal(first.stones, two)
    for _ in range(5):
        sc_.advance(st, two, two, np.array([True, True]), h, stats)
        assert sc_.current is first
    assert stats.capacitance_rebuilds == 1
    three = ids
    sc_.advance(st, three, three, np.array([True, True, True]), h, stats)
    assert sc_.current is not first and stats.capacitance_rebuilds == 2
    np.testing.assert_array_equal(sc_.current.stones, three)
    if patch == "none":
        n = gf.vertices.shape[0]
        G = G_dense(B_dense(n, gf.triangles[tris], bary), np.tile(UP, (3, 1)), False)
        allv = np.arange(n)
        W = G.T @ gf.compliance(allv, allv) @ G
        np.testing.assert_allclose(sc_.current.W, W, rtol=1e-12)
    sc_.advance(st, ids[2:], ids[2:], np.array([True]), h, stats)
    assert stats.capacitance_rebuilds == 3 and sc_.current.stones.tolist() == [ids[2]]
    if patch == "hertz":
        assert stats.patch_resizes == 0 and np.all(sc_.current.patch_radius == 0.003)
