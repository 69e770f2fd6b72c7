"""Materials per volume group: analytic layered cases, D across an interface, bad input.

The analytic cases have piecewise-linear exact solutions with the interface on
element faces, so P1 (and P2) reproduce them to solver precision: the
tolerances are round-off (1e-9 relative), not discretization error.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

from hailstorm.precompute import box_mesh, build_bundle
from hailstorm.precompute.fem import elasticity_basis, solve_direct, stiffness_matrix, vertex_dofs
from hailstorm.precompute.geometry import TetMesh, mesh_geometry, read_mesh
from hailstorm.precompute.greens import lumped_areas
from hailstorm.precompute.materials import (
    WHOLE_BODY,
    check_layers,
    parse_material,
    resolve_materials,
)
from hailstorm.runtime.bundle.read import load
from hailstorm.cli import main


def layered(mesh: TetMesh, axis: int, cut: float, low: str = "hard", high: str = "soft") -> TetMesh:
    """``mesh`` with two volume groups split at ``axis = cut`` (a plane of element faces)."""
    c = mesh.points[mesh.tets].mean(axis=1)[:, axis]
    return TetMesh(mesh.points, mesh.tets, mesh.groups, mesh.source,
                   {low: np.flatnonzero(c < cut), high: np.flatnonzero(c >= cut)})


def face_loads(mesh: TetMesh, axis: int, at: float, traction: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertices of the boundary face ``axis = at`` and their nodal forces for a uniform traction.

    For P1 a uniform traction's consistent nodal force is the lumped vertex area times the traction.
    """
    from hailstorm.precompute.geometry import boundary_triangles

    tris = boundary_triangles(mesh.tets)
    on = np.all(np.isclose(mesh.points[tris][:, :, axis], at), axis=1)
    nodes, local = np.unique(tris[on], return_inverse=True)
    areas = lumped_areas(mesh.points[nodes], local.reshape(-1, 3))
    return nodes, traction * areas


# ----------------------------------------------------------------------------- analytic layered cases

def test_two_material_bar_in_tension_is_springs_in_series(tmp_path):
    """Bar clamped at x = 0, uniform traction at x = L; nu = 0 so the clamp does not restrain any
    contraction: the exact solution is uniaxial stress, u_x(L) = sigma (L1/E1 + L2/E2), piecewise
    linear in x, which P1 represents exactly. Through the bundle's D (the pipeline path)."""
    L1, L2, E1, E2, sigma = 0.06, 0.04, 5e6, 1e6, 1e3
    mesh = layered(box_mesh((L1 + L2, 0.02, 0.02), 0.01, clamp="x0"), 0, L1, low="near", high="far")
    gf = load(build_bundle(tmp_path / "bar", mesh=mesh, materials={"near": (E1, 0.0), "far": (E2, 0.0)}))
    nodes, f = face_loads(mesh, 0, L1 + L2, sigma)
    col_of = {n: k for k, n in enumerate(gf.surface_nodes[gf.contactable])}
    rows = np.searchsorted(gf.surface_nodes, nodes)
    cols = np.array([col_of[n] for n in nodes])
    u = gf.D[np.ravel(3 * rows[:, None] + np.arange(3))][:, 3 * cols] @ f  # x-forces only
    ux = u.reshape(-1, 3)[:, 0]
    expected = sigma * (L1 / E1 + L2 / E2)
    assert np.allclose(ux, expected, rtol=1e-9)
    # a single-material bar of the soft material stretches more: the test sees the stiff part
    assert expected < 0.6 * sigma * (L1 + L2) / E2


