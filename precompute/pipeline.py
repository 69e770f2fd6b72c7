"""The offline stage end to end: mesh -> FEM -> compliance D -> bundle on disk.

:func:`build_bundle` is the one entry point (the CLI's ``hailstorm
precompute`` calls it). Its inputs are resolved once into two records
(:mod:`hailstorm.precompute.settings`: :class:`BuildSettings`, what the bundle is,
and :class:`RunSettings`, how it is computed). Its cache key covers everything that changes D - the
mesh itself (hashed after meshing, so a different gmsh that meshes
differently also misses), element order, the material of every volume, contactable selection,
solver and tolerance, and the bundle format - so asking again for the same
seat reuses the bundle and asking for a different one never returns the old.

The pieces: the surface (:mod:`hailstorm.precompute.surface`), the loops that
solve D's column blocks (:mod:`hailstorm.precompute.solve_loops`), the bundle's
files (:mod:`hailstorm.runtime.bundle.write`); here, the order of the work, the
cache key and the manifest.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hailstorm.precompute.cluster import check_scheduler, require_distributed
from hailstorm.precompute.fem import (
    clamp_dofs,
    elasticity_basis,
    rigid_modes_on_dofs,
    stiffness_matrix,
    vertex_dofs,
)
from hailstorm.precompute.geometry import DEFAULT_MESH_SIZE, load_seat
from hailstorm.precompute.blocks import remove_work_dir, work_dir
from hailstorm.precompute.hmatrix import compliance_record, compress_bundle
from hailstorm.precompute.greens import ColumnProblem, column_problem, hat_load_matrix
from hailstorm.precompute.resources import check_fits, estimate_mesh, peak_memory_bytes
from hailstorm.precompute.materials import (
    MaterialMap,
    check_layers,
    contact_material,
    resolve_materials,
    sort_tets_by_material,
)
from hailstorm.precompute.settings import LOADS, BuildSettings, RunSettings, settings_from_keywords
from hailstorm.precompute.solve_loops import CHECKPOINT_SECONDS, solve_dense, solve_streamed
from hailstorm.precompute.surface import Surface, extract_surface
from hailstorm.precompute.tetmesh import TetMesh, check_mesh
from hailstorm.runtime.bundle.format import FORMAT_VERSION, BundleError, bundle_key, is_bundle, read_manifest
from hailstorm.runtime.bundle.write import (
    bundle_lock,
    check_replaceable,
    check_writable,
    clean_stale_temporaries,
    dtype_cast_record,
    write_bundle,
)
from hailstorm.runtime.bundle.stamps import default_cache_dir, stamp

log = logging.getLogger(__name__)

__all__ = ["CHECKPOINT_SECONDS", "DEFAULT_MESH_SIZE", "LOADS", "BuildSettings", "RunSettings", "Surface",
           "build_bundle", "cache_key", "default_cache_dir", "extract_surface"]


def cache_key(mesh: TetMesh, options: dict) -> str:
    """SHA-256 over the mesh content and every option that changes D."""
    payload = json.dumps({"format_version": FORMAT_VERSION, "mesh": mesh.content_hash(), **options}, sort_keys=True)
    return hashlib.sha256(payload.encode()).hexdigest()


def _code_version() -> str:
    try:
        from importlib.metadata import version

        return version("hailstorm")
    except Exception:  # running from a source tree that is not installed
        return "unknown"


def build_bundle(out: str | os.PathLike | None = None, settings: BuildSettings | None = None, *,
                 run: RunSettings | None = None, **options: Any) -> Path:
    r"""Compute the Green's functions of a seat and write them as a bundle.

    Parameters
    ----------
    out
        Bundle directory. ``None``: ``default_cache_dir() / <key>``. It must
        be new, empty or a bundle (anything else is refused, naming the files
        in the way), and writable: both are checked before any work.
        Concurrent builds of one ``out`` take turns (the second waits, then
        reuses the first's bundle if the key matches).
    settings
        What the bundle is (:class:`~hailstorm.precompute.settings.BuildSettings`:
        the mesh or geometry and mesh size, order, grading, materials, contact group,
        solver, load, D's storage type, compression). Default: ``BuildSettings()``,
        the default saddle at the default mesh size, P1.
    run
        How it is computed (:class:`~hailstorm.precompute.settings.RunSettings`: reuse,
        progress, the memory check, the Dask cluster, the block size). Default:
        ``RunSettings()``.
    \*\*options
        Any field of either record by name (``mesh_size=0.004, order=2, workers=4``...),
        replacing that of ``settings`` or ``run``: the keyword call of earlier versions.
        An unknown name raises TypeError; a bad value ValueError, before any work.

    Returns
    -------
    pathlib.Path
        The bundle directory; ``hailstorm.runtime.load`` reads it.

    Raises
    ------
    ValueError
        A bad setting (before any work); :class:`hailstorm.precompute.geometry.MeshError`
        for a bad mesh or geometry.
    hailstorm.precompute.resources.TooLargeError
        The run would not fit in memory or on disk (unless ``allow_large``).
    hailstorm.runtime.bundle.format.BundleError
        ``out`` is in the way, not writable, or was just written by another run with other inputs.

    Notes
    -----
    D is streamed to ``.NAME.work/`` beside ``out`` block by block, each
    block durable and tagged with the cache key when it is written; a run
    that is killed or interrupted leaves it there, and the same call resumes
    it, computing only the missing blocks. It becomes the bundle's
    ``compliance.npy`` unchanged (and the work directory goes). With
    ``compress_tol`` the dense bundle is computed first (and reused if ``out``
    holds it), then replaced by its compressed copy; with ``stream`` too, D is
    compressed as it is solved, never whole (its state checkpointed every
    :data:`CHECKPOINT_SECONDS` to ``.NAME.work/stream.npz``, from which the same call resumes).
    """
    settings, run = settings_from_keywords(settings, run, **options)
    out = _check_out(out)  # an occupied or unwritable place is refused before any work
    if run.scheduler is not None:
        check_scheduler(run.scheduler)  # an unreachable cluster fails here, before any work
    elif run.workers is not None:
        require_distributed()
    t0 = time.perf_counter()
    seat = _prepare_seat(settings, run.allow_large)
    seat.t_mesh = time.perf_counter() - t0
    key_options = settings.key_options(seat.young, seat.poisson, seat.materials.key())
    key = cache_key(seat.mesh, key_options)
    final_key = settings.final_key(key)
    if out is None:
        out = (default_cache_dir() / final_key[:16]).absolute()
    job = _Job(out, settings, run, seat, key_options, key, final_key, t0)
    before = bundle_key(out)
    with bundle_lock(out):  # waits for another writer of `out`
        found = _found_key(out, before, key, final_key, run.reuse)
        if found == final_key:
            return out
        check_replaceable(out)
        if settings.stream:
            with _writing(out):
                return _compute(job)
        if found != key:  # (else `out` holds the dense source of the compressed bundle asked for)
            with _writing(out):
                _compute(job)
    if settings.compress_tol is None:
        return out
    with _writing(out):  # the dense bundle, replaced by its compressed copy (atomically, under the bundle's lock)
        return compress_bundle(out, out, settings.compress_tol, key=final_key, progress=run.progress)


def _check_out(out: str | os.PathLike | None) -> Path | None:
    """``out`` as an absolute path, refused if it is occupied (not a bundle) or its folder is
    not writable; None (the cache) if the cache folder is writable."""
    if out is None:
        check_writable(default_cache_dir())
        return None
    out = Path(out).absolute()
    check_replaceable(out)
    check_writable(out.parent)
    return out


@dataclass
class _Seat:
    """The mesh a bundle is computed on, with what was resolved on it."""

    mesh: TetMesh
    surface: Surface
    materials: MaterialMap
    young: float
    poisson: float
    t_mesh: float = 0.0


def _prepare_seat(settings: BuildSettings, allow_large: bool) -> _Seat:
    """Mesh (or check the ready mesh), resolve the materials on it, extract the surface and
    check the bundle fits (:func:`hailstorm.precompute.resources.check_fits`)."""
    if settings.mesh is None:
        mesh = load_seat(settings.geometry, settings.mesh_size, allow_large=allow_large, order=settings.order,
                         volume_size=settings.volume_size, coarsening=settings.coarsening)
    else:
        mesh = settings.mesh
        check_mesh(mesh)
    mats = resolve_materials(mesh, settings.materials, young=settings.young, poisson=settings.poisson)
    mesh, mats = sort_tets_by_material(mesh, mats)
    check_layers(mesh, mats)
    young, poisson = contact_material(mesh, mats, settings.contact_group)
    surface = extract_surface(mesh, settings.contact_group)
    check_fits(estimate_mesh(surface.nodes.size, int(surface.contactable.sum()), mesh.points.shape[0],
                             settings.order, settings.dtype),
               f"{mesh.source} (P{settings.order})", allow_large=allow_large)
    return _Seat(mesh, surface, mats, young, poisson)


def _found_key(out: Path, before: str | None, key: str, final_key: str, reuse: bool) -> str | None:
    """Under ``out``'s lock: refuse a bundle another run with other inputs wrote while this one
    waited (``before``: its key when this one started waiting), sweep a killed writer's debris,
    and return the key of a bundle at ``out`` this run can use (``final_key``: the bundle asked
    for, up to date; ``key``: the dense source of the compressed bundle asked for), or None."""
    now = bundle_key(out)  # (before a stranded bundle is put back: that is no other run's fresh result)
    if now is not None and now != before and now not in (key, final_key):
        raise BundleError(f"--out {out} was just written by another run with other inputs (key {now[:12]}) "
                          "while this one waited for it; not replacing that run's bundle: choose another "
                          "--out, or run again to replace it")
    clean_stale_temporaries(out.parent)  # a killed writer's debris; a stranded bundle is put back
    if not (reuse and is_bundle(out)):
        return None
    try:
        found = read_manifest(out)["key"]
    except ValueError:
        found = None
    if found == final_key:
        log.info("bundle %s is up to date (key %s); reusing it", out, final_key[:12])
        if work_dir(out).is_dir():  # a killed replacement's blocks (we hold the lock): not needed
            log.info("removing %s, the blocks of an interrupted run for other inputs", work_dir(out))
            remove_work_dir(work_dir(out))
        return found
    if found == key:
        return found
    log.info("bundle %s was built for other inputs; recomputing", out)
    return None


@contextmanager
def _writing(out: Path) -> Iterator[None]:
    """An OSError while the bundle is computed or written is a BundleError naming ``out``."""
    try:
        yield
    except OSError as exc:
        raise BundleError(f"cannot write bundle {out}: {exc.strerror or exc} ({exc.filename or out})") from exc


@dataclass(frozen=True)
class _Job:
    """One build once its checks passed: where, what, how, on which seat, under which keys."""

    out: Path
    settings: BuildSettings
    run: RunSettings
    seat: _Seat
    key_options: dict[str, Any]
    key: str
    final_key: str
    t0: float


def _compute(job: _Job) -> Path:
    """Assemble, solve for D and write the bundle (``build_bundle``'s work once its checks passed);
    with ``stream``, D compressed as it is solved (:func:`~hailstorm.precompute.solve_loops.solve_streamed`),
    under the final key."""
    settings, seat, out = job.settings, job.seat, job.out
    mesh, surface = seat.mesh, seat.surface
    log.info("mesh %s: %d points, %d tetrahedra (%.1f s)", mesh.source, mesh.points.shape[0], mesh.tets.shape[0],
             seat.t_mesh)
    t1 = time.perf_counter()
    problem, n_dofs = _column_problem(settings, seat)
    t_assemble = time.perf_counter() - t1
    t2 = time.perf_counter()
    what = f"P{settings.order}, {settings.solver}"
    if settings.stream:
        comp, stats = solve_streamed(out, problem, mesh.points[surface.nodes], np.flatnonzero(surface.contactable),
                                     settings.compress_tol, job.key, job.run, f"{what}, compressed")
        D = None
    else:
        D, stats, (scale, err) = solve_dense(out, problem, job.key, job.run, settings.dtype, what)
    timings = {"mesh": seat.t_mesh, "assemble": t_assemble, "solve": time.perf_counter() - t2}
    manifest = _manifest(job, n_dofs, timings, stats)
    if settings.dtype != "float64":  # what rounding each block to D's storage type cost, as convert_bundle records
        float64_options = {k: v for k, v in job.key_options.items() if k != "dtype"}
        manifest["dtype_cast"] = dtype_cast_record(cache_key(mesh, float64_options), "float64", err, scale)
    arrays = {
        "vertices": mesh.points[surface.nodes],
        "triangles": surface.triangles.astype(np.int64),
        "areas": surface.areas,
        "fixed": surface.fixed,
        "contactable": surface.contactable,
        "volume_points": mesh.points,
        "volume_tets": mesh.tets.astype(np.int64),
        "surface_nodes": surface.nodes.astype(np.int64),
    }
    if D is None:  # streamed: the H-matrix is the compliance
        arrays.update(comp.H.to_arrays())
        manifest["compliance"] = compliance_record(comp, construction="stream", source_key=job.key)
        path = write_bundle(out, arrays, manifest)
        log.info("wrote bundle %s (%d x %d compliance as an H-matrix, %.1f %% of its numbers; max column error "
                 "%.2g over %d exact columns) in %.1f s", path, *comp.H.shape,
                 100 * comp.H.stored / (comp.H.shape[0] * comp.H.shape[1]), comp.error["max"],
                 comp.error["columns"], time.perf_counter() - job.t0)
        return path
    arrays["compliance"] = D
    path = write_bundle(out, arrays, manifest)
    # D's hash was computed from its bytes on disk (BlockStore.finish) and the file moved, unchanged:
    # record that, so that loading it does not read all of D again (hailstorm.runtime.bundle.stamps)
    stamp(path / "compliance.npy", D.sha256)
    remove_work_dir(work_dir(out))
    log.info("wrote bundle %s (%d x %d compliance) in %.1f s", path, *D.shape, time.perf_counter() - job.t0)
    return path


def _column_problem(settings: BuildSettings, seat: _Seat) -> tuple[ColumnProblem, int]:
    """Assemble the stiffness on ``seat`` and set up the solve for D's columns; the problem and
    the stiffness' number of dofs (the FE basis, most of the assembly's memory, is dropped on return)."""
    mesh, surface, mats = seat.mesh, seat.surface, seat.materials
    basis = elasticity_basis(mesh, settings.order)
    K = stiffness_matrix(basis, seat.young, seat.poisson) if len(mats.names) == 1 else \
        stiffness_matrix(basis, mats.tet_young, mats.tet_poisson)
    fixed = clamp_dofs(basis, mesh)
    contact_nodes = surface.nodes[surface.contactable]
    load_dofs = vertex_dofs(basis, contact_nodes).ravel()
    read = vertex_dofs(basis, surface.nodes).ravel()
    loads = hat_load_matrix(basis, contact_nodes, surface.areas[surface.contactable]) \
        if settings.load == "hat" else None
    near_null = rigid_modes_on_dofs(basis) if settings.spec.needs_near_null else None
    problem = column_problem(K, fixed, load_dofs, read, solver=settings.solver, near_null=near_null,
                             tol=settings.tol, loads=loads)
    return problem, int(K.shape[0])


def _manifest(job: _Job, n_dofs: int, timings: dict[str, float], stats: dict[str, Any]) -> dict[str, Any]:
    """The bundle's manifest (its ``compliance`` and ``dtype_cast`` records aside)."""
    settings, seat = job.settings, job.seat
    mesh, surface = seat.mesh, seat.surface
    geometry = settings.geometry
    return {
        "key": job.final_key if settings.stream else job.key,  # (a dense source of a compressed one: its own)
        "code_version": _code_version(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "options": {**job.key_options, "mesh_size": float(settings.mesh_size),
                    "geometry": None if geometry is None else str(geometry)},
        "material": {"young": seat.young, "poisson": seat.poisson},
        "materials": seat.materials.record(),
        "mesh": {
            "source": mesh.source,
            "hash": mesh.content_hash(),
            "n_points": int(mesh.points.shape[0]),
            "n_tets": int(mesh.tets.shape[0]),
            "n_dofs": n_dofs,
            "n_surface_vertices": int(surface.nodes.size),
            "n_contactable": int(surface.contactable.sum()),
        },
        "timings_s": timings,
        "solve_stats": stats,
        # the building process's peak resident memory so far (it counts whatever ran before in the process)
        "process_peak_memory_bytes": peak_memory_bytes(),
    }
