"""Validity limits of the storm (hailstorm.runtime.storm.limits): the local pad thickness,
the per-impact measures, the statistics' keys and the warning."""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from hailstorm.precompute.geometry import box_mesh, boundary_triangles
from hailstorm.runtime.contact.hertz import hertz_impact
from hailstorm.runtime.contact.sphere_patch import sphere_radius
from hailstorm.runtime.storm.scene import Scene
from hailstorm.runtime.storm.driver import Storm
from hailstorm.runtime.bundle.thickness import PadThickness, RayCaster, surface_thickness
from hailstorm.runtime.storm.limits import (
    PAD_DENSITY,
    ImpactLimits,
    ValidityLimits,
    boundary_faces,
    contact_time_ratio,
    peak_strain,
    validity_warning,
)
from hailstorm.runtime.storm.recording import StormStats
from helpers import plate_gf

L, W, H = 0.1, 0.08, 0.02  # the box: x, y, thickness (clamped at z = 0)


@pytest.fixture(scope="module")
def box_gf(tmp_path_factory):
    from hailstorm.precompute import build_bundle
    from hailstorm.runtime.bundle.read import load

    m = box_mesh((L, W, H), 0.01)
    return load(build_bundle(tmp_path_factory.mktemp("gf") / "box", mesh=m, order=1, young=1e6, poisson=0.3))


def _box_source(mesh_size: float = 0.01) -> SimpleNamespace:
    """The surface and volume mesh of a clamped box, as a bundle carries them."""
    m = box_mesh((L, W, H), mesh_size)
    tris = boundary_triangles(m.tets)
    nodes = np.unique(tris)
    index = np.full(m.points.shape[0], -1)
    index[nodes] = np.arange(nodes.size)
    return SimpleNamespace(vertices=m.points[nodes], triangles=index[tris], volume_points=m.points,
                           volume_tets=m.tets, surface_nodes=nodes, young=1e6, poisson=0.3)


def test_thickness_of_a_box_is_its_height_and_width():
    """Top and bottom vertices (away from the edges) see the box's thickness H along the
    inward normal; vertices inside the side x = 0 see its length L."""
    gf = _box_source()
    h = surface_thickness(gf)
    X = gf.vertices
    inner_xy = (X[:, 0] > 1e-9) & (X[:, 0] < L - 1e-9) & (X[:, 1] > 1e-9) & (X[:, 1] < W - 1e-9)
    top = inner_xy & np.isclose(X[:, 2], H)
    bottom = inner_xy & np.isclose(X[:, 2], 0.0)
    side = np.isclose(X[:, 0], 0.0) & (X[:, 1] > 1e-9) & (X[:, 1] < W - 1e-9) & (X[:, 2] > 1e-9) & (X[:, 2] < H - 1e-9)
    assert top.sum() > 10 and bottom.sum() > 10 and side.sum() > 3
    # a ray along an axis of a box lands on a face (or its edges) exactly: rounding only
    np.testing.assert_allclose(h[top], H, rtol=1e-12)
    np.testing.assert_allclose(h[bottom], H, rtol=1e-12)
    np.testing.assert_allclose(h[side], L, rtol=1e-12)
    assert np.isfinite(h).all() and (h > 0).all()


def test_the_surface_is_the_volume_meshs_boundary_and_an_open_plate_has_no_thickness(box_gf):
    """The thickness is cast against the bundle's surface: on a bundle it is the volume mesh's
    boundary (boundary_faces of volume_tets through surface_nodes). The synthetic plate is an
    open surface: no ray hits (inf)."""
    faces = {tuple(f) for f in np.sort(boundary_faces(box_gf.volume_tets), axis=1)}
    assert faces == {tuple(f) for f in np.sort(np.asarray(box_gf.surface_nodes)[box_gf.triangles], axis=1)}
    assert np.isinf(surface_thickness(plate_gf(7))).all()


