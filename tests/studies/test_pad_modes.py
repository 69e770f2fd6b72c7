"""The pad's modes (hailstorm.studies.pad_modes): the eigenproblem, the mode-acceleration form
against the full peer, and how many modes a fast small stone needs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hailstorm.studies.axisymmetric import pad_mesh, without_contact_mass
from hailstorm.studies.dynamic_study import default_pad, hertz_estimate, simulate_impact
from hailstorm.studies.pad_modes import main, modal_rows, pad_modes


@pytest.fixture(scope="module")
def small_pad():
    """A 20 mm disc of the 200 kg/m^3 foam, meshed for a 5 mm stone at 5 m/s (5 cells per Hertz radius)."""
    pad = default_pad(200.0, radius=0.02)
    R, v = 0.005, 5.0
    a = math.sqrt(R * hertz_estimate(pad, R, v).max_depth)
    mesh = pad_mesh(pad, cell=a / 5, extent=1.5 * a)
    return mesh, R, v, mesh.top_uz[mesh.top_r < 0.999 * R]


def test_modes_solve_the_eigenproblem_and_are_mass_normalised(small_pad):
    mesh, _, _, C = small_pad
    m = pad_modes(mesh, 12, massless=C)
    M = without_contact_mass(mesh.M, C)
    P = m.shapes
    assert np.all(np.diff(m.omega2) > 0)
    np.testing.assert_allclose(P.T @ (M @ P), np.eye(m.count), atol=1e-9)
    R = mesh.K @ P - (M @ P) * m.omega2
    assert np.abs(R).max() <= 1e-8 * np.abs(mesh.K @ P).max()
    # the sparse path's lowest modes are the dense path's
    full = pad_modes(mesh, None, massless=C)
    np.testing.assert_allclose(m.omega2, full.omega2[:12], rtol=1e-9)
    assert full.count == mesh.K.shape[0] - C.size  # one mode per dof that keeps its mass
    assert m.max_frequency == pytest.approx(math.sqrt(m.omega2[-1]) / (2 * math.pi))


def test_every_mode_gives_back_the_full_peer(small_pad):
    """The mode-acceleration form with all modes is the same Newmark rule per mode: the peer to rounding
    (an independent check of the peer's integration: a modal superposition against the direct one)."""
    mesh, R, v, C = small_pad
    peer = simulate_impact(mesh, R, v, steps_per_contact=60)
    modal = simulate_impact(mesh, R, v, steps_per_contact=60, modes=pad_modes(mesh, None, massless=C))
    assert modal.steps == peer.steps and modal.modes == mesh.K.shape[0] - C.size
    scale = np.abs(peer.history).max(axis=0)
    np.testing.assert_array_less(np.abs(modal.history - peer.history).max(axis=0), 1e-9 * scale + 1e-300)
    # and none is the quasi-static peer: K^-1 alone
    qs = simulate_impact(mesh, R, v, steps_per_contact=60, dynamic=False)
    assert abs(qs.peak_force / peer.peak_force - 1) > 0.01


def test_a_fast_small_stone_needs_its_pads_modes_to_about_15_khz():
    """docs/_generated/pad_modes_200.txt: a 2.5 mm stone at its terminal speed on the 200 kg/m^3 pad; the
    quasi-static model misses the peer by 21 % (rebound), 100 modes (to ~14 kHz) by 3.6 % (peak force)."""
    pad = default_pad(200.0)
    (row,) = modal_rows(pad, [0.0025], [10, 100], cells_per_radius=6.0, steps_per_contact=120)
    qs_worst = max(abs(e) for e in row.row.errors().values())
    worst = [max(abs(e) for e in err.values()) for err in row.errors]
    assert qs_worst > 0.15
    assert worst[1] < 0.05 < qs_worst
    assert row.frequencies[1] > 10e3 and row.frequencies[0] < row.frequencies[1]


def test_refusals(small_pad):
    mesh, R, v, C = small_pad
    with pytest.raises(ValueError, match="count >= 1"):
        pad_modes(mesh, 0)
    with pytest.raises(ValueError, match="dynamic=True"):
        simulate_impact(mesh, R, v, dynamic=False, modes=pad_modes(mesh, 4, massless=C))
    with pytest.raises(SystemExit):
        main(["--counts", "0"])


def test_main_writes_the_table(tmp_path, capsys):
    out = tmp_path / "modes.txt"
    assert main(["--radii", "0.0125", "--counts", "20", "--cells-per-radius", "5", "--steps-per-contact", "60",
                 "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "quasi-static" in text and "20 modes" in text
    lines = out.read_text().splitlines()
    assert lines[0].startswith("$ python -m hailstorm.studies.pad_modes --radii 0.0125")
    assert "20 modes" in out.read_text()
