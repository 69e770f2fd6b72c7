"""The near field of a pad on its rigid base (hailstorm.runtime.contact.layer_kernel).

References: an independent finite-element solve of a Hertz pressure on the layer (its compliance,
which the kernel's point-force curve must reproduce through ``c(a) + <p, g p> / (E h)``); the layer's
limits (it carries nothing far from the load, the half-space's singularity is gone); the plain
statements in ``tests/reference/near_field_ref.py`` for the quadratures and the compiled sum.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import hailstorm.runtime
from hailstorm.precompute import build_bundle
from hailstorm.runtime.bundle.thickness import surface_thickness
from hailstorm.runtime.compiled.near_field import layer_sum
from hailstorm.runtime.contact.hat_defect import hat_defect
from hailstorm.runtime.contact.layer_kernel import hat_quadrature, layer_correction, layer_kernel, layer_surface
from hailstorm.runtime.contact.layer_solve import graded, layer_point_response
from studies.axisymmetric import axisymmetric_matrices
from hailstorm.runtime.contact.near_field import NearField, halfspace_patch_compliance, kernel_surface
from hailstorm.runtime.contact.weights import patch_weights
from helpers import plate_gf
from reference.layer_ref import layer_point_response_ref
from reference.near_field_ref import disc_ref, hat_defect_ref, hat_points_ref, layer_sum_ref

E, NU = 1.0e6, 0.3


@pytest.fixture(scope="module")
def kernel():
    return layer_kernel(0.35)


@pytest.fixture(scope="module")
def hat_box(tmp_path_factory, small_box):
    """:func:`small_box` (20 mm elements, 50 mm thick, clamped underneath) with P2 columns answering hat loads."""
    out = tmp_path_factory.mktemp("layerbox") / "box"
    return hailstorm.runtime.load(build_bundle(out, mesh=small_box, order=2, young=E, poisson=NU, load="hat"))


def hertz_on_layer(alpha: float, poisson: float, cells: int = 40) -> float:
    """The compliance ``<p, u>`` of a unit Hertz pressure of radius ``alpha`` on a unit layer (E = 1)
    clamped underneath: its own axisymmetric P1 solve with consistent nodal loads (Gauss-Legendre on
    each top segment), independent of the point-force curve the kernel is built from."""
    from scipy.sparse.linalg import splu
    from skfem import MeshTri

    cell = alpha / cells
    r = graded(12.0, cell, 1.2 * alpha, 1.04)
    z = np.sort(1.0 - graded(1.0, cell, 1.2 * alpha, 1.04))
    z[0] = 0.0
    mesh = MeshTri.init_tensor(r, z)
    K, _, basis = axisymmetric_matrices(mesh, 1.0, poisson, 1.0)
    x, nd = mesh.p, basis.nodal_dofs
    free = np.setdiff1d(np.arange(basis.N), np.concatenate([nd[:, x[1] < 1e-12].ravel(), nd[0, x[0] < 1e-12]]))
    top = np.flatnonzero(x[1] > 1 - 1e-12)
    top = top[np.argsort(x[0, top])]
    rt = x[0, top]
    s_, w_ = np.polynomial.legendre.leggauss(40)
    f = np.zeros(basis.N)
    for k in range(rt.size - 1):
        a, b = rt[k], min(rt[k + 1], alpha)
        if a >= alpha:
            break
        s = 0.5 * (s_ + 1) * (b - a) + a
        load = 3 / (2 * math.pi * alpha**2) * np.sqrt(np.clip(1 - (s / alpha) ** 2, 0, None)) * 2 * math.pi * s * 0.5 * w_ * (b - a)
        f[nd[1, top[k]]] += np.sum(load * (rt[k + 1] - s) / (rt[k + 1] - rt[k]))
        f[nd[1, top[k + 1]]] += np.sum(load * (s - rt[k]) / (rt[k + 1] - rt[k]))
    u = np.zeros(basis.N)
    u[free] = splu(K[free][:, free].tocsc()).solve(f[free])
    return float(f @ u)


@pytest.mark.parametrize("alpha", [0.3, 2.0])
def test_the_kernel_gives_a_hertz_disc_its_compliance_on_the_layer(kernel, alpha):
    """``c(a) + <p, g p> / (E h)`` against the layer's own solve with the pressure: within 0.3 %
    (measured 0.08-0.1 % for a/h = 0.1-2), where the half-space alone is 29 % (a = 0.3 h) and 350 %
    (a = 2 h) too compliant."""
    fem = hertz_on_layer(alpha, 0.35)
    model = halfspace_patch_compliance(alpha, 1.0, 0.35)[0] + kernel.disc(alpha)
    assert abs(model / fem - 1.0) < 3e-3
    assert halfspace_patch_compliance(alpha, 1.0, 0.35)[0] / fem - 1.0 > 0.25


def test_the_layer_carries_nothing_far_from_the_load_and_its_regular_part_is_smooth(kernel):
    hs = (1 - 0.35**2) / (np.pi * np.array([6.0, 8.0]))
    assert np.all(np.abs(kernel(np.array([6.0, 8.0])) + hs) < 0.02 * hs)  # u_layer < 2 % of the half-space's
    g = kernel(np.linspace(0.0, 0.3, 31))
    assert np.all(np.isfinite(g)) and np.all(np.diff(g) > 0)  # finite at 0, rising (the base's pull fades)
    assert np.max(np.abs(np.diff(g, 2))) < 1e-3  # no kink where the fit meets the solve
    r, uz = layer_point_response(0.35, cell=0.008)
    assert abs(uz[-1]) < 1e-3 * uz[1]


@pytest.mark.parametrize("poisson", [0.0, 0.35, 0.45])
def test_layer_point_response_is_its_reference(poisson):
    """The runtime's own assembly (numpy, Dunavant's rule) against scikit-fem's on the same grid:
    the same curve where the kernel reads it (from 0.1 thicknesses out) to 2e-5 (measured 5e-6); at the
    point force's own nodes the two quadratures of the ``u_r / r`` term differ by 2e-4."""
    r, u = layer_point_response(poisson, cell=0.008)
    r_ref, u_ref = layer_point_response_ref(poisson, cell=0.008)
    np.testing.assert_array_equal(r, r_ref)
    read = r >= 0.1
    np.testing.assert_allclose(u[read], u_ref[read], rtol=2e-5, atol=1e-6 * np.abs(u_ref[read]).max())
    np.testing.assert_allclose(u, u_ref, rtol=1e-3)


