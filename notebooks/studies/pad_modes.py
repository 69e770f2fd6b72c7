"""The pad's normal modes: how much of its dynamics an impact needs (issue #24, item 3).

``python -m hailstorm.studies.pad_modes [--density RHO] [--counts 10 30 100 200] [--out FILE]``
prints, for each stone at its terminal fall speed, how close the dynamic peer
(:mod:`hailstorm.studies.dynamic_study`) comes out when the pad's dynamics is cut to
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
(the peer's mass redistribution, :func:`~hailstorm.studies.axisymmetric.without_contact_mass`):
a massless dof has no finite mode and is quasi-static by construction.

What it measures
----------------
How many modes, up to which frequency, a dynamic near field needs: the cost of
a model that keeps the pad's inertia where the quasi-static one fails (the 2.5-5
mm stones at terminal speed, docs/validity.md §3). A contact-level form the storm
could carry (one force per contact, the Hertz pressure's shape) is not this: the
measurements in the issue's note show it rings.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from hailstorm.studies.axisymmetric import FOAM_DENSITY, PadMesh, without_contact_mass
from hailstorm.studies.dynamic_study import (
    Row,
    compare,
    default_pad,
    impact_errors,
    impact_mesh,
    simulate_impact,
    terminal_speed,
)

__all__ = ["PadModes", "ModalRow", "format_modal", "main", "modal_rows", "pad_modes"]

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
    """One stone: the peer's :class:`~hailstorm.studies.dynamic_study.Row` and, per mode count,
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
    ap.add_argument("--out", default=None, metavar="FILE", help="also write the output there (with its header)")
    args = ap.parse_args(argv)
    from hailstorm.studies import record

    stamp = record.stamp()
    try:
        pad = default_pad(args.density)
        if not args.counts or min(args.counts) < 1:
            raise ValueError(f"--counts must be positive integers, got {args.counts}")
        rows = modal_rows(pad, args.radii, args.counts, cells_per_radius=args.cells_per_radius,
                          steps_per_contact=args.steps_per_contact)
    except ValueError as exc:
        ap.error(str(exc))
    lines = [f"pad: E = {pad.young:g} Pa, nu = {pad.poisson:g}, rho = {pad.density:g} kg/m^3, {pad.thickness * 1e3:g} "
             f"mm thick, radius {pad.radius * 1e3:g} mm on a rigid base; each stone at its terminal speed",
             "errors against the dynamic peer [%]: peak force, contact time, rebound, largest dent; "
             "'n modes': the peer's pad cut to its n lowest modes, the rest quasi-static",
             format_modal(rows)]
    print("\n".join(lines))
    if args.out:
        record.write_run(args.out, record.command("python -m hailstorm.studies.pad_modes", argv), stamp, lines)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
