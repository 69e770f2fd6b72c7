"""A graded elastic block that stands in for a half-space: the analytic references' body.

Boussinesq (a point load) and Hertz (a sphere) are solutions on an elastic
half-space. A finite block approximates one when it is large against the
loaded region, and a finite-element mesh resolves one when its elements under
the load are small against the contact radius. :func:`halfspace_block` builds
such a block with gmsh: fine elements (``fine_size``) within ``fine_radius``
of the origin on the top face, growing smoothly to ``coarse_size`` away from
it, the bottom face clamped, and the hail-facing group ``top`` restricted to a
small square around the origin (only those vertices get columns of D: the
Green's functions cost what the load needs, not what the block needs).

The far field matters as much as the elements under the load: a Hertz
contact of radius ``a`` on a block clamped at depth ``H`` is stiffened by
about ``0.75 a / H`` (Boussinesq's on-axis displacement at the clamp), and P1
elements of size ``h ~ growth * r`` away from the load are stiff by
``O(growth^2)``. Measured on the 0.35 mm block at ``delta / R = 0.04``
(``a = 2 mm``): a 50 mm block clamped at 50 mm with 30 % growth to 8 mm was
5.4 % stiffer than the defaults (150 mm, 15 % growth to 30 mm; a 300 mm block
changes the force by a further 0.6 %), and a point force's far-field
coefficient (Boussinesq) was 0.90 instead of 0.97. The element count grows
with the logarithm of the block size (``h ~ growth * r``), not its volume.

The top face is the plane ``z = 0`` with outward normal ``+z``; the block
spans ``[-half_width, half_width]^2 x [-depth, 0]``.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from hailstorm.precompute.tetmesh import MeshError, TetMesh, read_mesh
from hailstorm.runtime.resources import require_extra

__all__ = ["halfspace_block"]


def halfspace_block(
    *,
    half_width: float = 0.15,
    depth: float = 0.15,
    top_half_width: float = 0.0022,
    fine_size: float = 2.5e-4,
    fine_radius: float = 0.003,
    coarse_size: float = 0.03,
    growth: float = 0.15,
) -> TetMesh:
    """Mesh a block graded towards the centre of its top face.

    Parameters
    ----------
    half_width, depth : float
        The block is ``[-half_width, half_width]^2 x [-depth, 0]`` [m].
    top_half_width : float
        Half width of the square ``top`` group around the origin [m]: the
        contactable vertices.
    fine_size : float
        Element size within ``fine_radius`` of the origin [m].
    fine_radius : float
        Radius of the finely meshed region [m] (at least ``top_half_width``
        is sensible).
    coarse_size : float
        Element size far from the origin [m].
    growth : float
        Rate at which the element size grows with the distance beyond
        ``fine_radius`` (``dh/dr``; 0.3: about 30 % per element layer) until
        it reaches ``coarse_size``.

    Returns
    -------
    TetMesh
        With groups ``top`` (the central square) and ``clamp`` (the bottom).

    Raises
    ------
    MeshError
        Inconsistent sizes.
    """
    sizes = dict(half_width=half_width, depth=depth, top_half_width=top_half_width, fine_size=fine_size,
                 fine_radius=fine_radius, coarse_size=coarse_size, growth=growth)
    for name, v in sizes.items():
        if not (v > 0):
            raise MeshError(f"halfspace_block: {name} must be positive, got {v!r}")
    if not top_half_width < half_width:
        raise MeshError("halfspace_block: top_half_width must be smaller than half_width")
    if not fine_size <= coarse_size:
        raise MeshError("halfspace_block: fine_size must not exceed coarse_size")
    gmsh = require_extra("gmsh", "precompute", "meshing (gmsh)")

    if gmsh.isInitialized():
        gmsh.finalize()
    gmsh.initialize(interruptible=False)
    try:
        for opt, val in (("General.Terminal", 0), ("General.Verbosity", 2), ("General.NumThreads", 1),
                         ("Mesh.MaxNumThreads3D", 1), ("Mesh.RandomSeed", 1), ("Mesh.Algorithm3D", 1),
                         ("Mesh.MeshSizeFromPoints", 0), ("Mesh.MeshSizeFromCurvature", 0),
                         ("Mesh.MeshSizeExtendFromBoundary", 0), ("Mesh.ElementOrder", 1)):
            gmsh.option.setNumber(opt, val)
        occ = gmsh.model.occ
        L, H, c = half_width, depth, top_half_width
        box = occ.addBox(-L, -L, -H, 2 * L, 2 * L, H)
        square = occ.addRectangle(-c, -c, 0.0, 2 * c, 2 * c)
        occ.fragment([(3, box)], [(2, square)])
        occ.synchronize()
        top, clamp = [], []
        tol = 1e-3 * c  # OCC bounding boxes are inflated by its tolerance (1e-7 m)
        for dim, tag in gmsh.model.getEntities(2):
            x0, y0, z0, x1, y1, z1 = gmsh.model.getBoundingBox(dim, tag)
            if abs(z0) < tol and abs(z1) < tol and max(abs(x0), abs(x1), abs(y0), abs(y1)) <= c + tol:
                top.append(tag)
            elif abs(z0 + H) < tol and abs(z1 + H) < tol:
                clamp.append(tag)
        if len(top) != 1 or not clamp:
            raise MeshError("halfspace_block: could not identify the top square and the bottom face")
        gmsh.model.addPhysicalGroup(2, top, name="top")
        gmsh.model.addPhysicalGroup(2, clamp, name="clamp")
        gmsh.model.addPhysicalGroup(3, [t for _, t in gmsh.model.getEntities(3)], name="body")
        point = occ.addPoint(0.0, 0.0, 0.0)
        occ.synchronize()
        f_dist = gmsh.model.mesh.field.add("Distance")
        gmsh.model.mesh.field.setNumbers(f_dist, "PointsList", [point])
        f_thr = gmsh.model.mesh.field.add("Threshold")
        gmsh.model.mesh.field.setNumber(f_thr, "InField", f_dist)
        gmsh.model.mesh.field.setNumber(f_thr, "SizeMin", fine_size)
        gmsh.model.mesh.field.setNumber(f_thr, "SizeMax", coarse_size)
        gmsh.model.mesh.field.setNumber(f_thr, "DistMin", fine_radius)
        # the size grows linearly with the distance, dh/dr = growth (a fraction growth per element layer)
        grow = (coarse_size - fine_size) / growth
        gmsh.model.mesh.field.setNumber(f_thr, "DistMax", fine_radius + max(grow, coarse_size))
        gmsh.model.mesh.field.setAsBackgroundMesh(f_thr)
        gmsh.option.setNumber("Mesh.MeshSizeMax", coarse_size)
        gmsh.model.mesh.generate(3)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "halfspace.msh"
            gmsh.write(str(path))
            mesh = read_mesh(path)
    finally:
        gmsh.finalize()
    mesh.source = f"halfspace_block(L={half_width:g}, H={depth:g}, h={fine_size:g}..{coarse_size:g})"
    return mesh
