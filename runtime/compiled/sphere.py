"""The contact law of a rigid sphere on an elastic half-space, for any contact radius (Sneddon).

Hertz's law replaces the sphere by the paraboloid ``r^2 / (2 R)`` and holds for
``a << R``. The frictionless rigid sphere itself has a closed form (Sneddon,
*Int. J. Engng Sci.* 3 (1965) 47, eq. 6.12; Johnson, *Contact Mechanics*,
1985, §5.2): with ``x = a / R`` and ``E* = E / (1 - nu^2)``,

    ``delta = R x atanh(x)``,   ``F = E* R^2 q(x)``,   ``q(x) = (1 + x^2) atanh(x) - x``,

which tends to Hertz's ``F = (4/3) E* a^3 / R``, ``delta = a^2 / R`` as ``x -> 0``
and gives ``a < R`` at every force. At ``a/R`` = 0.5 Hertz's law at the sphere's
depth is 2.8 % stiffer than the sphere, at 0.8 9.7 %.

:func:`sphere_radius_of` inverts ``F(a)`` (Newton from Hertz's radius, which lies
above the sphere's: ``q(x) >= 4 x^3 / 3``, and ``q`` is convex, so the iterates
fall monotonically); :func:`sphere_radii` is the same over arrays. The contact
API's numpy face is :func:`hailstorm.runtime.contact.sphere_patch.sphere_radius`.

An impact needs the law's work as well: ``W = E* R^3 w(x)``, ``w(x) = int_0^x q dt``
with ``t = delta / R`` (:func:`sphere_w`; no elementary closed form, so Gauss-Legendre
in ``u = atanh(x)``, where the integrand ``q(tanh u) ((1 - tanh^2 u) u + tanh u)`` is
analytic). A contact whose force is linear in the depth, ``F = (delta - o) / c``, meets
the sphere's peak ``(delta, F)`` of an impact of energy ``W`` when ``c = 2 W / F^2`` and
``o = delta - 2 W / F``: with Hertz's disc compliance ``c = 3 / (5 a_i E*)`` that is a
patch of radius ``a_i = R i(x)``, ``i(x) = 3 q^2 / (10 w)`` (:func:`impact_patch_x`; ``x`` for
Hertz, 4.0 % above the sphere's radius at ``x`` = 0.8), and the offset
``R (x atanh(x) - 2 w / q)`` (:func:`impact_offset_of_patch`, from the patch's ``a_i / R``).
"""

from __future__ import annotations

import math

import numpy as np

from hailstorm.runtime.compiled.jit import kernel

__all__ = ["IMPACT_SERIES_BELOW", "SERIES_BELOW", "X_MAX", "impact_offset_of_patch", "impact_offsets_of_patch", "impact_patch_x",
           "impact_radii", "impact_radius_of", "sphere_q", "sphere_qs", "sphere_radii", "sphere_radius_of", "sphere_w",
           "sphere_x_of_depth", "sphere_xs_of_depth"]

#: below this ``x = a/R``, ``q(x)`` is summed as its series (the closed form loses
#: ``eps / x^2`` to cancellation); the series' first omitted term is ``< 1e-17`` of ``q`` there
SERIES_BELOW = 0.05

#: the largest ``a / R`` returned (``q`` reaches 27.6 there: forces of ``27.6 E* R^2``)
X_MAX = 1.0 - 1e-12

#: Gauss-Legendre rule of :func:`sphere_w` on [-1, 1]: the integrand in ``u = atanh(x)`` is analytic
#: with its nearest poles at ``+-i pi / 2``, so 24 nodes are exact to rounding up to ``x = 1 - 1e-6``
#: (tested against adaptive quadrature)
_GL_U, _GL_W = np.polynomial.legendre.leggauss(24)

#: below this ``x`` the impact patch is the contact (``i(x) = x (1 + O(x^2))``, the ratio's
#: correction under 1e-16)
IMPACT_SERIES_BELOW = 1e-8


@kernel
def sphere_q(x):  # pragma: no cover (compiled)
    """``q(x) = (1 + x^2) atanh(x) - x = F / (E* R^2)`` at ``x = a / R`` in ``[0, 1)``."""
    if x < SERIES_BELOW:
        x2 = x * x
        term = x
        s = 0.0
        for k in range(1, 8):  # sum_k 4k x^(2k+1) / (4k^2 - 1)
            term *= x2
            s += 4.0 * k * term / (4.0 * k * k - 1.0)
        return s
    return (1.0 + x * x) * math.atanh(x) - x


@kernel
def sphere_qs(x):  # pragma: no cover (compiled)
    """:func:`sphere_q` over a 1-d array."""
    out = np.empty(x.size)
    for i in range(x.size):
        out[i] = sphere_q(x[i])
    return out


@kernel
def sphere_radius_of(F, R, e_star):  # pragma: no cover (compiled)
    """The contact radius ``a`` [m] of a rigid sphere of radius ``R`` pressed with force ``|F|``
    into a half-space of ``E*`` (the inverse of ``F = E* R^2 q(a / R)``; 0 for ``F = 0`` or ``R = 0``)."""
    if not R > 0.0:
        return 0.0
    f = abs(F) / (e_star * R * R)
    if not f > 0.0:
        return 0.0
    x = min(np.cbrt(0.75 * f), X_MAX)  # Hertz's radius: at or above the sphere's
    if sphere_q(x) <= f:
        return x * R  # past X_MAX, or Hertz's exactly (tiny forces)
    for _ in range(60):
        at = math.atanh(x)
        dq = 2.0 * x * at + 2.0 * x * x / (1.0 - x * x)
        step = (sphere_q(x) - f) / dq
        x -= step
        if step <= 1e-15 * x:
            break
    return x * R


