"""Patch contacts against Hertz on a graded block that stands in for a half-space.

``python -m studies.hertz_study [--fine 3.5e-4 2.5e-4 ...]`` builds
the block of :func:`hailstorm.precompute.halfspace.halfspace_block` at each
fine element size (cached in ``HAILSTORM_CACHE``) and prints, per block:

* a rigid sphere's force-indentation (:func:`hailstorm.runtime.contact.hertz.press_spheres`)
  against ``F = (4/3) E* sqrt(R) delta^(3/2)`` for ``delta / R`` = 0.01 ... 0.04;
* a storm's stone at rest under gravity (exact integrator, patch
  contacts): its depth against Hertz's at ``m g``, and its force against ``m g``;
* a storm's stone dropped on the block (restitution 1): peak force, maximum
  indentation and contact duration against Hertz's quasi-static impact
  (:func:`hailstorm.runtime.contact.hertz.hertz_impact`, with gravity), and against the
  law the storm's patch is on an ideal half-space (:func:`affine_oscillator`).

The helpers are what ``tests/test_hertz.py`` asserts.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from hailstorm.runtime.storm.hail import GRAVITY
from hailstorm.runtime.contact.sphere_patch import hertz_radius
from hailstorm.runtime.contact.hertz import HertzImpact, hertz_force, hertz_impact, press_spheres

__all__ = ["BLOCK", "DropResult", "block_bundle", "drop_stone", "force_ratios", "hertz_depth", "origin_contact",
           "rest_stone", "affine_oscillator", "main"]

#: the block's material and the pressed sphere (E [Pa], nu, R [m])
BLOCK = dict(young=2.0e6, poisson=0.35, sphere_radius=0.01)
RATIOS = (0.01, 0.02, 0.04)


def block_bundle(out: Any, fine_size: float) -> Any:
    """Build (or reuse) the P1 bundle of the graded half-space block with ``fine_size`` under the load.

    Parameters
    ----------
    out : path or None
        Bundle directory (``None``: the cache).
    fine_size : float
        Element size under the load [m].

    Returns
    -------
    GreensFunctions
    """
    import hailstorm.runtime
    from hailstorm.precompute import build_bundle
    from hailstorm.precompute.halfspace import halfspace_block

    mesh = halfspace_block(fine_size=fine_size)
    return hailstorm.runtime.load(build_bundle(out, mesh=mesh, order=1, young=BLOCK["young"],
                                               poisson=BLOCK["poisson"]))


def origin_contact(gf: Any) -> tuple[int, np.ndarray]:
    """The top-face triangle holding the origin and the origin's barycentric coordinates."""
    V, T = np.asarray(gf.vertices), np.asarray(gf.triangles)
    for t in np.flatnonzero(np.abs(V[T][:, :, 2]).max(axis=1) < 1e-9):
        P = V[T[t], :2]
        lam = np.linalg.solve((P[:2] - P[2]).T, -P[2])
        b = np.array([lam[0], lam[1], 1.0 - lam.sum()])
        if b.min() >= -1e-12:
            b = np.clip(b, 0.0, None)
            return int(t), b / b.sum()
    raise ValueError("no top triangle holds the origin")


def force_ratios(gf: Any, ratios: tuple[float, ...] = RATIOS) -> np.ndarray:
    """``F / F_Hertz`` of a rigid sphere (``BLOCK``'s R) pressed ``delta = ratio * R`` at the origin."""
    t, b = origin_contact(gf)
    R = BLOCK["sphere_radius"]
    out = []
    for rel in ratios:
        d = rel * R
        res = press_spheres(gf, [t], [b], [d], R)
        out.append(res.normal_force[0] / hertz_force(d, R, gf.young, gf.poisson))
    return np.array(out)


def hertz_depth(force: float, sphere_radius: float, young: float, poisson: float) -> float:
    """Hertz's depth ``(3 F / (4 E* sqrt(R)))^(2/3)`` of a rigid sphere carrying ``force`` [m]."""
    return float(hertz_radius(force, sphere_radius, young, poisson)) ** 2 / sphere_radius  # delta = a^2 / R


