"""What :func:`hailstorm.precompute.pipeline.build_bundle` is asked for, resolved once.

Two frozen records, each checked when it is made (a bad value raises ValueError
naming it, before any meshing or solving):

* :class:`BuildSettings` -- what the bundle is: the seat (a ready mesh or a
  geometry at a mesh size), the elements, the materials, the contactable
  surface, the solver, the load, D's storage. All of it that changes D goes into
  the bundle's cache key (:meth:`BuildSettings.key_options`).
* :class:`RunSettings` -- how it is computed: reuse, progress, the memory
  check, the Dask cluster, the block size. None of it changes D.

:func:`settings_from_keywords` maps ``build_bundle``'s keyword arguments onto
the two.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from hailstorm.precompute.geometry import DEFAULT_COARSENING, DEFAULT_MESH_SIZE, check_coarsening, check_volume_size
from hailstorm.precompute.greens import DEFAULT_STORE_BYTES, SolverSpec, solver_spec
from hailstorm.precompute.hmatrix import check_tol, compressed_key
from hailstorm.precompute.hstream import streamed_key
from hailstorm.precompute.materials import check_material_input
from hailstorm.precompute.tetmesh import TetMesh
from hailstorm.runtime.bundle.format import COMPLIANCE_DTYPES

__all__ = ["LOADS", "BuildSettings", "RunSettings", "settings_from_keywords"]

#: what a column of D responds to (``BuildSettings.load``)
LOADS = ("point", "hat")


@dataclass(frozen=True)
class BuildSettings:
    """What a bundle is computed for (``build_bundle``'s inputs that shape D), checked on construction.

    Attributes
    ----------
    mesh : TetMesh or None
        A ready mesh (tests, studies), checked when the build starts
        (:func:`hailstorm.precompute.geometry.check_mesh`). Otherwise ``geometry``
        is meshed at ``mesh_size``.
    geometry : str, os.PathLike or None
        A geometry (``.geo``, ``.step``...) or mesh file; None: the default saddle.
    mesh_size : float
        Element size on the hail-facing surface [m].
    order : {1, 2}
        P1 or P2 tetrahedra; the bundle always lives on the corner vertices.
    volume_size : float or None
        Volume grading of a meshed geometry [m] (at most ``mesh_size``; refused with a ready mesh).
    coarsening : float
        Elements of a meshed geometry grow to ``coarsening * mesh_size`` away from the
        contact surface (at least 1; refused, unless the default, with a ready mesh).
    young, poisson : float or None
        One material for the whole body [Pa], [-] (None: the defaults of
        :mod:`hailstorm.precompute.fem`).
    materials : Mapping[str, tuple[float, float]] or None
        Instead of ``young``/``poisson``: ``{volume group: (E, nu)}`` for every
        volume group of the mesh (gmsh Physical Volume names), e.g.
        ``{"pad": (0.5e6, 0.3), "shell": (2e9, 0.4)}``
        (:func:`hailstorm.precompute.materials.resolve_materials` lists what is refused).
        The bundle's ``young``/``poisson`` are then the material under the
        ``contact_group`` surface; the manifest's ``materials`` records each
        volume's (E, nu) and its range of ``volume_tets``.
    contact_group : str
        Surface group whose (unclamped) vertices get columns of D (``"all"``: every one).
    solver : str
        ``"supernodal"`` (default), ``"cholmod"``, ``"splu"`` or ``"amg"``
        (:func:`hailstorm.precompute.greens.factorize`).
    tol : float
        The iterative solver's relative residual, in (0, 1) (in the cache key only for a
        solver that uses it).
    load : {"point", "hat"}
        What a column of D responds to: ``"point"``, a unit nodal force at the vertex;
        ``"hat"``, one newton spread as a traction over the vertex's hat function
        (:func:`hailstorm.precompute.greens.hat_load_matrix`), the consistent choice for P2.
    dtype : {"float64", "float32"}
        D's storage type. Columns are always solved in float64; for ``"float32"`` each
        block is rounded to nearest as it is written (each entry off by at most 2^-24 of
        itself, the largest rounding recorded in the manifest's ``dtype_cast``).
    compress_tol : float or None
        Store D compressed, as an H-matrix whose columns are within this relative error
        of the exact ones on 200 exact columns drawn at random
        (:func:`hailstorm.precompute.hmatrix.compress_bundle`; format 3). Needs
        ``dtype="float64"``. None: D dense.
    stream : bool
        With ``compress_tol``: build the H-matrix from D's column blocks as they are
        solved (:class:`hailstorm.precompute.hstream.StreamedH`), so D is never on disk
        or in memory whole; its measured column error is within ``compress_tol`` or the
        run fails naming it; its cache key is its own
        (:func:`hailstorm.precompute.hstream.streamed_key`).

    Raises
    ------
    ValueError
        On construction, naming the first bad setting (the materials first, then
        in the order above).
    """

    mesh: TetMesh | None = None
    geometry: str | os.PathLike | None = None
    mesh_size: float = DEFAULT_MESH_SIZE
    order: int = 1
    volume_size: float | None = None
    coarsening: float = DEFAULT_COARSENING
    young: float | None = None
    poisson: float | None = None
    materials: Mapping[str, tuple[float, float]] | None = None
    contact_group: str = "top"
    solver: str = "supernodal"
    tol: float = 1e-10
    load: str = "point"
    dtype: str = "float64"
    compress_tol: float | None = None
    stream: bool = False

    def __post_init__(self) -> None:
        check_material_input(self.materials, young=self.young, poisson=self.poisson)  # before any meshing
        if self.order not in (1, 2):
            raise ValueError(f"element order must be 1 or 2, got {self.order!r}")
        if self.load not in LOADS:
            raise ValueError(f"unknown load {self.load!r}; choose one of {LOADS}")
        solver_spec(self.solver)
        if not (np.isfinite(self.tol) and 0 < self.tol < 1):
            raise ValueError(f"solver tolerance must be in (0, 1), got {self.tol!r}")
        if not (np.isfinite(self.mesh_size) and self.mesh_size > 0):
            raise ValueError(f"mesh size must be a positive length in metres, got {self.mesh_size!r}")
        check_volume_size(self.volume_size, self.mesh_size)
        if self.volume_size is not None and self.mesh is not None:
            raise ValueError("volume_size grades a geometry as it is meshed; a ready mesh is used as it is")
        object.__setattr__(self, "coarsening", check_coarsening(self.coarsening))
        if self.coarsening != DEFAULT_COARSENING and self.mesh is not None:
            raise ValueError("coarsening grades a geometry as it is meshed; a ready mesh is used as it is")
        if not isinstance(self.dtype, str) or self.dtype not in COMPLIANCE_DTYPES:
            raise ValueError(f"D's storage type must be one of {' or '.join(COMPLIANCE_DTYPES)}, got {self.dtype!r}")
        if self.compress_tol is not None:
            object.__setattr__(self, "compress_tol", check_tol(self.compress_tol))
            if self.dtype != "float64":
                raise ValueError(f"a compressed D is stored in float64: --tol and --dtype {self.dtype} do not go "
                                 "together")
        if not isinstance(self.stream, bool):
            raise ValueError(f"stream must be True or False, got {self.stream!r}")
        if self.stream and self.compress_tol is None:
            raise ValueError("streaming builds a compressed D: --stream needs --tol")

    @property
    def spec(self) -> SolverSpec:
        """The solver's registry entry (:func:`hailstorm.precompute.greens.solver_spec`)."""
        return solver_spec(self.solver)

    def key_options(self, young: float, poisson: float, materials_key: Any) -> dict[str, Any]:
        """The options that enter the dense bundle's cache key beside the mesh's hash
        (:func:`hailstorm.precompute.pipeline.cache_key`).

        ``young``, ``poisson``: the material under the contact surface; ``materials_key``:
        :meth:`hailstorm.precompute.materials.MaterialMap.key`. Settings at their old
        defaults add nothing (float64, no volume grading, the default coarsening), so the
        keys of bundles written before they existed stay valid.
        """
        options: dict[str, Any] = {
            "order": int(self.order),
            "young": young,
            "poisson": poisson,
            "materials": materials_key,
            "contact_group": self.contact_group,
            "solver": self.solver,
            "tol": self.tol if self.spec.uses_tol else None,
            "load": self.load,
        }
        if self.dtype != "float64":
            options["dtype"] = self.dtype
        if self.volume_size is not None:  # the mesh's hash already differs; recorded for the reader
            options["volume_size"] = float(self.volume_size)
        if self.coarsening != DEFAULT_COARSENING:  # likewise
            options["coarsening"] = self.coarsening
        return options

    def final_key(self, key: str) -> str:
        """The key of the bundle asked for, from its dense source's ``key``: the same, or the
        compressed (:func:`~hailstorm.precompute.hmatrix.compressed_key`) or streamed
        (:func:`~hailstorm.precompute.hstream.streamed_key`) bundle's."""
        if self.compress_tol is None:
            return key
        return streamed_key(key, self.compress_tol) if self.stream else compressed_key(key, self.compress_tol)


@dataclass(frozen=True)
class RunSettings:
    """How a bundle is computed (none of it changes D), checked on construction.

    Attributes
    ----------
    reuse : bool
        Return an existing bundle whose key matches, without recomputing.
    progress : bool
        Show a progress bar over D's column blocks.
    allow_large : bool
        Skip the memory check: by default a run whose estimated memory (from the
        geometry before meshing, from the mesh before assembly;
        :mod:`hailstorm.precompute.resources`) exceeds the memory available raises
        :class:`~hailstorm.precompute.resources.TooLargeError`; so does a D larger than
        the free disk.
    workers : int or None
        Solve the column blocks on a local Dask cluster of this many processes.
    scheduler : str or None
        Solve them on the running Dask cluster at this address (connected to when the
        build starts: an unreachable one raises
        :class:`hailstorm.precompute.cluster.ClusterError` before any work).
    block_bytes : int
        Size of one column block of D as solved (float64): the unit of work, of what is
        written to disk at once, and of what an interrupted run loses.

    Raises
    ------
    ValueError
        ``workers`` is not a positive number of processes.
    """

    reuse: bool = True
    progress: bool = False
    allow_large: bool = False
    workers: int | None = None
    scheduler: str | None = None
    block_bytes: int = DEFAULT_STORE_BYTES

    def __post_init__(self) -> None:
        w = self.workers
        if w is not None and (isinstance(w, bool) or not isinstance(w, int) or w < 1):
            raise ValueError(f"workers must be a positive number of processes, got {w!r}")
        object.__setattr__(self, "block_bytes", int(self.block_bytes))

    @property
    def in_process(self) -> bool:
        """The blocks are solved in this process (no Dask cluster)."""
        return self.scheduler is None and self.workers is None


_BUILD_FIELDS = frozenset(f.name for f in dataclasses.fields(BuildSettings))
_RUN_FIELDS = frozenset(f.name for f in dataclasses.fields(RunSettings))


def settings_from_keywords(settings: BuildSettings | None = None, run: RunSettings | None = None,
                           **keywords: Any) -> tuple[BuildSettings, RunSettings]:
    """``build_bundle``'s keyword arguments as the two records.

    Each keyword names a field of :class:`BuildSettings` or :class:`RunSettings`; given
    ``settings`` or ``run``, the keywords replace their fields.

    Raises
    ------
    TypeError
        A keyword that is neither record's field.
    ValueError
        A bad value (the records' checks).
    """
    unknown = sorted(set(keywords) - _BUILD_FIELDS - _RUN_FIELDS)
    if unknown:
        raise TypeError(f"build_bundle() got an unexpected keyword argument {unknown[0]!r}")
    build = {k: v for k, v in keywords.items() if k in _BUILD_FIELDS}
    how = {k: v for k, v in keywords.items() if k in _RUN_FIELDS}
    if settings is None:
        settings = BuildSettings(**build)
    elif build:
        settings = dataclasses.replace(settings, **build)
    if run is None:
        run = RunSettings(**how)
    elif how:
        run = dataclasses.replace(run, **how)
    return settings, run