@kernel
def sphere_x_of_depth(t):  # pragma: no cover (compiled)
    """``x = a / R`` of the sphere pressed to depth ``t R``: the root of ``x atanh(x) = t`` (Newton from
    Hertz's ``sqrt(t)``, which lies above it: ``x atanh(x) >= x^2``, convex, so the iterates fall
    monotonically); 0 for ``t <= 0``, :data:`X_MAX` past it."""
    if not t > 0.0:
        return 0.0
    x = min(math.sqrt(t), X_MAX)
    if x * math.atanh(x) <= t:
        return x
    for _ in range(60):
        at = math.atanh(x)
        step = (x * at - t) / (at + x / (1.0 - x * x))
        x -= step
        if step <= 1e-15 * x:
            break
    return x


@kernel
def sphere_xs_of_depth(t):  # pragma: no cover (compiled)
    """:func:`sphere_x_of_depth` over a 1-d array."""
    out = np.empty(t.size)
    for i in range(t.size):
        out[i] = sphere_x_of_depth(t[i])
    return out


@kernel
def sphere_radii(F, R, e_star):  # pragma: no cover (compiled)
    """:func:`sphere_radius_of` over arrays ``F``, ``R`` of one shape (1-d)."""
    out = np.empty(F.size)
    for i in range(F.size):
        out[i] = sphere_radius_of(F[i], R[i], e_star)
    return out


@kernel
def sphere_w(x):  # pragma: no cover (compiled)
    """``w(x) = W / (E* R^3)``: the work of pressing the sphere to ``x = a / R`` in ``[0, 1)``,
    ``int_0^x q(t) d(t atanh t)`` (Hertz's ``8 x^5 / 15`` for small ``x``)."""
    if not x > 0.0:
        return 0.0
    half = 0.5 * math.atanh(min(x, X_MAX))
    s = 0.0
    for k in range(_GL_U.size):
        u = half * (1.0 + _GL_U[k])
        t = math.tanh(u)
        s += _GL_W[k] * sphere_q(t) * ((1.0 - t * t) * u + t)
    return half * s


@kernel
def impact_patch_x(x):  # pragma: no cover (compiled)
    """``a_i / R = 3 q(x)^2 / (10 w(x))``: the patch (Hertz's disc) whose linear law meets the
    sphere's impact peak at contact ratio ``x`` (module docstring); ``x`` itself below
    :data:`IMPACT_SERIES_BELOW`."""
    if x < IMPACT_SERIES_BELOW:
        return x
    q = sphere_q(x)
    return 0.3 * q * q / sphere_w(x)


@kernel
def impact_radius_of(F, R, e_star):  # pragma: no cover (compiled)
    """The impact patch's radius [m] for a peak force ``|F|``: ``R`` :func:`impact_patch_x` of
    the sphere's own ratio (:func:`sphere_radius_of`)."""
    if not R > 0.0:
        return 0.0
    return R * impact_patch_x(sphere_radius_of(F, R, e_star) / R)


@kernel
def impact_radii(F, R, e_star):  # pragma: no cover (compiled)
    """:func:`impact_radius_of` over arrays ``F``, ``R`` of one shape (1-d)."""
    out = np.empty(F.size)
    for i in range(F.size):
        out[i] = impact_radius_of(F[i], R[i], e_star)
    return out


@kernel
def impact_offset_of_patch(p):  # pragma: no cover (compiled)
    """``o / R`` of an impact patch of ratio ``p = a_i / R``: ``x atanh(x) - 2 w(x) / q(x)`` at the
    ``x`` with :func:`impact_patch_x` ``(x) = p`` (``x^2 / 5`` for small ``x``). ``i`` grows with ``x``
    from ``i(x) >= x``, so Newton from ``x = p`` (above the root) with a bisection guard."""
    if not p > 0.0:
        return 0.0
    if p < IMPACT_SERIES_BELOW:
        return 0.2 * p * p
    hi = min(p, X_MAX)
    if impact_patch_x(hi) <= p:  # p beyond i(X_MAX) (about 1.19): the widest contact's x
        x = hi
    else:
        lo = 0.0
        x = hi
        for _ in range(100):
            g = impact_patch_x(x) - p
            if g > 0.0:
                hi = x
            else:
                lo = x
            q = sphere_q(x)
            w = sphere_w(x)
            at = math.atanh(x)
            dq = 2.0 * x * at + 2.0 * x * x / (1.0 - x * x)
            dw = q * (at + x / (1.0 - x * x))
            dg = 0.3 * (2.0 * q * dq * w - q * q * dw) / (w * w)
            nx = x - g / dg if dg > 0.0 else 0.5 * (lo + hi)
            if not lo < nx < hi:
                nx = 0.5 * (lo + hi)
            if abs(nx - x) <= 1e-15 * x:
                x = nx
                break
            x = nx
    if x < IMPACT_SERIES_BELOW:
        return 0.2 * x * x
    return x * math.atanh(x) - 2.0 * sphere_w(x) / sphere_q(x)


@kernel
def impact_offsets_of_patch(p):  # pragma: no cover (compiled)
    """:func:`impact_offset_of_patch` over a 1-d array."""
    out = np.empty(p.size)
    for i in range(p.size):
        out[i] = impact_offset_of_patch(p[i])
    return out
