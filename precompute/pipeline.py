"""The offline stage end to end: mesh -> FEM -> compliance D -> bundle on disk.

:func:`build_bundle` is the one entry point (the CLI's ``hailstorm
precompute`` calls it). Its cache key covers everything that changes D - the
mesh itself (hashed after meshing, so a different gmsh that meshes
differently also misses), element order, the material of every volume, contactable selection,
solver and tolerance, and the bundle format - so asking again for the same
seat reuses the bundle and asking for a different one never returns the old.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from contextlib import nullcontext
from dataclasses import dataclass
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from hailstorm.precompute.fem import (
    clamp_dofs,
    elasticity_basis,
    rigid_body_modes,
    stiffness_matrix,
    vertex_dofs,
)
from hailstorm.precompute.geometry import (
    DEFAULT_COARSENING,
    DEFAULT_MESH_SIZE,
    MeshError,
    TetMesh,
    boundary_triangles,
    check_coarsening,
    check_mesh,
    check_volume_size,
    load_seat,
)
from hailstorm.precompute.blocks import CHECKPOINT, BlockStore, remove_work_dir, work_dir
from hailstorm.precompute.hmatrix import (
    DEFAULT_ETA,
    DEFAULT_LEAF,
    ERROR_COLUMNS,
    Compressed,
    admissible_blocks,
    check_tol,
    cluster_tree,
    compliance_record,
    compress_bundle,
    compressed_key,
)
from hailstorm.precompute.hstream import StreamedH, streamed_key, tree_order
from hailstorm.precompute.cluster import SolveStats, check_scheduler, cluster_client, require_distributed, solve_blocks
from hailstorm.precompute.greens import (
    DEFAULT_STORE_BYTES,
    ColumnProblem,
    cholesky_nnz,
    column_blocks,
    column_problem,
    hat_load_matrix,
    lumped_areas,
    solver_spec,
)
from hailstorm.precompute.resources import (
    BASE_BYTES,
    TooLargeError,
    available_memory,
    check_disk,
    check_fits,
    estimate_memory,
    estimate_mesh,
    gib,
    peak_memory_bytes,
)
from hailstorm.precompute.materials import (
    MaterialMap,
    check_layers,
    check_material_input,
    contact_material,
    resolve_materials,
    sort_tets_by_material,
)
from hailstorm.runtime.bundle.write import dtype_cast_record
from hailstorm.runtime.bundle.format import (
    COMPLIANCE_DTYPES,
    FORMAT_VERSION,
    BundleError,
    RoundedBlock,
    bundle_key,
    is_bundle,
    read_manifest,
)
from hailstorm.runtime.bundle.write import (
    StagedArray,
    bundle_lock,
    check_replaceable,
    check_writable,
    clean_stale_temporaries,
    write_bundle,
)
from hailstorm.runtime.bundle.stamps import default_cache_dir, stamp

log = logging.getLogger(__name__)

__all__ = ["CHECKPOINT_SECONDS", "DEFAULT_MESH_SIZE", "LOADS", "Surface", "build_bundle", "cache_key",
           "default_cache_dir", "extract_surface"]

LOADS = ("point", "hat")


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
    """Surface vertices, triangles, areas and the fixed/contactable masks.

    Contactable vertices are those of ``contact_group`` that are not clamped
    (``contact_group="all"``: every unclamped surface vertex).
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


