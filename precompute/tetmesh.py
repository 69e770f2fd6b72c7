"""The tetrahedral mesh the offline stage works on, its checks, and the meshes made without gmsh.

:class:`TetMesh` holds what the pipeline needs from a mesh: points, tetrahedra,
the named surface groups ``top`` (where hail can land) and ``clamp`` (zero
displacement), and named volume groups (one material each). It comes from

* :mod:`hailstorm.precompute.geometry` -- a gmsh geometry meshed (the default
  saddle, a user's ``.geo``/``.step``...);
* :func:`read_mesh` -- a tetrahedral mesh in any format meshio reads, with the
  same group names (gmsh ``.msh`` physical names, or meshio cell sets);
* :func:`box_mesh` -- a box, for tests and analytic comparisons.

Every constructor returns a mesh that passed :func:`check_mesh`.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hailstorm.runtime.resources import require_extra

__all__ = ["MAX_COORDINATE", "REQUIRED_GROUPS", "MeshError", "TetMesh", "box_mesh", "boundary_triangles",
           "check_clamped", "check_mesh", "connected_parts", "read_mesh", "tet_volumes"]

#: the surface groups every mesh must have
REQUIRED_GROUPS = ("clamp",)


class MeshError(ValueError):
    """A geometry or mesh cannot be used (missing file or group, bad elements)."""



@dataclass(eq=False)
class TetMesh:
    """A linear tetrahedral mesh with named boundary groups.

    Attributes
    ----------
    points : (N, 3) float ndarray
        Node coordinates [m].
    tets : (T, 4) int ndarray
        Positively oriented tetrahedra.
    groups : dict of str -> (k, 3) int ndarray
        Named boundary triangles (node indices), e.g. ``"top"``, ``"clamp"``.
    source : str
        Where the mesh came from (for the manifest).
    volumes : dict of str -> (k,) int ndarray
        Named volume groups: indices into ``tets`` (gmsh Physical Volumes, meshio
        tetra cell sets). Materials are given per volume group
        (:mod:`hailstorm.precompute.materials`); empty for an unnamed body.
    """

    points: np.ndarray
    tets: np.ndarray
    groups: dict[str, np.ndarray] = field(default_factory=dict)
    source: str = ""
    volumes: dict[str, np.ndarray] = field(default_factory=dict)

    def content_hash(self) -> str:
        """SHA-256 of points, tets and groups: the mesh part of the cache key."""
        h = hashlib.sha256()
        for a in (self.points, self.tets):
            a = np.ascontiguousarray(a)
            h.update(a.dtype.str.encode() + str(a.shape).encode() + a.tobytes())
        for name in sorted(self.groups):
            g = np.ascontiguousarray(np.sort(self.groups[name], axis=1), dtype=np.int64)
            h.update(name.encode() + g.tobytes())
        for name in sorted(self.volumes):
            v = np.ascontiguousarray(np.sort(self.volumes[name]), dtype=np.int64)
            h.update(b"volume:" + name.encode() + v.tobytes())
        return h.hexdigest()

    def group_vertices(self, name: str) -> np.ndarray:
        """Sorted unique node indices of a boundary group."""
        if name not in self.groups:
            raise MeshError(f"{self.source or 'the mesh'}: the mesh has no surface group {name!r} "
                            f"(it has: {', '.join(sorted(self.groups)) or 'none'})")
        return np.unique(self.groups[name])


def tet_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes of tetrahedra (positive for the right-handed orientation)."""
    p = points[tets]
    return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0


#: the largest coordinate a mesh may hold [m] (a thousand kilometres: far beyond any solid this
#: models, far below where a tetrahedron's volume, a cube of coordinates, overflows)
MAX_COORDINATE = 1e6


