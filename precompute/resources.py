"""Up-front estimates of what a precompute run needs, checked against the machine.

The compliance D is dense: 3 n_surface x 3 n_contactable float64 values, so
its size grows as the fourth power of 1 / mesh size (D of the default seat is
152 MB at 6 mm, measured; so about 2.4 GB at 3 mm and 40 GB at 1.5 mm). :func:`estimate_geometry`
estimates it from a geometry's areas before meshing, :func:`estimate_mesh`
from a mesh before assembly, and :func:`check_fits` refuses a run that would
not fit in the memory available, unless overridden (``--allow-large``,
``allow_large=True``).
"""

from __future__ import annotations

from dataclasses import dataclass

from hailstorm.runtime.scene import available_memory as runtime_available_memory

#: surface vertices per unit area of a surface meshed at size h, times h^2: 2 / sqrt(3) = 1.15 for
#: equilateral triangles; measured 0.99-1.48 on the default seat's top at 4-15 mm (coarse meshes
#: have more, relatively, along edges): 1.5 errs on the safe side
VERTICES_PER_AREA = 1.5


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
        Size of D (float64).
    total_bytes : int
        D plus the stiffness, its factorization and the solve blocks.
    """

    n_surface: int
    n_contactable: int
    n_dofs: int
    d_bytes: int
    total_bytes: int


def _estimate(n_surface: float, n_contactable: float, n_points: float, order: int) -> Estimate:
    # P2 adds a node per edge: about 7 edges per vertex in a tetrahedral mesh
    n_dofs = 3.0 * n_points * (1 if order == 1 else 8)
    d_bytes = 72.0 * n_surface * n_contactable
    # a sparse Cholesky factor of a 3-D stiffness holds ~ n^(4/3) entries (nested dissection),
    # K ~ 80 entries per row for P1; 256 MiB of right-hand-side blocks (hailstorm.precompute.greens)
    solver = 12.0 * 8.0 * n_dofs ** (4.0 / 3.0) + 80.0 * 12.0 * n_dofs + 256 * 2**20
    return Estimate(int(n_surface), int(n_contactable), int(n_dofs), int(d_bytes), int(d_bytes + solver))


def estimate_geometry(area_top: float, area_all: float, volume: float, mesh_size: float, order: int = 1,
                      coarsening: float = 2.5) -> Estimate:
    """Estimate a bundle's needs from a geometry's areas [m^2] and volume [m^3], before meshing.

    Every surface is counted at ``mesh_size`` (an upper bound: sizes grow away
    from ``top``); the interior at ``coarsening * mesh_size``.
    """
    n_contactable = VERTICES_PER_AREA * area_top / mesh_size**2
    n_surface = VERTICES_PER_AREA * area_all / mesh_size**2
    n_points = 1.3 * n_surface + 1.5 * volume / (coarsening * mesh_size) ** 3
    return _estimate(n_surface, n_contactable, n_points, order)


def estimate_mesh(n_surface: int, n_contactable: int, n_points: int, order: int = 1) -> Estimate:
    """A bundle's needs for a mesh with these counts (D exact, the solver's share estimated)."""
    return _estimate(n_surface, n_contactable, n_points, order)


def available_memory() -> int:
    """Bytes of memory available to a new computation (the runtime's
    :func:`hailstorm.runtime.scene.available_memory`; unknown counts as unlimited)."""
    avail = runtime_available_memory()
    return 2**63 - 1 if avail is None else avail


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
            f"{what} would need about {gib(est.total_bytes)} of memory (D alone {gib(est.d_bytes)}: "
            f"{est.n_surface:.3g} surface x {est.n_contactable:.3g} contactable vertices; {est.n_dofs:.3g} dofs), "
            f"more than the {gib(available)} available; use a larger --mesh-size, or --allow-large "
            "(allow_large=True) to try anyway"
        )
