"""Meshing with gmsh: a geometry (or a ready-made mesh file) -> a checked tetrahedral mesh.

The pipeline needs three things from a mesh: tetrahedra, and two named
surface groups, ``top`` (where hail can land) and ``clamp`` (zero
displacement). :class:`~hailstorm.precompute.tetmesh.TetMesh` holds exactly
that (it and its checks live in :mod:`hailstorm.precompute.tetmesh`, re-exported
here). Here it is produced by

* :func:`mesh_default_seat` - the saddle in ``meshes/saddle.geo``;
* :func:`mesh_geometry` - any gmsh-readable geometry (``.geo``, ``.step``,
  ``.brep``...) carrying the physical groups ``top`` and ``clamp``;
* :func:`load_seat` - either, or a mesh file (:func:`~hailstorm.precompute.tetmesh.read_mesh`),
  for a precompute run.

Every constructor returns a mesh that passed :func:`check_mesh`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

# the mesh and its checks (they lived here: re-exported)
from hailstorm.precompute.tetmesh import (
    MAX_COORDINATE,
    REQUIRED_GROUPS,
    MeshError,
    TetMesh,
    box_mesh,
    boundary_triangles,
    check_clamped,
    check_mesh,
    connected_parts,
    read_mesh,
    tet_volumes,
)
from hailstorm.runtime.resources import require_extra

__all__ = ["ANNOUNCE_SURFACE_VERTICES", "DEFAULT_COARSENING", "DEFAULT_MESH_SIZE", "GEOMETRY_SUFFIXES", "GRADING_SLOPE",
           "MAX_COORDINATE", "REQUIRED_GROUPS", "SAMPLE_SPACING", "MeshError", "Refinement", "TetMesh", "box_mesh",
           "boundary_triangles", "check_clamped", "check_coarsening", "check_mesh", "check_volume_size",
           "connected_parts", "default_seat_path", "distance_sampling", "load_seat", "mesh_default_seat",
           "mesh_geometry", "read_mesh", "tet_volumes"]

#: Element size on the hail-facing surface [m], one default for every entry point
#: (``hailstorm precompute``, :func:`build_bundle`, the default scene's seat).
DEFAULT_MESH_SIZE = 0.006
GEOMETRY_SUFFIXES = frozenset({".geo", ".step", ".stp", ".brep", ".iges", ".igs", ".xao"})

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Refinement:
    """A local refinement of a gmsh mesh: element size ``size`` [m] through the whole
    thickness at the plan point (``x``, ``y``) [m], growing by ``growth`` metres per metre
    of plan distance from it (surface and volume alike; for reference solutions)."""

    x: float
    y: float
    size: float
    growth: float = 0.3

    def __post_init__(self) -> None:
        for name in ("x", "y", "size", "growth"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
                raise MeshError(f"refinement {name} must be a finite number, got {v!r}")
        if not (self.size > 0 and self.growth > 0):
            raise MeshError(f"refinement size and growth must be positive, got {self.size!r}, {self.growth!r}")


def default_seat_path() -> Path:
    """Path of the default saddle geometry shipped with the package."""
    return Path(str(resources.files("hailstorm.meshes").joinpath("saddle.geo")))


def _gmsh_session():
    gmsh = require_extra("gmsh", "precompute", "meshing (gmsh)")

    if gmsh.isInitialized():
        gmsh.finalize()
    gmsh.initialize(interruptible=False)
    _keep_python_handlers()
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.option.setNumber("General.Verbosity", 2)
    # determinism: one thread, fixed seed, a sequential 3D algorithm
    gmsh.option.setNumber("General.NumThreads", 1)
    gmsh.option.setNumber("Mesh.MaxNumThreads1D", 1)
    gmsh.option.setNumber("Mesh.MaxNumThreads2D", 1)
    gmsh.option.setNumber("Mesh.MaxNumThreads3D", 1)
    gmsh.option.setNumber("Mesh.RandomSeed", 1)
    gmsh.option.setNumber("Mesh.Algorithm3D", 1)
    return gmsh


#: signals whose Python handlers gmsh's initialisation replaces with its own (which end the process at
#: once: a SIGTERM during a precompute would skip its cleanup and its checkpoint)
_GMSH_TAKES = tuple(getattr(signal, name) for name in ("SIGTERM", "SIGHUP") if hasattr(signal, name))


def _keep_python_handlers() -> None:
    """Put Python's handlers of :data:`_GMSH_TAKES` back after ``gmsh.initialize`` (in the main thread:
    re-registering a handler re-installs Python's own at the C level)."""
    if threading.current_thread() is not threading.main_thread():
        return
    for signum in _GMSH_TAKES:
        handler = signal.getsignal(signum)
        if handler is not None:
            signal.signal(signum, handler)


