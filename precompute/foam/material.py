"""A compressible Ogden foam (Storåkers' energy; the HYPERFOAM form of commercial codes).

    ``W = sum_i 2 mu_i / alpha_i^2 [ l1^a_i + l2^a_i + l3^a_i - 3 + (J^(-a_i b_i) - 1) / b_i ]``

with principal stretches ``l1, l2, l3``, ``J = l1 l2 l3`` and ``b_i = nu_i / (1 - 2 nu_i)``
(B. Storåkers, On material representation and constitutive branching in finite compressible
elasticity, J. Mech. Phys. Solids 34 (1986) 125-145; the same form and the moduli below are the
Abaqus/3DEXPERIENCE "hyperfoam" documentation's). Small-strain moduli: ``mu0 = sum mu_i``,
``K0 = sum 2 mu_i (1/3 + b_i)``. With one ``b`` for every term, uniaxial stress keeps the lateral
stretch at ``l^(-nu)`` at every strain (the closed form of :meth:`Hyperfoam.uniaxial`).

* :class:`Hyperfoam` -- the parameters (validated), the energy, principal stresses, moduli;
* :class:`FoamStabilityError` -- parameters refused, naming the strain where they fail
  (:func:`hailstorm.precompute.foam.stability.check_stability`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hailstorm.precompute.foam.ogden import FoamStabilityError, term_energy  # (re-exported: they lived here)

__all__ = ["FoamStabilityError", "Hyperfoam", "term_energy"]



@dataclass(frozen=True)
class Hyperfoam:
    """An Ogden-Storåkers compressible foam (module notes), validated at construction.

    Attributes
    ----------
    mu : tuple of float
        ``mu_i`` [Pa]; ``mu_i alpha_i > 0`` each, ``sum mu_i > 0``.
    alpha : tuple of float
        ``alpha_i`` [-], non-zero.
    nu : tuple of float
        ``nu_i`` [-] in (-1, 0.5): each term's Poisson ratio, ``beta_i = nu_i / (1 - 2 nu_i)``.
    density : float
        [kg/m^3] (> 0).
    name : str
    source : str
        Where the numbers come from (a citation, and what of it is verified).
    check_range : tuple of float
        The nominal principal strains ``(min, max)`` in which :func:`~hailstorm.precompute.foam.stability.check_stability`
        holds the energy convex and the tangent strongly elliptic (checked at construction).

    Raises
    ------
    ValueError
        Unequal lengths, ``mu_i alpha_i <= 0``, ``nu_i`` outside (-1, 0.5), density <= 0.
    FoamStabilityError
        Non-convex energy or a tangent that loses definiteness within ``check_range``.
    """

    mu: tuple[float, ...]
    alpha: tuple[float, ...]
    nu: tuple[float, ...]
    density: float
    name: str = "foam"
    source: str = ""
    check_range: tuple[float, float] = (-0.8, 0.5)

    def __post_init__(self) -> None:
        for name in ("mu", "alpha", "nu"):
            object.__setattr__(self, name, tuple(float(x) for x in getattr(self, name)))
        n = len(self.mu)
        if n == 0 or len(self.alpha) != n or len(self.nu) != n:
            raise ValueError(f"hyperfoam needs as many mu, alpha, nu (>= 1), got {len(self.mu)}, {len(self.alpha)}, "
                             f"{len(self.nu)}")
        for i, (m, a, v) in enumerate(zip(self.mu, self.alpha, self.nu)):
            if not (math.isfinite(m) and math.isfinite(a) and a != 0.0 and m * a > 0.0):
                raise ValueError(f"hyperfoam term {i}: needs finite mu_i alpha_i > 0, got mu={m!r}, alpha={a!r}")
            if not (-1.0 < v < 0.5):
                raise ValueError(f"hyperfoam term {i}: nu_i must be in (-1, 0.5), got {v!r}")
        if not (math.isfinite(self.density) and self.density > 0):
            raise ValueError(f"hyperfoam density must be positive, got {self.density!r}")
        if self.shear_modulus <= 0 or self.bulk_modulus <= 0:
            raise ValueError(f"hyperfoam small-strain moduli must be positive, got mu0={self.shear_modulus!r}, "
                             f"K0={self.bulk_modulus!r}")
        lo, hi = self.check_range
        if not (-1.0 < lo < 0.0 < hi):
            raise ValueError(f"hyperfoam check_range needs -1 < min < 0 < max, got {self.check_range!r}")
        from hailstorm.precompute.foam.stability import check_stability

        check_stability(self, lo, hi)

    # -- small strain -------------------------------------------------------------------------
    @property
    def beta(self) -> tuple[float, ...]:
        """``beta_i = nu_i / (1 - 2 nu_i)``."""
        return tuple(v / (1.0 - 2.0 * v) for v in self.nu)

    @property
    def shear_modulus(self) -> float:
        """``mu0 = sum mu_i`` [Pa]."""
        return float(sum(self.mu))

    @property
    def bulk_modulus(self) -> float:
        """``K0 = sum 2 mu_i (1/3 + beta_i)`` [Pa]."""
        return float(sum(2.0 * m * (1.0 / 3.0 + b) for m, b in zip(self.mu, self.beta)))

    @property
    def young(self) -> float:
        """Small-strain Young's modulus ``9 K0 mu0 / (3 K0 + mu0)`` [Pa]."""
        K, G = self.bulk_modulus, self.shear_modulus
        return 9.0 * K * G / (3.0 * K + G)

    @property
    def poisson(self) -> float:
        """Small-strain Poisson ratio ``(3 K0 - 2 mu0) / (2 (3 K0 + mu0))``."""
        K, G = self.bulk_modulus, self.shear_modulus
        return (3.0 * K - 2.0 * G) / (2.0 * (3.0 * K + G))

    # -- large strain -------------------------------------------------------------------------
    def energy(self, l1: Any, l2: Any, l3: Any) -> np.ndarray:
        """``W`` at principal stretches [J/m^3] (broadcast; NaN where ``J <= 0``)."""
        lam = np.stack(np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (l1, l2, l3))), axis=-1)
        J = lam.prod(axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            lnl = np.log(lam)
            lnJ = lnl.sum(axis=-1)
            out = np.zeros(J.shape)
            for m, a, b in zip(self.mu, self.alpha, self.beta):
                out = out + 2.0 * m / a**2 * term_energy(lnl, lnJ, a, b)
        return np.where(np.all(lam > 0, axis=-1), out, np.nan)

    def kirchhoff(self, l1: Any, l2: Any, l3: Any) -> np.ndarray:
        """Principal Kirchhoff stresses ``tau_a = l_a dW/dl_a = sum 2 mu_i / a_i (l_a^a_i - J^(-a_i b_i))`` [Pa], (..., 3)."""
        lam = np.stack(np.broadcast_arrays(*(np.asarray(x, dtype=np.float64) for x in (l1, l2, l3))), axis=-1)
        J = lam.prod(axis=-1)[..., None]
        out = np.zeros_like(lam)
        for m, a, b in zip(self.mu, self.alpha, self.beta):
            out += 2.0 * m / a * (lam**a - J ** (-a * b))
        return out

    def cauchy(self, l1: Any, l2: Any, l3: Any) -> np.ndarray:
        """Principal Cauchy stresses ``tau_a / J`` [Pa], (..., 3)."""
        tau = self.kirchhoff(l1, l2, l3)
        return tau / (np.asarray(l1) * np.asarray(l2) * np.asarray(l3))[..., None]

    def lateral_stretch(self, stretch: float) -> float:
        """The lateral stretch of uniaxial stress at axial ``stretch`` (``tau_lateral = 0``):
        ``stretch^(-nu)`` when every ``nu_i`` is the same, else the root of the lateral stress."""
        stretch = float(stretch)
        if not stretch > 0:
            raise ValueError(f"stretch must be positive, got {stretch!r}")
        if len(set(self.nu)) == 1:
            return stretch ** (-self.nu[0])
        from scipy.optimize import brentq

        def lateral(t: float) -> float:
            return float(self.kirchhoff(stretch, t, t)[1])

        lo, hi = 1e-3, 1e3
        return float(brentq(lateral, lo, hi, xtol=1e-15, rtol=4 * np.finfo(float).eps))

    def uniaxial(self, stretch: float) -> tuple[float, float]:
        """Uniaxial stress at axial ``stretch``: (nominal stress ``P = tau_axial / stretch`` [Pa],
        lateral stretch); the closed form the finite elements are held to."""
        t = self.lateral_stretch(stretch)
        return float(self.kirchhoff(stretch, t, t)[0]) / float(stretch), t

    def uniaxial_energy(self, stretch: float) -> float:
        """``W`` in uniaxial stress at axial ``stretch`` [J/m^3]."""
        t = self.lateral_stretch(stretch)
        return float(self.energy(stretch, t, t))

    @property
    def wave_speed(self) -> float:
        """Small-strain dilatational wave speed ``sqrt((K0 + 4 mu0 / 3) / rho)`` [m/s]."""
        return math.sqrt((self.bulk_modulus + 4.0 * self.shear_modulus / 3.0) / self.density)
