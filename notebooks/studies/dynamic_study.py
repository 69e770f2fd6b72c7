"""A dynamic FEM peer for impacts: where the quasi-static Green's functions stop being true.

``python -m studies.dynamic_study [--full | --terminal] [--plot PATH]`` (or
``python tests/benchmarks/dynamic_peer.py``) prints, for a grid of stone radii
and impact speeds, the impact of one rigid ice sphere on the default seat's
foam pad computed twice on the same finite-element pad:

* **dynamic** -- the pad with its mass (implicit Newmark, average acceleration
  ``beta = 1/4``, ``gamma = 1/2``: unconditionally stable, no numerical
  damping), so elastic waves carry energy away from the contact;
* **quasi-static** -- the same pad without mass: its response to the contact
  forces is its static one, the storm's Green's-function assumption, and the
  sphere moves under that force with the same Newmark rule;

and Hertz's half-space impact (:func:`hailstorm.runtime.contact.hertz.hertz_impact`)
beside them. The peer itself, the pad and one impact on it, is the runtime's
(:mod:`hailstorm.runtime.inertia`: every storm runs it again for each of its impacts);
this study holds it to Hertz and to the storm, and charts where the two models agree. It compares peak force, contact duration, rebound speed (the
coefficient of restitution the elastic body itself gives) and the largest dent,
and marks where the quasi-static model is within 5 % of the dynamic peer.

The pad
-------
A disc of foam on a rigid base (the seat's shell, :mod:`hailstorm.meshes`
``saddle.geo``: the pad's underside is clamped), 15 mm thick (the saddle's
crown) and 60 mm in radius (about the half-width of a saddle's rear), of the
default seat's material (``meshes/default_scene.toml`` ``[seat]``: E = 2 MPa,
nu = 0.35). It is axisymmetric about the impact point, so the peer is a 2-D
(r, z) problem solved on a graded P1 triangle mesh with cells of a fraction of
the contact radius under the stone (scikit-fem, the weak forms weighted by
``2 pi r``). Side edge free, underside clamped, ``u_r = 0`` on the axis.

Density: flexible polyurethane foams span roughly 20-100 kg/m^3 (Gibson & Ashby,
*Cellular Solids*, 2nd ed. 1997); the default, :data:`~studies.axisymmetric.FOAM_DENSITY` = 70 kg/m^3, gives wave
speeds of 214 m/s (dilatational) and 103 m/s (shear) with E = 2 MPa. The
inertia of the pad scales with the density: ``--density`` changes it.

Contact
-------
The sphere (radius R, ice of 917 kg/m^3) is rigid and frictionless; it
touches the top surface's nodes unilaterally (node-to-sphere gap
``phi(r_i) - x - u_z,i >= 0`` with the sphere's exact profile
``phi(r) = R - sqrt(R^2 - r^2)`` at the node's undeformed radius, the small-
displacement rule of the storm and of Hertz), with Lagrange multipliers: each
step solves the linear complementarity problem of the candidate nodes'
multipliers exactly (active set on the Schur complement of the step's
effective stiffness, the sphere's own Newmark equation included). The contact
nodes' normal dofs carry no mass (Khenous, Laborde & Renard's mass
redistribution, :func:`~hailstorm.runtime.inertia.pad.without_contact_mass`: with it Newmark creates no
energy at contact and release). Gravity is
left out of both models (the comparison is of the pad's inertia alone).

Checks (tests/studies/test_dynamic_study.py): the axisymmetric mass is the
disc's mass; a slow stone on a thick block follows Hertz's quasi-static impact
(force, duration ``2.87 (m^2 / (R E*^2 v))^(1/5)``, dent); the quasi-static peer
gives back the impact speed (restitution 1) and agrees with the dynamic peer
for a slow stone.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, replace
from typing import Any, Sequence

import numpy as np

from hailstorm.runtime.contact.hertz import HertzImpact, hertz_impact
from hailstorm.runtime.inertia.impact import (
    ICE_DENSITY,
    ImpactResult,
    PeerResolutionError,
    check_density,
    hertz_estimate,
    impact_mesh,
    simulate_impact,
)
from hailstorm.runtime.inertia.pad import Pad
from hailstorm.runtime.storm.limits import ValidityLimits, contact_time_ratio
from studies.axisymmetric import FOAM_DENSITY

__all__ = [
    "ICE_DENSITY",
    "LIMIT_DENSITIES",
    "ImpactResult",
    "PeerResolutionError",
    "Row",
    "compare",
    "default_pad",
    "format_corrections",
    "format_storm",
    "format_table",
    "format_time_limit",
    "hertz_estimate",
    "impact_errors",
    "impact_mesh",
    "largest_error",
    "limit_speed",
    "main",
    "plot_agreement",
    "StormImpact",
    "pad_bundle",
    "radiation_dashpot",
    "run_grid",
    "scalar_corrections",
    "storm_impact",
    "simulate_impact",
    "terminal_speed",
    "time_ratio",
]

#: the grid of the short run and of ``--full`` (speeds [m/s], radii [m])
SMALL_SPEEDS, SMALL_RADII = (1.0, 5.0, 30.0), (0.0025, 0.0125)
FULL_SPEEDS, FULL_RADII = (1.0, 2.0, 5.0, 10.0, 20.0, 30.0), (0.0025, 0.005, 0.0075, 0.01, 0.0125)
#: agreement the table marks [-]
AGREE = 0.05
#: the foam densities of ``--limit`` [kg/m^3]: the default and the low end of what E = 2 MPa implies
LIMIT_DENSITIES = (FOAM_DENSITY, 200.0)


def default_pad(density: float = FOAM_DENSITY, **changes: float) -> Pad:
    """The default seat's foam (``meshes/default_scene.toml`` ``[seat]``) as a 15 mm pad of radius 60 mm."""
    from hailstorm.runtime.storm.scene import SeatSettings

    seat = SeatSettings.default()
    return replace(Pad(young=float(seat.young), poisson=float(seat.poisson), density=float(density)), **changes)


