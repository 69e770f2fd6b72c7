"""Up-front estimates of what a precompute run needs, checked against the machine.

The compliance D is dense: 3 n_surface x 3 n_contactable values of its storage
type (float64, or float32: half), so its size grows as the fourth power of 1 / mesh size (D of the default seat is
152 MB at 6 mm, measured; 1.4 GB at 3 mm and 7 GB for 10 000 contactable
vertices at 1.9 mm). D is streamed to disk in column blocks
(:mod:`hailstorm.precompute.blocks`), so it needs disk, not memory: the memory
is the stiffness, its factorization and a few blocks (solved in float64 whatever
D's storage type, so a float32 D halves the disk, not the memory). :func:`estimate_geometry`
estimates both from a geometry's areas before meshing, :func:`estimate_mesh`
from a mesh before assembly; :func:`check_fits` refuses a run that would not
fit in the memory available and :func:`check_disk` one whose D would not fit
on the disk, unless overridden (``--allow-large``, ``allow_large=True``).
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from hailstorm.runtime.resources import available_memory as runtime_available_memory

#: Bytes of one column block of D, the unit of work and of what is written to disk at once
#: (32 MiB: a few hundred blocks for 10 000 contactable vertices, each worth one file write).
DEFAULT_STORE_BYTES = 32 * 2**20

#: surface vertices per unit area of a surface meshed at size h, times h^2: 2 / sqrt(3) = 1.15 for
#: equilateral triangles; measured 0.99-1.48 on the default seat's top at 4-15 mm (coarse meshes
#: have more, relatively, along edges): 1.5 errs on the safe side
VERTICES_PER_AREA = 1.5
#: memory of the process before any mesh: Python, numpy, scipy, gmsh, scikit-fem (measured 190-240 MiB)
BASE_BYTES = 200 * 2**20
#: peak memory of building the FE basis and assembling the stiffness, per dof: scikit-fem's basis
#: (values and gradients at every quadrature point of every element) and the COO triplets of the
#: assembly (measured above the process's base: 278 MiB for 19 458 dofs, P1 at 3 mm, 14.6 KB;
#: 355 MiB for 35 637 dofs, P2 at 6 mm, 10.4 KB). Freed before the solve.
ASSEMBLY_BYTES_PER_DOF = 15_000
#: column blocks of D held at once: one being solved, one being written, slack for a worker's result
BLOCKS_IN_MEMORY = 4


class TooLargeError(ValueError):
    """A precompute run would need more memory than the machine has."""


@dataclass(frozen=True)
class Estimate:
    """What a bundle needs (rough for a geometry, exact in D for a mesh).

    Attributes
    ----------
    n_surface, n_contactable, n_dofs : int
        Surface vertices (rows of D / 3), contactable vertices (columns / 3),
        degrees of freedom of the stiffness.
    d_bytes : int
        Size of D in its storage type: what it needs on disk.
    total_bytes : int
        Peak memory: the larger of the assembly (the FE basis and the
        stiffness' triplets, :data:`ASSEMBLY_BYTES_PER_DOF`) and the solve (the
        stiffness, its factorization and a few column blocks of D,
        :data:`BLOCKS_IN_MEMORY`), never D.
    """

    n_surface: int
    n_contactable: int
    n_dofs: int
    d_bytes: int
    total_bytes: int


def _estimate(n_surface: float, n_contactable: float, n_points: float, order: int,
              dtype: str | np.dtype = "float64") -> Estimate:
    # P2 adds a node per edge: about 7 edges per vertex in a tetrahedral mesh
    n_dofs = 3.0 * n_points * (1 if order == 1 else 8)
    entries = 9.0 * n_surface * n_contactable
    d_bytes = entries * np.dtype(dtype).itemsize
    solver = _solver_bytes(n_dofs)
    # blocks are solved in float64 whatever D's storage type
    # and the sweeps' work space: two threads of 128 right-hand sides over every dof (supernodal)
    blocks = BLOCKS_IN_MEMORY * min(8.0 * entries, DEFAULT_STORE_BYTES) + 8.0 * n_dofs * 256
    peak = max(ASSEMBLY_BYTES_PER_DOF * n_dofs, solver + blocks)
    return Estimate(int(n_surface), int(n_contactable), int(n_dofs), int(d_bytes), int(BASE_BYTES + peak))


def estimate_memory(n_dofs: int, block_bytes: float, blocks_factor: int = 1) -> float:
    """Peak memory of the solve: the stiffness, its factorization (estimated) and
    :data:`BLOCKS_IN_MEMORY` column blocks of ``block_bytes`` (a block as solved, in
    float64; times ``blocks_factor`` in the client of a cluster, which holds two results
    per worker in flight)."""
    return BASE_BYTES + _solver_bytes(n_dofs) + BLOCKS_IN_MEMORY * blocks_factor * block_bytes


def _solver_bytes(n_dofs: float) -> float:
    """The stiffness and the largest factorization held at once.

    A sparse Cholesky factor of a 3-D stiffness holds ~ c n^(4/3) entries of 12 bytes (measured
    c = 6.9 at 3 mm, 10 at 1.6 mm on the previous default seat: 3.6 M and 24.7 M). The default
    supernodal solver is built from SuperLU's factor, which holds L and U and a copy of L
    while the panels are arranged (:func:`hailstorm.precompute.supernodal.supernodal_factor`):
    about 3 times that at its peak; CHOLMOD's path holds the same for its nnz(L) count
    (:func:`hailstorm.precompute.greens.cholesky_nnz`, freed before CHOLMOD factorizes).
    K ~ 80 entries per row for P1.
    """
    return 3.0 * 12.0 * 10.0 * n_dofs ** (4.0 / 3.0) + 80.0 * 12.0 * n_dofs


def estimate_geometry(area_top: float, area_all: float, volume: float, mesh_size: float, order: int = 1,
                      coarsening: float = 2.5, dtype: str | np.dtype = "float64", *,
                      volume_size: float | None = None) -> Estimate:
    """Estimate a bundle's needs from a geometry's areas [m^2] and volume [m^3], before meshing.

    Every surface is counted at ``mesh_size`` (an upper bound: sizes grow away
    from ``top``); the interior at ``coarsening * mesh_size``, or at ``volume_size``
    when the volume is graded finer. ``dtype``: D's storage type.
    """
    n_contactable = VERTICES_PER_AREA * area_top / mesh_size**2
    n_surface = VERTICES_PER_AREA * area_all / mesh_size**2
    interior = coarsening * mesh_size if volume_size is None else min(volume_size, coarsening * mesh_size)
    n_points = 1.3 * n_surface + 1.5 * volume / interior ** 3
    return _estimate(n_surface, n_contactable, n_points, order, dtype)


def estimate_mesh(n_surface: int, n_contactable: int, n_points: int, order: int = 1,
                  dtype: str | np.dtype = "float64") -> Estimate:
    """A bundle's needs for a mesh with these counts (D exact in D's storage type ``dtype``,
    the solver's share estimated)."""
    return _estimate(n_surface, n_contactable, n_points, order, dtype)


