"""The Ogden-Storåkers energy's terms, and the error a foam that fails its checks raises.

The module the foam's other modules share (:mod:`~hailstorm.precompute.foam.material`,
:mod:`~hailstorm.precompute.foam.constitutive`, :mod:`~hailstorm.precompute.foam.stability`),
so that the material's check at construction imports no module that imports the material.
:class:`OgdenTerms` is what the stress and the checks read of a foam (the material's terms), so
that they name no material, even for type checking.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

__all__ = ["FoamStabilityError", "OgdenTerms", "phi", "term_energy"]


class OgdenTerms(Protocol):
    """The terms of an Ogden-Storåkers energy, as the stress and the checks read them
    (:class:`~hailstorm.precompute.foam.material.Hyperfoam` is one): ``mu_i``, ``alpha_i``, ``beta_i``."""

    @property
    def mu(self) -> tuple[float, ...]: ...

    @property
    def alpha(self) -> tuple[float, ...]: ...

    @property
    def beta(self) -> tuple[float, ...]: ...


class FoamStabilityError(ValueError):
    """Foam parameters whose energy is non-convex or whose tangent loses definiteness in the
    checked strain range (the message names the principal strains where it first fails)."""


def phi(y: np.ndarray) -> np.ndarray:
    """``exp(y) - 1 - y``, accurate to round-off of its own size (a series below 1e-3)."""
    y = np.asarray(y, dtype=np.float64)
    small = np.abs(y) < 1e-3
    ys = np.where(small, y, 0.0)
    series = ys * ys * (0.5 + ys * (1.0 / 6.0 + ys * (1.0 / 24.0 + ys / 120.0)))
    with np.errstate(over="ignore"):
        return np.where(small, series, np.expm1(np.where(small, 0.0, y)) - y)


def term_energy(lnl: np.ndarray, lnJ: np.ndarray, a: float, b: float) -> np.ndarray:
    """One term's ``l1^a + l2^a + l3^a - 3 + (J^(-a b) - 1) / b`` from ``ln l_a`` (..., 3) and ``ln J``,
    as ``sum_a phi(a ln l_a) + phi(-a b ln J) / b`` (``phi(y) = e^y - 1 - y``): the first-order parts,
    which cancel at small strain, are never formed (the energy to round-off of its own size, which a
    line search needs)."""
    vol = np.zeros_like(lnJ) if b == 0.0 else phi(-a * b * lnJ) / b
    return phi(a * lnl).sum(axis=-1) + vol + a * (lnl.sum(axis=-1) - lnJ)
