"""The study that chose the default discretization (studies.defaults_study)."""

import math

import numpy as np
import pytest

from hailstorm.precompute import build_bundle, mesh_geometry
from hailstorm.precompute.geometry import Refinement
from hailstorm.runtime import load
from hailstorm.runtime.contact.normals import triangle_normals
from hailstorm.runtime.contact.weights import patch_weights
from hailstorm.runtime.storm.hail import stone_mass, terminal_velocity
from hailstorm.runtime.storm.scene import SeatSettings
from studies import defaults_study as ds
from studies.study import LoadCase, locate_probes, nodal_loads

E, NU = 2.0e6, 0.35
E_STAR = E / (1 - NU**2)


def test_stone_patch_radius_is_hertz_impact():
    """At the largest indentation the Hertz spring holds the stone's kinetic energy:
    int_0^d (4/3) E* sqrt(R) x^(3/2) dx = (8/15) E* sqrt(R) d^(5/2) = m v^2 / 2, and a = sqrt(R d)."""
    R = ds.STONE_RADIUS
    a = ds.stone_patch_radius(R, E, NU)
    d = a**2 / R
    m, v = float(stone_mass(R, 917.0)), float(terminal_velocity(R, cd=0.6, rho_air=1.2, density=917.0))
    assert 8 / 15 * E_STAR * math.sqrt(R) * d**2.5 == pytest.approx(0.5 * m * v**2, rel=1e-12)


def test_rates_and_richardson_on_an_exact_power_law():
    """q(h) = q* + C h^p exactly: the observed rate is p and Richardson's estimate the true error."""
    sizes = [0.004, 0.002, 0.001]
    q_star, p = np.array([10.0, 20.0, 30.0]), 1.5
    levels = [ds.Figures(q_star + 3e3 * h**p, q_star, 2 * q_star - 5e3 * h**p, 0, 0.0) for h in sizes]
    conv = ds.Convergence(sizes, levels)
    rates = conv.rates()
    assert np.allclose(rates["dent"], p) and np.allclose(rates["stiffness"], p)
    err = conv.extrapolation_error()
    assert err["dent"] == pytest.approx(np.max(3e3 * 0.001**p / (q_star + 3e3 * 0.001**p)), rel=1e-9)
    assert err["stiffness"] == pytest.approx(np.max(5e3 * 0.001**p / (2 * q_star - 5e3 * 0.001**p)), rel=1e-9)


@pytest.mark.parametrize("order, load_kind", [(1, "point"), (2, "hat"), (2, "point")])
def test_measure_setting_is_what_the_bundle_gives(tmp_path, small_box, order, load_kind):
    """Scored without forming D, the dent and the stone's capacitance equal those of the bundle's D
    (built by the pipeline: another code path) with the runtime's patch weights."""
    sites = {"c": (0.05, 0.05)}
    a = 0.006
    fig = ds.measure_setting(ds.Setting(0.02, order, load_kind), mesh=small_box, sites=sites, young=E, poisson=NU, jitter=0,
                             patch_radius=a)
    gf = load(build_bundle(tmp_path / "b", mesh=small_box, order=order, load=load_kind, young=E, poisson=NU))
    D = np.asarray(gf.D)
    c = np.flatnonzero(gf.contactable)
    rows = (3 * c[:, None] + np.arange(3)).ravel()
    n = gf.vertices.shape[0]
    loc = locate_probes(gf.vertices, gf.triangles, np.array([sites["c"]]))
    f = nodal_loads(gf.vertices, gf.triangles, gf.triangles, n, LoadCase(sites["c"], ds.DENT_RADIUS, 1.0))
    f /= np.linalg.norm(f.sum(axis=0))
    fc = f[c].ravel()
    assert fig.dent[0] == pytest.approx(fc @ D[rows] @ fc, rel=1e-8)
    nrm = triangle_normals(gf.vertices, gf.triangles[loc.triangle])
    verts, w = patch_weights(gf, loc.triangle, loc.lam, a, nrm)
    g = np.zeros((n, 3))
    np.add.at(g, verts[0], -w[0][:, None] * nrm[0])
    gc = g[c].ravel()
    assert fig.stiffness[0] == pytest.approx(1.0 / (gc @ D[rows] @ gc), rel=1e-8)


