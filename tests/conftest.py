"""Shared fixtures: small meshes and bundles, built once per session."""

import numpy as np
import pytest

from hailstorm.precompute import box_mesh, build_bundle


@pytest.fixture(scope="session")
def small_box():
    """A 0.1 x 0.1 x 0.05 m box clamped at z = 0 (216 nodes)."""
    return box_mesh((0.1, 0.1, 0.05), 0.02)


@pytest.fixture(scope="session")
def box_system(small_box):
    """The clamped P1 system of :func:`small_box` (E = 1 MPa, nu = 0.3): ``basis``, ``K``,
    ``fixed`` dofs, ``load`` dofs (every contactable vertex) and ``read`` dofs (the surface)."""
    from types import SimpleNamespace

    from hailstorm.precompute.fem import clamp_dofs, elasticity_basis, stiffness_matrix, vertex_dofs
    from hailstorm.precompute.pipeline import extract_surface

    basis = elasticity_basis(small_box, 1)
    surf = extract_surface(small_box)
    return SimpleNamespace(basis=basis, K=stiffness_matrix(basis, 1e6, 0.3), fixed=clamp_dofs(basis, small_box),
                           load=vertex_dofs(basis, surf.nodes[surf.contactable]).ravel(),
                           read=vertex_dofs(basis, surf.nodes).ravel())


@pytest.fixture(scope="session")
def box_bundle(tmp_path_factory, small_box):
    """A P1 bundle of :func:`small_box` (E = 1 MPa, nu = 0.3)."""
    return build_bundle(tmp_path_factory.mktemp("gf") / "box", mesh=small_box, order=1, young=1e6, poisson=0.3)


@pytest.fixture(scope="session")
def seat_bundle(tmp_path_factory):
    """The default saddle at a coarse 15 mm mesh (P1)."""
    return build_bundle(tmp_path_factory.mktemp("gf") / "seat", mesh_size=0.015, order=1)


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


@pytest.fixture
def run_notebook(tmp_path, monkeypatch):
    """Execute ``notebooks/<name>`` on small settings; return the text it printed.

    Checks that the notebook is committed without outputs; runs it with
    ``HAILSTORM_NOTEBOOK_SMALL=1``, a private cache and the Agg backend.
    """
    import os
    from pathlib import Path

    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")

    def run(name: str) -> str:
        path = Path(__file__).resolve().parents[1] / "notebooks" / name
        nb = nbformat.read(path, as_version=4)
        assert all(not c.get("outputs") for c in nb.cells if c.cell_type == "code"), "commit without outputs"
        monkeypatch.setenv("HAILSTORM_NOTEBOOK_SMALL", "1")
        monkeypatch.setenv("HAILSTORM_CACHE", str(tmp_path / "cache"))
        monkeypatch.setenv("MPLBACKEND", "Agg")
        # the kernel imports the studies (notebooks/studies, not in the package) as Jupyter does
        # when it starts in notebooks/: with that folder on its path
        monkeypatch.setenv("PYTHONPATH", os.pathsep.join(p for p in (str(path.parent), os.environ.get("PYTHONPATH"))
                                                         if p))
        nbclient.NotebookClient(nb, timeout=600, kernel_name="python3",
                                resources={"metadata": {"path": str(tmp_path)}}).execute()
        return "".join(o.get("text", "") for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []))

    return run
