"""The near field on a pad on its rigid base, against the pad's own converged contact.

A 15 mm pad of the default foam clamped underneath (:func:`studies.dynamic_study.pad_bundle`,
120 mm square, the default seat's settings: 6 mm, P2, hat loads) and the same pad as an axisymmetric
disc solved to convergence with the indenter's profile node by node
(:func:`studies.axisymmetric.press_disc` with the sphere's profile: the contacts follow the
sphere's law, :mod:`hailstorm.runtime.contact.hertz`). The default near field (``"layer"``: :mod:`hailstorm.runtime.contact.layer_kernel`) carries
the converged force at every site; the half-space kernel alone does not (so the test can fail).
"""

from __future__ import annotations

import numpy as np
import pytest

from hailstorm.runtime.contact.hat_defect import hat_defect
from hailstorm.runtime.contact.near_field import kernel_surface
from studies.dynamic_study import default_pad, pad_bundle
from studies.resolution_study import PAD_CASES, SITES, pad_table


@pytest.fixture(scope="module")
def pad():
    return default_pad()


@pytest.fixture(scope="module")
def pad_gf(pad):
    return pad_bundle(pad, mesh_size=0.006)


@pytest.fixture(scope="module")
def rows(pad, pad_gf):
    return pad_table(pad_gf, pad, PAD_CASES[:4])


def test_press_spheres_carries_the_pads_converged_force(rows):
    """Contact radii 1.6-7.0 mm (a stone of 2.5 and 5 mm at the peak of its impact at terminal speed, a
    7.5 mm one 4.5 mm deep, a 12.5 mm one 4 mm deep): the default (``"layer"``) within 1.5 % of the
    converged force and within 0.3 % of each other at every site (measured -0.2 .. +1.0 % against the
    converged sphere); the half-space kernel alone 1.5-5.6 % too soft, so the test can fail."""
    for row in rows:
        model = np.array([row[f"layer:{s}"] for s in SITES])
        half = np.array([row[f"halfspace:{s}"] for s in SITES])
        assert np.abs(model).max() < 0.015, row
        assert np.ptp(model) < 0.003, row
        assert half.max() < -0.012, row


def test_the_pads_defect_is_on_the_diagonal_and_first_ring(pad_gf):
    """Against the exact layer on the same hat loads, the finite elements give each top vertex too
    small a displacement under its own hat and its edge neighbours too large a one, by about as
    much in all (measured: -5 % and +4-6 %); what the near-pair form takes off."""
    d = hat_defect(pad_gf, float(pad_gf.young), float(pad_gf.poisson), kernel_surface(pad_gf), layer=True)
    n = d.normal.size
    i_, j_ = d.keys // n, d.keys % n
    V = np.asarray(pad_gf.vertices)
    top = np.abs(V[:, 2] - V[:, 2].max()) < 1e-9
    inner = top & (np.abs(V[:, 0] - 0.06) < 0.04) & (np.abs(V[:, 1] - 0.06) < 0.04)
    diag = (i_ == j_) & inner[i_]
    assert np.all(d.near_normal[diag] < 0)
    ring = np.bincount(i_[(i_ != j_) & inner[i_]], d.near_normal[(i_ != j_) & inner[i_]], minlength=n)
    own = np.zeros(n)
    own[i_[diag]] = d.near_normal[diag]
    sel = i_[diag]
    assert np.all(ring[sel] > 0)
    assert np.median(np.abs(own[sel] + ring[sel]) / np.abs(own[sel])) < 0.5


@pytest.mark.parametrize("R, v", [(0.0025, 9.1), (0.005, 12.9)])
def test_the_storms_inertia_factors_bring_it_to_the_dynamic_peer(pad_gf, R, v):
    """The 2.5 and 5 mm stones at their terminal speeds on the pad at 200 kg/m^3 (the largest
    inertia of the peer's terminal table): the quasi-static storm's peak force is 16-22 % over
    the dynamic peer's; times the storm's own inertia factors (its impact run again on the pad
    under it, :mod:`hailstorm.runtime.inertia`) its peak force, contact time, rebound and dent are
    within 3 % of the peer (measured: 0.7 % or better), the storm's own quasi-static error."""
    from dataclasses import replace

    from studies.dynamic_study import compare, storm_impact

    pad = replace(default_pad(), density=200.0)
    row = compare(pad, R, v)
    st = storm_impact(pad_gf, R, v, pad_density=200.0)
    d = row.dynamic
    assert st.peak_force / d.peak_force - 1 > 0.15  # the storm alone misses the pad's inertia
    fF, ft, fe, fd = st.inertia
    est = (st.peak_force * fF, st.duration * ft, st.rebound_speed / v * fe, st.max_dent * fd)
    ref = (d.peak_force, d.duration, d.restitution, d.max_dent)
    np.testing.assert_allclose(est, ref, rtol=0.03)