def test_layer_point_response_refuses_a_bad_poisson_ratio():
    with pytest.raises(ValueError, match="poisson"):
        layer_point_response(0.5)


@pytest.mark.parametrize("alpha", [0.1, 1.5, 4.5])
def test_disc_is_its_reference(kernel, alpha):
    """The table (to 4 thicknesses) and the quadrature beyond it against a plain grid."""
    assert kernel.disc(np.array([alpha]))[0] == pytest.approx(disc_ref(kernel, alpha), rel=2e-3)
    assert kernel.disc(np.array([alpha]))[0] == pytest.approx(kernel.disc_quadrature(alpha), rel=1e-5)


def test_hat_quadrature_is_each_hat_traction(hat_box):
    """Weights sum to 1 per vertex; a linear and a quadratic field exactly (``int_T lambda_1^a lambda_2^b
    lambda_3^c = 2 A a! b! c! / (a + b + c + 2)!``), and a Gaussian bump as the fine midpoint cloud does."""
    X, T = np.asarray(hat_box.vertices), np.asarray(hat_box.triangles)
    ptr, pts, w = hat_quadrature(X, T)
    assert np.allclose(np.add.reduceat(w, ptr[:-1]), 1.0)
    for v in (0, 7, int(np.flatnonzero(hat_box.contactable)[3])):
        fan = T[(T == v).any(axis=1)]
        area = 0.5 * np.linalg.norm(np.cross(X[fan[:, 1]] - X[fan[:, 0]], X[fan[:, 2]] - X[fan[:, 0]]), axis=1)
        first = (area[:, None] * (X[fan].sum(axis=1) + X[v])).sum(axis=0) / 12 / (area.sum() / 3)
        np.testing.assert_allclose(w[ptr[v]:ptr[v + 1]] @ pts[ptr[v]:ptr[v + 1]], first, rtol=1e-12, atol=1e-15)
        exact = 0.0
        for tri, A in zip(fan, area):
            c = list(tri).index(v)
            for k in range(3):
                for m_ in range(3):
                    counts = np.bincount([c, k, m_], minlength=3)
                    moment = 2 * A * np.prod([math.factorial(int(n)) for n in counts]) / math.factorial(5)
                    exact += moment * float(X[tri[k]] @ X[tri[m_]])
        quad = w[ptr[v]:ptr[v + 1]] @ (pts[ptr[v]:ptr[v + 1]] ** 2).sum(1)
        assert quad == pytest.approx(exact / (area.sum() / 3), rel=1e-12)
        y, m = hat_points_ref(X, T, v, k=16)
        bump = lambda p: np.exp(-((p - X[v]) ** 2).sum(1) / 0.02**2)  # noqa: E731
        assert w[ptr[v]:ptr[v + 1]] @ bump(pts[ptr[v]:ptr[v + 1]]) == pytest.approx(m @ bump(y), rel=5e-3)


