"""Contacts below the mesh: the near field against Hertz and against a finer seat.

Two measurements of :mod:`hailstorm.runtime.contact.near_field`:

* :func:`block_table` -- rigid spheres pressed into a thick graded block of the
  pad's foam (``[seat]`` settings: P2, hat-load columns, the default element
  size on top), with and without the near field, on a vertex, an edge and a
  centroid: ``F / F_Hertz - 1``, and against the block's own converged solution
  (:func:`studies.axisymmetric.press_disc` on the disc of the block's
  top area and depth): Hertz's half-space is not the block, whose clamp 400 mm
  down stiffens a wide contact (about +1.5 % at a = 8 mm), and a sphere is not
  Hertz's paraboloid (-1.6 % at a/R = 0.4 on a half-space, Segedin);
* :func:`pad_table` -- the same spheres pressed into the seat's pad itself, 15 mm of the
  foam on its rigid base (a 120 mm block at the default seat's settings), against the pad's
  own converged contact (the pad as an axisymmetric disc, node by node): where the layer
  kernel of the near field earns its place (:mod:`hailstorm.runtime.contact.layer_kernel`);
* :func:`impact_table` -- stones of 2.5, 5 and 12.5 mm dropped in a storm on the
  same block's top at 1, 5 and 15 m/s (exact integrator, restitution 1, no drag,
  dt 1/400 of Hertz's contact time) against Hertz's quasi-static impact
  (:func:`hailstorm.runtime.contact.hertz.hertz_impact`): peak force, deepest
  indentation of the stone's lowest point, the time the sphere is below the top
  and the time the contact carries force;
* :func:`seat_table` -- stones of 2.5, 5 and 12.5 mm at rest and at the peak
  of an impact at terminal speed, at the rear, middle and nose of the default
  seat, on a vertex, an edge and a centroid: the force at Hertz's depth on
  the default seat against the same on a finer seat (the reference), and
  the spread over the three sites.

Run ``python -m studies.resolution_study`` (``--help``); it prints
the tables (``--out FILE``: also into FILE, with the command, date, commit and load).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

__all__ = ["BLOCK_DEPTH", "BLOCK_HALF_WIDTH", "DEFAULT_MODEL", "MODELS", "SITES", "block_bundle", "block_disc", "block_sites", "block_table", "depth_at_force", "impact_table", "locate", "main", "PAD_CASES", "pad_table", "seat_bundle", "seat_sites", "seat_table",
           "stone_depths"]

#: where on a triangle a contact lands
SITES = ("vertex", "edge", "centroid")
_BARY = {"vertex": np.array([1.0, 0.0, 0.0]), "edge": np.array([0.5, 0.5, 0.0]), "centroid": np.full(3, 1 / 3)}


def seat_bundle(mesh_size: float, progress: bool = False) -> Any:
    """The default seat (``[seat]`` of the default scene: P2, hat columns, its material) at another surface
    size, built or read from the cache, loaded."""
    import hailstorm.runtime
    from hailstorm.precompute import build_bundle
    from hailstorm.runtime.storm.scene import SeatSettings

    seat = SeatSettings.default()
    return hailstorm.runtime.load(build_bundle(None, mesh_size=mesh_size, order=seat.order, load=seat.load,
                                               young=seat.young, poisson=seat.poisson,
                                               volume_size=seat.volume_size, progress=progress))


#: the thick block's half width and depth [m] (:func:`block_bundle`)
BLOCK_HALF_WIDTH, BLOCK_DEPTH = 0.4, 0.4


def block_bundle(out: Any = None, mesh_size: float | None = None, order: int = 2, young: float = 2.0e6,
                 poisson: float = 0.35) -> Any:
    """A graded block of foam clamped 400 mm down, ``mesh_size`` on its top centre (``None``: the
    default seat's), hat-load columns."""
    import hailstorm.runtime
    from hailstorm.precompute import build_bundle
    from hailstorm.precompute.halfspace import halfspace_block
    from hailstorm.runtime.storm.scene import SeatSettings

    if mesh_size is None:
        mesh_size = SeatSettings.default().mesh_size

    mesh = halfspace_block(half_width=BLOCK_HALF_WIDTH, depth=BLOCK_DEPTH, top_half_width=0.025, fine_size=mesh_size,
                           fine_radius=0.04, coarse_size=0.1, growth=0.3)
    return hailstorm.runtime.load(build_bundle(out, mesh=mesh, order=order, young=young, poisson=poisson,
                                               load="hat"))


def block_sites(gf: Any) -> dict[str, tuple[int, np.ndarray]]:
    """The vertex, edge midpoint and centroid of the top triangle nearest the centre of a block's
    flat top (its highest face, :func:`block_bundle`'s or :func:`pad_table`'s pad):
    ``{site: (triangle, barycentric)}``."""
    V, T = np.asarray(gf.vertices), np.asarray(gf.triangles)
    z = V[:, 2].max()
    top = np.flatnonzero((np.abs(V[T][:, :, 2] - z).max(axis=1) < 1e-9) & gf.contactable[T].all(axis=1))
    centre = 0.5 * (V[:, :2].max(axis=0) + V[:, :2].min(axis=0))
    tc = int(top[np.argmin(np.linalg.norm(V[T[top]].mean(axis=1)[:, :2] - centre, axis=1))])
    return {s: (tc, _BARY[s]) for s in SITES}


#: the near-field models the tables compare: the model (the layer kernel, the default's), the
#: half-space's kernel alone (the model before the layer), the layer without D's hat-scale
#: defect (:mod:`hailstorm.runtime.contact.hat_defect`), the discrete model
MODELS = ("layer", "halfspace", "nodefect", "none")
#: the model the storm and ``press_spheres`` use by default (``near_field="auto"`` on a hat-load bundle)
DEFAULT_MODEL = MODELS[0]


def model(name: str, gf: Any) -> Any:
    """The ``near_field`` argument of :data:`MODELS` entry ``name`` on bundle ``gf``."""
    from hailstorm.runtime.contact.near_field import NearField

    if name == "nodefect":
        return NearField("layer", float(gf.young), float(gf.poisson), defect=False)
    return name


def block_disc(young: float, poisson: float):
    """The axisymmetric stand-in of :func:`block_bundle`'s block: a disc of the block's top area
    (radius ``2 w / sqrt(pi)``, ``w`` the half width) and depth, clamped underneath, side free.
    Its radius moves the force of the widest contact here (a = 8 mm) by about 0.1 % (measured:
    +1.74 / +1.82 / +1.91 % over Hertz at radius 400 / 450 / 550 mm)."""
    from hailstorm.runtime.inertia.pad import Pad

    return Pad(young=young, poisson=poisson, thickness=BLOCK_DEPTH, radius=2 * BLOCK_HALF_WIDTH / np.sqrt(np.pi))


def block_table(gf: Any, radii: Sequence[float] = (0.5e-3, 1e-3, 2e-3, 4e-3, 8e-3),
                a_over_R: float = 0.2, exact: bool = True) -> list[dict[str, Any]]:
    """Rigid spheres at Hertz radius ``a`` (``R = a / a_over_R``, Hertz's depth ``a^2 / R``), per site and model.

    Keys ``"<near_field>:<site>"``: ``F / F_Hertz - 1``. With ``exact``, the block's own converged forces
    (:func:`block_disc`, :func:`studies.axisymmetric.press_disc`) over Hertz's, minus 1:
    ``"block"`` for Hertz's paraboloid (what Hertz solves, on this block instead of a half-space: the
    floor of a comparison with Hertz) and ``"block_sphere"`` for the sphere; and
    ``"<near_field>:<site>:block"``: the model's force over the block's sphere force, minus 1 (the
    model's own error; its contacts follow the sphere's law, :mod:`hailstorm.runtime.contact.hertz`).
    """
    from hailstorm.runtime.contact.hertz import hertz_force, press_spheres
    from studies.axisymmetric import press_disc

    rows = []
    disc = block_disc(float(gf.young), float(gf.poisson)) if exact else None
    for a in radii:
        R = a / a_over_R
        d = a * a / R
        F = hertz_force(d, R, gf.young, gf.poisson)
        row: dict[str, Any] = {"a_mm": a * 1e3, "R_mm": R * 1e3}
        F_block = None
        if disc is not None:
            row["block"] = press_disc(disc, R, d, profile="paraboloid").force / F - 1.0
            F_block = press_disc(disc, R, d).force
            row["block_sphere"] = F_block / F - 1.0
        for nf in MODELS:
            for site, (t, b) in block_sites(gf).items():
                res = press_spheres(gf, [t], [b], [d], R, rows=None, near_field=model(nf, gf))
                row[f"{nf}:{site}"] = float(res.normal_force[0] / F - 1.0)
                if F_block is not None:
                    row[f"{nf}:{site}:block"] = float(res.normal_force[0] / F_block - 1.0)
        rows.append(row)
    return rows


#: spheres pressed into the pad (:func:`pad_table`): radius and depth [m] -- a 2.5 and a 5 mm stone at
#: the peak of an impact at terminal speed, a 12.5 mm stone 4 and 6 mm deep, a wide shallow contact
PAD_CASES = ((2.5e-3, 1.07e-3), (5e-3, 2.7e-3), (7.5e-3, 4.5e-3), (12.5e-3, 4e-3), (60e-3, 0.6e-3), (12.5e-3, 6e-3))


def pad_table(gf: Any, pad: Any, cases: Sequence[tuple[float, float]] = PAD_CASES) -> list[dict[str, Any]]:
    """Rigid spheres pressed into a pad on its rigid base, per site and model, against the pad's own
    converged contact (:func:`studies.axisymmetric.press_disc` on the same pad as a disc of
    ``pad.radius``, node by node; ``gf`` the pad as a block, :func:`studies.dynamic_study.pad_bundle`).

    Keys: ``a_mm`` (the converged contact radius), ``R_mm``, ``depth_mm``, ``a_over_h``, ``F_N`` (the
    converged force) and ``"<near_field>:<site>"``: ``F / F_pad - 1``."""
    from hailstorm.runtime.contact.hertz import press_spheres
    from studies.axisymmetric import press_disc

    rows = []
    for R, d in cases:
        ref = press_disc(pad, R, d, profile="sphere")
        row: dict[str, Any] = {"a_mm": ref.contact_radius * 1e3, "R_mm": R * 1e3, "depth_mm": d * 1e3,
                               "a_over_h": ref.contact_radius / pad.thickness, "F_N": ref.force}
        for nf in MODELS:
            for site, (t, b) in block_sites(gf).items():
                res = press_spheres(gf, [t], [b], [d], R, rows=None, near_field=model(nf, gf))
                row[f"{nf}:{site}"] = float(res.normal_force[0] / ref.force - 1.0)
        rows.append(row)
    return rows


def locate(gf: Any, point: np.ndarray) -> tuple[int, np.ndarray]:
    """The contactable surface triangle nearest ``point`` and the barycentric coordinates of the
    point's projection on it (clipped into the triangle)."""
    V, T = np.asarray(gf.vertices), np.asarray(gf.triangles)
    ok = np.flatnonzero(gf.contactable[T].all(axis=1))
    P = V[T[ok]]
    c = P.mean(axis=1)
    near = ok[np.argsort(np.linalg.norm(c - point, axis=1))[:12]]
    best, out = np.inf, (int(near[0]), np.full(3, 1 / 3))
    for t in near:
        A = V[T[t]]
        M = np.column_stack([A[1] - A[0], A[2] - A[0]])
        lam, *_ = np.linalg.lstsq(M, point - A[0], rcond=None)
        b = np.clip(np.array([1 - lam.sum(), lam[0], lam[1]]), 0.0, None)
        b /= b.sum()
        dist = np.linalg.norm(b @ A - point)
        if dist < best:
            best, out = dist, (int(t), b)
    return out


def seat_sites(gf: Any, fractions: Sequence[float] = (0.2, 0.5, 0.8)) -> dict[str, dict[str, np.ndarray]]:
    """Points on the seat's top along its length (rear, middle, nose): for each, the vertex, an edge
    midpoint and the centroid of the contactable triangle nearest the seat's centre line there."""
    V, T = np.asarray(gf.vertices), np.asarray(gf.triangles)
    soft = np.flatnonzero(gf.contactable[T].all(axis=1))
    C = V[T[soft]].mean(axis=1)
    axis = int(np.argmax(np.ptp(C, axis=0)[:2]))  # the long horizontal axis
    other = 1 - axis
    lo, hi = C[:, axis].min(), C[:, axis].max()
    out = {}
    for name, f in zip(("rear", "middle", "nose"), fractions):
        x = lo + f * (hi - lo)
        band = soft[np.abs(C[:, axis] - x) < 0.01]
        Cb = V[T[band]].mean(axis=1)
        mid = np.median(Cb[:, other])
        t = int(band[np.argmin(np.abs(Cb[:, other] - mid) + 10 * np.abs(Cb[:, axis] - x))])  # the centre line
        P = V[T[t]]
        out[name] = {s: _BARY[s] @ P for s in SITES}
    return out


@dataclass(frozen=True)
class _Stone:
    radius: float
    state: str
    depth: float


def stone_depths(young: float, poisson: float, radii: Sequence[float] = (2.5e-3, 5e-3, 12.5e-3)) -> list[_Stone]:
    """Hertz's depth of each stone at rest (its weight) and at the peak of an impact at terminal speed."""
    from hailstorm.runtime.contact.hertz import hertz_impact
    from hailstorm.runtime.storm.hail import GRAVITY, stone_mass, terminal_velocity

    out = []
    e_star = young / (1 - poisson**2)
    for R in radii:
        m = float(stone_mass(R))
        rest = (3 * m * GRAVITY / (4 * e_star * np.sqrt(R))) ** (2 / 3)
        v = float(np.abs(np.asarray(terminal_velocity(R))).max())
        out.append(_Stone(R, "rest", float(rest)))
        out.append(_Stone(R, "impact", hertz_impact(m, v, R, young, poisson).max_depth))
    return out


def depth_at_force(gf: Any, tri: int, bary: np.ndarray, force: float, radius: float, start: float,
                   near_field: Any = DEFAULT_MODEL, tol: float = 1e-5, max_iter: int = 40) -> float:
    """The depth [m] at which a rigid sphere of ``radius`` pressed on ``gf`` at (``tri``, ``bary``)
    carries ``force`` [N]: from ``start``, steps ``d <- d (force / F(d))^(2/3)`` (Hertz's ``F ~ d^1.5``)
    to a relative change below ``tol``.

    Raises
    ------
    RuntimeError
        If the steps do not settle within ``max_iter`` (a force the patch's jumps skip over).
    """
    from hailstorm.runtime.contact.hertz import press_spheres

    d = float(start)
    for _ in range(max_iter):
        f = press_spheres(gf, [tri], [bary], [d], radius, rows=None, near_field=model(near_field, gf)).normal_force[0]
        new = d * (force / f) ** (2.0 / 3.0)
        if abs(new - d) <= tol * d:
            return new
        d = new
    raise RuntimeError(f"depth_at_force: no depth within {tol:g} carries {force:g} N after {max_iter} steps")


def seat_table(gf: Any, ref: Any, near_field: str = DEFAULT_MODEL, dent: bool = False) -> list[dict[str, Any]]:
    """Force at Hertz's depth on ``gf`` against ``ref`` (a finer seat), per stone, place and site
    (``near_field``: a :data:`MODELS` name). With ``dent``, also ``"<site>_dent"``: the depth at
    which ``gf`` carries the reference's force (:func:`depth_at_force`) over Hertz's depth, minus 1
    (the dent the seat shows under the reference's force)."""
    from hailstorm.runtime.contact.hertz import press_spheres

    rows = []
    for place, pts in seat_sites(gf).items():
        for st in stone_depths(gf.young, gf.poisson):
            row: dict[str, Any] = {"place": place, "R_mm": st.radius * 1e3, "state": st.state,
                                   "depth_mm": st.depth * 1e3}
            for site, p in pts.items():
                forces, where = [], []
                for body in (gf, ref):
                    t, b = locate(body, p)
                    where.append((t, b))
                    forces.append(press_spheres(body, [t], [b], [st.depth], st.radius, rows=None,
                                                near_field=model(near_field, body)).normal_force[0])
                row[site] = float(forces[0] / forces[1] - 1.0)
                row[f"{site}_N"] = float(forces[1])
                if dent:
                    t, b = where[0]
                    row[f"{site}_dent"] = depth_at_force(gf, t, b, forces[1], st.radius, st.depth, near_field) / st.depth - 1.0
            rows.append(row)
    return rows


def impact_table(gf: Any, radii: Sequence[float] = (2.5e-3, 5e-3, 12.5e-3),
                 speeds: Sequence[float] = (1.0, 5.0, 15.0), steps: int = 400) -> list[dict[str, Any]]:
    """Stones dropped on the middle of the block's top in a storm against Hertz's impact and the sphere's
    own (module notes).

    Each stone starts ``0.015 R`` above the top, straight down (gravity counted by Hertz's side);
    the storm runs ``steps`` steps per Hertz contact time until the stone is above the top again
    and moving up. Per row: ``a_over_R`` (Hertz's), relative differences ``force``, ``dent``
    (the storm's ``max_indentation_m``, the stone's lowest point), ``contact`` (time with the
    sphere's lowest point below the top) and ``pulse`` (time with a contact force), and the
    storm's ``patch_mm``; ``force_sphere``, ``dent_sphere``, ``contact_sphere``: the same against the
    sphere's own impact (:func:`hailstorm.runtime.contact.hertz.sphere_impact`, Sneddon's law), which the
    storm's contacts follow.
    """
    import math

    from hailstorm.runtime import Scene, Storm
    from hailstorm.runtime.contact.hertz import hertz_impact, sphere_impact
    from hailstorm.runtime.storm.hail import GRAVITY, RHO_ICE, stone_mass

    X = np.asarray(gf.vertices)
    top = float(X[:, 2].max())
    centre = np.array([0.5 * (X[:, 0].min() + X[:, 0].max()), 0.5 * (X[:, 1].min() + X[:, 1].max()), top])
    rows = []
    for R in radii:
        for v in speeds:
            m = float(stone_mass(R, RHO_ICE))
            v0 = math.sqrt(v * v + 2 * GRAVITY * 0.015 * R)  # at the top
            ref = hertz_impact(m, v0, R, float(gf.young), float(gf.poisson), gravity=GRAVITY)
            dt = ref.duration / steps
            sc = Scene.from_flat(duration=8 * ref.duration, stones=0, drag=False, dt=dt, integrator="exact",
                                 restitution=1.0, density=RHO_ICE)
            st = Storm(gf, sc, spawn=False)
            st.add_stones((centre + [0.0, 0.0, 1.015 * R])[None, :], np.array([[0.0, 0.0, -v]]), np.array([R]))
            below = pulse = 0
            for _ in range(8 * steps):
                st.step()
                z = float(st.stones.pos[0, 2]) - R - top
                below += z < 0
                ids, f = st.contact_forces()
                pulse += bool(ids.size and float(np.linalg.norm(f)) > 0)
                if below and z > 0 and st.stones.vel[0, 2] > 0:
                    break
            S = st.stats
            sph = sphere_impact(m, v0, R, float(gf.young), float(gf.poisson), gravity=GRAVITY)
            rows.append({"R_mm": R * 1e3, "v": v, "a_over_R": math.sqrt(ref.max_depth / R),
                         "force": S["max_contact_force"] / ref.max_force - 1,
                         "dent": S["max_indentation_m"] / ref.max_depth - 1,
                         "contact": below * dt / ref.duration - 1, "pulse": pulse * dt / ref.duration - 1,
                         "force_sphere": S["max_contact_force"] / sph.max_force - 1,
                         "dent_sphere": S["max_indentation_m"] / sph.max_depth - 1,
                         "contact_sphere": below * dt / sph.duration - 1,
                         "patch_mm": S["max_patch_radius_m"] * 1e3})
    return rows


def _table(rows: list[dict[str, Any]], keys: Sequence[str], fmt: dict[str, str]) -> list[str]:
    out = ["| " + " | ".join(keys) + " |", "|" + "---|" * len(keys)]
    for r in rows:
        out.append("| " + " | ".join(format(r[k], fmt.get(k, "")) if not isinstance(r[k], str) else r[k]
                                     for k in keys) + " |")
    return out


def main(argv: list[str] | None = None) -> None:
    """Print the block and seat tables (see the module notes); ``--out FILE``: also into FILE."""
    from studies import record

    ap = argparse.ArgumentParser(prog="python -m studies.resolution_study", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    from hailstorm.runtime.storm.scene import SeatSettings

    size = SeatSettings.default().mesh_size
    ap.add_argument("--mesh-size", type=float, default=size, help=f"element size on the top [m] (default {size}: "
                    "the default seat's)")
    ap.add_argument("--reference-size", type=float, default=0.003, help="the finer seat's [m] (default 0.003)")
    ap.add_argument("--skip-block", action="store_true")
    ap.add_argument("--skip-pad", action="store_true")
    ap.add_argument("--skip-seat", action="store_true")
    ap.add_argument("--skip-impacts", action="store_true")
    ap.add_argument("--out", default=None, metavar="FILE", help="also write the output there (with its header)")
    args = ap.parse_args(argv)
    stamp = record.stamp()
    lines: list[str] = []

    def say(*text: str) -> None:
        for t in text:
            print(t, flush=True)
            lines.append(t)

    if not args.skip_block:
        gf = block_bundle(mesh_size=args.mesh_size)
        for a_over_R in (0.2, 0.4):
            say("", f"## Thick block (P2, hat loads, {args.mesh_size * 1e3:g} mm on top), a/R = {a_over_R:g}: "
                    "F / F_Hertz - 1 [%]; block / block_sphere: the block's own converged force for Hertz's "
                    "paraboloid / the sphere (block_disc); ':block': the model's force over the block's "
                    "sphere force, - 1 [%] (the model follows the sphere)", "")
            rows = block_table(gf, a_over_R=a_over_R)
            keys = (["a_mm", "R_mm", "block", "block_sphere"]
                    + [f"{nf}:{s}" for nf in MODELS for s in SITES]
                    + [f"{DEFAULT_MODEL}:{s}:block" for s in SITES])
            for r in rows:
                for k in keys[2:]:
                    r[k] = 100 * r[k]
            say(*_table(rows, keys, {k: "+.1f" for k in keys[2:]} | {"a_mm": ".1f", "R_mm": ".1f"}))
    if not args.skip_pad:
        from studies.dynamic_study import default_pad, pad_bundle

        pad = default_pad()
        gf = pad_bundle(pad, mesh_size=args.mesh_size)
        say("", f"## The pad on its rigid base ({pad.thickness * 1e3:g} mm of the default foam, a 120 mm block, P2, hat "
                f"loads, {args.mesh_size * 1e3:g} mm): a sphere pressed to a depth, F / F_pad - 1 [%], "
                "F_pad the pad's own converged force (press_disc on the pad as a disc, node by node); a the "
                "converged contact radius", "")
        rows = pad_table(gf, pad)
        keys = ["R_mm", "depth_mm", "a_mm", "a_over_h", "F_N"] + [f"{nf}:{s}" for nf in MODELS for s in SITES]
        for r in rows:
            for k in keys[5:]:
                r[k] = 100 * r[k]
        say(*_table(rows, keys, {k: "+.1f" for k in keys[5:]} | {"R_mm": ".1f", "depth_mm": ".2f", "a_mm": ".2f",
                                                                 "a_over_h": ".2f", "F_N": ".4g"}))
    if not args.skip_impacts:
        gf = block_bundle(mesh_size=args.mesh_size)
        say("", f"## Thick block (P2, hat loads, {args.mesh_size * 1e3:g} mm on top): a stone dropped in the storm "
                "(exact, restitution 1) against Hertz's impact, relative difference [%]: peak force, deepest "
                "indentation, time below the top (contact) and with a force (pulse); *_sphere: the same against "
                "the sphere's own impact (sphere_impact), whose law the storm follows; Hertz's a/R; the storm's "
                "patch radius", "")
        rows = impact_table(gf)
        keys = ["R_mm", "v", "a_over_R", "force", "dent", "contact", "pulse", "force_sphere", "dent_sphere",
                "contact_sphere", "patch_mm"]
        for r in rows:
            for k in keys[3:10]:
                r[k] = 100 * r[k]
        say(*_table(rows, keys, {k: "+.1f" for k in keys[3:10]} | {"R_mm": ".1f", "v": "g", "a_over_R": ".2f",
                                                                    "patch_mm": ".2f"}))
    if not args.skip_seat:
        gf, ref = seat_bundle(args.mesh_size, progress=True), seat_bundle(args.reference_size, progress=True)
        for nf in MODELS:
            say("", f"## Default seat ({args.mesh_size * 1e3:g} mm) against {args.reference_size * 1e3:g} mm, "
                    f"near_field={nf!r}: force at Hertz's depth, relative difference [%]", "")
            rows = seat_table(gf, ref, nf)
            for r in rows:
                for s in SITES:
                    r[s] = 100 * r[s]
            say(*_table(rows, ["place", "R_mm", "state", "depth_mm", *SITES, "centroid_N"],
                        {s: "+.1f" for s in SITES} | {"R_mm": ".1f", "depth_mm": ".3f", "centroid_N": ".3g"}))
    if args.out:
        record.write_run(args.out, record.command("python -m studies.resolution_study", argv), stamp, lines)


if __name__ == "__main__":
    main()
