"""The default seat: a foam pad on a rigid shell that dents locally instead of bending.

Locality: a 1 N load on a 5 mm disc at the rear, middle and nose moves
surface points farther than 40 mm from it by at most 0.2 x the displacement under it.
Checked on a coarse 15 mm P1 mesh: there the 5 mm disc lies inside one triangle and
P1 underestimates the dent under the load far more than the far field (the dent is
local, the far field a smooth global response), so the coarse ratio is larger than the
converged one (measured, `python -m studies.seat_study`: 0.045 / 0.023 /
0.020 / 0.010 at 15 mm / 10 mm / 6 mm P1 / 6 mm P2 at the rear): passing at 15 mm with
the issue's 0.2 is the conservative check.
"""

from __future__ import annotations

import numpy as np
import pytest

from hailstorm.precompute.geometry import boundary_triangles, mesh_default_seat
from hailstorm.precompute.materials import layer_thickness
from studies.seat_study import SITES, measure, with_shell


@pytest.fixture(scope="module")
def pad():
    return mesh_default_seat(0.015)


def test_default_seat_is_a_pad_clamped_on_its_underside(pad):
    assert sorted(pad.volumes) == ["pad"]
    clamp = pad.group_vertices("clamp")
    top = pad.group_vertices("top")
    # the clamp is the whole underside: every boundary triangle is top or clamp
    assert len(boundary_triangles(pad.tets)) == len(pad.groups["top"]) + len(pad.groups["clamp"])
    # the pad is 12-15 mm of foam over the shell (2 V / A of a slab is its thickness, less its rim)
    thickness, _, _ = layer_thickness(pad, np.arange(pad.tets.shape[0]))
    assert 0.010 < thickness < 0.015
    # the clamp lies under the top: every clamp node at least 12 mm below the top's highest point above it
    zmax = pad.points[top, 2].max()
    assert pad.points[clamp, 2].max() < zmax - 0.012


def test_locality_ratio_at_rear_middle_nose(pad):
    sites = measure(pad, 1, 2e6, 0.35)
    assert [s.name for s in sites] == list(SITES)
    for s in sites:
        assert s.under > 0 and s.ratio <= 0.2, (s.name, s.ratio)


def test_a_very_stiff_elastic_shell_is_the_rigid_base(pad):
    """with_shell builds a conforming shell under the pad: as its modulus grows, the contact
    compliance tends to the rigid base's (to 1e-4 at E = 1e13 Pa, 5 million times the foam)."""
    shelled = with_shell(pad)
    assert sorted(shelled.volumes) == ["pad", "shell"]
    n = pad.tets.shape[0]
    is_pad = np.arange(shelled.tets.shape[0]) < n
    rigid = measure(pad, 1, 2e6, 0.35)
    stiff = measure(shelled, 1, np.where(is_pad, 2e6, 1e13), np.where(is_pad, 0.35, 0.3))
    soft = measure(shelled, 1, np.where(is_pad, 2e6, 3e8), np.where(is_pad, 0.35, 0.3))
    for r, s, w in zip(rigid, stiff, soft):
        assert abs(1 - r.mean_disc / s.mean_disc) < 1e-4
        assert w.mean_disc > s.mean_disc  # a softer shell gives: the shell is really there