def test_layer_sum_is_its_reference(hat_box, kernel, rng):
    X, T = np.asarray(hat_box.vertices), np.asarray(hat_box.triangles)
    ptr, pts, w = hat_quadrature(X, T)
    soft = np.flatnonzero(hat_box.contactable)
    verts = np.stack([rng.choice(soft, 4, replace=False) for _ in range(3)])
    weights = rng.uniform(0.1, 1.0, verts.shape)
    weights[0, -1] = 0.0  # padding
    h = np.array([0.05, 0.02, 0.01])
    got = layer_sum(verts, weights, X, ptr, pts, w, 1.0 / h, kernel.table, kernel.step)
    np.testing.assert_allclose(got, layer_sum_ref(kernel, X, T, verts, weights, h), rtol=2e-3)


def test_the_layer_term_stiffens_a_wide_patch_and_leaves_an_open_surface_alone(hat_box, kernel):
    """On the 50 mm box the term is negative (the mesh's coarse hats miss part of the base's pull)
    and equals its parts; on an open plate (no base under it: thickness inf) it is 0."""
    X, T = np.asarray(hat_box.vertices), np.asarray(hat_box.triangles)
    soft = np.flatnonzero(hat_box.contactable[T].all(axis=1))
    t = int(soft[np.argmin(np.linalg.norm(X[T[soft]].mean(axis=1)[:, :2] - 0.05, axis=1))])  # the top's middle
    v, w = patch_weights(hat_box, np.array([t]), np.array([[1 / 3, 1 / 3, 1 / 3]]), np.array([0.01]))
    surf = layer_surface(hat_box)
    got = layer_correction(kernel, surf, E, np.array([0.01]), v, w)
    h = float((w[0] * surface_thickness(hat_box, v[0])).sum() / w[0].sum())
    assert h == pytest.approx(0.05, rel=1e-6)
    S = layer_sum_ref(kernel, X, T, v, w, [h])[0]
    expect = (kernel.disc(0.01 / h) * w[0].sum() ** 2 - S) / (E * h)
    assert got[0] == pytest.approx(expect, rel=3e-3)
    assert got[0] < 0
    wide = layer_correction(kernel, surf, E, np.array([0.25]), v, w)[0]  # a / h = 5: past the disc's table
    assert wide == pytest.approx((kernel.disc_quadrature(0.25 / h) * w[0].sum() ** 2 - S) / (E * h), rel=3e-3)
    plate = plate_gf(7)
    pv, pw = np.array([[24, 25]]), np.array([[0.5, 0.5]])
    assert layer_correction(kernel, layer_surface(plate), 2e6, np.array([0.01]), pv, pw)[0] == 0.0


