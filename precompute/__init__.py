"""Offline stage: mesh a seat, assemble linear elasticity, compute its Green's functions.

The one entry point is :func:`build_bundle`; the pieces live in
:mod:`hailstorm.precompute.tetmesh` (:class:`TetMesh`, its checks, meshio's files, boxes),
:mod:`hailstorm.precompute.geometry` (gmsh -> :class:`TetMesh`),
:mod:`hailstorm.precompute.fem` (scikit-fem stiffness, clamp, dofs),
:mod:`hailstorm.precompute.greens` (the compliance D, A and Ξ = D A),
:mod:`hailstorm.precompute.blocks` (D's column blocks on disk, resumable),
:mod:`hailstorm.precompute.cluster` (the blocks in this process or on Dask),
:mod:`hailstorm.precompute.solve_loops` (D solved dense or compressed as it comes),
:mod:`hailstorm.precompute.surface` (the bundle's surface),
:mod:`hailstorm.precompute.settings` (:class:`BuildSettings`, :class:`RunSettings`: the
inputs, checked once) and :mod:`hailstorm.precompute.pipeline` (cache key, bundle).
"""

from hailstorm.precompute.geometry import mesh_default_seat, mesh_geometry
from hailstorm.precompute.pipeline import build_bundle, default_cache_dir
from hailstorm.precompute.settings import BuildSettings, RunSettings
from hailstorm.precompute.surface import extract_surface
from hailstorm.precompute.tetmesh import MeshError, TetMesh, box_mesh, read_mesh

__all__ = [
    "BuildSettings",
    "MeshError",
    "RunSettings",
    "TetMesh",
    "box_mesh",
    "build_bundle",
    "default_cache_dir",
    "extract_surface",
    "mesh_default_seat",
    "mesh_geometry",
    "read_mesh",
]