def build_bundle(
    out: str | os.PathLike | None = None,
    *,
    mesh: TetMesh | None = None,
    geometry: str | os.PathLike | None = None,
    mesh_size: float = DEFAULT_MESH_SIZE,
    order: int = 1,
    volume_size: float | None = None,
    coarsening: float = DEFAULT_COARSENING,
    young: float | None = None,
    poisson: float | None = None,
    materials: Mapping[str, tuple[float, float]] | None = None,
    contact_group: str = "top",
    solver: str = "supernodal",
    tol: float = 1e-10,
    load: str = "point",
    reuse: bool = True,
    progress: bool = False,
    allow_large: bool = False,
    workers: int | None = None,
    scheduler: str | None = None,
    block_bytes: int = DEFAULT_STORE_BYTES,
    dtype: str = "float64",
    compress_tol: float | None = None,
    stream: bool = False,
) -> Path:
    """Compute the Green's functions of a seat and write them as a bundle.

    Parameters
    ----------
    out
        Bundle directory. ``None``: ``default_cache_dir() / <key>``. It must
        be new, empty or a bundle (anything else is refused, naming the files
        in the way), and writable: both are checked before any work.
        Concurrent builds of one ``out`` take turns (the second waits, then
        reuses the first's bundle if the key matches).
    mesh
        A ready :class:`TetMesh` (tests, studies); it is checked
        (:func:`hailstorm.precompute.geometry.check_mesh`: every part clamped...).
        Otherwise ``geometry`` is meshed at ``mesh_size`` (``None``: the
        default saddle).
    mesh_size
        Element size on the hail-facing surface [m].
    order
        1 or 2: P1 or P2 tetrahedra. The bundle always lives on the corner
        vertices.
    volume_size
        Volume grading of a meshed geometry [m]: tetrahedra inside the body at
        most this size (``<= mesh_size``) under the same surface mesh, so D has
        the same shape and the runtime the same cost
        (:func:`hailstorm.precompute.geometry.mesh_geometry`). ``None``: none.
        Refused with a ready ``mesh`` or a mesh file (they are used as they are).
    coarsening
        Elements of a meshed geometry grow to ``coarsening * mesh_size`` away
        from the contact surface (at least 1; default
        :data:`hailstorm.precompute.geometry.DEFAULT_COARSENING`). Refused with
        a ready mesh like ``volume_size``.
    young, poisson
        One material for the whole body [Pa], [-] (default
        :data:`hailstorm.precompute.fem.DEFAULT_YOUNG`, ``DEFAULT_POISSON``).
    materials
        Instead of ``young``/``poisson``: ``{volume group: (E, nu)}`` for every
        volume group of the mesh (gmsh Physical Volume names), e.g.
        ``{"pad": (0.5e6, 0.3), "shell": (2e9, 0.4)}``
        (:func:`hailstorm.precompute.materials.resolve_materials` lists what is refused).
        The bundle's ``young``/``poisson`` are then the material under the
        ``contact_group`` surface; the manifest's ``materials`` records each
        volume's (E, nu) and its range of ``volume_tets``.
    contact_group
        Surface group whose (unclamped) vertices get columns of D.
    solver, tol
        ``"supernodal"`` (default), ``"cholmod"``, ``"splu"`` or ``"amg"``
        with relative residual ``tol`` (:func:`hailstorm.precompute.greens.factorize`).
    load
        What a column of D responds to: ``"point"`` (default), a unit nodal
        force at the vertex; ``"hat"``, one newton spread as a traction over
        the vertex's hat function (:func:`hailstorm.precompute.greens.hat_load_matrix`),
        the consistent choice for P2 (measured: 12 % instead of 37 % error
        under distributed loads at 6 mm).
    reuse
        Return an existing bundle at ``out`` whose key matches, without
        recomputing.
    progress
        Show a progress bar over the column blocks of D.
    allow_large
        Skip the memory check: by default a run whose estimated memory (from
        the geometry before meshing, from the mesh before assembly; see
        :mod:`hailstorm.precompute.resources`) exceeds the memory available raises
        :class:`hailstorm.precompute.resources.TooLargeError`; so does a D
        larger than the free disk.
    workers, scheduler
        Solve the column blocks on a local Dask cluster of ``workers``
        processes, or on the running Dask cluster at address ``scheduler``
        (connected to first: an unreachable one raises
        :class:`hailstorm.precompute.cluster.ClusterError` before any work).
        Default: in this process. D does not depend on it.
    block_bytes
        Size of one column block of D as solved (float64): the unit of work,
        of what is written to disk at once, and of what an interrupted run loses.
    dtype : {"float64", "float32"}
        D's storage type. Columns are always solved in float64; for
        ``"float32"`` each block is rounded to nearest as it is written (half
        the disk and the runtime's memory for D; each entry off by at most
        2^-24 of itself, the largest rounding recorded in the manifest's
        ``dtype_cast``) and ``options.dtype = "float32"`` goes into the cache
        key (float64 adds nothing to it: the keys of float64 bundles stay as
        they were).
    compress_tol
        Store D compressed, as an H-matrix whose columns are within this
        relative error of the exact ones on 200 exact columns drawn at random
        (:func:`hailstorm.precompute.hmatrix.compress_bundle`; the error is recorded in the
        manifest's ``compliance``; format 3). The dense bundle is computed
        first (and reused if ``out`` holds it), then replaced by its compressed
        copy. ``None`` (default): D dense. Needs ``dtype="float64"``.
    stream
        With ``compress_tol``: build the H-matrix from D's column blocks as they are
        solved (:class:`hailstorm.precompute.hstream.StreamedH`), so D is never on
        disk or in memory whole (a compressed bundle of a surface whose dense D would
        not fit). Its measured column error is within ``compress_tol`` or the run
        fails naming it; its cache key is its own
        (:func:`hailstorm.precompute.hstream.streamed_key`). Its state is
        checkpointed to ``.NAME.work/stream.npz`` every
        :data:`CHECKPOINT_SECONDS` and when the run is interrupted, and the same
        call resumes from it (to the numbers an uninterrupted run gives).

    D is streamed to ``.NAME.work/`` beside ``out`` block by block, each
    block durable and tagged with the cache key when it is written; a run
    that is killed or interrupted leaves it there, and the same call resumes
    it, computing only the missing blocks. It becomes the bundle's
    ``compliance.npy`` unchanged (and the work directory goes).

    Returns
    -------
    pathlib.Path
        The bundle directory; ``hailstorm.runtime.load`` reads it.
    """
    check_material_input(materials, young=young, poisson=poisson)  # before any meshing
    if order not in (1, 2):
        raise ValueError(f"element order must be 1 or 2, got {order!r}")
    if load not in LOADS:
        raise ValueError(f"unknown load {load!r}; choose one of {LOADS}")
    spec = solver_spec(solver)
    if not (np.isfinite(tol) and 0 < tol < 1):
        raise ValueError(f"solver tolerance must be in (0, 1), got {tol!r}")
    if not (np.isfinite(mesh_size) and mesh_size > 0):
        raise ValueError(f"mesh size must be a positive length in metres, got {mesh_size!r}")
    check_volume_size(volume_size, mesh_size)
    if volume_size is not None and mesh is not None:
        raise ValueError("volume_size grades a geometry as it is meshed; a ready mesh is used as it is")
    coarsening = check_coarsening(coarsening)
    if coarsening != DEFAULT_COARSENING and mesh is not None:
        raise ValueError("coarsening grades a geometry as it is meshed; a ready mesh is used as it is")
    if not isinstance(dtype, str) or dtype not in COMPLIANCE_DTYPES:
        raise ValueError(f"D's storage type must be one of {' or '.join(COMPLIANCE_DTYPES)}, got {dtype!r}")
    if compress_tol is not None:
        compress_tol = check_tol(compress_tol)
        if dtype != "float64":
            raise ValueError(f"a compressed D is stored in float64: --tol and --dtype {dtype} do not go together")
    if not isinstance(stream, bool):
        raise ValueError(f"stream must be True or False, got {stream!r}")
    if stream and compress_tol is None:
        raise ValueError("streaming builds a compressed D: --stream needs --tol")
    # the output first: an occupied or unwritable place is refused before any work
    if out is not None:
        out = Path(out).absolute()
        check_replaceable(out)
        check_writable(out.parent)
    else:
        check_writable(default_cache_dir())
    if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
        raise ValueError(f"workers must be a positive number of processes, got {workers!r}")
    if scheduler is not None:
        check_scheduler(scheduler)  # an unreachable cluster fails here, before any work
    elif workers is not None:
        require_distributed()
    run = _RunSettings(scheduler, workers, int(block_bytes), allow_large, dtype)
    t0 = time.perf_counter()
    if mesh is None:
        mesh = load_seat(geometry, mesh_size, allow_large=allow_large, order=order, volume_size=volume_size,
                         coarsening=coarsening)
    else:
        check_mesh(mesh)
    mats = resolve_materials(mesh, materials, young=young, poisson=poisson)
    mesh, mats = sort_tets_by_material(mesh, mats)
    check_layers(mesh, mats)
    young, poisson = contact_material(mesh, mats, contact_group)
    t_mesh = time.perf_counter() - t0
    surface = extract_surface(mesh, contact_group)
    check_fits(estimate_mesh(surface.nodes.size, int(surface.contactable.sum()), mesh.points.shape[0], order, dtype),
               f"{mesh.source} (P{order})", allow_large=allow_large)

    options = {
        "order": int(order),
        "young": young,
        "poisson": poisson,
        "materials": mats.key(),
        "contact_group": contact_group,
        "solver": solver,
        "tol": tol if spec.uses_tol else None,
        "load": load,
    }
    if dtype != "float64":  # float64 adds nothing: the keys of the bundles written before stay valid
        options["dtype"] = dtype
    if volume_size is not None:  # the mesh's hash already differs; recorded for the reader (old keys unchanged)
        options["volume_size"] = float(volume_size)
    if coarsening != DEFAULT_COARSENING:  # likewise
        options["coarsening"] = coarsening
    key = cache_key(mesh, options)
    if compress_tol is None:
        final_key = key
    else:
        final_key = streamed_key(key, compress_tol) if stream else compressed_key(key, compress_tol)
    if out is None:
        out = (default_cache_dir() / final_key[:16]).absolute()
    before = bundle_key(out)
    with bundle_lock(out):  # waits for another writer of `out`
        now = bundle_key(out)  # (before a stranded bundle is put back: that is no other run's fresh result)
        if now is not None and now != before and now not in (key, final_key):
            raise BundleError(f"--out {out} was just written by another run with other inputs (key {now[:12]}) "
                              "while this one waited for it; not replacing that run's bundle: choose another "
                              "--out, or run again to replace it")
        clean_stale_temporaries(out.parent)  # a killed writer's debris; a stranded bundle is put back
        dense_ready = False
        if reuse and is_bundle(out):
            try:
                found = read_manifest(out)["key"]
                if found == final_key:
                    log.info("bundle %s is up to date (key %s); reusing it", out, final_key[:12])
                    if work_dir(out).is_dir():  # a killed replacement's blocks (we hold the lock): not needed
                        log.info("removing %s, the blocks of an interrupted run for other inputs", work_dir(out))
                        remove_work_dir(work_dir(out))
                    return out
                dense_ready = found == key  # the dense source of the compressed bundle asked for
            except ValueError:
                pass
            if not dense_ready:
                log.info("bundle %s was built for other inputs; recomputing", out)
        check_replaceable(out)
        if stream:
            try:
                return _compute(out, mesh, surface, options, key, geometry, mesh_size, tol, t0, t_mesh, progress,
                                run, mats, stream_tol=compress_tol, final_key=final_key)
            except OSError as exc:
                raise BundleError(f"cannot write bundle {out}: {exc.strerror or exc} ({exc.filename or out})") from exc
        if not dense_ready:
            try:
                _compute(out, mesh, surface, options, key, geometry, mesh_size, tol, t0, t_mesh, progress, run, mats)
            except OSError as exc:
                raise BundleError(f"cannot write bundle {out}: {exc.strerror or exc} ({exc.filename or out})") from exc
    if compress_tol is None:
        return out
    try:  # the dense bundle, replaced by its compressed copy (atomically, under the bundle's lock)
        return compress_bundle(out, out, compress_tol, key=final_key, progress=progress)
    except OSError as exc:
        raise BundleError(f"cannot write bundle {out}: {exc.strerror or exc} ({exc.filename or out})") from exc


