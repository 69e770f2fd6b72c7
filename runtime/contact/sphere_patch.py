"""A sphere's contact patch: its radius and the offset of its mean displacement.

Part of the contact core (:mod:`hailstorm.runtime.contact`); the patch's weights are
:func:`hailstorm.runtime.contact.weights.patch_weights`.

:func:`hertz_radius` gives the Hertz contact radius
``a = (3 F R / (4 E*))^(1/3)``, ``E* = E / (1 - nu^2)``, of a rigid sphere of
radius ``R`` pressed with force ``F`` on the seat (the paraboloid's, ``a << R``);
:func:`sphere_radius` the sphere's own at any ``a / R``, which patch contacts are
sized by, and :func:`sphere_offset` the matching offset of the patch's mean
displacement below the sphere's lowest point. An impact's patch is sized for the
sphere's work as well as its force (:func:`impact_radius`, :func:`impact_offset`:
the patch whose linear law reaches the sphere's peak force and depth with the
sphere's energy; the storm's). :func:`resolved_fraction` is how much of such an offset
the surface mesh can follow, and :func:`sphere_mean_offset` the offset as far as it does.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hailstorm.runtime.compiled.sphere import impact_offsets_of_patch, impact_radii, sphere_qs, sphere_radii

__all__ = [
    "OFFSET_PEAK",
    "hertz_radius",
    "impact_offset",
    "impact_radius",
    "resolved_fraction",
    "sphere_mean_offset",
    "sphere_offset",
    "sphere_radius",
]


def hertz_radius(force: Any, stone_radius: Any, young: float, poisson: float, *,
                 a_min: float = 0.0, a_max: float | None = None) -> np.ndarray:
    """Hertz contact radius of a rigid sphere pressed on the (elastic) seat.

    ``a = (3 F R / (4 E*))^(1/3)`` with ``E* = E / (1 - nu^2)`` (rigid
    sphere on an elastic half-space; Johnson, *Contact Mechanics*, ch. 4),
    clipped to ``[a_min, a_max]``.

    Parameters
    ----------
    force : float or (s,) array_like
        Normal load [N]; the magnitude is used (a force on the seat pressing
        in has ``f . n < 0``).
    stone_radius : float or (s,) array_like
        Sphere radius R [m].
    young, poisson : float
        The seat's material [Pa], [-].
    a_min : float
        Floor [m], e.g. a fraction of the mesh size: the radius of a patch
        contact at vanishing load (0 recovers a point contact).
    a_max : float, optional
        Ceiling [m] (e.g. the stone radius).

    Returns
    -------
    ndarray
        Contact radius [m], broadcast shape of ``force`` and ``stone_radius``.
    """
    F = np.abs(np.asarray(force, dtype=np.float64))
    R = np.asarray(stone_radius, dtype=np.float64)
    if np.any(R < 0) or not (young > 0 and -1.0 < poisson < 0.5):
        raise ValueError("hertz_radius needs R >= 0, E > 0 and -1 < nu < 0.5")
    e_star = young / (1.0 - poisson**2)
    a = np.cbrt(3.0 * F * R / (4.0 * e_star))
    a = np.maximum(a, a_min)
    if a_max is not None:
        a = np.minimum(a, a_max)
    return a


#: the ``a / R`` at which :func:`sphere_offset` peaks (0.149 R); held there beyond
OFFSET_PEAK = 0.9099577964991118


def sphere_radius(force: Any, stone_radius: Any, young: float, poisson: float, *,
                  a_min: float = 0.0, a_max: float | None = None) -> np.ndarray:
    """Contact radius of a rigid sphere pressed on the (elastic) seat, at any ``a / R``.

    The inverse of the sphere's own law ``F = E* R^2 ((1 + x^2) atanh(x) - x)``,
    ``x = a / R`` (Sneddon 1965; :mod:`hailstorm.runtime.compiled.sphere`), which is
    :func:`hertz_radius` for ``a << R`` and stays below ``R`` at every force (Hertz's
    paraboloid reaches ``R`` at ``F = (4/3) E* R^2``). Clipped to ``[a_min, a_max]``.
    Parameters and result as :func:`hertz_radius`'s.
    """
    return _radius_of_force(sphere_radii, "sphere_radius", force, stone_radius, young, poisson, a_min, a_max)


def sphere_offset(patch_radius: Any, sphere_radius: Any) -> np.ndarray:
    """How far a patch's mean surface displacement lies short of the sphere's lowest point [m]
    (0 for a point contact, ``a = 0``): the offset that makes a patch of radius ``a``, whose
    compliance is Hertz's disc's ``3 / (5 a E*)``, carry the sphere's own force at its depth.

    ``R (x atanh(x) - (3/5) q(x) / x)`` with ``x = a / R`` and ``q`` the sphere's force
    (:mod:`hailstorm.runtime.compiled.sphere`): ``delta(a) - 3 F(a) / (5 a E*)``. For
    ``a << R`` it is ``a^2 / (5 R) (1 + x^2 / 15 + ...)``, the Hertz-weighted mean of the
    paraboloid ``r^2 / (2 R)`` (``<r^2> = 2 a^2 / 5``), so a patch is consistent with
    Hertz where Hertz holds and with the sphere beyond (on a half-space exactly) up to
    ``a/R`` = :data:`OFFSET_PEAK` (0.910), where it peaks at 0.149 R; it is held at that peak
    beyond (where it would fall to 0 at 0.993), so that a wider patch never has a smaller
    offset: contacts that wide are far outside the model's limits
    (:mod:`hailstorm.runtime.storm.limits`).
    """
    a = np.asarray(patch_radius, dtype=np.float64)
    R = np.asarray(sphere_radius, dtype=np.float64)
    a, R = np.broadcast_arrays(a, R)
    x = np.where(R > 0, np.minimum(a / np.where(R > 0, R, 1.0), OFFSET_PEAK), 0.0)
    q = sphere_qs(np.ascontiguousarray(x, dtype=np.float64).ravel()).reshape(x.shape)
    off = R * (x * np.arctanh(x) - 0.6 * q / np.where(x > 0, x, 1.0))
    return np.where(x > 0, off, 0.0)


def impact_radius(force: Any, stone_radius: Any, young: float, poisson: float, *,
                  a_min: float = 0.0, a_max: float | None = None) -> np.ndarray:
    """The patch radius of an impact whose peak force is ``force``: a Hertz disc whose
    linear law ``F = (delta - o) / c``, ``c = 3 / (5 a E*)``, reaches the sphere's peak
    ``(delta, F)`` with the sphere's work ``W`` (``c = 2 W / F^2``).

    ``R i(x)``, ``i(x) = 3 q(x)^2 / (10 w(x))`` at the sphere's own ``x = a / R``
    (:func:`sphere_radius`; :func:`hailstorm.runtime.compiled.sphere.impact_patch_x`):
    the sphere's radius for ``a << R`` (Hertz's law is its own linearisation's energy),
    1.1 % above it at ``a/R`` 0.5, 4.0 % at 0.8. Sized by the sphere's radius instead
    (with :func:`sphere_offset`), an impact on a half-space is 1.1 / 2.2 % soft in peak
    force at ``a/R`` 0.62 / 0.80.
    Clipped to ``[a_min, a_max]``; parameters and result as :func:`hertz_radius`'s.
    """
    return _radius_of_force(impact_radii, "impact_radius", force, stone_radius, young, poisson, a_min, a_max)


def _radius_of_force(radii: Any, name: str, force: Any, stone_radius: Any, young: float, poisson: float,
                     a_min: float, a_max: float | None) -> np.ndarray:
    """The numpy face of a compiled ``radii(F, R, e_star)`` over 1-d arrays: checked, broadcast, clipped."""
    F = np.abs(np.asarray(force, dtype=np.float64))
    R = np.asarray(stone_radius, dtype=np.float64)
    if np.any(R < 0) or not (young > 0 and -1.0 < poisson < 0.5):
        raise ValueError(f"{name} needs R >= 0, E > 0 and -1 < nu < 0.5")
    F, R = np.broadcast_arrays(F, R)
    e_star = young / (1.0 - poisson**2)
    a = radii(np.ascontiguousarray(F.ravel()), np.ascontiguousarray(R.ravel()), e_star).reshape(F.shape)
    a = np.maximum(a, a_min)
    if a_max is not None:
        a = np.minimum(a, a_max)
    return a


def impact_offset(patch_radius: Any, sphere_radius: Any) -> np.ndarray:
    """The offset [m] that goes with an impact patch of radius ``a_i`` (:func:`impact_radius`):
    ``delta - 2 W / F`` of the sphere whose impact patch it is, so the patch's linear law passes
    through the sphere's peak ``(delta, F)`` (its static point at that force too).

    ``R (x atanh(x) - 2 w(x) / q(x))`` at the ``x`` with ``i(x) = a_i / R``
    (:func:`hailstorm.runtime.compiled.sphere.impact_offset_of_patch`): ``a^2 / (5 R)`` for
    ``a << R`` like :func:`sphere_offset`, and growing with ``a_i`` at every size (no peak).
    """
    a = np.asarray(patch_radius, dtype=np.float64)
    R = np.asarray(sphere_radius, dtype=np.float64)
    a, R = np.broadcast_arrays(a, R)
    p = np.where(R > 0, a / np.where(R > 0, R, 1.0), 0.0)
    o = impact_offsets_of_patch(np.ascontiguousarray(p, dtype=np.float64).ravel()).reshape(p.shape)
    return R * o


def resolved_fraction(points: np.ndarray, verts: np.ndarray, weights: np.ndarray, centres: np.ndarray,
                      normals: np.ndarray, patch_radius: Any) -> np.ndarray:
    """How much of a sphere's offset a patch's mesh can follow, in ``[0, 1]``, (s,).

    An offset such as :func:`sphere_offset` assumes a surface that follows the sphere over
    the whole disc. A piecewise-linear surface can only do so where its
    triangles are small against the disc: a disc inside one triangle sees a
    plane, whose weighted mean is its value at the contact point, offset 0.
    The weights' tangential second moment about the contact point,
    ``m2 = sum_p w_p |rho_p|^2``, measures this: it is ``2 a^2 / 5`` plus an
    ``O(h^2)`` smear of the hat functions. The fraction is
    ``min(1, (2 a^2 / 5) / m2)``: 1 on a resolved patch, vanishing as the patch shrinks
    inside a triangle.

    Parameters
    ----------
    points : (n, 3) ndarray
        Undeformed surface vertices.
    verts, weights : (s, P) ndarrays
        Each contact's weighted vertices and weights
        (:func:`hailstorm.runtime.contact.weights.patch_weights`;
        padding has weight 0).
    centres, normals : (s, 3) ndarrays
        Contact points and unit normals.
    patch_radius : float or (s,) array_like
        ``a`` [m].
    """
    a = np.broadcast_to(np.asarray(patch_radius, dtype=np.float64), (verts.shape[0],))
    rho = np.asarray(points, dtype=np.float64)[verts] - centres[:, None, :]
    rho = rho - np.einsum("kpd,kd->kp", rho, normals)[..., None] * normals[:, None, :]
    m2 = np.einsum("kp,kpd,kpd->k", weights, rho, rho)
    m2_disc = 0.4 * a * a
    return np.where(m2 > m2_disc, m2_disc / np.where(m2 > 0, m2, 1.0), 1.0)


def sphere_mean_offset(points: np.ndarray, verts: np.ndarray, weights: np.ndarray, centres: np.ndarray,
                       normals: np.ndarray, patch_radius: Any, sphere_radius: Any) -> np.ndarray:
    """The patch-mean offset of a sphere's profile as the surface mesh can follow it [m], (s,):
    :func:`sphere_offset` times :func:`resolved_fraction` (parameters as there; ``sphere_radius``
    ``R`` [m])."""
    fraction = resolved_fraction(points, verts, weights, centres, normals, patch_radius)
    return sphere_offset(patch_radius, sphere_radius) * fraction
