"""The block table of studies.resolution_study: the near field against Hertz and against the
block's own converged solution (a coarse block, one contact size)."""

from __future__ import annotations

import pytest

from studies.resolution_study import SITES, block_bundle, block_table


def test_block_table_measures_against_hertz_and_the_block(tmp_path):
    gf = block_bundle(tmp_path / "block", mesh_size=0.012)
    (row,) = block_table(gf, radii=(4e-3,), a_over_R=0.4)
    assert row["a_mm"] == pytest.approx(4.0) and row["R_mm"] == pytest.approx(10.0)
    # the 400 mm block is stiffer than the half-space, by 0.5-2 % for a 4 mm contact (measured +0.9 %);
    # the sphere softer than the paraboloid (Segedin: -1.6 % at a/R 0.4 on a half-space)
    assert 0.005 < row["block"] < 0.02
    assert row["block_sphere"] < row["block"] - 0.01
    for s in SITES:
        # the same force, measured against two references
        assert (1 + row[f"halfspace:{s}"]) / (1 + row["block_sphere"]) - 1 == pytest.approx(
            row[f"halfspace:{s}:block"], abs=1e-12)
        # with the near field within a few % on a 12 mm mesh; the discrete model several times off
        assert abs(row[f"halfspace:{s}:block"]) < 0.05
        assert row[f"none:{s}"] > 0.5


def test_depth_at_force_inverts_the_press(tmp_path):
    """On the coarse block: the depth found for a force carries that force (to the steps' 1e-5), and
    Hertz's force at Hertz's depth gives back Hertz's depth within the model's error against
    Hertz there (the block table's, a few %)."""
    from hailstorm.runtime.contact.hertz import hertz_force, press_spheres
    from studies.resolution_study import block_sites, depth_at_force

    gf = block_bundle(tmp_path / "block", mesh_size=0.012)
    R, a = 10e-3, 4e-3
    d_hertz = a * a / R
    F = float(hertz_force(d_hertz, R, gf.young, gf.poisson))
    for t, b in block_sites(gf).values():
        d = depth_at_force(gf, t, b, F, R, start=0.5 * d_hertz)
        got = press_spheres(gf, [t], [b], [d], R, rows=None).normal_force[0]
        assert got == pytest.approx(F, rel=3e-5)
        assert d == pytest.approx(d_hertz, rel=0.04)
        assert abs(d / d_hertz - 1) > 1e-4  # a real model, not Hertz itself
    with pytest.raises(RuntimeError, match="no depth"):
        depth_at_force(gf, t, b, F, R, start=0.5 * d_hertz, max_iter=1)
