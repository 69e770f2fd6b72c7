"""Runtime stage: load a Green's-function bundle, resolve contacts, run the storm.

Imports numpy, scipy and numba only (no gmsh, no scikit-fem): a bundle written by
``hailstorm precompute`` is all it needs. The storm runs its per-step geometry and
contact work in compiled kernels (:mod:`hailstorm.runtime.compiled`).

* :func:`load` -> :class:`GreensFunctions` (D, surface, ``compliance(rows, cols)``);
* :func:`barycentric_matrix` (B), :func:`patch_weights`, :func:`hertz_radius`, :func:`sphere_radius`,
  :func:`impact_radius`;
* :func:`capacitance` -> :class:`Capacitance` (W = Bᵀ D B, K = W⁻¹, low-rank updates);
* :func:`solve_contacts` -> :class:`ContactSolution`;
* :func:`press_spheres` -> :class:`SphereContacts` (rigid spheres, patches consistent with the sphere);
  :func:`hertz_impact` -> :class:`HertzImpact` (Hertz's quasi-static impact, the reference);
* :class:`Scene` (its sections :class:`StormSettings`, :class:`HailSettings`,
  :class:`ContactSettings`, :class:`TimeSettings`, :class:`OutputSettings`, :class:`ValiditySettings`; the default seat's
  precompute settings :class:`SeatSettings`), :func:`run_storm` -> :class:`StormResult` (the hail storm);
  :class:`Storm`, the storm driver stepped by hand (studies, tests);
* :mod:`hailstorm.runtime.inertia`: the pad's inertia in each impact (a storm's inertia factors,
  its local dynamic peer).
"""

from hailstorm.runtime.bundle import BundleError, GreensFunctions, load
from hailstorm.runtime.contact import (
    Capacitance,
    ContactSolution,
    barycentric_matrix,
    capacitance,
    hertz_radius,
    impact_radius,
    patch_weights,
    solve_contacts,
    sphere_radius,
)
from hailstorm.runtime.contact.hertz import (HertzImpact, SphereContacts, hertz_force, hertz_impact, press_spheres,
                                             sphere_force, sphere_impact)
from hailstorm.runtime.seat_settings import SeatSettings
from hailstorm.runtime.storm.scene import Scene, SceneError
from hailstorm.runtime.storm.scene_sections import (
    ContactSettings,
    HailSettings,
    OutputSettings,
    StormSettings,
    TimeSettings,
    ValiditySettings,
)
from hailstorm.runtime.storm.driver import Storm, StormResult
from hailstorm.runtime.storm.run import run_storm

__all__ = [
    "BundleError",
    "Capacitance",
    "ContactSettings",
    "ContactSolution",
    "GreensFunctions",
    "HertzImpact",
    "HailSettings",
    "OutputSettings",
    "Scene",
    "SceneError",
    "SeatSettings",
    "SphereContacts",
    "Storm",
    "StormResult",
    "StormSettings",
    "TimeSettings",
    "ValiditySettings",
    "barycentric_matrix",
    "capacitance",
    "hertz_force",
    "hertz_impact",
    "hertz_radius",
    "impact_radius",
    "load",
    "patch_weights",
    "press_spheres",
    "sphere_force",
    "sphere_impact",
    "sphere_radius",
    "run_storm",
    "solve_contacts",
]