def available_memory() -> int:
    """Bytes of memory available to a new computation (the runtime's
    :func:`hailstorm.runtime.resources.available_memory`; unknown counts as unlimited)."""
    avail = runtime_available_memory()
    return 2**63 - 1 if avail is None else avail


def peak_memory_bytes() -> int:
    """This process's peak resident memory so far [bytes] (``getrusage``; Linux reports KiB)."""
    import resource

    return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024


def gib(n: float) -> str:
    """A byte count for people: '3.2 GiB', '150 MiB'."""
    if n >= 2**30:
        return f"{n / 2**30:.3g} GiB"
    return f"{n / 2**20:.3g} MiB"


def check_fits(est: Estimate, what: str, *, allow_large: bool = False, available: int | None = None) -> None:
    """Raise :class:`TooLargeError` if ``est`` exceeds the memory available (unless ``allow_large``).

    Parameters
    ----------
    est
        The estimate.
    what
        The run, for the message (e.g. ``"saddle.geo at mesh size 0.001 m"``).
    allow_large
        Skip the check (the explicit override).
    available
        Bytes available (default: :func:`available_memory`).
    """
    if allow_large:
        return
    available = available_memory() if available is None else available
    if est.total_bytes > available:
        raise TooLargeError(
            f"{what} would need about {gib(est.total_bytes)} of memory (D, on disk: {gib(est.d_bytes)}: "
            f"{est.n_surface:.3g} surface x {est.n_contactable:.3g} contactable vertices; {est.n_dofs:.3g} dofs), "
            f"more than the {gib(available)} available; use a larger --mesh-size, or --allow-large "
            "(allow_large=True) to try anyway"
        )


def check_disk(need_bytes: float, directory: str | os.PathLike, what: str, *, allow_large: bool = False) -> None:
    """Raise :class:`TooLargeError` if ``directory``'s file system has less than ``need_bytes`` free.

    Parameters
    ----------
    need_bytes
        Bytes still to write (D less the blocks already on disk).
    directory
        Where D is written (the nearest existing ancestor is asked).
    what
        The run, for the message.
    allow_large
        Skip the check.
    """
    if allow_large:
        return
    probe = Path(directory).absolute()
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    free = shutil.disk_usage(probe).free
    if need_bytes > free:
        raise TooLargeError(f"{what} needs about {gib(need_bytes)} of disk for D in {probe}, "
                            f"more than the {gib(free)} free; free some space, write elsewhere (--out), "
                            "or --allow-large (allow_large=True) to try anyway")
