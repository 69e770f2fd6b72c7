"""The foam of the pad at large strain: its material and the nonlinear local pad (issue #46).

* :mod:`~hailstorm.precompute.foam.material` -- :class:`Hyperfoam` (Ogden-Storåkers), validated;
* :mod:`~hailstorm.precompute.foam.catalogue` -- the default pad's foam, cited;
* :mod:`~hailstorm.precompute.foam.constitutive` -- its stress and exact tangent at any ``F``;
* :mod:`~hailstorm.precompute.foam.stability` -- convexity and ellipticity checks;
* :mod:`~hailstorm.precompute.foam.pad` -- the axisymmetric total-Lagrangian pad (scikit-fem);
* :mod:`~hailstorm.precompute.foam.contact` -- the sphere's frictionless contact (augmented Lagrangian);
* :mod:`~hailstorm.precompute.foam.indent` -- a rigid sphere pressed in: the force-approach curve;
* :mod:`~hailstorm.precompute.foam.impact` -- a rigid sphere striking the pad (its mass, implicit Newmark);
* :mod:`~hailstorm.precompute.foam.oscillator` -- the quasi-static law as a 1-DOF oscillator (the
  impact's reference in its quasi-static limit).

Offline only (scikit-fem is a ``precompute`` extra): the storm reads the tables it makes.
"""

from hailstorm.precompute.foam.material import FoamStabilityError, Hyperfoam

__all__ = ["FoamStabilityError", "Hyperfoam"]
