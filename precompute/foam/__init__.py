"""The foam of the pad at large strain: its material and the nonlinear local pad (issue #46).

* :mod:`~hailstorm.precompute.foam.material` -- :class:`Hyperfoam` (Ogden-Storåkers), validated;
* :mod:`~hailstorm.precompute.foam.catalogue` -- the default pad's foam, cited;
* :mod:`~hailstorm.precompute.foam.constitutive` -- its stress and exact tangent at any ``F``;
* :mod:`~hailstorm.precompute.foam.stability` -- convexity and ellipticity checks;
* :mod:`~hailstorm.precompute.foam.pad` -- the axisymmetric total-Lagrangian pad (scikit-fem);
* :mod:`~hailstorm.precompute.foam.indent` -- a rigid sphere pressed in: the force-approach curve.

Offline only (scikit-fem is a ``precompute`` extra): the storm reads the tables it makes.
"""

from hailstorm.precompute.foam.material import FoamStabilityError, Hyperfoam

__all__ = ["FoamStabilityError", "Hyperfoam"]
