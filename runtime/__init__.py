"""Runtime stage: load a Green's-function bundle and resolve contacts on it.

Imports numpy and scipy only (no gmsh, no scikit-fem): a bundle written by
``hailstorm precompute`` is all it needs.
"""

from runtime.bundle import BundleError, GreensFunctions, load
from runtime.contact import (  # noqa: E402
    Capacitance,
    ContactSolution,
    barycentric_matrix,
    capacitance,
    solve_contacts,
)
