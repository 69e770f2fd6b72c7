"""build_bundle's inputs resolved once (:class:`hailstorm.precompute.settings.BuildSettings`), and
what a build says about its mesh."""

import logging

import pytest

from hailstorm.precompute import geometry
from hailstorm.precompute.geometry import mesh_default_seat
from hailstorm.precompute.pipeline import build_bundle


def _messages(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno >= logging.INFO]


def test_a_warm_build_does_not_say_it_meshes(tmp_path, caplog):
    """A build that reuses its bundle meshes the seat only to find the key, and says nothing of
    it (issue: a lean house); the build that computes names the mesh it computed for."""
    out = tmp_path / "b"
    with caplog.at_level(logging.INFO, logger="hailstorm"):
        build_bundle(out, mesh_size=0.02)
    cold = _messages(caplog)
    assert any(m.startswith("mesh saddle.geo@h=0.02:") and "tetrahedra" in m for m in cold), cold
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="hailstorm"):
        assert build_bundle(out, mesh_size=0.02) == out.absolute()
    warm = _messages(caplog)
    assert any("is up to date" in m for m in warm), warm
    assert not any("mesh" in m.split(" ", 1)[0] for m in warm), warm


def test_a_large_geometry_is_announced_before_it_is_meshed(caplog, monkeypatch):
    """Meshing that takes a while (more estimated surface vertices than
    ``ANNOUNCE_SURFACE_VERTICES``) is announced; a small mesh is made silently."""
    with caplog.at_level(logging.INFO, logger="hailstorm"):
        mesh_default_seat(0.03)
    assert not any(m.startswith("meshing") for m in _messages(caplog))
    monkeypatch.setattr(geometry, "ANNOUNCE_SURFACE_VERTICES", 0)
    with caplog.at_level(logging.INFO, logger="hailstorm"):
        mesh_default_seat(0.03)
    assert any(m.startswith("meshing saddle.geo at 0.03 m (about") for m in _messages(caplog))


def test_the_settings_are_checked_when_they_are_made():
    """A bad value is refused on construction, naming it (before any meshing)."""
    from hailstorm.precompute.settings import BuildSettings, RunSettings

    for kwargs, match in ((dict(order=3), "element order"), (dict(load="disc"), "unknown load"),
                          (dict(solver="magic"), "unknown solver"), (dict(tol=2.0), "solver tolerance"),
                          (dict(mesh_size=-1.0), "mesh size"), (dict(dtype="float16"), "storage type"),
                          (dict(compress_tol=1e-2, dtype="float32"), "compressed D is stored in float64"),
                          (dict(stream=True), "--stream needs --tol"),
                          (dict(young=1e6, materials={"pad": (1e6, 0.3)}), "not both")):
        with pytest.raises(ValueError, match=match):
            BuildSettings(**kwargs)
    with pytest.raises(ValueError, match="coarsening grades a geometry"):
        BuildSettings(mesh=geometry.box_mesh(), coarsening=3.0)
    with pytest.raises(ValueError, match="workers must be a positive number"):
        RunSettings(workers=0)
    assert BuildSettings(coarsening=3).coarsening == 3.0 and BuildSettings(compress_tol=1e-2).compress_tol == 1e-2


def test_keywords_map_onto_the_two_records():
    """``build_bundle``'s keyword arguments are the records' fields, split between them and
    replacing given records' fields; an unknown one is a TypeError as for any function."""
    from hailstorm.precompute.settings import BuildSettings, RunSettings, settings_from_keywords

    build, run = settings_from_keywords(mesh_size=0.004, order=2, workers=2, reuse=False)
    assert build == BuildSettings(mesh_size=0.004, order=2) and run == RunSettings(workers=2, reuse=False)
    build, run = settings_from_keywords(build, run, order=1, progress=True)
    assert (build.mesh_size, build.order, run.workers, run.progress) == (0.004, 1, 2, True)
    with pytest.raises(TypeError, match="unexpected keyword argument 'mesh_sise'"):
        settings_from_keywords(mesh_sise=0.004)
    with pytest.raises(TypeError, match="unexpected keyword argument"):
        build_bundle(None, mesh_sise=0.004)


def test_a_settings_object_builds_the_bundle_the_keywords_build(tmp_path):
    """``build_bundle(out, BuildSettings(...))`` and the keyword call are one bundle (one key)."""
    from hailstorm.precompute.settings import BuildSettings
    from hailstorm.runtime.bundle.format import read_manifest

    mesh = geometry.box_mesh((0.02, 0.02, 0.01), 0.01)
    a = build_bundle(tmp_path / "a", mesh=mesh, order=1, load="hat")
    b = build_bundle(tmp_path / "b", BuildSettings(mesh=mesh, order=1, load="hat"))
    assert read_manifest(a)["key"] == read_manifest(b)["key"]
    assert read_manifest(a)["options"] == read_manifest(b)["options"]