def _block(tmp_path, size):
    geo = tmp_path / "block.geo"
    geo.write_text('SetFactory("OpenCASCADE");\nBox(1) = {0, 0, 0, 0.08, 0.08, 0.04};\n'
                   'Physical Volume("solid") = {1};\nPhysical Surface("clamp") = {5};\n'
                   'Physical Surface("top") = {1, 2, 3, 4, 6};\n')
    return mesh_geometry(geo, 0.012, refine=(Refinement(0.04, 0.04, size, 0.3),))


@pytest.mark.slow
def test_reference_is_boussinesq_on_a_block(tmp_path):
    """The reference's definitions on a thick block against the half-space (Johnson ch. 3): the
    pressure-weighted mean displacement of 1 N is 16/(3 pi^2) / (E* a) for a uniform disc and
    3/5 / (E* a) for Hertz's pressure. The block's finite size adds a near-constant compliance
    (its clamp and sides), removed by taking the difference of two radii (a ratio of 2)."""
    mesh = _block(tmp_path, 0.0007)
    sites = {"c": (0.04, 0.04)}
    small = ds.measure_consistent(mesh, 2, sites=sites, young=E, poisson=NU, patch_radius=0.002, dent_radius=0.002)
    big = ds.measure_consistent(mesh, 2, sites=sites, young=E, poisson=NU, patch_radius=0.004, dent_radius=0.004)
    dc = (1 / 0.002 - 1 / 0.004) / E_STAR
    # tolerance: P2 at 0.7 mm under a 2 mm disc (~3 elements across the radius) and the block's
    # offset's small dependence on the radius, O((a/40 mm)^2) ~ 1 %
    assert small.dent[0] - big.dent[0] == pytest.approx(16 / (3 * math.pi**2) * dc, rel=0.04)
    assert 1 / small.stiffness[0] - 1 / big.stiffness[0] == pytest.approx(0.6 * dc, rel=0.04)


def _default_setting() -> ds.Setting:
    s = SeatSettings.default()
    return ds.Setting(s.mesh_size, s.order, s.load, s.volume_size)


@pytest.mark.slow
def test_default_beats_the_old_default_against_the_p2_reference():
    """The packaged default's dent and stone stiffness at the middle of the crown against P2 refined
    to 1 mm there (1 % from the 0.7 mm reference: README "Choosing the default"). Measured there:
    dent -13 %, stiffness -6 % (the issue's 5 % is not met on a 6 mm surface: README); the old
    default (P1, 6 mm) is off by 66 % and 131 %. The bounds: the measured errors with the
    reference's 1 % and a few per cent of mesh-to-mesh jitter (another gmsh may mesh differently)."""
    sites = {"middle": ds.SITES["middle"]}
    ref = ds.measure_consistent(ds.reference_mesh(0.001, sites=sites), 2, sites=sites)
    ek, ed = ds.measure_setting(_default_setting(), sites=sites).errors(ref)
    assert ek <= 0.10 and ed <= 0.18
    old_k, old_d = ds.measure_setting(ds.Setting(0.006, 1, "point"), sites=sites).errors(ref)
    assert old_k > 3 * ek and old_d > 3 * ed


def test_volume_grading_keeps_the_surface_and_refines_the_volume(tmp_path):
    """--volume-size: the same surface mesh (the bundle's, hence the runtime's cost), a finer interior."""
    geo = tmp_path / "slab.geo"
    geo.write_text('SetFactory("OpenCASCADE");\nBox(1) = {0, 0, 0, 0.06, 0.06, 0.03};\n'
                   'Physical Volume("pad") = {1};\nPhysical Surface("clamp") = {5};\n'
                   'Physical Surface("top") = {1, 2, 3, 4, 6};\n')
    from hailstorm.precompute.geometry import boundary_triangles

    plain, graded = mesh_geometry(geo, 0.012), mesh_geometry(geo, 0.012, volume_size=0.004)

    def surface(m):
        return np.unique(np.round(m.points[np.unique(boundary_triangles(m.tets))], 9), axis=0)

    assert np.array_equal(surface(plain), surface(graded))
    assert graded.tets.shape[0] > 3 * plain.tets.shape[0]
    assert graded.content_hash() != plain.content_hash()  # hence another cache key