#: how often (seconds of solving) a streamed compression checkpoints its state
CHECKPOINT_SECONDS = 120.0


@dataclass(frozen=True)
class _RunSettings:
    """How D is computed (none of it changes D): where, in which blocks, with which checks."""

    scheduler: str | None
    workers: int | None
    block_bytes: int
    allow_large: bool
    dtype: str = "float64"


def _compute(out: Path, mesh: TetMesh, surface: Surface, options: dict, key: str, geometry, mesh_size: float,
             tol: float, t0: float, t_mesh: float, progress: bool, run: _RunSettings,
             mats: MaterialMap, stream_tol: float | None = None, final_key: str | None = None) -> Path:
    """Assemble, solve for D and write the bundle (``build_bundle``'s work once its checks passed);
    with ``stream_tol``, D compressed as it is solved (:func:`_stream_hmatrix`), under ``final_key``."""
    order, young, poisson = options["order"], options["young"], options["poisson"]
    solver, load = options["solver"], options["load"]
    log.info("mesh %s: %d points, %d tetrahedra (%.1f s)", mesh.source, mesh.points.shape[0], mesh.tets.shape[0],
             t_mesh)
    t1 = time.perf_counter()
    basis = elasticity_basis(mesh, order)
    K = stiffness_matrix(basis, young, poisson) if len(mats.names) == 1 else \
        stiffness_matrix(basis, mats.tet_young, mats.tet_poisson)
    fixed = clamp_dofs(basis, mesh)
    contact_nodes = surface.nodes[surface.contactable]
    load_dofs = vertex_dofs(basis, contact_nodes).ravel()
    read = vertex_dofs(basis, surface.nodes).ravel()
    loads = hat_load_matrix(basis, contact_nodes, surface.areas[surface.contactable]) if load == "hat" else None
    near_null = None
    if solver_spec(solver).needs_near_null:
        near_null = _rigid_modes_on_dofs(basis)
    t_assemble = time.perf_counter() - t1

    t2 = time.perf_counter()
    problem = column_problem(K, fixed, load_dofs, read, solver=solver, near_null=near_null, tol=tol, loads=loads)
    n_dofs = int(K.shape[0])
    del basis, K  # the solve needs only the problem: the FE basis is most of the assembly's memory
    if stream_tol is not None:
        comp, stats = _stream_hmatrix(out, problem, mesh.points[surface.nodes], np.flatnonzero(surface.contactable),
                                      stream_tol, key, progress, run, f"P{order}, {solver}, compressed")
        D = None
    else:
        D, stats, (scale, err) = _stream_compliance(out, problem, key, progress, run, f"P{order}, {solver}")
    t_solve = time.perf_counter() - t2
    cast = None
    if run.dtype != "float64":  # what the rounding of each block to D's storage type cost, as convert_bundle records
        float64_options = {k: v for k, v in options.items() if k != "dtype"}
        cast = dtype_cast_record(cache_key(mesh, float64_options), "float64", err, scale)

    manifest = {
        "key": key if final_key is None else final_key,
        "code_version": _code_version(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "options": {**options, "mesh_size": float(mesh_size), "geometry": None if geometry is None else str(geometry)},
        "material": {"young": young, "poisson": poisson},
        "materials": mats.record(),
        "mesh": {
            "source": mesh.source,
            "hash": mesh.content_hash(),
            "n_points": int(mesh.points.shape[0]),
            "n_tets": int(mesh.tets.shape[0]),
            "n_dofs": n_dofs,
            "n_surface_vertices": int(surface.nodes.size),
            "n_contactable": int(surface.contactable.sum()),
        },
        "timings_s": {"mesh": t_mesh, "assemble": t_assemble, "solve": t_solve},
        "solve_stats": stats,
        # the building process's peak resident memory so far (it counts whatever ran before in the process)
        "process_peak_memory_bytes": peak_memory_bytes(),
    }
    if cast is not None:
        manifest["dtype_cast"] = cast
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
        manifest["compliance"] = compliance_record(comp, construction="stream", source_key=key)
        path = write_bundle(out, arrays, manifest)
        log.info("wrote bundle %s (%d x %d compliance as an H-matrix, %.1f %% of its numbers; max column error "
                 "%.2g over %d exact columns) in %.1f s", path, *comp.H.shape,
                 100 * comp.H.stored / (comp.H.shape[0] * comp.H.shape[1]), comp.error["max"],
                 comp.error["columns"], time.perf_counter() - t0)
        return path
    arrays["compliance"] = D
    path = write_bundle(out, arrays, manifest)
    # D's hash was computed from its bytes on disk (BlockStore.finish) and the file moved, unchanged:
    # record that, so that loading it does not read all of D again (hailstorm.runtime.bundle.stamps)
    stamp(path / "compliance.npy", D.sha256)
    remove_work_dir(work_dir(out))
    log.info("wrote bundle %s (%d x %d compliance) in %.1f s", path, *D.shape, time.perf_counter() - t0)
    return path


def _stream_compliance(out: Path, problem: ColumnProblem, key: str, progress: bool, run: _RunSettings,
                       what: str) -> tuple[StagedArray, dict, tuple[float, float]]:
    """Solve D block by block into the work directory beside ``out``, resuming what a
    previous run of the same key left; return the finished D (staged), the run's statistics
    and (largest |entry|, largest rounding error) of the cast to D's storage type."""
    n_rows, ncols = problem.shape
    blocks = column_blocks(n_rows, ncols, run.block_bytes, problem.batch)
    store = BlockStore(work_dir(out), key, (n_rows, ncols), blocks, run.dtype)
    todo = store.missing
    done = len(blocks) - len(todo)
    if done:
        log.info("resuming: %d of %d blocks done (in %s)", done, len(blocks), store.path)
    d_disk = store.data_bytes
    block_disk = d_disk / max(len(blocks), 1)
    try:
        check_disk(block_disk * len(todo), store.path, f"D ({n_rows} x {ncols})", allow_large=run.allow_large)
    except TooLargeError:
        if not done:  # refused before any work: leave no empty work directory behind
            remove_work_dir(store.path)
        raise
    n_dofs = problem.Kff.shape[0]
    block_solved = 8 * n_rows * (blocks[0][1] - blocks[0][0])  # a block is solved in float64 whatever D's type
    est = estimate_memory(n_dofs, block_solved, 1 if run.scheduler is None and run.workers is None else 2)
    # the nnz(L) count factors K_ff once more here (SuperLU): skipped when that would not fit comfortably
    count_fill = problem.spec.proxy_fill and bool(todo) and 2 * (est - BASE_BYTES) < available_memory()
    nnz_l = cholesky_nnz(problem.Kff) if count_fill else None
    log.info("D: %d x %d %s, %s on disk (%d blocks of %d columns, %d to compute); "
             "peak memory about %s%s", n_rows, ncols, run.dtype, gib(d_disk), len(blocks), blocks[0][1] - blocks[0][0],
             len(todo), gib(est), "" if nnz_l is None else f"; nnz(L) about {nnz_l:,}")
    bar = None
    if progress and todo:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(blocks), initial=done, desc=f"Green's functions ({what})", unit="block")

    def on_first(stats: SolveStats) -> None:
        rest = len(todo) - 1
        per = stats.first_block_s - stats.factor_s
        eta = per * rest / max(stats.workers, 1)
        log.info("first block: %.2f s (factorization %.2f s); estimated %.0f s for the other %d blocks",
                 stats.first_block_s, stats.factor_s, eta, rest)

    def on_block(i: int, values: np.ndarray | RoundedBlock) -> None:
        store.write(i, values)
        if bar is not None:
            bar.update(1)

    try:
        with cluster_client(workers=run.workers, scheduler=run.scheduler) if todo else nullcontext() as client, \
                _logging_beside(bar):
            stats = solve_blocks(problem, blocks, todo, on_block, client=client, key=key, on_first=on_first,
                                 dtype=run.dtype)
    except KeyboardInterrupt:
        log.warning("interrupted: %d of %d blocks of D are kept in %s; run the same command again to resume",
                    len(store.done), len(blocks), store.path)
        raise
    except OSError as exc:
        raise BundleError(f"cannot write D to {store.path}: {exc.strerror or exc}; {len(store.done)} of "
                          f"{len(blocks)} finished blocks are kept there (the same command resumes)") from exc
    except Exception:
        if not store.done:  # failed before any block (e.g. the factorization): nothing to resume
            remove_work_dir(store.path)
        raise
    finally:
        if bar is not None:
            bar.close()
    info = _solve_record(stats, problem, len(blocks), done)
    if np.isfinite(stats.first_block_s):
        info["first_block_s"] = stats.first_block_s
    nnz_l = stats.nnz_L if stats.nnz_L is not None else nnz_l
    if nnz_l is not None and stats.columns:
        seconds = max(stats.solve_s - stats.factor_s, 1e-9)
        full = 4.0 * nnz_l * stats.columns  # a full forward and backward solve per column
        done_flops = float(stats.solve_flops) if stats.solve_flops else full
        info.update(nnz_L=nnz_l, solve_flops=done_flops, full_solve_flops=full,
                    solve_gflop_per_s=done_flops / seconds / 1e9)
        log.info("solved %d blocks (%d columns) in %.1f s on %d worker(s): nnz(L) %s; triangular solves %.3g GFLOP "
                 "(%.0f %% of 4 nnz(L) per column), %.2f GFLOP/s", stats.blocks, stats.columns, stats.solve_s,
                 stats.workers, f"{nnz_l:,}", done_flops / 1e9, 100 * done_flops / full, done_flops / seconds / 1e9)
    return store.finish(), info, store.rounding


