"""The bundle's surface: the boundary of a tet mesh as a P1 triangle surface on its corner
vertices, with lumped vertex areas and which vertices are clamped and which hail can reach."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hailstorm.precompute.tetmesh import MeshError, TetMesh, boundary_triangles
from hailstorm.precompute.greens import lumped_areas

__all__ = ["Surface", "extract_surface"]


@dataclass(frozen=True)
class Surface:
    """The boundary of a tet mesh as a P1 triangle surface on the corner vertices.

    Attributes
    ----------
    nodes : (n,) int
        Volume node of each surface vertex (``surface_nodes`` in the bundle).
    triangles : (m, 3) int
        Outward triangles in surface-vertex numbering.
    fixed, contactable : (n,) bool
    areas : (n,) float
        Lumped vertex areas.
    """

    nodes: np.ndarray
    triangles: np.ndarray
    fixed: np.ndarray
    contactable: np.ndarray
    areas: np.ndarray


def extract_surface(mesh: TetMesh, contact_group: str = "top") -> Surface:
    """Surface vertices, triangles, areas and the fixed/contactable masks of ``mesh``.

    Parameters
    ----------
    mesh : TetMesh
        A checked mesh with a ``clamp`` group.
    contact_group : str
        The surface group hail can reach: its vertices that are not clamped are
        contactable (``"all"``: every unclamped surface vertex).

    Returns
    -------
    Surface

    Raises
    ------
    MeshError
        No vertex is contactable (the group lies entirely on the clamp).
    """
    tris = boundary_triangles(mesh.tets)
    nodes, local = np.unique(tris, return_inverse=True)
    triangles = local.reshape(-1, 3)
    fixed = np.isin(nodes, mesh.group_vertices("clamp"))
    if contact_group == "all":
        contactable = ~fixed
    else:
        contactable = np.isin(nodes, mesh.group_vertices(contact_group)) & ~fixed
    if not contactable.any():
        raise MeshError(f"{mesh.source}: no contactable vertices: group {contact_group!r} lies entirely on the clamp")
    areas = lumped_areas(mesh.points[nodes], triangles)
    return Surface(nodes, triangles, fixed, contactable, areas)