@contextlib.contextmanager
def _interruptible():
    """Let Ctrl-C end the process while gmsh runs (its C++ loop never returns to Python to
    raise KeyboardInterrupt): SIGINT takes its default action, in the main thread only, and
    Python's handler is put back afterwards."""
    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def _measure(gmsh, names: dict) -> tuple[float, float, float, float]:
    """Area of ``top``, area of every surface, volume, and smallest bounding-box extent of the model."""
    def mass(dim: int, tags) -> float:
        total = 0.0
        for t in tags:
            try:
                total += gmsh.model.occ.getMass(dim, t)
            except Exception:  # built-in kernel: no masses; fall back on the bounding box
                return float("nan")
        return total

    box = np.array(gmsh.model.getBoundingBox(-1, -1), dtype=float)
    ext = np.maximum(box[3:] - box[:3], 0.0)
    area_all = mass(2, [t for _, t in gmsh.model.getEntities(2)])
    volume = mass(3, [t for _, t in gmsh.model.getEntities(3)])
    area_top = mass(2, gmsh.model.getEntitiesForPhysicalGroup(*names["top"])) if "top" in names else area_all
    if not np.isfinite(area_all + volume + area_top):
        area_all = area_top = 2.0 * (ext[0] * ext[1] + ext[1] * ext[2] + ext[0] * ext[2])
        volume = float(np.prod(ext))
    return area_top, area_all, volume, float(ext.min())


#: a geometry whose estimated surface has more vertices than this is announced before it is
#: meshed (meshing it takes a while); smaller ones are meshed silently
ANNOUNCE_SURFACE_VERTICES = 20_000

#: distance between the points at which gmsh samples ``top`` for the distance field, in
#: units of the mesh size: the farthest surface point from a sample is then ~0.35 of it, inside
#: the band (0.5 of it) where the field asks for the mesh size itself. gmsh's own default
#: (20 samples along each surface's parameters) left points of a 270 mm surface up to ~7 mm from
#: a sample, so below ~3 mm the top mesh was coarser than asked (at 0.9 mm: edges 1.5x the size,
#: median, and up to 3.6x)
SAMPLE_SPACING = 0.5

#: growth of the element size per unit distance from ``top`` (size / distance): elements grow
#: by about this fraction from one layer to the next
GRADING_SLOPE = 0.6

#: default of ``coarsening`` (elements grow to this many mesh sizes away from ``top``)
DEFAULT_COARSENING = 2.5


def check_coarsening(coarsening: float) -> float:
    """Refuse a ``coarsening`` that is not a finite number of at least 1 (:class:`MeshError`)."""
    if isinstance(coarsening, bool) or not isinstance(coarsening, (int, float)) or not np.isfinite(coarsening) \
            or coarsening < 1:
        raise MeshError(f"coarsening must be a number of mesh sizes of at least 1, got {coarsening!r}")
    return float(coarsening)


def check_volume_size(volume_size: float | None, mesh_size: float) -> None:
    """Refuse a ``volume_size`` that is not a positive length at most ``mesh_size``
    (:class:`MeshError`); ``None`` (no volume grading) passes."""
    if volume_size is None:
        return
    if isinstance(volume_size, bool) or not isinstance(volume_size, (int, float)) or not np.isfinite(volume_size) \
            or volume_size <= 0:
        raise MeshError(f"volume size must be a positive length in metres, got {volume_size!r}")
    if volume_size > mesh_size:
        raise MeshError(f"volume size {volume_size:g} m must not exceed the surface mesh size {mesh_size:g} m "
                        "(it refines the volume under the same surface)")