def test_volume_size_bad_input(tmp_path, capsys, small_box):
    from hailstorm.precompute.geometry import MeshError
    from hailstorm.cli import EXIT_INPUT, main
    from hailstorm.runtime.storm.scene import SceneError

    with pytest.raises(MeshError, match="must not exceed the surface mesh size"):
        build_bundle(tmp_path / "b", mesh_size=0.006, volume_size=0.008)
    with pytest.raises(ValueError, match="ready mesh"):
        build_bundle(tmp_path / "b", mesh=small_box, mesh_size=0.02, volume_size=0.01)
    rc = main(["precompute", "--mesh-size", "0.006", "--volume-size", "0.01", "--out", str(tmp_path / "c")])
    err = capsys.readouterr().err
    assert rc == EXIT_INPUT and len(err.strip().splitlines()) == 1 and "volume size" in err
    with pytest.raises(SceneError, match="volume_size"):
        SeatSettings(mesh_size=0.006, volume_size=0.007)
    with pytest.raises(SceneError, match="load"):
        SeatSettings(load="disc")


def test_seat_settings_round_trip_with_grading(tmp_path):
    from hailstorm.runtime.storm.scene import Scene

    seat = SeatSettings(mesh_size=0.006, order=2, load="hat", volume_size=0.004)
    p = tmp_path / "scene.toml"
    Scene.default().to_toml(p, seat=seat)
    assert SeatSettings.from_toml(p) == seat
    none = SeatSettings(volume_size=None)
    Scene.default().to_toml(p, seat=none)
    assert "volume_size" not in p.read_text().split("[seat]")[1]


def _figures(scale: float) -> ds.Figures:
    return ds.Figures(scale * np.array([80e-6, 80e-6, 82e-6]), scale * np.array([90e-6, 91e-6, 92e-6]),
                      np.array([18e3, 18e3, 17e3]) / scale, 1000, 1.0, {"n_tets": 10, "patch_radius": 0.004})


def test_reference_cache_round_trip_and_key(tmp_path, monkeypatch):
    """A saved reference is read back as it was, only for the same levels; cached_reference computes
    once and then reads the file."""
    sizes = (0.002, 0.001)
    conv = ds.Convergence(list(sizes), [_figures(0.9), _figures(1.0)])
    path = tmp_path / "ref.npz"
    ds.save_convergence(conv, path)
    back = ds.load_convergence(path, sizes)
    for a, b in zip(conv.levels, back.levels):
        assert np.array_equal(a.dent, b.dent) and np.array_equal(a.stiffness, b.stiffness)
        assert np.array_equal(a.dent_centre, b.dent_centre) and a.n_dofs == b.n_dofs and a.extra == b.extra
    assert ds.load_convergence(path, (0.002, 0.0014)) is None  # other levels
    assert ds.load_convergence(path, sizes, sites={"c": (0.1, 0.0)}) is None  # other sites
    assert ds.load_convergence(tmp_path / "none.npz", sizes) is None
    (tmp_path / "bad.npz").write_text("not a reference")
    assert ds.load_convergence(tmp_path / "bad.npz", sizes) is None

    calls = []
    monkeypatch.setattr(ds, "converge_reference", lambda s, sites: calls.append(s) or conv)
    other = tmp_path / "other.npz"
    assert ds.cached_reference(sizes, other) is conv and len(calls) == 1
    again = ds.cached_reference(sizes, other)
    assert len(calls) == 1 and np.array_equal(again.reference.dent, conv.reference.dent)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.npz", "other.npz", "ref.npz"]  # nothing left over


