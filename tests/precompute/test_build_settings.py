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