def mesh_geometry(path: str | os.PathLike, mesh_size: float, *, coarsening: float = DEFAULT_COARSENING,
                  allow_large: bool = False, order: int = 1, volume_size: float | None = None,
                  refine: tuple[Refinement, ...] = ()) -> TetMesh:
    """Mesh a gmsh-readable geometry with linear tetrahedra.

    Parameters
    ----------
    path
        ``.geo``, ``.step``/``.stp``, ``.brep``... with physical groups
        ``top`` and ``clamp`` (Physical Surface) and one or more volumes.
    mesh_size
        Element size on ``top`` [m] (the hail-facing surface). A size larger
        than the body's smallest extent is logged as a warning.
    coarsening
        Elements grow to ``coarsening * mesh_size`` away from ``top``, by about
        :data:`GRADING_SLOPE` of their size per layer (at least 1; 1: the whole
        body at ``mesh_size``). At fine sizes a thin pad's interior holds many
        of the volume's vertices: a larger value keeps the top mesh and cuts
        the factor (``python -m studies.coarsening_study`` measures
        both and what it costs in accuracy).
    volume_size
        Volume grading: tetrahedra inside the body are at most this size [m]
        (``<= mesh_size``) while the surfaces keep their sizes, so the surface
        (the bundle, and the runtime's cost) is the same as without it and only
        the precompute grows. ``None``: the volume follows the surface sizes.
    refine
        :class:`Refinement` regions (finer surface and volume near plan points).
    allow_large, order
        Before meshing, the bundle's memory is estimated from the geometry's
        areas (:func:`hailstorm.precompute.resources.estimate_geometry`, for elements of
        ``order``); a run that would not fit in the memory available raises
        :class:`hailstorm.precompute.resources.TooLargeError` unless ``allow_large``.

    Returns
    -------
    TetMesh

    Notes
    -----
    Ctrl-C (SIGINT) during meshing ends the process at once (gmsh cannot be
    interrupted otherwise); nothing has been written by then.
    """
    from hailstorm.precompute.resources import check_fits, estimate_geometry

    path = Path(path)
    if path.is_dir():
        raise MeshError(f"geometry {path} is a directory, not a geometry file")
    if not path.is_file():
        raise MeshError(f"geometry file {path} does not exist")
    if not (np.isfinite(mesh_size) and mesh_size > 0):
        raise MeshError(f"mesh size must be a positive length in metres, got {mesh_size!r}")
    check_volume_size(volume_size, mesh_size)
    coarsening = check_coarsening(coarsening)
    gmsh = _gmsh_session()
    try:
        try:
            with _interruptible():
                gmsh.open(str(path))
        except Exception as exc:  # gmsh raises bare Exception
            raise MeshError(f"gmsh could not read {path}: {exc}") from exc
        names = {gmsh.model.getPhysicalName(d, t): (d, t) for d, t in gmsh.model.getPhysicalGroups()}
        if "clamp" not in names:
            raise MeshError(
                f"{path}: no physical group named 'clamp'; the clamped patch must be a "
                f"Physical Surface called 'clamp' (found: {sorted(names) or 'none'})"
            )
        if not gmsh.model.getEntities(3):
            raise MeshError(f"{path}: the geometry has no volume to mesh")
        area_top, area_all, volume, smallest = _measure(gmsh, names)
        if mesh_size > smallest:
            log.warning("%s: mesh size %g m is larger than the body's smallest extent (%.3g m): the mesh cannot "
                        "resolve the body, and its Green's functions mean little", path.name, mesh_size, smallest)
        estimate = estimate_geometry(area_top, area_all, volume, mesh_size, order, coarsening,
                                     volume_size=volume_size)
        check_fits(estimate, f"{path.name} at mesh size {mesh_size:g} m", allow_large=allow_large)
        _set_sizes(gmsh, names, mesh_size, coarsening, volume_size, refine)
        gmsh.option.setNumber("Mesh.ElementOrder", 1)
        # announced ahead only when it takes a while (build_bundle reports a mesh it computes
        # a bundle for; a warm run meshes only to find its bundle's key, and says nothing of it)
        log.log(logging.INFO if estimate.n_surface > ANNOUNCE_SURFACE_VERTICES else logging.DEBUG,
                "meshing %s at %g m (about %s surface vertices) ...", path.name, mesh_size,
                f"{estimate.n_surface:,}")
        try:
            with _interruptible():
                gmsh.model.mesh.generate(3)
        except Exception as exc:
            raise MeshError(f"gmsh failed to mesh {path} at mesh size {mesh_size}: {exc}") from exc
        tag = f"{path.name}@h={mesh_size:g}" + ("" if volume_size is None else f",volume={volume_size:g}") + \
            ("" if coarsening == DEFAULT_COARSENING else f",coarsening={coarsening:g}") + \
            "".join(f",refine=({r.x:g},{r.y:g},{r.size:g},{r.growth:g})" for r in refine)
        return _mesh_from_gmsh(gmsh, names, source=tag)
    finally:
        gmsh.finalize()