# ---------------------------------------------------------------------------------------------
# the comparison
# ---------------------------------------------------------------------------------------------
@dataclass
class Row:
    """One (radius, speed) of the comparison: dynamic peer, quasi-static peer, Hertz, and the
    mesh's free dofs and the pad's thickness [m]."""

    radius: float
    speed: float
    dynamic: ImpactResult
    quasi_static: ImpactResult
    hertz: HertzImpact
    dofs: int
    thickness: float

    def errors(self) -> dict[str, float]:
        """Quasi-static over dynamic, minus 1, per measure."""
        return impact_errors(self.quasi_static, self.dynamic)

    def agrees(self, tol: float = AGREE) -> bool:
        """All four measures within ``tol``."""
        return all(abs(e) <= tol for e in self.errors().values())


def impact_errors(model: ImpactResult, reference: ImpactResult) -> dict[str, float]:
    """``model`` over ``reference``, minus 1, per measure: peak force, duration, rebound, largest dent."""
    m, r = model, reference
    return {"force": m.peak_force / r.peak_force - 1, "duration": m.duration / r.duration - 1,
            "rebound": m.rebound_speed / r.rebound_speed - 1, "dent": m.max_dent / r.max_dent - 1}


def compare(pad: Pad, radius: float, speed: float, *, cells_per_radius: float = 8.0, steps_per_contact: int = 200,
            ice_density: float = ICE_DENSITY) -> Row:
    """The impact of one stone, dynamic and quasi-static on the same mesh (:func:`impact_mesh`), and Hertz's."""
    ref = hertz_estimate(pad, radius, speed, ice_density)
    mesh = impact_mesh(pad, radius, speed, cells_per_radius, ice_density)
    kw = dict(steps_per_contact=steps_per_contact, ice_density=ice_density)
    dyn = simulate_impact(mesh, radius, speed, dynamic=True, **kw)
    qs = simulate_impact(mesh, radius, speed, dynamic=False, **kw)
    return Row(radius=radius, speed=speed, dynamic=dyn, quasi_static=qs, hertz=ref, dofs=mesh.K.shape[0],
               thickness=pad.thickness)


@dataclass(frozen=True)
class StormImpact:
    """One stone's impact in the storm itself (:func:`storm_impact`).

    Attributes
    ----------
    peak_force : float
        The storm's ``max_contact_force`` [N].
    duration : float
        Time the stone's sphere is below the block's top [s] (to the step): from its first
        touch to its leaving, as the peer's contact (the storm's force lasts about 0.85 of
        it, none through the patch law's dead zone; :mod:`hailstorm.runtime.storm.contact_set`).
    rebound_speed : float
        The stone's normal speed after the contact [m/s].
    max_dent : float
        The storm's ``max_indentation_m`` [m].
    inertia : tuple of float
        The storm's inertia factors of the impact (force, duration, restitution, dent:
        :class:`hailstorm.runtime.inertia.factors.InertiaFactors`, on the pad under it at the
        scene's ``pad_density``); NaN when the storm recorded no impact.
    """

    peak_force: float
    duration: float
    rebound_speed: float
    max_dent: float
    inertia: tuple[float, float, float, float] = (math.nan,) * 4


