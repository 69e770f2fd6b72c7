"""The contact core's factor handling (issue 12, the fresh solve): the one SPD factor and
the active set's re-solves with it, against dense algebra (numpy's solve of the principal
block ``W[a, a]``) and against a fresh capacitance of the kept contacts alone."""

from __future__ import annotations

import numpy as np
import pytest

import hailstorm.runtime
from hailstorm.runtime.bundle import load
from hailstorm.runtime.contact import capacitance, solve_contacts, triangle_normals
from hailstorm.runtime.contact import contact_capacitance
from hailstorm.runtime.contact.policy import SPDFactor

precompute = pytest.importorskip("hailstorm.precompute")


@pytest.fixture(scope="module")
def box(tmp_path_factory):
    """A small clamped box (0.1 x 0.1 x 0.05 m, h = 0.02) and its bundle."""
    mesh = hailstorm.precompute.box_mesh(size=(0.1, 0.1, 0.05), mesh_size=0.02)
    path = hailstorm.precompute.build_bundle(
        tmp_path_factory.mktemp("bundle") / "box", mesh=mesh, young=1.0e6, poisson=0.3, solver="splu"
    )
    gf = load(path)
    tv = gf.triangles
    unclamped = np.flatnonzero(gf.contactable[tv].all(axis=1))
    return gf, unclamped


def rel(a, b):
    return np.abs(a - b).max() / max(np.abs(b).max(), 1e-300)


def test_spd_factor_against_dense_algebra():
    """One right-hand side (two triangular solves) and several (potrs), the inverse (potri),
    against numpy; a W with a NaN or an infinity is caught from the factor's diagonal (the
    pseudo-inverse branch, not a Cholesky of garbage)."""
    rng = np.random.default_rng(5)
    A = rng.normal(size=(40, 40))
    W = A @ A.T + 40.0 * np.eye(40)
    F = SPDFactor(W)
    assert F.exact
    b = rng.normal(size=40)
    B = rng.normal(size=(40, 3))
    assert rel(F.solve(b), np.linalg.solve(W, b)) < 1e-13
    assert rel(F.solve(B), np.linalg.solve(W, B)) < 1e-13
    assert rel(F.inverse(), np.linalg.inv(W)) < 1e-13
    np.testing.assert_array_equal(F.inverse(), F.inverse().T)
    for bad in (np.nan, np.inf):
        Wb = W.copy()
        Wb[3, 17] = Wb[17, 3] = bad
        assert not SPDFactor(Wb).exact
        Wd = W.copy()
        Wd[9, 9] = bad
        assert not SPDFactor(Wd).exact