def _set_sizes(gmsh, names: dict, mesh_size: float, coarsening: float, volume_size: float | None,
               refine: tuple[Refinement, ...]) -> None:
    """gmsh's element sizes for :func:`mesh_geometry`: ``mesh_size`` on ``top``, growing to
    ``coarsening * mesh_size`` away from it (:data:`GRADING_SLOPE`), the volume grading and the
    refinements (:func:`_grading_fields`), the smallest of them where they meet."""
    fine = []
    if "top" in names:
        fine = list(gmsh.model.getEntitiesForPhysicalGroup(*names["top"]))
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeMax", coarsening * mesh_size)
    smallest_size = min([0.25 * mesh_size, volume_size or mesh_size] + [r.size for r in refine])
    gmsh.option.setNumber("Mesh.MeshSizeMin", smallest_size)
    extra = _grading_fields(gmsh, volume_size, refine)
    if fine:
        f_dist = gmsh.model.mesh.field.add("Distance")
        gmsh.model.mesh.field.setNumbers(f_dist, "SurfacesList", fine)
        gmsh.model.mesh.field.setNumber(f_dist, "Sampling", distance_sampling(gmsh, fine, mesh_size))
        f_thr = gmsh.model.mesh.field.add("Threshold")
        gmsh.model.mesh.field.setNumber(f_thr, "InField", f_dist)
        gmsh.model.mesh.field.setNumber(f_thr, "SizeMin", mesh_size)
        gmsh.model.mesh.field.setNumber(f_thr, "SizeMax", coarsening * mesh_size)
        gmsh.model.mesh.field.setNumber(f_thr, "DistMin", 0.5 * mesh_size)
        gmsh.model.mesh.field.setNumber(f_thr, "DistMax", (0.5 + (coarsening - 1.0) / GRADING_SLOPE) * mesh_size)
        extra.append(f_thr)
    else:
        gmsh.option.setNumber("Mesh.MeshSizeMax", mesh_size)
    if len(extra) == 1:
        gmsh.model.mesh.field.setAsBackgroundMesh(extra[0])
    elif extra:
        f_min = gmsh.model.mesh.field.add("Min")
        gmsh.model.mesh.field.setNumbers(f_min, "FieldsList", extra)
        gmsh.model.mesh.field.setAsBackgroundMesh(f_min)


def distance_sampling(gmsh, surfaces: list[int], mesh_size: float) -> int:
    """Samples along each parameter of ``surfaces`` for a gmsh ``Distance`` field, so that
    they are at most :data:`SAMPLE_SPACING` ``* mesh_size`` apart on the largest surface
    (and never fewer than gmsh's default, 20)."""
    extent = 0.0
    for tag in surfaces:
        x0, y0, z0, x1, y1, z1 = gmsh.model.getBoundingBox(2, tag)
        extent = max(extent, x1 - x0, y1 - y0, z1 - z0)
    return int(max(20, np.ceil(extent / (SAMPLE_SPACING * mesh_size))))


def _grading_fields(gmsh, volume_size: float | None, refine: tuple[Refinement, ...]) -> list[int]:
    """gmsh size fields of the volume grading (a constant size inside the volumes only: the
    surfaces keep theirs) and of the local refinements; their tags (for a Min field)."""
    fields = []
    if volume_size is not None:
        const = gmsh.model.mesh.field.add("MathEval")
        gmsh.model.mesh.field.setString(const, "F", repr(float(volume_size)))
        inside = gmsh.model.mesh.field.add("Restrict")
        gmsh.model.mesh.field.setNumber(inside, "InField", const)
        gmsh.model.mesh.field.setNumbers(inside, "VolumesList", [t for _, t in gmsh.model.getEntities(3)])
        gmsh.model.mesh.field.setNumber(inside, "IncludeBoundary", 0)  # not the surfaces: they keep their size
        fields.append(inside)
    for r in refine:
        f = gmsh.model.mesh.field.add("MathEval")
        gmsh.model.mesh.field.setString(f, "F", f"{r.size!r} + {r.growth!r} * Sqrt((x - ({r.x!r}))^2 + (y - ({r.y!r}))^2)")
        fields.append(f)
    return fields