def pad_bundle(pad: Pad, mesh_size: float = 0.006, order: int = 2, width: float = 0.12, load: str | None = None) -> Any:
    """A bundle of the pad as a square block (``width`` wide, clamped underneath) at the default
    seat's resolution (6 mm, P2, its ``load``: ``meshes/default_scene.toml`` ``[seat]``), built
    once in the cache; the storm's Green's functions of the pad."""
    import hailstorm.runtime
    from hailstorm.precompute import box_mesh, build_bundle
    from hailstorm.runtime.storm.scene import SeatSettings

    load = SeatSettings.default().load if load is None else load
    mesh = box_mesh((width, width, pad.thickness), mesh_size)
    return hailstorm.runtime.load(build_bundle(None, mesh=mesh, order=order, load=load, young=pad.young,
                                               poisson=pad.poisson, progress=False))


def storm_impact(gf: Any, radius: float, speed: float, *, dt: float = 2e-6, ice_density: float = ICE_DENSITY,
                 pad_density: float = FOAM_DENSITY) -> StormImpact:
    """One stone dropped on the middle of a block's top in a storm (the quasi-static Green's
    functions, patch contacts, the ``exact`` integrator, restitution 1: no dashpot, drag off;
    gravity stays, a 0.1-1 % change of the speed over the contact), and the storm's inertia
    factors of it at ``pad_density`` (the scene's ``[validity] pad_density``).

    The stone starts ``0.015 R`` above the top at ``speed`` straight down (the storm
    opens a contact within 1 % of the radius).
    """
    from hailstorm.runtime import Scene, Storm

    check_density("ice", ice_density)
    X = np.asarray(gf.vertices)
    top = X[:, 2].max()
    centre = np.array([0.5 * (X[:, 0].min() + X[:, 0].max()), 0.5 * (X[:, 1].min() + X[:, 1].max()), top])
    ref = hertz_impact(ice_density * 4 / 3 * math.pi * radius**3, speed, radius, float(gf.young), float(gf.poisson))
    duration = 6.0 * ref.duration
    sc = Scene.from_flat(duration=duration, stones=0, drag=False, dt=dt, integrator="exact", restitution=1.0,
                         density=ice_density, pad_density=pad_density)
    st = Storm(gf, sc, spawn=False)
    st.add_stones((centre + [0.0, 0.0, 1.015 * radius])[None, :], np.array([[0.0, 0.0, -float(speed)]]),
                  np.array([float(radius)]))
    below = 0
    for i in range(int(round(duration / dt))):
        st.step()
        if float(st.pos[0, 2]) - radius < top:
            below += 1
        elif below and st.vel[0, 2] > 0:
            break
    S = st.stats
    factors = S.validity.inertia() if S.validity is not None else None
    inertia = tuple(float(f[0]) for f in factors.astuple()) if factors is not None and factors.impacts else (math.nan,) * 4
    return StormImpact(peak_force=float(S["max_contact_force"]), duration=below * dt,
                       rebound_speed=float(st.vel[0, 2]), max_dent=float(S["max_indentation_m"]),
                       inertia=inertia)


def run_grid(pad: Pad, radii: Sequence[float], speeds: Sequence[float], **kw: Any) -> list[Row]:
    """:func:`compare` over every (radius, speed)."""
    return [compare(pad, R, v, **kw) for R in radii for v in speeds]


def format_table(rows: Sequence[Row], tol: float = AGREE) -> str:
    """The quasi-static-vs-dynamic table (one line per impact) and where they agree within ``tol``."""
    head = (f"{'R mm':>5} {'v m/s':>5} | {'F dyn N':>8} {'F qs':>8} {'dF%':>6} | {'t dyn ms':>8} {'t qs':>6} {'dt%':>6} | "
            f"{'e dyn':>5} {'e qs':>5} {'de%':>6} | {'dent dyn mm':>11} {'qs':>6} {'dd%':>6} | "
            f"{'Hertz F':>7} {'t':>5} {'dent':>5} | {'a/R':>4} {'dent/h':>6} | within {tol:.0%}")
    lines = [head, "-" * len(head)]
    for row in rows:
        d, q, h, e = row.dynamic, row.quasi_static, row.hertz, row.errors()
        lines.append(
            f"{row.radius * 1e3:5.1f} {row.speed:5.1f} | {d.peak_force:8.3f} {q.peak_force:8.3f} {100 * e['force']:+6.1f} | "
            f"{d.duration * 1e3:8.3f} {q.duration * 1e3:6.3f} {100 * e['duration']:+6.1f} | "
            f"{d.restitution:5.3f} {q.restitution:5.3f} {100 * e['rebound']:+6.1f} | "
            f"{d.max_dent * 1e3:11.3f} {q.max_dent * 1e3:6.3f} {100 * e['dent']:+6.1f} | "
            f"{h.max_force:7.2f} {h.duration * 1e3:5.2f} {h.max_depth * 1e3:5.2f} | "
            f"{d.max_contact_radius / row.radius:4.2f} {d.max_dent / row.thickness:6.2f} | "
            f"{'yes' if row.agrees(tol) else 'no'}")
    return "\n".join(lines)