@pytest.mark.parametrize("order", [1, 2])
def test_layer_on_stiffer_layer_laterally_confined(order):
    """A soft layer (t1, E1, nu1) bonded on a stiff one (t2, E2, nu2) on a rigid base, side walls on
    rollers (no lateral displacement), uniform pressure p on top: 1-D strain, each layer shortens by
    p t / M with M = E (1 - nu) / ((1 + nu)(1 - 2 nu)) the constrained modulus."""
    t_hard, t_soft, p = 0.01, 0.02, 2e3
    E = {"soft": 1e6, "hard": 3e7}
    nu = {"soft": 0.3, "hard": 0.45}
    size = (0.02, 0.02, t_hard + t_soft)
    mesh = layered(box_mesh(size, 0.005), 2, t_hard)
    mats = resolve_materials(mesh, {k: (E[k], nu[k]) for k in E})
    basis = elasticity_basis(mesh, order)
    K = stiffness_matrix(basis, mats.tet_young, mats.tet_poisson)
    # rollers: u_x = 0 on x faces, u_y = 0 on y faces, u_z = 0 at the base (every dof at those locations)
    loc = basis.doflocs
    comp = np.empty(K.shape[0], dtype=np.int64)
    for d in range(3):
        comp[basis.nodal_dofs[d]] = d
        if basis.edge_dofs.size:
            comp[basis.edge_dofs[d]] = d
    fixed = np.flatnonzero(
        ((comp == 0) & (np.isclose(loc[0], 0) | np.isclose(loc[0], size[0])))
        | ((comp == 1) & (np.isclose(loc[1], 0) | np.isclose(loc[1], size[1])))
        | ((comp == 2) & np.isclose(loc[2], 0)))
    # uniform pressure: consistent load of the top face through a facet basis (exact for P1 and P2)
    from skfem import FacetBasis, LinearForm

    top = basis.mesh.facets_satisfying(lambda X: np.isclose(X[2], size[2]))
    fb = FacetBasis(basis.mesh, basis.elem, facets=top, intorder=4)

    @LinearForm
    def pressure(v, w):
        return -p * v[2]

    f = pressure.assemble(fb)
    u = solve_direct(K, f, fixed)
    M = {k: E[k] * (1 - nu[k]) / ((1 + nu[k]) * (1 - 2 * nu[k])) for k in E}
    top_nodes = np.flatnonzero(np.isclose(mesh.points[:, 2], size[2]))
    mid_nodes = np.flatnonzero(np.isclose(mesh.points[:, 2], t_hard))
    uz_top = u[vertex_dofs(basis, top_nodes)[:, 2]]
    uz_mid = u[vertex_dofs(basis, mid_nodes)[:, 2]]
    assert np.allclose(uz_mid, -p * t_hard / M["hard"], rtol=1e-9)
    assert np.allclose(uz_top, -p * (t_hard / M["hard"] + t_soft / M["soft"]), rtol=1e-9)


def test_per_tet_stiffness_equals_scalar_for_one_material(small_box):
    basis = elasticity_basis(small_box, 1)
    n = small_box.tets.shape[0]
    K1 = stiffness_matrix(basis, 2e6, 0.35)
    K2 = stiffness_matrix(basis, np.full(n, 2e6), np.full(n, 0.35))
    assert abs(K1 - K2).max() <= 1e-12 * abs(K1).max()


# ----------------------------------------------------------------------------- D across the interface

@pytest.fixture(scope="module")
def two_layer(tmp_path_factory):
    mesh = layered(box_mesh((0.04, 0.04, 0.02), 0.005), 2, 0.01)
    mats = {"soft": (1e6, 0.3), "hard": (5e7, 0.4)}
    out = tmp_path_factory.mktemp("gf") / "two"
    return mesh, mats, load(build_bundle(out, mesh=mesh, materials=mats, order=2))


def test_d_is_symmetric_across_the_interface(two_layer):
    """Reciprocity: D on contactable rows and columns is symmetric, including the blocks that couple a
    vertex of one material to a vertex of the other."""
    mesh, _, gf = two_layer
    c = gf.contact_vertices
    Dcc = gf.compliance(c, c)
    assert np.allclose(Dcc, Dcc.T, atol=1e-10 * np.abs(Dcc).max())
    z = gf.vertices[c, 2]
    soft, hard = np.flatnonzero(z > 0.0101), np.flatnonzero(z < 0.0099)
    assert soft.size and hard.size
    cross = gf.compliance(c[soft], c[hard])
    assert np.abs(cross).max() > 1e-3 * np.abs(Dcc).max()  # the coupling is real, not zero
    assert np.allclose(cross, gf.compliance(c[hard], c[soft]).T, atol=1e-10 * np.abs(Dcc).max())


def test_bundle_records_materials_and_tet_fields(two_layer):
    mesh, mats, gf = two_layer
    rec = {m["volume"]: m for m in gf.manifest["materials"]}
    assert {k: (v["young"], v["poisson"]) for k, v in rec.items()} == mats
    # per-tet fields follow the geometry: tets above z = 1 cm are soft
    zc = gf.volume_points[gf.volume_tets].mean(axis=1)[:, 2]
    assert np.all(gf.tet_young[zc > 0.01] == 1e6) and np.all(gf.tet_young[zc < 0.01] == 5e7)
    assert np.all(gf.tet_poisson[zc > 0.01] == 0.3) and np.all(gf.tet_poisson[zc < 0.01] == 0.4)
    # the bundle's single (E, nu) is the material under most of the contactable surface: the soft top
    assert (gf.young, gf.poisson) == (1e6, 0.3)


