"""The pad's normal modes: how much of its dynamics an impact needs (issue #24, item 3).

``python -m studies.pad_modes [--density RHO] [--counts 10 30 100 200] [--out FILE]``
prints, for each stone at its terminal fall speed, how close the dynamic peer
(:mod:`studies.dynamic_study`) comes out when the pad's dynamics is cut to
its ``n`` lowest modes and the rest is taken quasi-statically (the
*mode-acceleration* form, below), and the quasi-static model's own error beside it.

The mode-acceleration form
--------------------------
With ``M u'' + K u = f`` and the modes ``K phi_i = omega_i^2 M phi_i``
(``phi_i^T M phi_i = 1``), the displacement is exactly

    u = K^-1 f  -  sum_i phi_i (phi_i^T f / omega_i^2 - eta_i),
    eta_i'' + omega_i^2 eta_i = phi_i^T f,

the quasi-static response (the storm's Green's functions) plus what the
retained modes lag behind it. With every mode it is the peer itself (the same
Newmark rule on each mode: :func:`simulate_impact` with ``modes`` equals the
full peer to rounding, tested); cut to the modes below a frequency, the modes
above answer quasi-statically. The contact sees the compliance
``C K^-1 C^T - sum_i phi_C,i phi_C,i^T / (omega_i^2 (1 + beta h^2 omega_i^2))``
in a step ``h`` and a free displacement carried by the modes.

The modes are those of the peer's pad with the contact nodes' normal mass removed
(the peer's mass redistribution, :func:`~hailstorm.runtime.inertia.pad.without_contact_mass`):
a massless dof has no finite mode and is quasi-static by construction.

What it measures
----------------
How many modes, up to which frequency, a dynamic near field needs: the cost of
a model that keeps the pad's inertia where the quasi-static one fails (the 2.5-5
mm stones at terminal speed, docs/validity.md §3).

One force per contact (``--one-force``)
---------------------------------------
The form the storm's patch contacts could carry: the contact is one force ``F`` with a
fixed Hertz pressure of the impact's radius (:func:`hertz_load`), and the stone meets the
pad's pressure-weighted mean displacement under it (the storm's patch law, through the
origin), ``x = c_r F + sum_i p_i eta_i`` with ``p_i = g^T phi_i`` and ``c_r`` the static
compliance less the retained modes' share (:func:`one_force_impact`). It is compared with
the peer by its *inertia ratios* (its dynamic over its own quasi-static impact, per
measure, against the peer's), so that the patch law's own error drops out.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from hailstorm.runtime.inertia.pad import PadMesh, without_contact_mass
from studies.axisymmetric import FOAM_DENSITY
from studies.dynamic_study import (
    ICE_DENSITY,
    ImpactResult,
    Row,
    compare,
    default_pad,
    hertz_estimate,
    impact_errors,
    impact_mesh,
    simulate_impact,
    terminal_speed,
)

__all__ = ["ModalRow", "OneForceRow", "PadModes", "format_modal", "format_one_force", "hertz_load", "main",
           "modal_rows", "one_force_impact", "one_force_rows", "pad_modes", "patch_compliance"]

#: the mode counts of the printed table
COUNTS = (10, 30, 100, 200)


@dataclass(frozen=True)
class PadModes:
    """The lowest normal modes of a pad (:func:`pad_modes`).

    Attributes
    ----------
    omega2 : (n,) ndarray
        Squared circular frequencies [1/s^2], ascending.
    shapes : (f, n) ndarray
        Mode shapes on the pad's free dofs, mass-normalised (``phi^T M phi = 1``).
    """

    omega2: np.ndarray
    shapes: np.ndarray

    @property
    def count(self) -> int:
        """Number of modes."""
        return int(self.omega2.size)

    @property
    def max_frequency(self) -> float:
        """The highest mode's frequency [Hz] (0 without modes)."""
        return float(math.sqrt(self.omega2[-1]) / (2 * math.pi)) if self.count else 0.0