def _ice_time_ratio(radius: float, speed: float, thickness: float, pad: Pad, ice_density: float) -> float:
    """``t_c / T`` of an ice sphere (:func:`hailstorm.runtime.storm.limits.contact_time_ratio`)."""
    m = ice_density * 4.0 / 3.0 * math.pi * radius**3
    return float(contact_time_ratio(m, radius, speed, thickness, pad.young, pad.poisson, pad.density))


def time_ratio(row: Row, pad: Pad, ice_density: float = ICE_DENSITY) -> float:
    """The storm's contact-time measure of the row's impact, ``t_c / T``
    (:func:`hailstorm.runtime.storm.limits.contact_time_ratio` at the row's pad thickness)."""
    return _ice_time_ratio(row.radius, row.speed, row.thickness, pad, ice_density)


def limit_speed(radius: float, pad: Pad, limit: float = ValidityLimits.contact_time,
                ice_density: float = ICE_DENSITY) -> float:
    """The impact speed [m/s] at which a stone of ``radius`` on ``pad`` meets the storm's contact-time
    limit, ``t_c / T = limit``: slower impacts are within it (Hertz's ``t_c`` goes as ``v^(-1/5)``)."""
    return (_ice_time_ratio(radius, 1.0, pad.thickness, pad, ice_density) / limit) ** 5


def largest_error(row: Row) -> tuple[str, float]:
    """The measure the quasi-static model misses most on, and by how much (quasi-static / dynamic - 1)."""
    return max(row.errors().items(), key=lambda kv: abs(kv[1]))


def format_time_limit(grids: Sequence[tuple[Pad, Sequence[Row]]], limit: float = ValidityLimits.contact_time,
                      tol: float = AGREE) -> str:
    """Every impact of ``grids`` (pads and their rows) sorted by the storm's ``t_c / T``
    (:func:`time_ratio`), with the quasi-static model's largest error, and whether the
    limit ``t_c / T >= limit`` separates the impacts within ``tol`` of the peer from the others."""
    rows = sorted(((time_ratio(r, pad), pad, r) for pad, rs in grids for r in rs), key=lambda x: x[0])
    head = f"{'rho kg/m^3':>10} {'R mm':>5} {'v m/s':>5} | {'t_c/T':>5} | {'worst error':>18} | within {tol:.0%} | within the limit"
    lines = [head, "-" * len(head)]
    for tr, pad, r in rows:
        name, err = largest_error(r)
        lines.append(f"{pad.density:10.0f} {r.radius * 1e3:5.1f} {r.speed:5.1f} | {tr:5.2f} | {name:>9} {100 * err:+7.1f} % | "
                     f"{'yes' if r.agrees(tol) else 'no':>9} | {'yes' if tr >= limit else 'no'}")
    inside = [abs(largest_error(r)[1]) for tr, _, r in rows if tr >= limit]
    bad = [tr for tr, _, r in rows if not r.agrees(tol)]
    lines.append(f"t_c/T >= {limit:g} (the storm's limit): {len(inside)} of {len(rows)} impacts, the largest error of the "
                 f"four measures {100 * max(inside, default=0.0):.1f} %")
    lines.append(f"beyond {tol:.0%} of the peer on some measure: {len(bad)} impacts, t_c/T up to {max(bad, default=0.0):.2f}"
                 f" -> the limit {'separates them' if max(bad, default=0.0) < limit else 'does NOT separate them'}")
    return "\n".join(lines)