def _storm(gf: Any, dt: float, restitution: float | None = None) -> Any:
    import hailstorm.runtime

    kw: dict[str, Any] = dict(integrator="exact", dt=dt, drag=False)
    if restitution is not None:
        kw["restitution"] = restitution
    return hailstorm.runtime.Storm(gf, hailstorm.runtime.Scene.default().with_(**kw), spawn=False)


def rest_stone(gf: Any, stone_radius: float = 0.02, steps: int = 800, dt: float = 5e-4) -> tuple[float, float, float, float]:
    """A stone let down onto the block's top by the storm (exact integrator, patch contacts).

    Returns
    -------
    depth, force, weight, patch_radius : float
        Depth of its lowest point [m], its contact force [N], ``m g`` [N] and
        its patch radius [m] once at rest (after ``steps`` steps of ``dt``).
    """
    st = _storm(gf, dt)
    st.add_stones(np.array([[1e-4, -2e-4, stone_radius + 1e-4]]), np.zeros((1, 3)), np.array([stone_radius]))
    for _ in range(steps):
        st.step()
    _, f = st.contact_forces()
    return (stone_radius - float(st.pos[0, 2]), float(np.linalg.norm(f)), float(st.mass[0]) * GRAVITY,
            float(st.crad[0]))


def affine_oscillator(mass: float, speed: float, stiffness: float, offset: float,
                      gravity: float = GRAVITY) -> HertzImpact:
    """The impact of a mass on the storm's patch law ``F = k (delta - o)`` for ``delta > o``
    (0 above), under gravity, from first touch (``delta = 0``) at ``speed`` to release.

    Through the dead zone the mass falls freely to ``v1 = sqrt(v^2 + 2 g o)`` (taking
    ``(v1 - v) / g``, or ``o / v`` without gravity, each way); then a linear spring of
    static deflection ``delta_s = m g / k``, ``omega = sqrt(k / m)``, amplitude
    ``A = sqrt(delta_s^2 + (v1 / omega)^2)``: ``delta_max = o + delta_s + A``,
    ``F_max = k (delta_s + A)``, and ``(pi + 2 asin(delta_s / A)) / omega`` in the spring.

    On a half-space at the radius ``a`` of its own peak force (``k = 5 E* a / 3``, the Hertz
    disc's, and ``o = a^2 / (5 R)``), without gravity, this is Hertz's impact in
    ``delta_max`` and ``F_max`` exactly and 0.990 of its duration
    (``tests/runtime/contact/test_hertz.py``).
    """
    ds = mass * gravity / stiffness
    w = math.sqrt(stiffness / mass)
    v1 = math.sqrt(speed**2 + 2.0 * gravity * offset)
    A = math.hypot(ds, v1 / w)
    dead = (v1 - speed) / gravity if gravity > 0 else offset / speed
    return HertzImpact(max_depth=offset + ds + A, max_force=stiffness * (ds + A),
                       duration=2.0 * dead + (math.pi + 2 * math.asin(ds / A)) / w)


@dataclass(frozen=True)
class DropResult:
    """A stone dropped on the block by the storm (:func:`drop_stone`) and its references.

    Attributes
    ----------
    storm : HertzImpact
        What the storm gave (peak indentation, peak force, contact duration).
    hertz : HertzImpact
        Hertz's quasi-static impact at the same mass, speed and radius, with gravity.
    affine : HertzImpact
        The storm's law on an ideal half-space (:func:`affine_oscillator`) at the
        storm's patch radius ``a`` and offset ``o``: ``k = 5 E* a / 3``, the Hertz
        disc's stiffness.
    patch_radius : float
        The storm's patch radius during the impact [m].
    speed : float
        Speed at first touch [m/s].
    rebound : float
        Speed at release over ``speed``.
    """

    storm: HertzImpact
    hertz: HertzImpact
    affine: HertzImpact
    patch_radius: float
    offset: float
    speed: float
    rebound: float