def pad_modes(mesh: PadMesh, count: int | None = None, massless: np.ndarray | None = None) -> PadModes:
    """The ``count`` lowest modes of the pad (``None``: all of them, dense; small meshes).

    Parameters
    ----------
    mesh : PadMesh
    count : int, optional
        How many (>= 1).
    massless : int ndarray, optional
        Free dofs without mass (the contact nodes' normal dofs): they have no finite mode.

    Returns
    -------
    PadModes

    Notes
    -----
    Solves ``M psi = mu K psi`` for the largest ``mu = 1 / omega^2`` (K is SPD: the pad is
    clamped; M may be singular), so a massless dof gives ``mu = 0`` and no mode.
    """
    from scipy.linalg import eigh
    from scipy.sparse.linalg import eigsh

    M = mesh.M if massless is None else without_contact_mass(mesh.M, np.asarray(massless))
    n = mesh.K.shape[0]
    if count is not None and not (isinstance(count, (int, np.integer)) and count >= 1):
        raise ValueError(f"pad_modes needs count >= 1, got {count!r}")
    if count is None or count >= n - 1:
        mu, psi = eigh(M.toarray(), mesh.K.toarray())
    else:
        mu, psi = eigsh(M, k=int(count), M=mesh.K, which="LA")
    order = np.argsort(-mu)
    mu, psi = mu[order], psi[:, order]
    keep = mu > 1e-12 * mu[0]
    omega2 = 1.0 / mu[keep]
    return PadModes(omega2=omega2, shapes=psi[:, keep] * np.sqrt(omega2))  # psi^T K psi = 1 -> phi^T M phi = 1


@dataclass(frozen=True)
class ModalRow:
    """One stone: the peer's :class:`~studies.dynamic_study.Row` and, per mode count,
    the modal model's errors against the dynamic peer (:meth:`Row.errors`'s measures)."""

    row: Row
    counts: tuple[int, ...]
    frequencies: tuple[float, ...]
    errors: tuple[dict[str, float], ...]


def modal_rows(pad: Any, radii: Sequence[float], counts: Sequence[int] = COUNTS, *,
               speeds: Sequence[float] | None = None, cells_per_radius: float = 8.0,
               steps_per_contact: int = 200) -> list[ModalRow]:
    """Each stone (at ``speeds``, default its terminal speed) on the peer (:func:`compare`, its mesh
    :func:`impact_mesh`), and the peer cut to ``counts`` modes."""
    out = []
    speeds = [terminal_speed(R) for R in radii] if speeds is None else list(speeds)
    for R, v in zip(radii, speeds):
        row = compare(pad, R, v, cells_per_radius=cells_per_radius, steps_per_contact=steps_per_contact)
        mesh = impact_mesh(pad, R, v, cells_per_radius)
        C = mesh.top_uz[mesh.top_r < 0.999 * R]  # the peer's contact candidates
        errs, freqs = [], []
        for n in counts:
            modes = pad_modes(mesh, n, massless=C)
            r = simulate_impact(mesh, R, v, modes=modes, steps_per_contact=steps_per_contact)
            errs.append(impact_errors(r, row.dynamic))
            freqs.append(modes.max_frequency)
        out.append(ModalRow(row=row, counts=tuple(counts), frequencies=tuple(freqs), errors=tuple(errs)))
    return out


def hertz_load(mesh: PadMesh, radius: float, points: int = 8) -> np.ndarray:
    """The consistent nodal load of a Hertz pressure disc on the pad's top, of total 1.

    ``p(r)`` proportional to ``sqrt(1 - r^2 / a^2)`` integrated against each top node's P1 hat
    with the ring's ``2 pi r dr`` (Gauss-Legendre in ``theta``, ``r = a sin(theta)``, split at the
    nodes, so smooth on each piece).

    Parameters
    ----------
    mesh : PadMesh
    radius : float
        The disc's radius ``a`` [m] (> 0, inside the top).
    points : int
        Gauss points per piece.

    Returns
    -------
    (f,) ndarray
        The load on the pad's free dofs (on the top nodes' ``u_z``), summing to 1.
    """
    r = mesh.top_r
    if not (radius > 0 and radius < r[-1]):
        raise ValueError(f"hertz_load needs 0 < radius < {r[-1]!r} (the pad's top), got {radius!r}")
    inside = np.count_nonzero(r < radius)
    cuts = np.r_[np.arcsin(r[:inside] / radius), 0.5 * math.pi]
    x, w = np.polynomial.legendre.leggauss(points)
    nodal = np.zeros(r.size)
    for j in range(inside):  # the piece from node j to node j + 1 (or to the disc's edge)
        half = 0.5 * (cuts[j + 1] - cuts[j])
        th = half * x + 0.5 * (cuts[j + 1] + cuts[j])
        rr = radius * np.sin(th)
        f = np.cos(th) * 2.0 * math.pi * rr * radius * np.cos(th) * (half * w)  # p dA, dr = a cos(theta) dtheta
        t = (rr - r[j]) / (r[j + 1] - r[j])
        nodal[j] += np.sum(f * (1.0 - t))
        nodal[j + 1] += np.sum(f * t)
    g = np.zeros(mesh.K.shape[0])
    g[mesh.top_uz] = nodal / nodal.sum()
    return g


