"""The pad's inertia in an impact: what the quasi-static storm leaves out, measured per impact.

* :mod:`~hailstorm.runtime.inertia.pad` -- the local pad (:class:`Pad`), a disc of the seat's
  foam on a rigid base, axisymmetric about the impact: its mesh and matrices
  (:func:`pad_mesh` -> :class:`PadMesh`, numpy and scipy alone);
* :mod:`~hailstorm.runtime.inertia.impact` -- one stone's impact on it, with the pad's mass
  and without (:func:`simulate_impact` -> :class:`ImpactResult`): the dynamic peer; one
  impact's inertia factors (:func:`impact_inertia`);
* :mod:`~hailstorm.runtime.inertia.factors` -- per impact of a storm, the dynamic over the
  quasi-static impact on the pad under it (:func:`inertia_factors` ->
  :class:`InertiaFactors`);
* :mod:`~hailstorm.runtime.inertia.table` -- those factors tabulated once per material in
  ``R/h`` and ``v/c`` and interpolated per impact (:func:`inertia_table` -> :class:`InertiaTable`).
"""

from hailstorm.runtime.inertia.factors import InertiaFactors, inertia_factors
from hailstorm.runtime.inertia.impact import ImpactResult, PeerResolutionError, impact_inertia, simulate_impact
from hailstorm.runtime.inertia.pad import Pad, PadMesh, pad_mesh
from hailstorm.runtime.inertia.table import InertiaTable, inertia_table

__all__ = ["ImpactResult", "InertiaFactors", "InertiaTable", "Pad", "PadMesh", "PeerResolutionError", "impact_inertia",
           "inertia_factors", "inertia_table", "pad_mesh", "simulate_impact"]