def test_cache_key_includes_every_material(tmp_path):
    mesh = layered(box_mesh((0.02, 0.02, 0.02), 0.01), 2, 0.01)
    out = tmp_path / "b"
    p = build_bundle(out, mesh=mesh, materials={"soft": (1e6, 0.3), "hard": (5e7, 0.4)})
    k1 = json.loads((Path(p) / "manifest.json").read_text())["key"]
    build_bundle(out, mesh=mesh, materials={"soft": (1e6, 0.3), "hard": (5e7, 0.4)})
    assert json.loads((Path(p) / "manifest.json").read_text())["key"] == k1  # reused
    build_bundle(out, mesh=mesh, materials={"soft": (1e6, 0.3), "hard": (6e7, 0.4)})  # the buried layer only
    k2 = json.loads((Path(p) / "manifest.json").read_text())["key"]
    assert k2 != k1
    assert load(out).tet_young.max() == 6e7


TWO_BOXES = '''SetFactory("OpenCASCADE");
Box(1) = {0, 0, 0, 0.03, 0.03, 0.01};
Box(2) = {0, 0, 0.01, 0.03, 0.03, 0.01};
BooleanFragments{ Volume{1}; Delete; }{ Volume{2}; Delete; }
eps = 1e-6;
Physical Volume("shell") = {1};
Physical Volume("pad") = {2};
Physical Surface("clamp") = {Surface In BoundingBox{-eps, -eps, -eps, 0.03 + eps, 0.03 + eps, eps}};
Physical Surface("top") = {Surface In BoundingBox{-eps, -eps, 0.02 - eps, 0.03 + eps, 0.03 + eps, 0.02 + eps}};
'''


@pytest.fixture(scope="module")
def two_boxes(tmp_path_factory) -> tuple[Path, Path]:
    """A .geo of a 'pad' box on a 'shell' box (gmsh Physical Volumes), and its .msh meshed by gmsh."""
    import gmsh

    d = tmp_path_factory.mktemp("geo")
    geo, msh = d / "two.geo", d / "two.msh"
    geo.write_text(TWO_BOXES)
    gmsh.initialize()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.open(str(geo))
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.006)
        gmsh.model.mesh.generate(3)
        gmsh.write(str(msh))
    finally:
        gmsh.finalize()
    return geo, msh


def test_gmsh_volume_groups_reach_the_mesh_and_msh_files(two_boxes):
    """Two boxes fused by gmsh with Physical Volumes: mesh_geometry and read_mesh (.msh) both see them."""
    geo, msh = two_boxes
    for mesh in (mesh_geometry(geo, 0.006), read_mesh(msh)):
        assert sorted(mesh.volumes) == ["pad", "shell"]
        zc = mesh.points[mesh.tets].mean(axis=1)[:, 2]
        assert np.all(zc[mesh.volumes["pad"]] > 0.01) and np.all(zc[mesh.volumes["shell"]] < 0.01)
        assert mesh.volumes["pad"].size + mesh.volumes["shell"].size == mesh.tets.shape[0]


# ----------------------------------------------------------------------------- bad input

@pytest.fixture(scope="module")
def pad_on_shell():
    return layered(box_mesh((0.02, 0.02, 0.02), 0.01), 2, 0.01, low="shell", high="pad")


def test_volume_without_material_is_named(pad_on_shell):
    with pytest.raises(ValueError, match=r"volume group 'shell' .* has no material.*--material shell=E,nu"):
        resolve_materials(pad_on_shell, {"pad": (1e6, 0.3)})


def test_material_naming_no_volume(pad_on_shell):
    with pytest.raises(ValueError, match=r"'foam' names no volume group.*'pad', 'shell'"):
        resolve_materials(pad_on_shell, {"pad": (1e6, 0.3), "shell": (1e9, 0.3), "foam": (1e6, 0.3)})


@pytest.mark.parametrize("bad, why", [((-1.0, 0.3), "Young's modulus"), ((1e6, 0.5), "incompressible"),
                                      ((float("nan"), 0.3), "Young's modulus"), ((1e6, -1.0), "not a stable"),
                                      ((1e6,), "a pair")])
def test_invalid_material_names_its_group(pad_on_shell, bad, why):
    with pytest.raises(ValueError, match=rf"volume 'shell'.*{why}"):
        resolve_materials(pad_on_shell, {"pad": (1e6, 0.3), "shell": bad})


def test_invalid_material_refused_before_meshing(tmp_path, monkeypatch):
    import hailstorm.precompute.pipeline as pipeline

    monkeypatch.setattr(pipeline, "load_seat", lambda *a, **k: pytest.fail("meshed before checking materials"))
    with pytest.raises(ValueError, match="volume 'pad'"):
        build_bundle(tmp_path / "x", materials={"pad": (0.0, 0.3)})
    with pytest.raises(ValueError, match="not both"):
        build_bundle(tmp_path / "x", materials={"pad": (1e6, 0.3)}, young=1e6)