def patch_compliance(mesh: PadMesh, patch_radius: float) -> float:
    """The static compliance ``g^T K^-1 g`` [m/N] of the pad under :func:`hertz_load`'s disc."""
    from scipy.sparse.linalg import splu

    g = hertz_load(mesh, patch_radius)
    return float(g @ splu(mesh.K.tocsc()).solve(g))


def one_force_impact(mesh: PadMesh, radius: float, speed: float, patch_radius: float,
                     modes: PadModes | None = None, *, steps_per_contact: int = 200,
                     ice_density: float = ICE_DENSITY, compliance: float | None = None) -> ImpactResult:
    """A rigid ice sphere on the pad as one force with a fixed Hertz pressure (the module's notes).

    The stone's penetration ``x`` (from first touch) meets the load's weighted mean displacement,
    ``x = c_r F + sum_i p_i zeta_i``, ``zeta_i'' + omega_i^2 zeta_i = p_i F``, ``F >= 0``; Newmark's
    average acceleration on the stone and on each mode, with the peer's step (Hertz's contact
    duration over ``steps_per_contact``). Without ``modes`` it is the quasi-static patch, a linear
    spring of compliance ``c = g^T K^-1 g``: peak force ``v sqrt(m / c)``, contact time
    ``pi sqrt(m c)``, rebound ``v``.

    Parameters
    ----------
    mesh : PadMesh
    radius, speed : float
        The sphere's radius [m] and impact speed [m/s] (> 0).
    patch_radius : float
        The Hertz pressure's radius [m] (:func:`hertz_load`).
    modes : PadModes, optional
        The retained modes (of the pad with the nodes under the patch massless); None: quasi-static.
    steps_per_contact : int
    ice_density : float
    compliance : float, optional
        The patch's static compliance ``g^T K^-1 g`` [m/N] (:func:`patch_compliance`), when the
        caller has it; computed otherwise.

    Returns
    -------
    ImpactResult
        ``max_dent`` is the stone's largest penetration (the mean displacement under the patch),
        ``max_contact_radius`` the patch's radius; ``history`` as the peer's, its dent column the
        penetration.
    """
    if not (radius > 0 and speed > 0 and ice_density > 0):
        raise ValueError(f"one_force_impact needs radius, speed, ice_density > 0, got {radius!r}, {speed!r}, "
                         f"{ice_density!r}")
    m = ice_density * 4.0 / 3.0 * math.pi * radius**3
    duration_ref = hertz_estimate(mesh.pad, radius, speed, ice_density).duration
    dt = duration_ref / steps_per_contact
    g = hertz_load(mesh, patch_radius)
    c = patch_compliance(mesh, patch_radius) if compliance is None else float(compliance)
    beta, gamma = 0.25, 0.5
    if modes is None:
        p, w2 = np.zeros(0), np.zeros(0)
    else:
        p, w2 = modes.shapes.T @ g, modes.omega2
    lag = 1.0 / (1.0 + beta * dt * dt * w2)
    denom = c - np.sum(p * p / w2) + beta * dt * dt * (1.0 / m + np.sum(p * p * lag))
    x, xv, xa = 0.0, float(speed), 0.0
    z, zv, za = np.zeros(p.size), np.zeros(p.size), np.zeros(p.size)
    t, last_touch, hist = 0.0, -1.0, []
    while t < 8.0 * duration_ref:
        t += dt
        x_hat = x + dt * xv + (0.5 - beta) * dt * dt * xa
        z_hat = z + dt * zv + (0.5 - beta) * dt * dt * za
        F = max(0.0, (x_hat - float(np.sum(p * lag * z_hat))) / denom)
        x_new, xa_new = x_hat - beta * dt * dt * F / m, -F / m
        z_new = (z_hat + beta * dt * dt * p * F) * lag
        za_new = p * F - w2 * z_new
        zv = zv + dt * ((1 - gamma) * za + gamma * za_new)
        xv = xv + dt * ((1 - gamma) * xa + gamma * xa_new)
        x, xa, z, za = x_new, xa_new, z_new, za_new
        hist.append((t, F, x, x))
        if F > 0:
            last_touch = t
        elif last_touch > 0 and xv < 0 and t > last_touch + 0.5 * duration_ref:
            break
    H = np.array(hist)
    return ImpactResult(dynamic=modes is not None, speed=float(speed), peak_force=float(H[:, 1].max()),
                        duration=last_touch + 0.5 * dt if last_touch > 0 else 0.0, rebound_speed=float(-xv),
                        max_dent=float(H[:, 2].max()), max_contact_radius=float(patch_radius), dt=dt,
                        steps=len(hist), history=H, modes=None if modes is None else modes.count)


