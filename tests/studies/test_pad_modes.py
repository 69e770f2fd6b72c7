"""The pad's modes (studies.pad_modes): the eigenproblem, the mode-acceleration form
against the full peer, how many modes a fast small stone needs, and the contact as one force."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hailstorm.runtime.inertia.pad import pad_mesh, without_contact_mass
from studies.dynamic_study import default_pad, hertz_estimate, simulate_impact
from studies.pad_modes import (
    hertz_load,
    main,
    modal_rows,
    one_force_impact,
    one_force_rows,
    pad_modes,
)


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
    assert lines[0].startswith("$ python -m studies.pad_modes --radii 0.0125")
    assert "20 modes" in out.read_text()


def test_hertz_load_is_the_consistent_load_of_the_disc(small_pad):
    """Total 1, nothing beyond the disc's last piece, and its first moment exactly the disc's: the hats
    interpolate r exactly, so sum g_i r_i = int p r dA / int p dA = 3 pi a / 16."""
    mesh, R, v, _ = small_pad
    for a in (0.37 * R, 0.61 * R, float(mesh.top_r[5])):  # off the nodes, and on one
        g = hertz_load(mesh, a)
        top = g[mesh.top_uz]
        assert top.sum() == pytest.approx(1.0, abs=1e-14) and np.all(top >= 0)
        assert np.count_nonzero(g) == np.count_nonzero(top) and top[mesh.top_r > a].sum() <= top.max()
        assert top[np.searchsorted(mesh.top_r, a) + 1:].sum() == 0.0
        assert top @ mesh.top_r == pytest.approx(3 * math.pi * a / 16, rel=1e-9)
    with pytest.raises(ValueError, match="0 < radius"):
        hertz_load(mesh, 0.0)


def test_one_force_without_modes_is_a_linear_spring(small_pad):
    """The quasi-static patch: Newmark's average acceleration on a linear spring of compliance
    c = g^T K^-1 g keeps its energy and its peak v sqrt(m / c) to O(dt^2); the release falls inside a
    step, which costs the rebound O(dt^2) too (1e-5 at 400 steps)."""
    from scipy.sparse.linalg import spsolve

    mesh, R, v, _ = small_pad
    a = 0.5 * R
    g = hertz_load(mesh, a)
    c = float(g @ spsolve(mesh.K.tocsc(), g))
    m = 917.0 * 4 / 3 * math.pi * R**3
    r = one_force_impact(mesh, R, v, a, steps_per_contact=400)
    assert r.peak_force == pytest.approx(v * math.sqrt(m / c), rel=1e-4)
    assert r.max_dent == pytest.approx(v * math.sqrt(m * c), rel=1e-4)
    assert r.duration == pytest.approx(math.pi * math.sqrt(m * c), abs=r.dt)
    assert r.restitution == pytest.approx(1.0, abs=1e-4)


def test_one_force_on_every_mode_is_the_direct_integration(small_pad):
    """With every mode of the pad (the nodes under the patch massless) the one-force model is the same
    Newmark rule on the whole pad under the same one-force contact, integrated directly here."""
    from scipy.sparse.linalg import splu

    mesh, R, v, _ = small_pad
    a = 0.5 * R
    g = hertz_load(mesh, a)
    massless = mesh.top_uz[mesh.top_r <= a]
    modal = one_force_impact(mesh, R, v, a, pad_modes(mesh, None, massless=massless), steps_per_contact=60)
    M = without_contact_mass(mesh.M, massless)
    m, dt, b = 917.0 * 4 / 3 * math.pi * R**3, modal.dt, 0.25
    lu = splu((mesh.K + M / (b * dt * dt)).tocsc())
    G = lu.solve(g)
    n = g.size
    u, uv, ua = np.zeros(n), np.zeros(n), np.zeros(n)  # the pad's displacement, positive into it
    x, xv, xa, forces = 0.0, v, 0.0, []
    for _ in range(modal.steps):
        x_hat = x + dt * xv + (0.5 - b) * dt * dt * xa
        u_hat = u + dt * uv + (0.5 - b) * dt * dt * ua
        u_free = lu.solve(M @ u_hat) / (b * dt * dt)
        F = max(0.0, (x_hat - g @ u_free) / (g @ G + b * dt * dt / m))
        u_new, x_new = u_free + G * F, x_hat - b * dt * dt * F / m
        ua_new, xa_new = (u_new - u_hat) / (b * dt * dt), -F / m
        uv, xv = uv + dt * 0.5 * (ua + ua_new), xv + dt * 0.5 * (xa + xa_new)
        u, ua, x, xa = u_new, ua_new, x_new, xa_new
        forces.append(F)
    np.testing.assert_allclose(modal.history[:, 1], forces, rtol=0, atol=1e-9 * max(forces))
    assert modal.rebound_speed == pytest.approx(-xv, rel=1e-9)


def test_one_force_misses_the_inertia_the_resolved_contact_keeps():
    """docs/validity.md: a 12.5 mm stone at its terminal speed on the 70 kg/m^3 pad. Resolved on the
    pad's 10 lowest modes the peer is within 5 %; as one force on the same modes its peak force is
    about 12 % high (the force rings), worse than the quasi-static model's 2 %."""
    pad = default_pad(70.0)
    kw = dict(cells_per_radius=6.0, steps_per_contact=120)
    (resolved,) = modal_rows(pad, [0.0125], [10], **kw)
    (one,) = one_force_rows(pad, [0.0125], [10], **kw)
    assert abs(resolved.errors[0]["force"]) < 0.05 and abs(one.row.errors()["force"]) < 0.05
    assert one.errors[0]["force"] > 0.08


def test_main_one_force_writes_its_table(tmp_path, capsys):
    out = tmp_path / "one.txt"
    assert main(["--one-force", "--radii", "0.0125", "--counts", "5", "--cells-per-radius", "5",
                 "--steps-per-contact", "60", "--out", str(out)]) == 0
    assert "5 modes, 1 force" in capsys.readouterr().out and "5 modes, 1 force" in out.read_text()