def test_frontier_on_a_small_box(tmp_path, small_box):
    """The frontier's bookkeeping on a tiny mesh: signed errors against the reference, the landing
    spread (recomputed from one-point measurements), the columns of D (the pipeline's count), the
    cheapest row within the target, and the precompute's runs (the budget stops repeats)."""
    sites = {"c": (0.05, 0.05)}
    p1, p2 = ds.Setting(0.02, 1, "point"), ds.Setting(0.02, 2, "point")
    meshes = {p1: small_box, p2: small_box}
    ref = ds.measure_setting(p2, mesh=small_box, sites=sites, young=E, poisson=NU)
    rows = ds.frontier([p1, p2], ref, sites=sites, meshes=meshes, young=E, poisson=NU, consistent=True)
    assert [r.setting for r in rows] == [p1, p2]
    cons = ds.measure_consistent(small_box, 2, sites=sites, young=E, poisson=NU, patch_radius=ref.extra["patch_radius"])
    for r in rows:  # one mesh: the same consistent-load errors for both
        assert np.allclose(r.consistent[0], cons.dent / ref.dent - 1) and np.allclose(r.consistent[1], cons.stiffness / ref.stiffness - 1)
    assert np.allclose(rows[1].dent_error, 0.0) and np.allclose(rows[1].stiffness_error, 0.0) and rows[1].ok
    assert rows[0].dent_error[0] == pytest.approx(rows[0].figures.dent[0] / ref.dent[0] - 1.0)
    assert not rows[0].ok  # P1 on a 2-element-thick box is far from P2
    assert ds.cheapest(rows) is rows[1]

    # spread: the largest deviation from the mean over the site and its 6 landing points
    pts = ds.jittered(sites, 0.5 * p2.mesh_size)["c"]
    one = [ds.measure_setting(p2, mesh=small_box, sites={"p": tuple(x)}, young=E, poisson=NU, jitter=0)
           for x in pts]
    for q in ("dent", "stiffness"):
        vals = np.array([getattr(f, q)[0] for f in one])
        assert rows[1].figures.extra["spread"][q][0] == pytest.approx(np.max(np.abs(vals / vals.mean() - 1)))
    assert rows[1].spread == pytest.approx(max(np.max(v) for v in rows[1].figures.extra["spread"].values()))

    gf = load(build_bundle(tmp_path / "b", mesh=small_box, order=2, young=E, poisson=NU))
    assert rows[1].n_contactable == int(np.count_nonzero(gf.contactable)) == np.asarray(gf.D).shape[1] // 3

    ds.time_frontier(rows, repeats=2, budget=0.0, meshes=meshes)  # every run exceeds a zero budget: one each
    for r in rows:
        assert len(r.cost.wall) == len(r.cost.cpu) == len(r.cost.load) == 1 and r.cost.cpu[0] > 0
    ds.time_frontier(rows[1:], repeats=2, meshes=meshes)
    assert len(rows[1].cost.wall) == 2

    text = ds.format_frontier(rows)
    assert "cheapest within 5%: P2 point 20 mm" in text and len(text.splitlines()) == 5
    far_ref = ds.Figures(2 * ref.dent, ref.dent_centre, ref.stiffness, 0, 0.0)  # P2's dent 50 % off
    far = ds.frontier([p2], far_ref, sites=sites, meshes=meshes, young=E, poisson=NU)
    assert ds.cheapest(far) is None and "no setting meets" in ds.format_frontier(far)


def test_study_cli_bad_input(tmp_path, capsys):
    """An unwritable reference cache: one line, exit 3, before any work; bad sizes: a usage error."""
    rc = ds.main(["--frontier", "--reference-cache", str(tmp_path / "missing" / "ref.npz")])
    err = capsys.readouterr().err
    assert rc == 3 and len(err.strip().splitlines()) == 1 and "reference cache" in err
    with pytest.raises(SystemExit) as exc:
        ds.main(["--frontier", "--sizes", "6,x"])
    assert exc.value.code == 2