def test_ray_caster_against_the_analytic_box_and_brute_force(rng):
    """Rays from inside the box in random directions: the distance to the boundary is
    min over the axes of the distance to the face ahead (closed form); the pruned search
    equals the brute-force pass over every face."""
    m = box_mesh((L, W, H), 0.01)
    faces = boundary_faces(m.tets)
    o = rng.uniform([0.01, 0.01, 0.002], [L - 0.01, W - 0.01, H - 0.002], size=(200, 3))
    d = rng.normal(size=(200, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    hi = np.array([L, W, H])
    exact = np.min(np.where(d > 0, (hi - o) / np.where(d > 0, d, 1.0), -o / np.where(d < 0, d, -1.0)), axis=1)
    rc = RayCaster(m.points, faces)
    t = rc.cast(o, d)
    np.testing.assert_allclose(t, exact, rtol=1e-10)
    np.testing.assert_array_equal(t, rc.cast(o, d, start_radius=np.inf))


def test_ray_caster_in_small_chunks_is_the_same(rng, monkeypatch):
    """A few (ray, face) pairs per pass (the chunking that bounds the caster's memory on a large
    surface): the same distances, for the pruned search and the brute-force pass."""
    from hailstorm.runtime.bundle import thickness

    m = box_mesh((L, W, H), 0.01)
    faces = boundary_faces(m.tets)
    o = rng.uniform([0.01, 0.01, 0.002], [L - 0.01, W - 0.01, H - 0.002], size=(60, 3))
    d = rng.normal(size=(60, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    whole = RayCaster(m.points, faces).cast(o, d), RayCaster(m.points, faces).cast(o, d, start_radius=np.inf)
    monkeypatch.setattr(thickness, "PAIRS_PER_PASS", 50)
    rc = RayCaster(m.points, faces)
    np.testing.assert_array_equal(rc.cast(o, d), whole[0])
    np.testing.assert_array_equal(rc.cast(o, d, start_radius=np.inf), whole[1])


def test_pad_thickness_casts_each_vertex_once():
    gf = _box_source()
    pad = PadThickness(gf)
    calls = []
    real = pad._cast
    pad._cast = lambda v: calls.append(v.size) or real(v)
    first = pad(gf.triangles[:5])
    again = pad(gf.triangles[:5])
    np.testing.assert_array_equal(first, again)
    assert calls == [np.unique(gf.triangles[:5]).size]


def test_peak_strain_is_hertz_centre_strain_or_the_layer_compression():
    # eps_z at the centre of a Hertz contact: (2/pi)(1 - 2 nu)/(1 - nu) a/R, from the stresses
    # sigma_z = -p0, sigma_r = sigma_theta = -(1 + 2 nu) p0 / 2 and p0 = 2 E* a / (pi R)
    nu, aR = 0.35, 0.2
    p0_over_E = 2.0 / np.pi * aR / (1 - nu**2)
    eps = p0_over_E * (1 - nu * (1 + 2 * nu))  # Hooke: (sigma_z - nu (sigma_r + sigma_theta)) / E
    assert peak_strain(aR, 0.0, nu) == pytest.approx(eps, rel=1e-12)
    assert peak_strain(aR, 0.5, nu) == 0.5
    assert peak_strain(0.2, 0.0, 0.35) == pytest.approx(0.294 * 0.2, rel=2e-3)


def _inner_top_triangle(gf) -> int:
    """A triangle on the box's top none of whose vertices is on an edge of the box."""
    P = gf.vertices[gf.triangles]
    ok = (np.isclose(P[..., 2], H) & (P[..., 0] > 1e-9) & (P[..., 0] < L - 1e-9) & (P[..., 1] > 1e-9)
          & (P[..., 1] < W - 1e-9)).all(axis=1)
    return int(np.flatnonzero(ok)[0])


M5 = 917.0 * 4 / 3 * np.pi * 0.005**3  # an ice stone of 5 mm


def _time_ratio(m, R, v, h, young, poisson, density):
    """t_c / T from Hertz's impact (hertz_impact's duration) and the shear wave's quarter period across h."""
    c_s = np.sqrt(young / (2 * (1 + poisson) * density))
    return hertz_impact(m, v, R, young, poisson).duration / (4 * h / c_s)


def test_contact_time_ratio_is_hertzs_time_over_the_pads_wave_period():
    """contact_time_ratio against hertz_impact's duration (its closed form) and 4 h / c_s, over sizes, speeds
    and densities; it scales as rho^(-1/2) and 1/h; no speed gives no measure (inf), no pad under the impact 0."""
    for R, v, h, rho in [(0.0025, 9.1, 0.015, 70.0), (0.0125, 20.4, 0.015, 200.0), (0.005, 0.3, 0.04, 30.0)]:
        m = 917.0 * 4 / 3 * np.pi * R**3
        got = contact_time_ratio(m, R, v, h, 2e6, 0.35, rho)
        assert got == pytest.approx(_time_ratio(m, R, v, h, 2e6, 0.35, rho), rel=1e-12)
        assert contact_time_ratio(m, R, -v, 2 * h, 2e6, 0.35, 4 * rho) == pytest.approx(got / 4, rel=1e-12)
    r = contact_time_ratio([M5, M5, M5], [0.005] * 3, [0.0, 3.0, 3.0], [H, np.inf, H], 1e6, 0.3, 70.0)
    assert r[0] == np.inf and r[1] == 0.0 and 0 < r[2] < np.inf
    # the peer's 2.5 mm stone at its terminal 9.1 m/s on the 70 kg/m^3 pad: 0.36 ms against 4 h / c_s = 0.58 ms
    assert float(contact_time_ratio(917 * 4 / 3 * np.pi * 0.0025**3, 0.0025, 9.1, 0.015, 2e6, 0.35, 70.0)) == \
        pytest.approx(0.61, abs=0.01)


def _limits(rest_speed: float = 0.05) -> ImpactLimits:
    return ImpactLimits(_box_source(), rest_speed)


def test_impact_records_follow_the_storms_impact_rule():
    """A record opens only for a contact that opens, carries force and comes in faster than
    rest_speed; it takes the peaks of its contact until the next opening; a slow touch
    opens none and ends the stone's record."""
    lim = _limits()
    tri = _inner_top_triangle(_box_source())

    def obs(opening, vin, touched, indent, force):  # one stone (id 3, R = 5 mm) at the triangle's centroid
        lim.observe([3], [0.005], [M5], [tri], [[1 / 3] * 3], [opening], [vin], [touched], [indent], [force])

    obs(True, -0.01, True, 1e-4, 0.1)  # a slow touch: no record
    assert lim.n == 0 and lim.summary()["impacts_beyond_any_limit"] == 0
    obs(True, -3.0, False, 0.0, 0.0)  # opened but carried no force: no record
    assert lim.n == 0
    obs(True, -3.0, True, 1e-4, 0.5)  # an impact
    obs(False, -1.0, True, 3e-3, 2.0)  # its deepest instant
    obs(False, 1.0, True, 1e-3, 0.7)
    assert lim.n == 1
    assert lim.indentation[0] == 3e-3 and lim.force[0] == 2.0 and lim._thickness.size == 0  # cast when read
    dh, aR, eps = lim.ratios()
    assert lim.thickness[0] == pytest.approx(H, rel=1e-12)
    assert dh[0] == pytest.approx(3e-3 / H) and aR[0] == pytest.approx(sphere_radius(2.0, 0.005, 1e6, 0.3) / 0.005)
    st = lim.summary()
    assert st["max_indentation_thickness_ratio"] == pytest.approx(0.15)
    assert st["impacts_beyond_indentation_limit"] == 1 and st["min_impact_thickness_m"] == pytest.approx(H)
    assert st["impacts_beyond_radius_limit"] == int(aR[0] > 0.8) and st["impacts_beyond_strain_limit"] == 1
    assert lim.speed == [3.0] and lim.mass == [M5]  # at the onset
    tr = lim.time_ratios()
    assert tr[0] == pytest.approx(_time_ratio(M5, 0.005, 3.0, H, 1e6, 0.3, PAD_DENSITY), rel=1e-12)
    assert st["min_contact_time_ratio"] == pytest.approx(tr[0]) and st["pad_density"] == PAD_DENSITY
    assert st["impacts_beyond_contact_time_limit"] == int(tr[0] < 1.6)
    obs(True, -0.01, True, 5e-3, 5.0)  # a slow re-touch: the impact's record is closed
    assert lim.indentation[0] == 3e-3 and lim.n == 1


def test_counts_against_the_stated_limits():
    lim, st = _limits(), StormStats()
    assert (st["limit_indentation_thickness_ratio"], st["limit_contact_radius_ratio"], st["limit_strain_ratio"]) == (
        ValidityLimits.indentation_thickness, ValidityLimits.contact_radius, ValidityLimits.strain) == (0.1, 0.8, 0.05)
    lim.radius, lim._thickness = [0.005] * 3, np.full(3, H)  # thicknesses known: nothing to cast
    lim.mass, lim.speed = [M5] * 3, [0.06, 5.0, 30.0]
    # a/R from the force: the sphere's F = E* R^2 ((1 + x^2) atanh(x) - x) at x = a/R (Sneddon)
    Es = 1e6 / (1 - 0.3**2)
    aR = np.array([0.05, 0.5, 0.9])
    lim.force = list(Es * 0.005**2 * ((1 + aR**2) * np.arctanh(aR) - aR))
    lim.indentation = list(np.array([0.001, 0.0019, 0.0021]) * H / 0.02)  # delta/h 0.05, 0.095, 0.105
    st.validity = lim  # the statistics read the records
    assert st["impacts_beyond_indentation_limit"] == 1 and st["impacts_beyond_radius_limit"] == 1
    eps = peak_strain(aR, np.array(lim.indentation) / H, 0.3)
    assert st["impacts_beyond_strain_limit"] == int((eps > 0.05).sum())
    assert st["max_strain_ratio"] == pytest.approx(eps.max())
    tr = np.array([_time_ratio(M5, 0.005, v, H, 1e6, 0.3, PAD_DENSITY) for v in lim.speed])
    assert st["limit_contact_time_ratio"] == ValidityLimits.contact_time == 1.6
    assert st["impacts_beyond_contact_time_limit"] == int((tr < 1.6).sum()) and 0 < int((tr < 1.6).sum()) < 3
    assert st["min_contact_time_ratio"] == pytest.approx(tr.min(), rel=1e-12)
    assert st["impacts_beyond_any_limit"] == int(((np.array(lim.indentation) / H > 0.1) | (aR > 0.8) | (eps > 0.05)
                                                  | (tr < 1.6)).sum())
    assert st["max_contact_radius_ratio"] == pytest.approx(0.9, rel=1e-9)
    assert dict(st)["max_contact_radius_ratio"] == st["max_contact_radius_ratio"] and "validity" not in dict(st)


@pytest.mark.parametrize("integrator, mode, patch", [("exact", "frictionless", "hertz"), ("implicit", "frictionless", "hertz"),
                                                     ("exact", "sticky", "hertz"), ("exact", "frictionless", "none")])
def test_a_drop_on_the_box_records_its_impact(box_gf, integrator, mode, patch):
    """One stone dropped on the middle of the box: one record per counted impact, its peak
    indentation the storm's ``max_indentation_m``, its thickness the box's, a/R the sphere's of
    the storm's peak force."""
    sc = Scene.from_flat(duration=0.03, stones=0, drag=False, dt=2e-4, integrator=integrator, restitution=0.5,
                         mode=mode, patch=patch)
    st = Storm(box_gf, sc, spawn=False)
    R = 0.004
    st.add_stones(np.array([[0.047, 0.037, H + R + 1e-3]]), np.array([[0.0, 0.0, -4.0]]), np.array([R]))
    force = []  # (step end, the stone's contact force then)
    for _ in range(int(0.03 / 2e-4)):
        st.step()
        f = st.contact_forces()[1]
        force.append((st.t, float(np.linalg.norm(f, axis=1).sum()) if len(f) else 0.0))
    S, lim = st.stats, st.contacts.limits
    # its times: the onset when the stone, falling 1 mm at 4 m/s under gravity, reaches the surface (a
    # patch's contact surface lies its sphere's offset, ~0.1 mm, deeper: ~25 us later, within a step);
    # the peak at the step ends nearest the largest force of the first impact, within one step
    table = lim.table()
    t_touch = (-4.0 + np.sqrt(16.0 + 2 * 9.81 * 1e-3)) / 9.81
    assert t_touch - 1e-9 <= table["t_onset_s"][0] <= t_touch + 2e-4
    t, fs = np.array(force).T
    first = (t > table["t_onset_s"][0]) & (t < (table["t_onset_s"][1] if lim.n > 1 else np.inf))
    assert abs(table["t_peak_s"][0] - t[first][np.argmax(fs[first])]) <= 2e-4 + 1e-12
    assert np.all(table["t_onset_s"] < table["t_peak_s"])
    assert S["impacts"] >= 1 and lim.n == S["impacts"]
    assert max(lim.indentation) == S["max_indentation_m"]
    np.testing.assert_allclose(lim.thickness, H, rtol=1e-12)
    assert S["max_indentation_thickness_ratio"] == pytest.approx(S["max_indentation_m"] / H, rel=1e-12)
    a = sphere_radius(S["max_contact_force"], R, 1e6, 0.3)
    assert S["max_contact_radius_ratio"] == pytest.approx(a / R, rel=1e-12)
    assert S["max_strain_ratio"] == pytest.approx(float(peak_strain(a / R, S["max_indentation_m"] / H, 0.3)), rel=1e-12)
    assert S["min_impact_thickness_m"] == pytest.approx(H, rel=1e-12)
    # its first impact's normal speed: 4 m/s and 1 mm of gravity's pull; the box is E = 1 MPa, nu = 0.3
    v = np.sqrt(4.0**2 + 2 * 9.81 * 1e-3)
    m = 917.0 * 4 / 3 * np.pi * R**3
    assert lim.speed[0] == pytest.approx(v, rel=1e-3)
    assert lim.time_ratios()[0] == pytest.approx(_time_ratio(m, R, v, H, 1e6, 0.3, PAD_DENSITY), rel=1e-3)
    beyond = [S["max_indentation_thickness_ratio"] > 0.1, S["max_contact_radius_ratio"] > 0.8, S["max_strain_ratio"] > 0.05,
              S["min_contact_time_ratio"] < 1.6]
    assert (S["impacts_beyond_any_limit"] > 0) == any(beyond)


@pytest.mark.parametrize("inertia", [True, False])
def test_the_summary_carries_each_impacts_inertia(box_gf, inertia):
    """A stone dropped twice on the box: the inertia keys are the impacts' factors (each impact
    run again on a pad of the box's thickness at its onset speed and the scene's pad density,
    :func:`impact_inertia`) with their peak forces; with ``[validity] inertia = false`` they are
    empty (NaN, ``null`` in summary.json) and the count 0."""
    from hailstorm.runtime.inertia import impact_inertia

    sc = Scene.from_flat(duration=0.02, stones=0, drag=False, dt=2e-4, restitution=0.5, pad_density=200.0,
                         inertia=inertia)
    st = Storm(box_gf, sc, spawn=False)
    R = np.array([0.003, 0.005])
    st.add_stones(np.array([[0.03, 0.037, H + R[0] + 1e-3], [0.065, 0.04, H + R[1] + 1e-3]]),
                  np.array([[0.0, 0.0, -6.0], [0.0, 0.0, -3.0]]), R)
    for _ in range(int(0.02 / 2e-4)):
        st.step()
    S, lim = st.stats, st.contacts.limits
    assert lim.n >= 2
    F = np.array(lim.force)
    assert S["max_impact_force_N"] == pytest.approx(F.max(), rel=1e-12)
    table = _read_impacts_csv(S)
    assert table["stone"].tolist() == lim.stone and set(table["stone"]) == {0, 1}
    np.testing.assert_allclose(table["peak_force_N"], F, rtol=1e-8)
    np.testing.assert_allclose(table["speed_m_s"], lim.speed, rtol=1e-8)
    np.testing.assert_allclose(table["z_m"], H, rtol=1e-8)  # on the box's top
    np.testing.assert_allclose(table["thickness_m"], H, rtol=1e-8)
    np.testing.assert_allclose(table["contact_time_ratio"], lim.time_ratios(), rtol=1e-8)
    if not inertia:
        assert math.isnan(S["max_impact_force_dynamic_N"]) and math.isnan(S["min_inertia_force_factor"])
        assert S["impacts_beyond_inertia_limit"] == 0 and lim._inertia is None
        assert np.isnan(table["peak_force_dynamic_N"]).all() and np.isnan(table["inertia_force"]).all()
        return
    f = np.array([impact_inertia(lim.radius[k], lim.mass[k], lim.speed[k], H, 1e6, 0.3, 200.0) for k in range(lim.n)])
    np.testing.assert_allclose(np.column_stack(lim.inertia().astuple()), f, rtol=1e-12)
    assert S["max_impact_force_dynamic_N"] == pytest.approx((F * f[:, 0]).max(), rel=1e-12)
    assert S["min_inertia_force_factor"] == pytest.approx(f[:, 0].min(), rel=1e-12)
    assert S["min_inertia_restitution_factor"] == pytest.approx(f[:, 2].min(), rel=1e-12)
    assert S["impacts_beyond_inertia_limit"] == int((np.abs(f - 1).max(axis=1) > 0.05).sum())
    assert f[:, 0].min() < 0.99  # a 1 MPa pad of 200 kg/m^3: the stones feel its inertia
    np.testing.assert_allclose(table["inertia_force"], f[:, 0], rtol=1e-8)
    assert np.nanmax(table["peak_force_dynamic_N"]) == pytest.approx(S["max_impact_force_dynamic_N"], rel=1e-8)
    beyond = [set(b.split(";")) - {""} for b in table["beyond"]]
    assert sum("inertia" in b for b in beyond) == S["impacts_beyond_inertia_limit"]
    assert sum(bool(b) for b in beyond) == S["impacts_beyond_any_limit"]


def _read_impacts_csv(stats) -> dict:
    """``impacts.csv``'s text for ``stats`` read back: numbers as float arrays (an empty field NaN), ``beyond`` as text."""
    import csv
    import io

    from hailstorm.runtime.output.files import impacts_csv
    from hailstorm.runtime.storm.limits import IMPACT_COLUMNS

    rows = list(csv.DictReader(io.StringIO(impacts_csv(stats))))
    assert rows and tuple(rows[0]) == IMPACT_COLUMNS
    return {k: (np.array([r[k] for r in rows], dtype=object) if k == "beyond" else
                np.array([float(r[k]) if r[k] else np.nan for r in rows])) for k in IMPACT_COLUMNS}


def test_validity_warning_names_the_numbers():
    st = dict(StormStats())
    assert validity_warning(st) is None
    st.update(impacts=22, impacts_beyond_any_limit=22, impacts_beyond_indentation_limit=6,
              max_indentation_thickness_ratio=0.1725, impacts_beyond_radius_limit=22, max_contact_radius_ratio=0.848,
              impacts_beyond_strain_limit=22, max_strain_ratio=0.19)
    msg = validity_warning(st)
    assert msg.startswith("22 of 22 impacts are beyond the model's validity limits")
    assert "indentation/thickness up to 0.172 (limit 0.1, 6 impacts beyond)" in msg
    assert "contact radius/stone radius up to 0.848 (limit 0.8, 22 impacts beyond)" in msg
    assert "contact time/pad wave period down to 0 (limit 1.6 at 70 kg/m^3, 0 impacts beyond)" in msg
    older = {k: v for k, v in st.items() if "contact_time" not in k and k != "pad_density"}
    assert "contact time" not in validity_warning(older)  # a summary.json of an older version: no such keys
    st.update(impacts_beyond_contact_time_limit=9, min_contact_time_ratio=0.613, limit_contact_time_ratio=1.6,
              pad_density=70.0)
    assert "contact time/pad wave period down to 0.613 (limit 1.6 at 70 kg/m^3, 9 impacts beyond)" in validity_warning(st)
    assert "docs/validity.md" in msg and "\n" not in msg
    assert "the pad's inertia changes 0 impacts by more than 5 %" in msg  # (the statistics' neutral values)
    st.update(impacts_beyond_inertia_limit=7, limit_inertia_change=0.05, min_inertia_force_factor=0.8964,
              max_impact_force_N=150.396, max_impact_force_dynamic_N=147.463)
    assert ("the pad's inertia changes 7 impacts by more than 5 % (peak forces down to x0.896; the largest "
            "147.5 N dynamic against 150.4 N quasi-static)") in validity_warning(st)
    st.update(max_impact_force_dynamic_N=None)  # measured off: nothing said
    assert "inertia" not in validity_warning(st)


@pytest.mark.parametrize("stones", [6, 0])
def test_cli_storm_warns_once_and_the_summary_carries_the_limits(box_gf, tmp_path, caplog, stones):
    """`hailstorm storm` on the 1 MPa box: impacts beyond the limits give one warning line with
    the numbers, and summary.json carries the counts, the worst values and the limits; a storm
    without impacts warns nothing."""
    import json

    from hailstorm.cli import main

    out = tmp_path / "out"
    rc = main(["storm", "--gf", str(box_gf.path), "--duration", "0.03", "--stones", str(stones), "--seed", "2",
               "--out", str(out), "--no-video", "-q"])
    assert rc == 0
    s = json.loads((out / "summary.json").read_text())
    for k in ("impacts_beyond_indentation_limit", "impacts_beyond_radius_limit", "impacts_beyond_strain_limit",
              "impacts_beyond_any_limit", "max_indentation_thickness_ratio", "max_contact_radius_ratio",
              "max_strain_ratio", "min_impact_thickness_m", "impacts_beyond_contact_time_limit",
              "min_contact_time_ratio", "impacts_beyond_inertia_limit", "max_impact_force_N",
              "max_impact_force_dynamic_N", "min_inertia_force_factor", "min_inertia_restitution_factor"):
        assert k in s
    assert (s["limit_indentation_thickness_ratio"], s["limit_contact_radius_ratio"], s["limit_strain_ratio"],
            s["limit_contact_time_ratio"], s["pad_density"]) == (0.1, 0.8, 0.05, 1.6, 70.0)
    warned = [r.getMessage() for r in caplog.records if "validity limits" in r.getMessage()]
    if stones:
        assert s["impacts"] > 0 and s["impacts_beyond_any_limit"] > 0  # 1 MPa foam: every stone is beyond
        assert len(warned) == 1 and warned[0] == "warning: " + validity_warning(s, brief=True)  # (-q: one short line)
    else:
        assert s["impacts"] == 0 and s["impacts_beyond_any_limit"] == 0 and warned == []
        assert s["min_impact_thickness_m"] is None  # no impact, no pad under one (not a pad of 0 m)
