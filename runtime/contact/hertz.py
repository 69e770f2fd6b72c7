"""Rigid spheres pressed into the seat: patch contacts consistent with the sphere (Hertz for ``a << R``).

A rigid sphere of radius ``R`` pressed a depth ``delta`` into an elastic
half-space touches a disc of radius ``a = sqrt(R delta)`` and the surface
under it follows the sphere, ``u(r) = delta - r^2 / (2 R)`` (Johnson,
*Contact Mechanics*, ch. 4). Hertz's pressure ``p ~ sqrt(1 - r^2/a^2)``
produces exactly that profile, with ``F = (4/3) E* sqrt(R) delta^(3/2)``,
``E* = E / (1 - nu^2)``.

A patch contact (:func:`hailstorm.runtime.solve_contacts` with ``patch_radius``)
prescribes the pressure-weighted *mean* displacement of its disc, ``B^T u_V``.
Under a sphere that mean is not ``delta``: with Hertz weights

    ``<u> = delta - <r^2> / (2 R) = delta - a^2 / (5 R)``

(``<r^2> = 2 a^2 / 5``), which is ``0.8 delta`` when ``a^2 = R delta``.
Prescribing ``delta`` itself makes the contact ~1.3x too stiff. And the
radius must be the one the force produces, ``a = (3 F R / (4 E*))^(1/3)``,
not a guess: :func:`press_spheres`
solves for the pair (force, radius) by fixed-point iteration. The map
``a -> a(F(a))`` contracts with slope about 1/6 at the solution, so a few
iterations reach ``tol``.

Hertz's paraboloid holds for ``a << R``; the hail's contacts reach ``a/R`` 0.8. So the
radius and the offset are the sphere's own (Sneddon 1965): the radius
:func:`hailstorm.runtime.contact.sphere_patch.sphere_radius` and the offset
:func:`hailstorm.runtime.contact.sphere_patch.sphere_offset`, ``delta(a) - 3 F(a) / (5 a E*)``, which
makes a patch whose disc compliance is Hertz's carry the sphere's force at its depth on a
half-space at every ``a/R``; both are Hertz's to ``O((a/R)^2)``. (Hertz's law at the
sphere's depth is 2.8 % stiffer than the sphere at ``a/R`` 0.5, 9.7 % at 0.8.)

:func:`hailstorm.runtime.contact.sphere_patch.sphere_mean_offset` is that offset as far as the
surface mesh resolves the patch (a patch inside one triangle sees a plane:
no offset); the storm's patch contacts use the same functions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hailstorm.runtime.contact import ContactSolution, solve_contacts
from hailstorm.runtime.bundle.compliance import ElasticSource
from hailstorm.runtime.compiled.sphere import sphere_q, sphere_qs, sphere_x_of_depth, sphere_xs_of_depth
from hailstorm.runtime.contact.capacitance_build import resolve_near_field
from hailstorm.runtime.contact.normals import smooth_normals
from hailstorm.runtime.contact.sphere_patch import sphere_mean_offset, sphere_offset, sphere_radius
from hailstorm.runtime.contact.weights import contact_points, patch_weights

__all__ = ["HertzImpact", "SphereContacts", "hertz_force", "hertz_impact", "press_spheres", "sphere_force",
           "sphere_impact"]


def hertz_force(depth: Any, sphere_radius: Any, young: float, poisson: float) -> np.ndarray:
    """Hertz force ``(4/3) E* sqrt(R) delta^(3/2)`` of a rigid sphere on a half-space [N]."""
    d = np.clip(np.asarray(depth, dtype=np.float64), 0.0, None)
    R = np.asarray(sphere_radius, dtype=np.float64)
    return 4.0 / 3.0 * young / (1.0 - poisson**2) * np.sqrt(R) * d**1.5


def sphere_force(depth: Any, sphere_radius: Any, young: float, poisson: float) -> np.ndarray:
    """The rigid sphere's own force at depth ``delta`` on a half-space, at any ``a / R`` [N].

    Sneddon's ``F = E* R^2 ((1 + x^2) atanh(x) - x)`` at the ``x = a / R`` of
    ``delta = R x atanh(x)`` (:mod:`hailstorm.runtime.compiled.sphere`); :func:`hertz_force`
    for ``delta << R``.
    """
    d = np.asarray(depth, dtype=np.float64)
    R = np.asarray(sphere_radius, dtype=np.float64)
    d, R = np.broadcast_arrays(d, R)
    if np.any(R <= 0) or not (young > 0 and -1.0 < poisson < 0.5):
        raise ValueError("sphere_force needs R > 0, E > 0 and -1 < nu < 0.5")
    x = sphere_xs_of_depth(np.ascontiguousarray(d / R, dtype=np.float64).ravel())
    e_star = young / (1.0 - poisson**2)
    return e_star * R * R * sphere_qs(x).reshape(d.shape)


@dataclass(frozen=True)
class HertzImpact:
    """A quasi-static impact of a sphere on a half-space: Hertz's (:func:`hertz_impact`) or the
    sphere's own (:func:`sphere_impact`).

    Attributes
    ----------
    max_depth : float
        Maximum indentation ``delta_max`` [m].
    max_force : float
        Peak force (Hertz's ``(4/3) E* sqrt(R) delta_max^(3/2)``) [N].
    duration : float
        Contact duration [s] (first touch to release).
    """

    max_depth: float
    max_force: float
    duration: float


def hertz_impact(mass: float, speed: float, sphere_radius: float, young: float, poisson: float,
                 gravity: float = 0.0) -> HertzImpact:
    """Hertz's quasi-static impact of a rigid sphere on an elastic half-space.

    The sphere (mass ``m``) arrives at ``v`` along the normal and the contact
    force follows Hertz, ``F = K delta^(3/2)``, ``K = (4/3) E* sqrt(R)``
    (Johnson, *Contact Mechanics*, 11.4). Without gravity
    ``delta_max = (15 m v^2 / (16 E* sqrt(R)))^(2/5)`` and the duration is
    ``2.9432 delta_max / v``. With a body force ``g`` along the approach the
    energy balance ``m v^2 / 2 + m g delta = (2/5) K delta^(5/2)`` gives
    ``delta_max`` and the duration is ``2 * integral_0^delta_max d delta /
    sqrt(v^2 + 2 g delta - (4 K / 5 m) delta^(5/2))`` (by quadrature).

    Parameters
    ----------
    mass : float
        Sphere mass [kg] (> 0).
    speed : float
        Approach speed at first touch [m/s] (> 0).
    sphere_radius : float
        R [m] (> 0).
    young, poisson : float
        The elastic body [Pa], [-].
    gravity : float
        Body acceleration pressing the sphere in [m/s^2] (>= 0; 0: Hertz's
        closed form).

    Returns
    -------
    HertzImpact

    Raises
    ------
    ValueError
        Non-positive mass, speed or radius, negative gravity, invalid material.
    """
    m, v, R, g = float(mass), float(speed), float(sphere_radius), float(gravity)
    if not (m > 0 and v > 0 and R > 0 and g >= 0 and np.isfinite([m, v, R, g]).all()):
        raise ValueError("hertz_impact needs mass, speed and radius > 0 and gravity >= 0")
    if not (young > 0 and -1.0 < poisson < 0.5):
        raise ValueError("hertz_impact needs E > 0 and -1 < nu < 0.5")
    K = 4.0 / 3.0 * young / (1.0 - poisson**2) * np.sqrt(R)
    d0 = (15.0 * m * v * v / (16.0 * K * 3.0 / 4.0)) ** 0.4  # E* sqrt(R) = 3 K / 4
    if g == 0.0:  # 2 integral_0^1 dx / sqrt(1 - x^(5/2)) = (4/5) B(2/5, 1/2) = 2.9432
        c = 0.8 * math.gamma(0.4) * math.gamma(0.5) / math.gamma(0.9)
        return HertzImpact(max_depth=float(d0), max_force=float(K * d0**1.5), duration=float(c * d0 / v))
    from scipy.integrate import quad
    from scipy.optimize import brentq

    def speed2(d: float) -> float:
        return v * v + 2.0 * g * d - 0.8 * K / m * d**2.5

    hi = d0
    while speed2(hi) > 0:
        hi *= 1.5
    dm = brentq(speed2, d0, hi, xtol=1e-15 * d0, rtol=1e-14)
    # delta = dm (1 - s^2): the integrand 2 dm s / sqrt(speed2) is finite at s = 0
    half, _ = quad(lambda s: 2.0 * dm * s / np.sqrt(max(speed2(dm * (1.0 - s * s)), 1e-300)) if s > 0 else
                   2.0 * dm / np.sqrt(dm * (0.8 * K / m * 2.5 * dm**1.5 - 2.0 * g)), 0.0, 1.0,
                   epsabs=0.0, epsrel=1e-10, limit=200)
    return HertzImpact(max_depth=float(dm), max_force=float(K * dm**1.5), duration=float(2.0 * half))


def sphere_impact(mass: float, speed: float, sphere_radius: float, young: float, poisson: float,
                  gravity: float = 0.0) -> HertzImpact:
    """The rigid sphere's own quasi-static impact on an elastic half-space, at any ``a / R``.

    :func:`hertz_impact` with the sphere's force law (:func:`sphere_force`, Sneddon) in place of
    Hertz's ``K delta^(3/2)``: ``delta_max`` from the energy balance
    ``m v^2 / 2 + m g delta = W(delta)``, ``W`` the work of the sphere's force (by quadrature in
    ``x = a / R``, where ``delta = R x atanh(x)`` and ``F = E* R^2 ((1 + x^2) atanh(x) - x)``), the
    duration ``2 * integral_0^delta_max d delta / sqrt(v^2 + 2 g delta - 2 W(delta) / m)`` (by
    quadrature). Tends to :func:`hertz_impact` as ``delta_max / R -> 0``; parameters, result and
    errors as its.
    """
    m, v, R, g = float(mass), float(speed), float(sphere_radius), float(gravity)
    if not (m > 0 and v > 0 and R > 0 and g >= 0 and np.isfinite([m, v, R, g]).all()):
        raise ValueError("sphere_impact needs mass, speed and radius > 0 and gravity >= 0")
    if not (young > 0 and -1.0 < poisson < 0.5):
        raise ValueError("sphere_impact needs E > 0 and -1 < nu < 0.5")
    from scipy.integrate import quad
    from scipy.optimize import brentq

    e_star = young / (1.0 - poisson**2)

    def work(x: float) -> float:  # integral of F d delta from 0 to x, d delta / dx = R (atanh x + x / (1 - x^2))
        w, _ = quad(lambda t: sphere_q(t) * (math.atanh(t) + t / (1.0 - t * t)), 0.0, x, epsabs=0.0, epsrel=1e-12)
        return e_star * R**3 * w

    def speed2(x: float) -> float:
        return v * v + 2.0 * g * R * x * math.atanh(x) - 2.0 * work(x) / m

    if speed2(0.999) > 0.0:
        raise ValueError(f"sphere_impact: a {R:g} m sphere at {v:g} m/s would press deeper than a/R 0.999")
    xm = brentq(speed2, 0.0, 0.999, xtol=1e-16, rtol=1e-14)
    dm = R * xm * math.atanh(xm)
    fm = e_star * R * R * sphere_q(xm)
    # delta = dm (1 - s^2): the integrand 2 dm s / sqrt(speed2) is finite at s = 0
    half, _ = quad(lambda s: 2.0 * dm * s / math.sqrt(max(speed2(sphere_x_of_depth((1.0 - s * s) * dm / R)), 1e-300)) if s > 0 else
                   2.0 * dm / math.sqrt(dm * (2.0 * fm / m - 2.0 * g)), 0.0, 1.0, epsabs=0.0, epsrel=1e-9, limit=200)
    return HertzImpact(max_depth=float(dm), max_force=float(fm), duration=float(2.0 * half))


@dataclass
class SphereContacts:
    """Result of :func:`press_spheres`.

    Attributes
    ----------
    solution : ContactSolution
        The frictionless, unilateral patch-contact solution at the final radii.
    patch_radius : (s,) ndarray
        Contact radius of each sphere [m] (consistent with its force).
    normal_force : (s,) ndarray
        Force each sphere presses with, along the inward normal [N] (>= 0).
    iterations : int
        Fixed-point iterations taken.
    """

    solution: ContactSolution
    patch_radius: np.ndarray
    normal_force: np.ndarray
    iterations: int


def press_spheres(
    gf: ElasticSource,
    triangles: Any,
    barycentric: Any,
    depths: Any,
    sphere_radii: Any,
    *,
    normals: Any = None,
    rows: Any = "all",
    tol: float = 1e-6,
    max_iter: int = 50,
    near_field: str | None = "auto",
) -> SphereContacts:
    """Rigid spheres pressed into the seat, with patches consistent with the sphere (Hertz for ``a << R``).

    Parameters
    ----------
    gf : ElasticSource
        Loaded bundle (its ``young`` and ``poisson`` size the patches).
    triangles : (s,) int array_like
        Surface triangle under each sphere's lowest point.
    barycentric : (s, 3) float array_like
        Barycentric coordinates of that point.
    depths : (s,) float array_like
        Indentation ``delta`` of each sphere's lowest point along the inward
        normal [m] (>= 0).
    sphere_radii : float or (s,) float array_like
        Sphere radii ``R`` [m] (> 0).
    normals : (s, 3) float array_like, optional
        Outward normals along which each sphere presses (default: the surface's smooth normal at
        the point, :func:`hailstorm.runtime.contact.normals.smooth_normals`; a triangle's own
        normal jumps between facets, and a sphere on a vertex of the 6 mm seat pressed along
        one facet's normal, 11 degrees off, came out 7.5 % softer than on a 3 mm seat).
    rows : "all", None or (r,) int array_like
        Where to evaluate the surface displacement (see :func:`hailstorm.runtime.solve_contacts`).
    tol : float
        Relative change of the radii at which the iteration stops (the fixed point
        ``a = sphere_radius(F(a))``; an update that overshoots is damped).
    max_iter : int
        Bound on the iterations.
    near_field : {"auto", "layer", "halfspace", "none"} or None
        Resolve contacts smaller than the surface elements at their own scale
        (:mod:`hailstorm.runtime.contact.near_field`): each sphere's Hertz disc
        gets its own compliance in place of the mesh's near field, and the
        sphere's profile is followed over its own disc (:func:`sphere_offset`).
        "auto" (default): the layer kernel on a bundle of hat-load columns (the
        default seat's); "halfspace": the half-space's kernel alone; "none": the
        discrete model (the patch as the mesh resolves it).

    Returns
    -------
    SphereContacts

    Raises
    ------
    ValueError
        Negative depths, non-positive radii, shape mismatch (and everything
        :func:`hailstorm.runtime.solve_contacts` refuses).
    RuntimeError
        If the radii do not converge within ``max_iter`` iterations.
    """
    t = np.asarray(triangles, dtype=np.intp).reshape(-1)
    s = t.size
    d = np.asarray(depths, dtype=np.float64).reshape(-1)
    R = np.broadcast_to(np.asarray(sphere_radii, dtype=np.float64), (s,)).copy() if s else np.zeros(0)
    if d.shape != (s,):
        raise ValueError(f"depths must have shape ({s},) to match triangles, got {d.shape}")
    if not (np.isfinite(d).all() and np.all(d >= 0)):
        raise ValueError("depths must be finite and >= 0 (indentation along the inward normal)")
    if not (np.isfinite(R).all() and np.all(R > 0)):
        raise ValueError("sphere radii must be finite and > 0")
    if normals is None:
        if t.size and (t.min() < 0 or t.max() >= len(gf.triangles)):
            raise IndexError("triangle index out of range")
        bary = np.asarray(barycentric, dtype=np.float64)
        if bary.shape != (s, 3):
            raise ValueError(f"barycentric must have shape ({s}, 3), got {bary.shape}")
        n = smooth_normals(np.asarray(gf.vertices), np.asarray(gf.triangles), t, bary)
    else:
        n = np.asarray(normals, dtype=np.float64).reshape(s, 3)
    E, nu = float(gf.young), float(gf.poisson)
    a = np.minimum(np.sqrt(R * d), 0.99 * R)  # the geometric Hertz radius: the start of the iteration
    X = contact_points(np.asarray(gf.vertices), np.asarray(gf.triangles), t, barycentric)
    near = resolve_near_field(gf, near_field)
    lo, hi = np.full(s, -np.inf), np.full(s, np.inf)  # per sphere: radii below / above its fixed point
    for it in range(1, max_iter + 1):
        off = np.zeros(s)
        if near is not None:
            off = sphere_offset(a, R)  # the sphere over its own disc (resolved at its scale)
        elif np.any(a > 0):
            verts, w = patch_weights(gf, t, barycentric, a, n)
            off = sphere_mean_offset(np.asarray(gf.vertices), verts, w, X, n, a, R)
        ubar = -(d - off)[:, None] * n
        sol = solve_contacts(gf, t, barycentric, ubar, mode="frictionless", unilateral=True, normals=n,
                             rows=rows, patch_radius=np.maximum(a, 0.0), near_field=near)
        fn = np.clip(-np.einsum("ki,ki->k", sol.forces, n), 0.0, None)
        a_new = sphere_radius(fn, R, E, nu)
        scale = np.maximum(a, np.finfo(float).tiny)
        if np.all(np.abs(a_new - a) <= tol * scale):
            return SphereContacts(solution=sol, patch_radius=a_new, normal_force=fn, iterations=it)
        # a patch that grows stiffens the contact and lowers its force, hence its radius. The
        # plain update a <- a_new can overshoot and cycle for ever (seen: a 12.5 mm stone 10.6 mm deep
        # on the 15 mm and 3 mm seats), and where the patch's vertex set changes at the fixed point
        # F(a) jumps there by more than tol. So once a sphere's residual has changed sign its radius
        # is bracketed and bisected: the fixed point (or the jump) is then pinned to tol.
        delta = a_new - a
        lo = np.where(delta > 0, np.maximum(lo, a), lo)
        hi = np.where(delta < 0, np.minimum(hi, a), hi)
        bracketed = np.isfinite(lo) & np.isfinite(hi)
        if np.all((np.abs(delta) <= tol * scale) | bracketed & (hi - lo <= tol * scale)):
            return SphereContacts(solution=sol, patch_radius=a, normal_force=fn, iterations=it)
        a = a_new.copy()
        a[bracketed] = 0.5 * (lo[bracketed] + hi[bracketed])
    raise RuntimeError(f"press_spheres: the contact radii did not converge in {max_iter} iterations")