def format_storm(rows: Sequence[Row], gf: Any, density: float = FOAM_DENSITY) -> str:
    """The same impacts in the storm (:func:`storm_impact` on ``gf``) against the dynamic peer
    (``vs dyn``) and against the peer's quasi-static column (``vs qs``: the storm's own
    discretisation, the same model on a converged mesh); then the storm's figures times its
    inertia factors at the pad's ``density`` (what its summary's ``max_impact_force_dynamic_N``
    is of the peak force) against the dynamic peer."""
    head = (f"storm on a {np.ptp(np.asarray(gf.vertices)[:, 0]) * 1e3:.0f} mm block bundle "
            f"({len(gf.vertices)} surface vertices, P{gf.order}, {gf.manifest.get('options', {}).get('load', 'point')} "
            f"loads), quasi-static Green's functions, restitution 1:\n"
            f"{'R mm':>5} {'v m/s':>5} | {'F storm N':>9} {'vs dyn':>7} {'vs qs':>7} | {'t storm ms':>10} {'vs dyn':>7} "
            f"{'vs qs':>7} | {'e storm':>7} {'vs dyn':>7} | {'dent storm mm':>13} {'vs dyn':>7} {'vs qs':>7}")
    lines = [head]

    def rel(a: float, b: float) -> str:
        return f"{100 * (a / b - 1):+6.1f}%"

    impacts = [storm_impact(gf, row.radius, row.speed, pad_density=density) for row in rows]
    for row, st in zip(rows, impacts):
        d, q = row.dynamic, row.quasi_static
        e = st.rebound_speed / row.speed
        lines.append(f"{row.radius * 1e3:5.1f} {row.speed:5.1f} | {st.peak_force:9.3f} {rel(st.peak_force, d.peak_force)} "
                     f"{rel(st.peak_force, q.peak_force)} | {st.duration * 1e3:10.3f} {rel(st.duration, d.duration)} "
                     f"{rel(st.duration, q.duration)} | {e:7.3f} {rel(e, d.restitution)} | "
                     f"{st.max_dent * 1e3:13.3f} {rel(st.max_dent, d.max_dent)} {rel(st.max_dent, q.max_dent)}")
    lines.append(f"the storm with the pad's inertia (its figures times its inertia factors at {density:g} kg/m^3, "
                 "the pad under the impact run dynamic and quasi-static), against the dynamic peer:")
    lines.append(f"{'R mm':>5} {'v m/s':>5} | {'F factor':>8} {'F dyn est N':>11} {'vs dyn':>7} | {'t est ms':>8} "
                 f"{'vs dyn':>7} | {'e est':>6} {'vs dyn':>7} | {'dent est mm':>11} {'vs dyn':>7}")
    for row, st in zip(rows, impacts):
        d = row.dynamic
        fF, ft, fe, fd = st.inertia
        F, t, e, dent = st.peak_force * fF, st.duration * ft, st.rebound_speed / row.speed * fe, st.max_dent * fd
        lines.append(f"{row.radius * 1e3:5.1f} {row.speed:5.1f} | {fF:8.3f} {F:11.3f} {rel(F, d.peak_force)} | "
                     f"{t * 1e3:8.3f} {rel(t, d.duration)} | {e:6.3f} {rel(e, d.restitution)} | "
                     f"{dent * 1e3:11.3f} {rel(dent, d.max_dent)}")
    return "\n".join(lines)


def scalar_corrections(rows: Sequence[Row]) -> list[dict[str, float]]:
    """What a one-number correction of the quasi-static contact, matched to the peer's peak force,
    would predict for the other three measures, per row (ratios dynamic / quasi-static).

    With Hertz's impact scalings (``F ~ k^(2/5) m^(3/5) v^(6/5)``, ``t ~ k^(-2/5) m^(2/5) v^(-1/5)``,
    ``dent ~ k^(-2/5) m^(2/5) v^(4/5)``): a *pad stiffness factor* ``s = f^(5/2)`` (``f`` the peer's
    force ratio) predicts ``t = 1/f``, ``dent = 1/f`` and no loss; an *added pad mass* picked up at the
    touch and left behind at the release (``r = (m + m_p)/m = f^(-5/3)``) predicts ``t = 1/f``,
    ``dent = f^(2/3)`` and ``e = f^(5/3)``.

    Returns
    -------
    list of dict
        Per row: ``R_mm``, ``v``, the peer's ``f``, ``t``, ``dent``, ``e`` and each model's predicted
        ``t``, ``dent``, ``e`` (keys ``stiff_*``, ``mass_*``).
    """
    out = []
    for r in rows:
        d, q = r.dynamic, r.quasi_static
        f = d.peak_force / q.peak_force
        out.append({"R_mm": r.radius * 1e3, "v": r.speed, "f": f, "t": d.duration / q.duration,
                    "dent": d.max_dent / q.max_dent, "e": d.restitution / q.restitution,
                    "stiff_t": 1 / f, "stiff_dent": 1 / f, "stiff_e": 1.0,
                    "mass_t": 1 / f, "mass_dent": f ** (2 / 3), "mass_e": f ** (5 / 3)})
    return out