def _mesh_from_gmsh(gmsh, names: dict, source: str) -> TetMesh:
    tags, coords, _ = gmsh.model.mesh.getNodes()
    order = np.argsort(tags)
    tags = tags[order]
    points = coords.reshape(-1, 3)[order]
    index = np.full(int(tags.max()) + 1, -1, dtype=np.int64)
    index[tags] = np.arange(tags.size)

    etypes, etags, enodes = gmsh.model.mesh.getElements(3)
    tet_nodes = [n for t, n in zip(etypes, enodes) if t == 4]  # 4 = 4-node tetrahedron
    if not tet_nodes:
        raise MeshError(f"{source}: meshing produced no tetrahedra")
    tets = index[np.concatenate(tet_nodes).astype(np.int64)].reshape(-1, 4)
    tet_tags = np.concatenate([g for t, g in zip(etypes, etags) if t == 4]).astype(np.int64)
    tag_order = np.argsort(tet_tags)
    groups, volumes = {}, {}
    for name, (dim, tag) in names.items():
        if dim == 3:
            ids = []
            for ent in gmsh.model.getEntitiesForPhysicalGroup(dim, tag):
                et, eg, _ = gmsh.model.mesh.getElements(3, ent)
                ids += [g.astype(np.int64) for t, g in zip(et, eg) if t == 4]
            tags_here = np.concatenate(ids) if ids else np.zeros(0, np.int64)
            volumes[name] = np.sort(tag_order[np.searchsorted(tet_tags, tags_here, sorter=tag_order)])
            continue
        if dim != 2:
            continue
        tris = []
        for ent in gmsh.model.getEntitiesForPhysicalGroup(dim, tag):
            et, _, en = gmsh.model.mesh.getElements(2, ent)
            tris += [index[n.astype(np.int64)].reshape(-1, 3) for t, n in zip(et, en) if t == 2]
        groups[name] = np.concatenate(tris) if tris else np.zeros((0, 3), np.int64)
    # keep only nodes used by tetrahedra (drop geometry-only points)
    used = np.unique(tets)
    remap = np.full(points.shape[0], -1, dtype=np.int64)
    remap[used] = np.arange(used.size)
    mesh = TetMesh(points[used], remap[tets], {k: remap[v] for k, v in groups.items()}, source, volumes)
    return check_mesh(mesh)


def mesh_default_seat(mesh_size: float = DEFAULT_MESH_SIZE, *, allow_large: bool = False, order: int = 1,
                      volume_size: float | None = None, refine: tuple[Refinement, ...] = (),
                      coarsening: float = DEFAULT_COARSENING) -> TetMesh:
    """Mesh the default saddle (``meshes/saddle.geo``) at ``mesh_size`` on top [m]
    (``allow_large``, ``order``, ``volume_size``, ``refine``, ``coarsening``: see :func:`mesh_geometry`)."""
    return mesh_geometry(default_seat_path(), mesh_size, allow_large=allow_large, order=order,
                         volume_size=volume_size, refine=refine, coarsening=coarsening)


def load_seat(geometry: str | os.PathLike | None, mesh_size: float, *, allow_large: bool = False,
              order: int = 1, volume_size: float | None = None,
              coarsening: float = DEFAULT_COARSENING) -> TetMesh:
    """The mesh for a precompute run: default seat, a geometry file or a mesh file
    (``allow_large``, ``order``, ``volume_size``, ``coarsening``: see :func:`mesh_geometry`; a
    ready mesh file is used as it is, and ``volume_size`` or ``coarsening`` is refused with it)."""
    if geometry is None:
        return mesh_default_seat(mesh_size, allow_large=allow_large, order=order, volume_size=volume_size,
                                 coarsening=coarsening)
    path = Path(geometry)
    if path.is_dir():
        raise MeshError(f"--geometry {path} is a directory; give a geometry (.geo, .step, .brep...) or mesh file")
    if not path.exists():
        raise MeshError(f"geometry file {path} does not exist")
    if path.suffix.lower() in GEOMETRY_SUFFIXES:
        return mesh_geometry(path, mesh_size, allow_large=allow_large, order=order, volume_size=volume_size,
                             coarsening=coarsening)
    if coarsening != DEFAULT_COARSENING:
        raise MeshError(f"--coarsening grades a geometry as it is meshed; {path.name} is a ready mesh "
                        "(give a .geo/.step/.brep, or leave out the coarsening)")
    if volume_size is not None:
        raise MeshError(f"--volume-size grades a geometry as it is meshed; {path.name} is a ready mesh "
                        "(give a .geo/.step/.brep, or leave out the volume size)")
    return read_mesh(path)