@dataclass(frozen=True)
class OneForceRow(ModalRow):
    """A :class:`ModalRow` of the one-force model: its ``errors`` are its inertia ratios against the
    peer's, minus 1, per measure; ``patch_radius`` the Hertz pressure's radius [m]."""

    patch_radius: float


def one_force_rows(pad: Any, radii: Sequence[float], counts: Sequence[int] = COUNTS, *,
                   speeds: Sequence[float] | None = None, cells_per_radius: float = 8.0,
                   steps_per_contact: int = 200) -> list[OneForceRow]:
    """Each stone (at ``speeds``, default its terminal speed) on the peer (:func:`compare`) and as one
    force (:func:`one_force_impact`) with the quasi-static peer's peak contact radius, cut to ``counts``
    modes of the pad whose nodes under the patch are massless.

    A measure's error is ``(one-force dynamic / one-force quasi-static) / (peer dynamic / peer
    quasi-static) - 1``: what the model gets of the pad's inertia, the patch law's own error apart."""
    out = []
    speeds = [terminal_speed(R) for R in radii] if speeds is None else list(speeds)
    for R, v in zip(radii, speeds):
        row = compare(pad, R, v, cells_per_radius=cells_per_radius, steps_per_contact=steps_per_contact)
        mesh = impact_mesh(pad, R, v, cells_per_radius)
        a = row.quasi_static.max_contact_radius
        kw = dict(steps_per_contact=steps_per_contact, compliance=patch_compliance(mesh, a))  # one factor per stone
        every = pad_modes(mesh, max(counts), massless=mesh.top_uz[mesh.top_r <= a])
        qs = one_force_impact(mesh, R, v, a, **kw)
        peer = impact_errors(row.dynamic, row.quasi_static)
        errs, freqs = [], []
        for n in counts:
            cut = PadModes(omega2=every.omega2[:n], shapes=every.shapes[:, :n])
            own = impact_errors(one_force_impact(mesh, R, v, a, cut, **kw), qs)
            errs.append({k: (1.0 + own[k]) / (1.0 + peer[k]) - 1.0 for k in own})
            freqs.append(cut.max_frequency)
        out.append(OneForceRow(row=row, counts=tuple(counts), frequencies=tuple(freqs), errors=tuple(errs),
                               patch_radius=a))
    return out