def radiation_dashpot(pad: Pad, radius: float, speed: float, ice_density: float = ICE_DENSITY) -> dict[str, float]:
    """What a radiation dashpot predicts, as ratios (with / without it) of peak force, contact time,
    largest dent and rebound speed: the rigid sphere's own law on a half-space of the pad's material
    (:func:`hailstorm.runtime.contact.hertz.sphere_force`) with, in parallel, the dashpot of a rigid
    disc of the current contact radius ``a`` vibrating on an elastic half-space,
    ``C = 3.4 a^2 sqrt(rho G) / (1 - nu)`` (Lysmer's analog; Lysmer & Richart, *J. Soil Mech. Found.
    Div.* 92 (1966) 65), the total force floored at 0. No fitted parameter: the pad's density,
    modulus and Poisson ratio only. Integrated (``solve_ivp``, release when the dent returns to 0).
    """
    from scipy.integrate import solve_ivp

    from hailstorm.runtime.compiled.sphere import sphere_q, sphere_x_of_depth

    R, E, nu = float(radius), pad.young, pad.poisson
    e_star = E / (1.0 - nu**2)
    m = ice_density * 4.0 / 3.0 * math.pi * R**3
    c0 = 3.4 * math.sqrt(pad.density * E / (2.0 * (1.0 + nu))) / (1.0 - nu)

    def law(d: float) -> tuple[float, float]:  # (force, contact radius) of the sphere at depth d
        x = sphere_x_of_depth(d / R)
        return e_star * R * R * sphere_q(x), x * R

    def run(damped: bool) -> tuple[float, float, float, float]:
        def force(y):
            f, a = law(y[0])
            return max(f + (c0 * a * a * y[1] if damped else 0.0), 0.0)

        def released(t, y):
            return y[0] + 1e-15 * (t == 0.0)
        released.terminal, released.direction = True, -1
        t_h = hertz_impact(m, speed, R, E, nu).duration
        sol = solve_ivp(lambda t, y: [y[1], -force(y) / m], (0.0, 10 * t_h), [0.0, speed], events=released,
                        rtol=1e-9, atol=1e-14, max_step=t_h / 400)
        peak = float(max(force(y) for y in sol.y.T))
        return peak, float(sol.t_events[0][0]), float(sol.y[0].max()), float(-sol.y_events[0][0][1])

    bare, damped = run(False), run(True)
    return {"f": damped[0] / bare[0], "t": damped[1] / bare[1], "dent": damped[2] / bare[2],
            "e": damped[3] / bare[3]}


def format_corrections(rows: Sequence[Row], pad: Pad | None = None) -> str:
    """:func:`scalar_corrections` as a table: the peer's ratios, each model's, and its worst miss; with
    ``pad``, also :func:`radiation_dashpot`'s ratios (``dash``) and their worst miss of the peer's."""
    c = scalar_corrections(rows)
    dash = [radiation_dashpot(pad, r.radius, r.speed) for r in rows] if pad is not None else None
    lines = [" R mm v m/s |  F d/q | t d/q  stiff   mass | dent d/q  stiff   mass | e d/q  stiff   mass",
             "-" * 92]
    for x in c:
        lines.append(f"{x['R_mm']:5.1f} {x['v']:5.1f} | {x['f']:6.3f} | {x['t']:5.3f} {x['stiff_t']:6.3f} "
                     f"{x['mass_t']:6.3f} | {x['dent']:8.3f} {x['stiff_dent']:6.3f} {x['mass_dent']:6.3f} | "
                     f"{x['e']:5.3f} {x['stiff_e']:6.3f} {x['mass_e']:6.3f}")
    for name in ("stiff", "mass"):
        miss = {k: max(abs(x[f"{name}_{k}"] / x[k] - 1) for x in c) for k in ("t", "dent", "e")}
        label = "pad stiffness factor" if name == "stiff" else "added pad mass"
        lines.append(f"{label}, matched to the peak force: worst miss of the peer's contact time "
                     f"{100 * miss['t']:.1f} %, dent {100 * miss['dent']:.1f} %, restitution {100 * miss['e']:.1f} %")
    if dash is not None:
        lines.append("radiation dashpot (Lysmer's, half-space; no fitted parameter), its ratios with / without it:")
        lines.append(" R mm v m/s |  F d/q   dash | t d/q   dash | dent d/q   dash | e d/q   dash")
        for x, y in zip(c, dash):
            lines.append(f"{x['R_mm']:5.1f} {x['v']:5.1f} | {x['f']:6.3f} {y['f']:6.3f} | {x['t']:5.3f} {y['t']:6.3f} | "
                         f"{x['dent']:8.3f} {y['dent']:6.3f} | {x['e']:5.3f} {y['e']:6.3f}")
        miss = {k: max(abs(y[k] / x[k] - 1) for x, y in zip(c, dash)) for k in ("f", "t", "dent", "e")}
        lines.append(f"radiation dashpot: worst miss of the peer's peak force {100 * miss['f']:.1f} %, contact time "
                     f"{100 * miss['t']:.1f} %, dent {100 * miss['dent']:.1f} %, restitution {100 * miss['e']:.1f} %")
    return "\n".join(lines)


