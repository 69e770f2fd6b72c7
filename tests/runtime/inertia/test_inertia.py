"""The pad's inertia per impact (hailstorm.runtime.inertia): the local pad's matrices against
scikit-fem's, the factors against the studies' converged peer, their similarity law and limits."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hailstorm.runtime.contact.layer_solve import axisymmetric_p1, graded
from hailstorm.runtime.inertia import InertiaFactors, impact_inertia, inertia_factors
from hailstorm.runtime.inertia.pad import Pad, pad_mesh

E, NU = 2e6, 0.35


def _stone(R: float) -> float:
    return 917.0 * 4.0 / 3.0 * math.pi * R**3


def _grid(R: float = 0.03, H: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    r = graded(R, 0.001, 0.004, 1.2)
    z = np.sort(H - graded(H, 0.001, 0.004, 1.2))
    z[0] = 0.0
    return r, z


def test_pad_matrices_are_scikit_fems():
    """The numpy assembly against scikit-fem's forms on the same triangles: the mass (a cubic
    integrand, exact in both quadratures) to rounding; the stiffness to the quadratures'
    difference in the hoop term ``u_r / r`` (Dunavant's 6 points here, scikit-fem's degree-3
    rule there), 3.3e-3 of the largest entry next to the axis and 2e-5 away from it; the disc's
    mass ``rho pi R^2 H`` exactly."""
    from skfem import MeshTri

    from studies.axisymmetric import axisymmetric_matrices

    r, z = _grid()
    K, M, nodes = axisymmetric_p1(r, z, NU, 70.0)
    mesh = MeshTri.init_tensor(r, z)
    Ks, Ms, basis = axisymmetric_matrices(mesh, 1.0, NU, 70.0)
    ir, iz = (a.ravel() for a in np.meshgrid(np.arange(r.size), np.arange(z.size)))  # node k = iz * nr + ir here
    theirs = ir * z.size + iz  # scikit-fem's tensor mesh numbers them column by column
    np.testing.assert_array_equal(mesh.p[:, theirs].T, nodes)
    perm = np.stack([basis.nodal_dofs[0, theirs], basis.nodal_dofs[1, theirs]], axis=1).ravel()
    Ks, Ms = Ks[perm][:, perm], Ms[perm][:, perm]
    assert abs(M - Ms).max() <= 1e-13 * abs(Ms).max()
    assert abs(K - Ks).max() <= 4e-3 * abs(Ks).max()
    away = np.repeat(ir >= 2, 2)  # nodes whose triangles do not touch the axis
    assert abs((K - Ks)[away][:, away]).max() <= 2e-5 * abs(Ks).max()
    ez = np.zeros(K.shape[0])
    ez[1::2] = 1.0
    assert ez @ M @ ez == pytest.approx(70.0 * math.pi * r[-1] ** 2 * z[-1], rel=1e-13)


def test_pad_mesh_clamps_the_base_and_the_axis():
    pad = Pad(young=E, poisson=NU, density=70.0, thickness=0.01, radius=0.03)
    mesh = pad_mesh(pad, cell=0.001, extent=0.004, growth=1.2)
    nr, nz = mesh.r.size, mesh.z.size
    assert mesh.K.shape[0] == 2 * nr * nz - 2 * nr - (nz - 1)  # the base's dofs and u_r on the axis removed
    np.testing.assert_array_equal(mesh.top_r, mesh.r)
    assert mesh.cell == pytest.approx(0.001)
    with pytest.raises(ValueError, match="cell > 0"):
        pad_mesh(pad, cell=0.0, extent=0.004)


@pytest.mark.parametrize("R, v", [(0.0025, 9.1), (0.005, 12.9)])
def test_factors_are_the_converged_peers(R, v):
    """The runtime's factors (8 cells per contact radius, 100 steps per contact, numpy's
    assembly) against the studies' peer at 12 cells and 300 steps on scikit-fem's, at the
    terminal speeds on the 200 kg/m^3 pad (its largest inertia: peak force x0.85 and x0.82):
    within 1.5 % on each of the four measures."""
    from studies.dynamic_study import compare, default_pad

    got = impact_inertia(R, _stone(R), v, 0.015, E, NU, 200.0)
    row = compare(default_pad(200.0), R, v, cells_per_radius=12, steps_per_contact=300)
    d, q = row.dynamic, row.quasi_static
    ref = (d.peak_force / q.peak_force, d.duration / q.duration, d.rebound_speed / q.rebound_speed,
           d.max_dent / q.max_dent)
    np.testing.assert_allclose(got, ref, rtol=0.015)
    assert ref[0] < 0.87  # the case has inertia to measure


def test_similar_impacts_have_the_same_factors():
    """Dimensional analysis: every length twice (stone, pad, mesh) at the same speed, moduli and
    densities is the same dimensionless problem (times twice too), discretised the same way: the
    same factors, to rounding."""
    one = impact_inertia(0.003, _stone(0.003), 8.0, 0.01, E, NU, 120.0, pad_radius=0.04)
    two = impact_inertia(0.006, _stone(0.006), 8.0, 0.02, E, NU, 120.0, pad_radius=0.08)
    np.testing.assert_allclose(two, one, rtol=1e-9)
    assert one[0] < 0.95  # and not trivially 1


def test_a_long_impact_sees_no_inertia():
    """A slow stone on a light pad (Hertz's contact time 4 times the pad's wave period): every
    factor within 0.5 % of 1; the same stone 20 times faster on a pad 3 times as dense (an impact
    shorter than the wave period) loses peak force."""
    slow = impact_inertia(0.005, _stone(0.005), 0.5, 0.015, E, NU, 20.0)
    np.testing.assert_allclose(slow, 1.0, atol=5e-3)
    fast = impact_inertia(0.005, _stone(0.005), 10.0, 0.015, E, NU, 60.0)
    assert fast[0] < 0.98 and fast[1] > 1.01


def test_inertia_factors_of_many_impacts(monkeypatch):
    """The batch is each impact's factors; no pad under an impact (inf), or a contact its pad
    cannot resolve, gives NaN, and the largest change ignores it; progress is reported per
    impact; bad input is refused."""
    R, v, h = [0.0025, 0.004, 0.003], [9.0, 11.0, 5.0], [0.015, np.inf, 0.012]
    m = [_stone(x) for x in R]
    seen = []
    got = inertia_factors(R, m, v, h, E, NU, 70.0, progress=lambda k, n: seen.append((k, n)), table=False)
    assert seen == [(1, 2), (2, 2)] and got.impacts == 3 and got.direct_runs == 2  # no run without a pad
    for k in (0, 2):
        np.testing.assert_allclose([f[k] for f in got.astuple()], impact_inertia(R[k], m[k], v[k], h[k], E, NU, 70.0),
                                   rtol=1e-12)
    assert np.isnan(got.force[1]) and np.isnan(got.largest_change()[1])
    change = got.largest_change()
    assert change[0] == pytest.approx(max(abs(f[0] - 1) for f in got.astuple()))
    both = InertiaFactors.empty() + got
    np.testing.assert_array_equal(both.force, got.force)
    from hailstorm.runtime.inertia import PeerResolutionError, factors

    def unresolved(*a, **k):
        raise PeerResolutionError("too coarse")

    monkeypatch.setattr(factors, "impact_inertia", unresolved)  # a contact the local pad cannot resolve: NaN
    assert np.isnan(inertia_factors(R[:1], m[:1], v[:1], h[:1], E, NU, 70.0, table=False).force).all()
    with pytest.raises(ValueError, match="differ in length"):
        inertia_factors(R[:2], m, v, h, E, NU, 70.0)
    with pytest.raises(ValueError, match="pad density must be positive"):
        inertia_factors(R, m, v, h, E, NU, 0.0)
    with pytest.raises(ValueError, match="thickness > 0"):
        impact_inertia(0.003, _stone(0.003), 5.0, 0.0, E, NU, 70.0)