def test_tets_without_a_group_or_in_two(pad_on_shell):
    m = pad_on_shell
    partial = TetMesh(m.points, m.tets, m.groups, "partial", {"pad": m.volumes["pad"], "shell": m.volumes["shell"][1:]})
    with pytest.raises(ValueError, match=r"1 tetrahedra .* in no volume group"):
        resolve_materials(partial, {"pad": (1e6, 0.3), "shell": (1e9, 0.3)})
    both = TetMesh(m.points, m.tets, m.groups, "both", {"pad": m.volumes["pad"], "shell": np.arange(m.tets.shape[0])})
    with pytest.raises(ValueError, match="in both volume groups"):
        resolve_materials(both, {"pad": (1e6, 0.3), "shell": (1e9, 0.3)})


def test_single_material_ignores_volume_groups(pad_on_shell):
    mats = resolve_materials(pad_on_shell, young=3e6, poisson=0.2)
    assert mats.names == (WHOLE_BODY,) and np.all(mats.tet_young == 3e6) and mats.key() is None


def test_pad_thinner_than_one_element_warns_with_numbers(caplog):
    """A 2 mm pad one element thick on a shell two elements thick: the warning names the pad with its
    numbers; layers two elements thick do not warn."""
    thick = box_mesh((0.04, 0.04, 0.012), 0.004)  # 3 element layers at z = 0, 4, 8, 12 mm
    p = thick.points.copy()
    p[np.isclose(p[:, 2], 0.008), 2] = 0.010  # -> a 10 mm shell of 2 layers under a 2 mm pad of 1
    p[np.isclose(p[:, 2], 0.004), 2] = 0.005
    thin = layered(TetMesh(p, thick.tets, thick.groups, "thin"), 2, 0.010, low="shell", high="pad")
    mats = resolve_materials(thin, {"pad": (1e6, 0.3), "shell": (1e9, 0.3)})
    with caplog.at_level(logging.WARNING):
        said = check_layers(thin, mats)
    assert len(said) == 1 and "'pad'" in said[0]
    assert "about 1.82 mm thick" in said[0]  # 2 V / A of a 40 x 40 x 2 mm slab: 2 mm / (1 + 2 t / L), L = 20 t
    assert "mm (median edge)" in said[0] and "pad" in caplog.text
    ok = layered(box_mesh((0.04, 0.04, 0.02), 0.005), 2, 0.01, low="shell", high="pad")
    assert check_layers(ok, resolve_materials(ok, {"pad": (1e6, 0.3), "shell": (1e9, 0.3)})) == []


@pytest.mark.parametrize("text, name, e, nu", [("pad=0.5e6,0.3", "pad", 0.5e6, 0.3), (" shell = 2e9 , 0.4", "shell", 2e9, 0.4)])
def test_parse_material(text, name, e, nu):
    assert parse_material(text) == (name, e, nu)


@pytest.mark.parametrize("args, says", [
    (["--material", "pad"], "expected NAME=E,nu"),
    (["--material", "pad=1e6"], "expected NAME=E,nu"),
    (["--material", "pad=soft,0.3"], "must be numbers"),
    (["--material", "pad=1e6,0.6"], "volume 'pad'"),
    (["--material", "pad=1e6,0.3", "--material", "pad=2e6,0.3"], "already given"),
    (["--material", "pad=1e6,0.3"], "'shell' .* has no material"),
    (["--material", "pad=1e6,0.3", "--material", "shell=1e9,0.3", "--material", "foam=1e6,0.3"], "'foam' names no volume"),
    (["--material", "pad=1e6,0.3", "--material", "shell=1e9,0.3", "--young", "1e6"], "not both"),
])
def test_cli_material_errors_one_line_exit_3(tmp_path, capsys, two_boxes, args, says):
    import re

    rc = main(["precompute", "-q", "--order", "1", "--geometry", str(two_boxes[1]), "--out", str(tmp_path / "out"), *args])
    err = capsys.readouterr().err
    assert rc == 3
    assert err.count("\n") == 1 and err.startswith("hailstorm: error: ") and re.search(says, err), err
    assert not (tmp_path / "out").exists()


def test_cli_materials_build_and_info(tmp_path, capsys, two_boxes):
    rc = main(["precompute", "-q", "--order", "1", "--geometry", str(two_boxes[1]), "--out", str(tmp_path / "out"),
               "--material", "pad=1e6,0.3", "--material", "shell=2e9,0.4"])
    assert rc == 0
    out = capsys.readouterr().out
    assert "volume pad: E = 1e+06 Pa, nu = 0.3" in out and "volume shell: E = 2e+09 Pa, nu = 0.4" in out
    gf = load(tmp_path / "out")
    assert sorted(np.unique(gf.tet_young)) == [1e6, 2e9]