def terminal_speed(radius: float) -> float:
    """The terminal fall speed of a stone of the default scene's hail (``[hail]``: density, drag) [m/s]."""
    from hailstorm.runtime.storm.scene import Scene
    from hailstorm.runtime.storm.hail import terminal_velocity

    hail = Scene.default().hail
    return float(terminal_velocity(radius, cd=hail.cd, rho_air=hail.rho_air, density=hail.density))


def plot_agreement(rows: Sequence[Row], path: str, tol: float = AGREE, density: float | None = None) -> str:
    """Chart of where the quasi-static model is within ``tol`` of the dynamic peer.

    One square per (radius, speed) of ``rows``: green where all four measures (peak
    force, contact duration, rebound speed, largest dent) are within ``tol``, red where
    one is not, labelled with the worst measure's error; the terminal fall speed of the
    default scene's hail (:func:`terminal_speed`) is drawn over it, and the radii of its
    storm (``[hail] r_min``-``r_max``) shaded, and with ``density`` the storm's contact-time limit
    (:func:`limit_speed`). Written to ``path`` (PNG, or what its
    suffix says); returns ``path``.
    """
    import os

    import matplotlib

    from studies import record

    if "MPLBACKEND" not in os.environ:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    from hailstorm.runtime.storm.scene import Scene

    if not rows:
        raise ValueError("plot_agreement needs at least one row")
    names = {"force": "F", "duration": "t", "rebound": "e", "dent": "dent"}
    hail = Scene.default().hail
    fig, ax = plt.subplots(figsize=(7.5, 6.0), layout="constrained")
    ax.axvspan(hail.r_min * 1e3, hail.r_max * 1e3, color="0.93", zorder=0,
               label=f"the default storm's radii ({hail.r_min * 1e3:g}-{hail.r_max * 1e3:g} mm)")
    radii = np.array([r.radius for r in rows])
    speeds = np.array([r.speed for r in rows])
    R = np.linspace(min(radii.min(), hail.r_min) * 0.8, max(radii.max(), hail.r_max) * 1.1, 200)
    ax.plot(R * 1e3, [terminal_speed(x) for x in R], color="0.2", lw=1.5, zorder=1,
            label=f"terminal fall speed of the scene's hail (C_d = {hail.cd:g}, air {hail.rho_air:g} kg/m³)")
    if density is not None:  # the storm's contact-time limit on this pad: within it below the line
        pad = default_pad(density, thickness=rows[0].thickness)
        lim = ValidityLimits.contact_time
        ax.plot(R * 1e3, [limit_speed(x, pad, lim) for x in R], color="#377eb8", lw=1.5, ls="--", zorder=1,
                label=f"the storm's contact-time limit t_c/T = {lim:g}: within it below")
    for row in rows:
        err = row.errors()
        worst = max(err, key=lambda k: abs(err[k]))
        ok = row.agrees(tol)
        ax.scatter([row.radius * 1e3], [row.speed], marker="s", s=760, zorder=2,
                   color="#4daf4a" if ok else "#e41a1c", edgecolors="k", linewidths=0.5)
        ax.annotate(f"{names[worst]}\n{100 * err[worst]:+.1f}%", (row.radius * 1e3, row.speed), ha="center",
                    va="center", fontsize=7, zorder=3, color="k" if ok else "w")
    ax.set_yscale("log")
    ax.set_ylim(speeds.min() / 1.5, speeds.max() * 1.5)
    ax.set_xlim(R[0] * 1e3, R[-1] * 1e3)
    ax.set_xlabel("stone radius R [mm]")
    ax.set_ylabel("impact speed v [m/s]")
    from matplotlib.ticker import FixedLocator, NullLocator, StrMethodFormatter

    lo, hi = ax.get_ylim()
    ax.yaxis.set_major_locator(FixedLocator([t for t in (0.5, 1, 2, 5, 10, 20, 30, 50, 100) if lo <= t <= hi]))
    ax.yaxis.set_major_formatter(StrMethodFormatter("{x:g}"))
    ax.yaxis.set_minor_locator(NullLocator())
    rho = f" (foam {density:g} kg/m³)" if density is not None else ""
    ax.set_title(f"Quasi-static model against the dynamic peer{rho}:\nall four measures (peak force, contact time, "
                 f"rebound, dent) within {tol:.0%}?", fontsize=9)
    handles, _ = ax.get_legend_handles_labels()
    handles += [Line2D([], [], ls="", label="label: the largest of the four errors, quasi-static / dynamic - 1\n"
                                            "(F peak force, t contact time, e rebound, dent)"),
                Line2D([], [], ls="", marker="s", ms=9, mfc="#4daf4a", mec="k", label=f"within {tol:.0%}"),
                Line2D([], [], ls="", marker="s", ms=9, mfc="#e41a1c", mec="k", label=f"beyond {tol:.0%}")]
    fig.legend(handles=handles, fontsize=7.5, loc="outside lower center", ncol=2, frameon=False)
    record.save_figure(fig, path)
    return path