def _stream_hmatrix(out: Path, problem: ColumnProblem, vertices: np.ndarray, contact_vertices: np.ndarray,
                    tol: float, key: str, progress: bool, run: _RunSettings, what: str) -> tuple[Compressed, dict]:
    """Solve D's columns in the column tree's order and compress them as they come
    (:class:`hailstorm.precompute.hstream.StreamedH`, far blocks to ``tol / 2`` each); measure the
    result on :data:`hailstorm.precompute.hmatrix.ERROR_COLUMNS` exact columns drawn at random (seed 0)
    before the solve. Raises ValueError naming the error reached if it exceeds ``tol``.

    The state is checkpointed beside ``out`` (``.NAME.work/stream.npz``) every
    :data:`CHECKPOINT_SECONDS` of solving and when the solve stops on an error or an
    interruption; a run with the same key, tolerance and blocks resumes from it."""
    t0 = time.perf_counter()
    V = np.asarray(vertices, dtype=np.float64)
    rows, cols = cluster_tree(V, leaf=DEFAULT_LEAF), cluster_tree(V[contact_vertices], leaf=DEFAULT_LEAF)
    part = admissible_blocks(rows, cols, DEFAULT_ETA)
    n_rows, ncols = problem.shape
    blocks = column_blocks(n_rows, ncols, run.block_bytes, problem.batch)
    picked = np.sort(np.random.default_rng(0).choice(ncols, size=min(ERROR_COLUMNS, ncols), replace=False))
    streamed = StreamedH(rows, cols, part, tol / 2, blocks, keep=picked)
    wd = work_dir(out)
    checkpoint = wd / CHECKPOINT
    tag = {"key": key, "tol": tol, "blocks": [list(b) for b in blocks], "error_columns": picked.tolist()}
    if checkpoint.is_file() and not streamed.resume(checkpoint, tag):
        log.info("checkpoint %s was for other inputs (or unreadable); starting afresh", checkpoint)
    have = set(streamed.starts)
    todo = [i for i, (start, _) in enumerate(blocks) if start not in have]
    done = len(blocks) - len(todo)
    if done:
        log.info("resuming: %d of %d blocks done (checkpoint %s)", done, len(blocks), checkpoint)
    log.info("D: %d x %d, compressed as it is solved (%d blocks of %d columns, %d to compute; the dense D "
             "would be %s)", n_rows, ncols, len(blocks), blocks[0][1] - blocks[0][0], len(todo),
             gib(8 * n_rows * ncols))
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=len(blocks), initial=done, desc=f"Green's functions ({what})", unit="block")
    saving = {"last": time.monotonic(), "ok": True}

    def save() -> bool:
        """Checkpoint the state; a failed write warns once and the run goes on without."""
        if not saving["ok"] or not streamed.starts:
            return False
        t = time.perf_counter()
        try:
            wd.mkdir(exist_ok=True)
            saved = streamed.save(checkpoint, tag)
        except OSError as exc:
            saving["ok"] = False
            log.warning("cannot checkpoint the streamed compression to %s (%s); going on without: an "
                        "interruption will start the solve afresh", checkpoint, exc.strerror or exc)
            return False
        saving["last"] = time.monotonic()
        if saved:
            log.info("checkpoint: %d of %d blocks, %s in %.1f s", len(streamed.starts), len(blocks),
                     gib(checkpoint.stat().st_size), time.perf_counter() - t)
        return saved

    def on_block(i: int, values: np.ndarray | RoundedBlock) -> None:
        streamed.add(blocks[i][0], values)
        if time.monotonic() - saving["last"] >= CHECKPOINT_SECONDS:
            save()
        if bar is not None:
            bar.update(1)

    try:
        with cluster_client(workers=run.workers, scheduler=run.scheduler) if todo else nullcontext() as client, \
                _logging_beside(bar):
            # its own solve key: the workers cache the problem by key, and these columns are in another order
            stats = solve_blocks(tree_order(problem, cols), blocks, todo, on_block, client=client,
                                 key=f"{key}:tree", dtype="float64")
    except BaseException:
        if save():
            log.warning("stopped: %d of %d blocks of D are compressed in %s; run the same command again to resume",
                        len(streamed.starts), len(blocks), checkpoint)
        raise
    finally:
        if bar is not None:
            bar.close()
    H = streamed.finish()
    _, err = streamed.errors(H)
    checkpoint.unlink(missing_ok=True)  # what is left is deterministic: a resumed run would end the same
    try:
        wd.rmdir()  # only if empty: an interrupted dense build of the same bundle keeps its blocks
    except OSError:
        pass
    worst = float(err.max(initial=0.0))
    if worst > tol:
        raise ValueError(f"the compression tolerance {tol:g} is unreachable while streaming: the H-matrix "
                         f"(per-block truncation {tol / 2:g}) has columns off by up to {worst:.3g}")
    error = {"columns": int(err.size), "max": worst, "median": float(np.median(err)) if err.size else 0.0, "seed": 0}
    return Compressed(H, tol, tol / 2, error, time.perf_counter() - t0), _solve_record(stats, problem, len(blocks), done)