def drop_stone(gf: Any, stone_radius: float = 0.01, speed: float = 0.4, dt: float = 2e-5) -> DropResult:
    """One stone dropped on the block's top at ``speed`` by the storm (exact integrator,
    patch contacts, restitution 1, no drag). Its duration runs from the sphere's first touch
    of the top to its leaving it (the dead zone of the patch law included)."""
    st = _storm(gf, dt, restitution=1.0)
    gap = 1e-6
    st.add_stones(np.array([[1e-4, -2e-4, stone_radius + gap]]), np.array([[0.0, 0.0, -speed]]),
                  np.array([stone_radius]))
    m = float(st.mass[0])
    v = math.sqrt(speed**2 + 2 * GRAVITY * gap)
    ref = hertz_impact(m, v, stone_radius, gf.young, gf.poisson, gravity=GRAVITY)
    t, d, f, a, vz, off = [0.0], [-gap], [0.0], [0.0], [-speed], [0.0]
    while len(t) < 10 * ref.duration / dt:
        st.step()
        _, fs = st.contact_forces()
        t.append(st.t)
        d.append(stone_radius - float(st.pos[0, 2]))
        f.append(float(np.linalg.norm(fs)) if len(fs) else 0.0)
        a.append(float(st.crad[0]))
        off.append(float(st.stones.offset[0]))
        vz.append(float(st.vel[0, 2]))
        if d[-2] > 0 >= d[-1]:
            break
    else:
        raise RuntimeError("drop_stone: the stone did not leave the block")
    T, D = np.array(t), np.array(d)
    i0 = int(np.flatnonzero(D > 0)[0])
    i1 = len(D) - 1

    def crossing(i: int) -> float:  # where the depth crosses 0 between steps i - 1 and i (linear)
        return float(T[i - 1] - D[i - 1] * (T[i] - T[i - 1]) / (D[i] - D[i - 1]))

    storm = HertzImpact(max_depth=float(D.max()), max_force=float(max(f)), duration=crossing(i1) - crossing(i0))
    radius, offset = float(max(a)), float(max(off))
    k = 5.0 / 3.0 * gf.young / (1.0 - gf.poisson**2) * radius
    return DropResult(storm=storm, hertz=ref, affine=affine_oscillator(m, v, k, offset), patch_radius=radius,
                      offset=offset, speed=v, rebound=vz[-1] / v)


def main(argv: list[str] | None = None) -> None:
    """Print the Hertz figures of the graded blocks (module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--fine", type=float, nargs="+", default=[3.5e-4, 2.5e-4, 1.77e-4],
                    help="fine element sizes of the blocks [m]")
    ap.add_argument("--speed", type=float, default=0.4, help="drop speed of the impact [m/s]")
    args = ap.parse_args(argv)
    E, nu, R = BLOCK["young"], BLOCK["poisson"], BLOCK["sphere_radius"]
    print(f"graded half-space block, P1, E = {E:g} Pa, nu = {nu}; rigid sphere R = {R * 1e3:g} mm")
    print(" fine [mm] | F/F_Hertz at delta/R = " + " / ".join(f"{r:g}" for r in RATIOS)
          + " | rest (20 mm stone): depth/Hertz, force/mg | drop: storm/Hertz dmax, Fmax, t_c"
            " | storm/affine dmax, Fmax, t_c | a [mm]")
    for h in args.fine:
        gf = block_bundle(None, h)
        fr = force_ratios(gf)
        depth, force, mg, _ = rest_stone(gf)
        dr = drop_stone(gf, speed=args.speed)
        s, hz, sc = dr.storm, dr.hertz, dr.affine
        print(f" {h * 1e3:9.3f} | " + " / ".join(f"{x:.3f}" for x in fr)
              + f" | {depth / hertz_depth(mg, 0.02, E, nu):.3f}, {force / mg:.4f}"
              + f" | {s.max_depth / hz.max_depth:.3f}, {s.max_force / hz.max_force:.3f}, {s.duration / hz.duration:.3f}"
              + f" | {s.max_depth / sc.max_depth:.3f}, {s.max_force / sc.max_force:.3f}, {s.duration / sc.duration:.3f}"
              + f" | {dr.patch_radius * 1e3:.3f}", flush=True)
    hz = dr.hertz
    sc = dr.affine
    print(f"drop: 10 mm stone at {args.speed} m/s; Hertz (with gravity) dmax {hz.max_depth * 1e6:.1f} um, "
          f"Fmax {hz.max_force:.3f} N, t_c {hz.duration * 1e3:.3f} ms; the patch law on an ideal half-space "
          f"{sc.max_depth / hz.max_depth:.3f} / {sc.max_force / hz.max_force:.3f} / {sc.duration / hz.duration:.3f} of Hertz")


if __name__ == "__main__":
    main()