def check_mesh(mesh: TetMesh, required=REQUIRED_GROUPS) -> TetMesh:
    """Validate a mesh; raise :class:`MeshError` naming the problem.

    Checks finite coordinates within :data:`MAX_COORDINATE` of the origin, index ranges, the
    required groups, and that no
    tetrahedron is inverted or degenerate (volume <= 1e-9 of the mean edge
    length cubed).
    """
    pts, tets = mesh.points, mesh.tets
    if pts.ndim != 2 or pts.shape[1] != 3 or not np.all(np.isfinite(pts)):
        raise MeshError(f"{mesh.source}: points must be a finite (N, 3) array")
    far = np.abs(pts).max(axis=1) > MAX_COORDINATE
    if far.any():
        k = int(np.flatnonzero(far)[0])
        raise MeshError(f"{mesh.source}: node {k} lies at {pts[k].tolist()}, beyond {MAX_COORDINATE:g} m of the origin "
                        f"({int(far.sum())} such nodes): a unit mix-up or a damaged mesh (coordinates are in metres)")
    if tets.ndim != 2 or tets.shape[1] != 4 or tets.shape[0] == 0:
        raise MeshError(f"{mesh.source}: the mesh has no tetrahedra (got cells of shape {tets.shape})")
    if tets.min() < 0 or tets.max() >= pts.shape[0]:
        raise MeshError(f"{mesh.source}: tetrahedra reference nodes outside 0..{pts.shape[0] - 1}")
    for name in required:
        if name not in mesh.groups or len(mesh.groups[name]) == 0:
            raise MeshError(
                f"{mesh.source}: the mesh has no {name!r} surface group; name the clamped patch "
                f"'clamp' (a gmsh Physical Surface). Groups present: {sorted(mesh.groups) or 'none'}"
            )
    vol = tet_volumes(pts, tets)
    edge = np.linalg.norm(pts[tets[:, 1]] - pts[tets[:, 0]], axis=1).mean()
    bad = vol <= 1e-9 * edge**3
    if bad.any():
        idx = np.flatnonzero(bad)
        kinds = []
        if np.any(vol[idx] < -1e-9 * edge**3):
            kinds.append(f"{int(np.sum(vol < -1e-9 * edge**3))} inverted")
        n_degen = int(np.sum(np.abs(vol) <= 1e-9 * edge**3))
        if n_degen:
            kinds.append(f"{n_degen} degenerate (zero-volume)")
        raise MeshError(
            f"{mesh.source}: {' and '.join(kinds)} tetrahedra, e.g. tet {idx[0]} with nodes "
            f"{tets[idx[0]].tolist()} (volume {vol[idx[0]]:.3g} m^3); fix the mesh orientation/quality"
        )
    for name, ids in mesh.volumes.items():
        ids = np.asarray(ids)
        if ids.ndim != 1 or (ids.size and (not np.issubdtype(ids.dtype, np.integer) or ids.min() < 0
                                           or ids.max() >= tets.shape[0])):
            raise MeshError(f"{mesh.source}: volume group {name!r} must list tetrahedra by index in 0..{tets.shape[0] - 1}")
    _check_duplicates(mesh)
    surf = boundary_triangles(tets)
    surf_keys = set(map(tuple, np.sort(surf, axis=1).tolist()))
    for name, tris in mesh.groups.items():
        missing = [t for t in map(tuple, np.sort(tris, axis=1).tolist()) if t not in surf_keys]
        if missing:
            raise MeshError(f"{mesh.source}: {len(missing)} triangles of group {name!r} are not on the boundary of the tetrahedra")
    if "clamp" in required:
        check_clamped(mesh)
    return mesh


def _check_duplicates(mesh: TetMesh) -> None:
    """Refuse tetrahedra listed twice, and faces shared by more than two tetrahedra."""
    tets = mesh.tets
    key = np.sort(tets, axis=1)
    _, first, inv, counts = np.unique(key, axis=0, return_index=True, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    if np.any(counts > 1):
        dup = np.flatnonzero(counts[inv] > 1)
        j = dup[0]
        other = int(dup[(inv[dup] == inv[j]) & (dup != j)][0])
        raise MeshError(
            f"{mesh.source}: {int(np.sum(counts[counts > 1] - 1))} duplicated tetrahedra (the same four nodes twice), "
            f"e.g. tets {int(j)} and {other} with nodes {tets[j].tolist()}; remove the duplicates"
        )
    faces = np.sort(np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]]), axis=1)
    _, fcounts = np.unique(faces, axis=0, return_counts=True)
    if np.any(fcounts > 2):
        raise MeshError(
            f"{mesh.source}: {int(np.sum(fcounts > 2))} faces are shared by more than two tetrahedra "
            "(overlapping elements); the mesh is not a valid solid"
        )