def _solve_record(stats: SolveStats, problem: ColumnProblem, blocks: int, resumed: int) -> dict:
    """The manifest's ``solve_stats`` of a block loop: blocks, columns, workers, seconds, solver."""
    return {"blocks": blocks, "blocks_solved": stats.blocks, "blocks_resumed": resumed,
            "columns_solved": stats.columns, "workers": stats.workers, "factorizations": stats.factorizations,
            "factor_s": stats.factor_s, "solve_s": stats.solve_s, "solver": problem.solver, "batch": problem.batch}


def _logging_beside(bar):
    """Log messages above the progress bar instead of through it."""
    if bar is None:
        return nullcontext()
    from tqdm.contrib.logging import logging_redirect_tqdm

    return logging_redirect_tqdm()


def _rigid_modes_on_dofs(basis) -> np.ndarray:
    """Rigid-body modes evaluated at every dof location in scikit-fem's dof order."""
    locs = basis.doflocs.T  # (n_dofs, 3)
    comp = np.empty(locs.shape[0], dtype=np.int64)
    for d in range(3):
        comp[basis.nodal_dofs[d]] = d
        if basis.edge_dofs.size:
            comp[basis.edge_dofs[d]] = d
    modes = rigid_body_modes(locs)  # (3 n_dofs, 6): rows 3k+c = component c at location k
    return modes.reshape(-1, 3, 6)[np.arange(locs.shape[0]), comp]