def main(argv: list[str] | None = None) -> int:
    """Print the quasi-static-vs-dynamic table (the small grid; ``--full``: the whole grid)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--full", action="store_true", help="speeds 1-30 m/s x radii 2.5-12.5 mm (6 x 5)")
    ap.add_argument("--density", type=float, default=FOAM_DENSITY, help="foam density [kg/m^3]")
    ap.add_argument("--terminal", action="store_true",
                    help="each radius at its terminal fall speed (the default scene's hail: the default storm's impacts)")
    ap.add_argument("--storm", action="store_true",
                    help="also one stone in the storm on a block bundle of the pad (6 mm, P2; built once in the cache)")
    ap.add_argument("--speeds", type=float, nargs="*", default=None, help="impact speeds [m/s]")
    ap.add_argument("--radii", type=float, nargs="*", default=None, help="stone radii [m]")
    ap.add_argument("--steps-per-contact", type=int, default=200)
    ap.add_argument("--cells-per-radius", type=float, default=8.0)
    ap.add_argument("--corrections", action="store_true",
                    help="also what a one-number correction matched to the peak force would predict (scalar_corrections)")
    ap.add_argument("--limit", action="store_true",
                    help="the whole grid at 70 and 200 kg/m^3, sorted by the storm's contact-time measure t_c/T "
                         "(the measured limit of docs/validity.md) instead of the table")
    ap.add_argument("--plot", default=None, metavar="PATH",
                    help="also chart the rows: within/beyond 5%% on all four measures, over the terminal-speed curve")
    args = ap.parse_args(argv)
    try:
        pad = default_pad(check_density("foam", args.density))
    except ValueError as exc:
        ap.error(str(exc))  # one line, exit 2
    speeds = args.speeds or (FULL_SPEEDS if args.full or args.limit else SMALL_SPEEDS)
    radii = args.radii or (FULL_RADII if args.full or args.limit else SMALL_RADII)
    cp, cs = pad.wave_speeds
    print(f"pad: E = {pad.young:g} Pa, nu = {pad.poisson:g}, rho = {pad.density:g} kg/m^3, {pad.thickness * 1e3:g} mm "
          f"thick, radius {pad.radius * 1e3:g} mm on a rigid base; waves {cp:.0f} m/s (P), {cs:.0f} m/s (S)")
    print(f"stone: rigid ice sphere, {ICE_DENSITY:g} kg/m^3, frictionless, no gravity; Newmark average acceleration, "
          f"{args.steps_per_contact} steps per Hertz contact time, {args.cells_per_radius:g} cells per Hertz radius")
    try:
        kw = dict(cells_per_radius=args.cells_per_radius, steps_per_contact=args.steps_per_contact)
        if args.limit:
            pads = [default_pad(rho) for rho in LIMIT_DENSITIES]
            print("the same pad at " + " and ".join(f"rho = {p.density:g} kg/m^3 (waves {p.wave_speeds[0]:.0f}, "
                                                     f"{p.wave_speeds[1]:.0f} m/s)" for p in pads)
                  + "; t_c/T: Hertz's contact time over 4 h / c_s (the storm's measure, docs/validity.md)")
            print(format_time_limit([(p, run_grid(p, radii, speeds, **kw)) for p in pads]))
            return 0
        if args.terminal:
            rows = [compare(pad, R, float(terminal_speed(R)), **kw) for R in radii]
        else:
            rows = run_grid(pad, radii, speeds, **kw)
    except ValueError as exc:  # a bad radius or speed, a peer too coarse for its impact
        ap.error(str(exc))
    print(format_table(rows))
    if args.corrections:
        print(format_corrections(rows, pad))
    if args.storm:
        print(format_storm(rows, pad_bundle(pad), pad.density))
    ok = [r for r in rows if r.agrees()]
    print(f"quasi-static within {AGREE:.0%} of the dynamic peer on all four measures: "
          + (", ".join(f"R = {r.radius * 1e3:g} mm at {r.speed:.3g} m/s" for r in ok) if ok else "none"))
    if args.plot:
        print(f"chart: {plot_agreement(rows, args.plot, density=pad.density)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