def test_the_layer_near_field_adds_the_term_to_the_normal_only(hat_box):
    T = np.asarray(hat_box.triangles)
    t = np.flatnonzero(hat_box.contactable[T].all(axis=1))[:2]
    bary = np.full((2, 3), 1 / 3)
    a = np.array([0.01, 0.03])
    v, w = patch_weights(hat_box, t, bary, a)
    X = np.asarray(hat_box.vertices)[T[t]].mean(axis=1)
    n = np.tile([0.0, 0.0, 1.0], (2, 1))
    half = NearField("halfspace", E, NU).blocks(hat_box, a, v, w, X, n, True)
    lay = NearField("layer", E, NU).blocks(hat_box, a, v, w, X, n, True)
    term = layer_correction(layer_kernel(NU), layer_surface(hat_box), E, a, v, w)
    d_half = hat_defect(hat_box, E, NU, kernel_surface(hat_box))
    d_lay = hat_defect(hat_box, E, NU, kernel_surface(hat_box), layer=True)
    from hailstorm.runtime.contact.hat_defect import patch_defect

    shift = patch_defect(d_lay, v, w)[0] - patch_defect(d_half, v, w)[0]
    nn = np.einsum("ki,kj->kij", n, n)
    np.testing.assert_allclose(lay - half, (term + shift)[:, None, None] * nn, atol=1e-12 * np.abs(half).max())


def test_the_layer_defect_is_its_reference(hat_box):
    kern = layer_kernel(NU)
    h = surface_thickness(hat_box)
    got = hat_defect(hat_box, E, NU, kernel_surface(hat_box), layer=True)
    want = hat_defect_ref(hat_box, E, NU, layer=(kern, h))
    n = got.normal.size
    have = {(int(k // n), int(k % n)): (a, b) for k, a, b in zip(got.keys, got.near_normal, got.near_tangential)}
    assert set(have) == set(want)
    scale_n = max(abs(v[0]) for v in want.values())
    scale_t = max(abs(v[1]) for v in want.values())
    for key, (dn, dt) in want.items():  # the layer's part by the 6-point rule against the fine cloud
        assert have[key][0] == pytest.approx(dn, abs=3e-3 * scale_n)
        assert have[key][1] == pytest.approx(dt, abs=1e-9 * scale_t)


def test_the_kernel_is_solved_once_per_machine_and_a_bad_cache_is_passed_by(tmp_path, monkeypatch):
    """Written atomically into the cache directory, read back equal; a damaged file is solved again
    (and rewritten), never read as a kernel."""
    from hailstorm.runtime.contact import layer_kernel as lk

    monkeypatch.setenv("HAILSTORM_CACHE", str(tmp_path))
    lk.layer_kernel.cache_clear()
    try:
        first = lk.layer_kernel(0.3)
        files = list((tmp_path / "layer_kernel").glob("*.npz"))
        assert len(files) == 1 and not list((tmp_path / "layer_kernel").glob(".*"))
        lk.layer_kernel.cache_clear()
        again = lk.layer_kernel(0.3)
        np.testing.assert_array_equal(again.table, first.table)
        np.testing.assert_array_equal(again.disc_table, first.disc_table)
        files[0].write_bytes(b"not a kernel")
        lk.layer_kernel.cache_clear()
        fresh = lk.layer_kernel(0.3)
        np.testing.assert_array_equal(fresh.table, first.table)
        assert lk._read_cached(files[0], 0.3) is not None  # rewritten
        assert lk._read_cached(files[0], 0.31) is None  # another material's is not this one's
    finally:
        lk.layer_kernel.cache_clear()
