"""The rigid sphere's impact patch, the plain way: the oracle of
:func:`hailstorm.runtime.compiled.sphere.sphere_w`, :func:`~hailstorm.runtime.compiled.sphere.impact_patch_x`
and :func:`~hailstorm.runtime.compiled.sphere.impact_offset_of_patch`.

Sneddon's law in its closed form (``delta / R = x atanh x``, ``F / (E* R^2) = (1 + x^2) atanh x - x``),
its work by adaptive quadrature in the depth (scipy's ``quad``), and the impact patch's inverse by
bracketing (``brentq``): none of the kernels' series, Gauss-Legendre rule or Newton steps.
"""

from __future__ import annotations

import numpy as np
from scipy.integrate import quad
from scipy.optimize import brentq


def q_ref(x: float) -> float:
    """``F / (E* R^2)`` at ``x = a / R`` (closed form: loses ``eps / x^2`` for small ``x``)."""
    return (1.0 + x * x) * np.arctanh(x) - x


def w_ref(x: float) -> float:
    """``W / (E* R^3)``: ``int q d(delta / R)`` from 0 to the depth of ``x``."""
    f = lambda t: q_ref(t) * (np.arctanh(t) + t / (1.0 - t * t))  # noqa: E731
    cuts = [0.0] + [c for c in (0.5, 0.9, 0.99) if c < x] + [x]  # the 1 / (1 - t) ahead: shorter pieces
    return sum(quad(f, lo, hi, epsabs=0.0, epsrel=1e-12, limit=200)[0] for lo, hi in zip(cuts[:-1], cuts[1:]))


def impact_patch_ref(x: float) -> float:
    """``a_i / R``: the Hertz disc whose linear law has the sphere's peak and work, ``c = 2 W / F^2``."""
    return 0.3 * q_ref(x) ** 2 / w_ref(x)


def impact_offset_ref(a: float, R: float) -> float:
    """The offset [m] of an impact patch of radius ``a`` on a sphere of radius ``R``: ``delta - 2 W / F``
    at the sphere's ``x`` whose impact patch it is."""
    p = a / R  # i(x) lies in [x, 1.2 x)
    x = brentq(lambda t: impact_patch_ref(t) - p, 0.8 * p, min(p, 1.0 - 1e-5), xtol=1e-15, rtol=1e-15)
    return R * (x * np.arctanh(x) - 2.0 * w_ref(x) / q_ref(x))