def format_one_force(rows: Sequence[OneForceRow]) -> str:
    """The table: per stone, the quasi-static model's errors, then the one-force model's per mode count."""
    head = (f"{'R mm':>5} {'v m/s':>5} {'a/R':>4} {'model':>16} {'f max kHz':>9} | {'dF%':>6} {'dt%':>6} "
            f"{'de%':>6} {'dd%':>6} | worst")
    lines = [head, "-" * len(head)]
    for m in rows:
        label = f"{m.row.radius * 1e3:5.1f} {m.row.speed:5.1f} {m.patch_radius / m.row.radius:4.2f}"
        lines.append(f"{label} {'quasi-static':>16} {'':>9} | " + _errs(m.row.errors()))
        for n, f, err in zip(m.counts, m.frequencies, m.errors):
            lines.append(f"{'':>16} {f'{n} modes, 1 force':>16} {f / 1e3:9.1f} | " + _errs(err))
    return "\n".join(lines)


def format_modal(rows: Sequence[ModalRow]) -> str:
    """The table: per stone, the quasi-static model's errors, then the modal model's per mode count."""
    head = (f"{'R mm':>5} {'v m/s':>5} {'model':>16} {'f max kHz':>9} | {'dF%':>6} {'dt%':>6} {'de%':>6} "
            f"{'dd%':>6} | worst")
    lines = [head, "-" * len(head)]
    for m in rows:
        e = m.row.errors()
        label = f"{m.row.radius * 1e3:5.1f} {m.row.speed:5.1f}"
        lines.append(f"{label} {'quasi-static':>16} {'':>9} | " + _errs(e))
        for n, f, err in zip(m.counts, m.frequencies, m.errors):
            lines.append(f"{'':>11} {f'{n} modes':>16} {f / 1e3:9.1f} | " + _errs(err))
    return "\n".join(lines)


def _errs(e: dict[str, float]) -> str:
    worst = max(abs(x) for x in e.values())
    return (f"{100 * e['force']:+6.1f} {100 * e['duration']:+6.1f} {100 * e['rebound']:+6.1f} {100 * e['dent']:+6.1f}"
            f" | {100 * worst:5.1f}")


def main(argv: list[str] | None = None) -> int:
    """Print the modal table for the default storm's stones at their terminal speeds."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--density", type=float, default=FOAM_DENSITY, help="foam density [kg/m^3]")
    ap.add_argument("--radii", type=float, nargs="*", default=[0.0025, 0.005, 0.0075, 0.01, 0.0125],
                    help="stone radii [m] (each at its terminal speed)")
    ap.add_argument("--counts", type=int, nargs="*", default=list(COUNTS), help="mode counts")
    ap.add_argument("--steps-per-contact", type=int, default=200)
    ap.add_argument("--cells-per-radius", type=float, default=8.0)
    ap.add_argument("--one-force", action="store_true",
                    help="the contact as one force with a fixed Hertz pressure (the storm's patch) on the modes")
    ap.add_argument("--out", default=None, metavar="FILE", help="also write the output there (with its header)")
    args = ap.parse_args(argv)
    from studies import record

    stamp = record.stamp()
    try:
        pad = default_pad(args.density)
        if not args.counts or min(args.counts) < 1:
            raise ValueError(f"--counts must be positive integers, got {args.counts}")
        kw = dict(cells_per_radius=args.cells_per_radius, steps_per_contact=args.steps_per_contact)
        if args.one_force:
            table = format_one_force(one_force_rows(pad, args.radii, args.counts, **kw))
        else:
            table = format_modal(modal_rows(pad, args.radii, args.counts, **kw))
    except ValueError as exc:
        ap.error(str(exc))
    what = ("'n modes, 1 force': the contact as one force with a fixed Hertz pressure of the quasi-static peer's "
            "peak contact radius (a), on the n lowest modes of the pad with the nodes under it massless; its "
            "errors are its inertia ratios (dynamic over its own quasi-static) over the peer's"
            if args.one_force else "'n modes': the peer's pad cut to its n lowest modes, the rest quasi-static")
    lines = [f"pad: E = {pad.young:g} Pa, nu = {pad.poisson:g}, rho = {pad.density:g} kg/m^3, {pad.thickness * 1e3:g} "
             f"mm thick, radius {pad.radius * 1e3:g} mm on a rigid base; each stone at its terminal speed",
             "errors against the dynamic peer [%]: peak force, contact time, rebound, largest dent; " + what,
             table]
    print("\n".join(lines))
    if args.out:
        record.write_run(args.out, record.command("python -m studies.pad_modes", argv), stamp, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