def connected_parts(tets: np.ndarray) -> np.ndarray:
    """Label of the connected part of each tetrahedron, (T,) int.

    Two tetrahedra are connected when they share a face (a shared edge or
    vertex is a hinge, not a connection: the parts can rotate about it).
    Labels are 0, 1, ... in the order of each part's first tetrahedron.
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    n = tets.shape[0]
    faces = np.sort(np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]]), axis=1)
    owner = np.tile(np.arange(n), 4)
    order = np.lexsort(faces.T[::-1])
    f, o = faces[order], owner[order]
    same = np.all(f[1:] == f[:-1], axis=1)
    a, b = o[:-1][same], o[1:][same]
    graph = sp.coo_matrix((np.ones(a.size), (a, b)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    # relabel in order of first appearance, so part 1 is the one holding tet 0
    _, first = np.unique(labels, return_index=True)
    rank = np.empty_like(first)
    rank[np.argsort(first)] = np.arange(first.size)
    return rank[labels]


def check_clamped(mesh: TetMesh, group: str = "clamp") -> None:
    """Refuse a mesh with a part (connected through shared faces) that touches no clamp face.

    Such a part is free to move as a rigid body: its stiffness is singular and
    its Green's functions do not exist.
    """
    labels = connected_parts(mesh.tets)
    n_parts = int(labels.max()) + 1
    clamp = np.sort(np.asarray(mesh.groups.get(group, np.zeros((0, 3), np.int64))), axis=1)
    tets = mesh.tets
    faces = np.sort(np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]]), axis=1)
    owner = np.tile(np.arange(tets.shape[0]), 4)
    n = int(mesh.points.shape[0]) + 1
    fkey = (faces[:, 0] * n + faces[:, 1]) * n + faces[:, 2]
    ckey = (clamp[:, 0] * n + clamp[:, 1]) * n + clamp[:, 2]
    held = np.unique(labels[owner[np.isin(fkey, ckey)]])
    free = np.setdiff1d(np.arange(n_parts), held)
    if free.size:
        sizes = np.bincount(labels, minlength=n_parts)
        desc = ", ".join(f"part {k + 1} ({sizes[k]} tets, e.g. tet {int(np.flatnonzero(labels == k)[0])})"
                         for k in free[:5]) + (f" and {free.size - 5} more" if free.size > 5 else "")
        raise MeshError(
            f"{mesh.source}: the body has {n_parts} parts connected through shared faces, and {free.size} of them "
            f"touch no {group!r} face: {desc}. A part without a clamp can move freely (a shared edge or vertex "
            "is only a hinge), so its Green's functions do not exist; clamp every part or remove it"
        )


def boundary_triangles(tets: np.ndarray) -> np.ndarray:
    """Outward-oriented boundary faces of a positively oriented tet mesh, (k, 3)."""
    # faces opposite each vertex, ordered so the normal points away from it
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]])
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inv.ravel()] == 1]


def read_mesh(path: str | os.PathLike) -> TetMesh:
    """Read a tetrahedral mesh with meshio, taking groups from its physical names.

    Groups come from gmsh physical names (``field_data`` + ``gmsh:physical``)
    or from meshio ``cell_sets`` of triangles; volume groups (for materials) from
    gmsh physical volumes or ``cell_sets`` of tetrahedra.
    """
    meshio = require_extra("meshio", "precompute", "reading a mesh file (meshio)")

    path = Path(path)
    if path.is_dir():
        raise MeshError(f"mesh {path} is a directory, not a mesh file")
    if not path.is_file():
        raise MeshError(f"mesh file {path} does not exist")
    said = io.StringIO()
    try:
        # meshio prints its readers' complaints, and exits (sys.exit(1)) when none could read the file
        with contextlib.redirect_stdout(said), contextlib.redirect_stderr(said):
            m = meshio.read(path)
    except SystemExit as exc:
        lines = [ln.strip() for ln in said.getvalue().splitlines() if ln.strip()]
        why = lines[-1].removeprefix("Error: ") if lines else f"not a valid {path.suffix or 'mesh'} file"
        raise MeshError(f"meshio could not read {path}: {why}") from exc
    except Exception as exc:
        raise MeshError(f"meshio could not read {path}: {exc}") from exc
    tets = [c.data for c in m.cells if c.type == "tetra"]
    if not tets:
        kinds = sorted({c.type for c in m.cells})
        raise MeshError(f"{path}: no linear tetrahedra ('tetra' cells) in the mesh (found {kinds})")
    points = np.asarray(m.points, dtype=np.float64)
    if points.shape[1] == 2:
        raise MeshError(f"{path}: the mesh is 2-D; a solid needs 3-D points")
    groups: dict[str, list[np.ndarray]] = {}
    volumes: dict[str, list[np.ndarray]] = {}
    # row of each tetra block's first cell in the concatenated tets
    starts, n_tets = [], 0
    for block in m.cells:
        starts.append(n_tets)
        n_tets += len(block.data) if block.type == "tetra" else 0
    phys = m.cell_data.get("gmsh:physical")
    if phys is not None and m.field_data:
        by_tag = {int(v[0]): k for k, v in m.field_data.items() if int(v[1]) == 2}
        vol_tag = {int(v[0]): k for k, v in m.field_data.items() if int(v[1]) == 3}
        for block, tags, start in zip(m.cells, phys, starts):
            if block.type == "tetra":
                for tag in np.unique(tags):
                    if int(tag) in vol_tag:
                        volumes.setdefault(vol_tag[int(tag)], []).append(start + np.flatnonzero(tags == tag))
            if block.type != "triangle":
                continue
            for tag in np.unique(tags):
                if int(tag) in by_tag:
                    groups.setdefault(by_tag[int(tag)], []).append(block.data[tags == tag])
    for name, per_block in (m.cell_sets or {}).items():
        for block, ids, start in zip(m.cells, per_block, starts):
            if ids is None or not len(ids):
                continue
            if block.type == "triangle":
                groups.setdefault(name, []).append(block.data[np.asarray(ids)])
            elif block.type == "tetra" and not name.startswith("gmsh:"):
                volumes.setdefault(name, []).append(start + np.asarray(ids, dtype=np.int64))
    mesh = TetMesh(
        points,
        np.concatenate(tets).astype(np.int64),
        {k: np.concatenate(v).astype(np.int64) for k, v in groups.items()},
        source=path.name,
        volumes={k: np.unique(np.concatenate(v)).astype(np.int64) for k, v in volumes.items()},
    )
    return check_mesh(mesh)


def box_mesh(size=(1.0, 1.0, 1.0), mesh_size: float = 0.25, *, clamp: str = "z0") -> TetMesh:
    """A structured tetrahedral box [0,Lx]x[0,Ly]x[0,Lz] (6 tets per cube).

    Groups: ``clamp`` is the face ``x=0`` (``clamp="x0"``) or ``z=0``
    (``clamp="z0"``); ``top`` is every other face. Deterministic, no gmsh.
    """
    size = np.asarray(size, dtype=float)
    n = np.maximum(1, np.round(size / mesh_size).astype(int))
    axes = [np.linspace(0.0, size[i], n[i] + 1) for i in range(3)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    points = np.column_stack([X.ravel(), Y.ravel(), Z.ravel()])
    idx = np.arange(points.shape[0]).reshape(n + 1)
    c = [idx[i:n[0] + i, j:n[1] + j, k:n[2] + k].ravel() for i in (0, 1) for j in (0, 1) for k in (0, 1)]
    v000, v001, v010, v011, v100, v101, v110, v111 = c
    # Kuhn subdivision of each cube along the main diagonal v000-v111
    paths = [(v100, v110), (v100, v101), (v010, v110), (v010, v011), (v001, v101), (v001, v011)]
    tets = np.concatenate([np.column_stack([v000, a, b, v111]) for a, b in paths])
    vol = tet_volumes(points, tets)
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    bnd = boundary_triangles(tets)
    cen = points[bnd].mean(axis=1)
    axis = {"x0": 0, "z0": 2}[clamp]
    on_clamp = np.isclose(cen[:, axis], 0.0)
    groups = {"clamp": bnd[on_clamp], "top": bnd[~on_clamp]}
    return check_mesh(TetMesh(points, tets, groups, source=f"box{tuple(size.tolist())}@h={mesh_size:g}"))
