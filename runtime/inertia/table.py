"""The pad's inertia factors tabulated once per material: an interpolation, not a peer run, per impact.

:func:`~hailstorm.runtime.inertia.impact.impact_inertia` runs a dynamic and a quasi-static
impact on the local pad (about 0.05-0.1 s an impact): over a storm of thousands of impacts
that is minutes, ten to a hundred times the storm itself. The factors depend on few groups.
A rigid sphere of radius ``R`` and density ``rho_s`` hits, at normal speed ``v``, a layer of
thickness ``h`` of a material ``E``, ``nu``, ``rho`` on a rigid base (the pad's radius, at
least four thicknesses, is outside the contact's reach: changing it from 0.06 to 0.2 m
moves no factor by 1e-4). Lengths scale with ``h``, stresses with ``E``, times with
``h / c`` where ``c = sqrt(E / rho)``; so the four factors are functions of

* ``R / h`` (the stone against the layer) and ``v / c`` (the impact's speed against the
  pad's waves), tabulated here on a logarithmic grid;
* ``nu`` and the mass ratio ``rho_s / rho`` of the material: one table for each
  (:class:`InertiaTable`), whatever the modulus.

A table is computed once per machine and material (:func:`inertia_table`: 400 peer runs,
about 30-60 s, with a progress bar), written to hailstorm's cache directory
(``inertia_table/<key>.npz``, atomically; a file that cannot be read or written is passed
by) and kept per process; the default scene's material ships with the package (``inertia_table_<key>.npz`` beside this module,
written by ``python -m hailstorm.runtime.inertia.table``), so its first storm does not pay it. A storm of a material without a table computes one only
when it has at least :data:`BUILD_MIN_IMPACTS` impacts to measure (fewer are cheaper run
directly, :func:`available_table`).

Interpolation: a cubic (four-point Lagrange) rule in ``log(R/h)`` and ``log(v/c)``, a 4 x 4
stencil per impact (one-sided at the grid's edges). An impact outside the grid, or whose
stencil holds a point the peer could not resolve, is computed directly
(:func:`~hailstorm.runtime.inertia.factors.inertia_factors` counts them). The error against
direct runs: ``tests/benchmarks/bench_inertia_table.py`` (docs "Performance").
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

__all__ = ["SIZE_RANGE", "SPEED_RANGE", "InertiaTable", "available_table", "build_inertia_table", "inertia_table", "mass_ratio_key",
           "shipped_path", "wave_speed", "write_table"]

_log = logging.getLogger(__name__)

#: the grid's range of ``R / h`` and its points (logarithmic)
SIZE_RANGE, SIZE_POINTS = (0.05, 2.0), 20
#: the grid's range of ``v / c`` (``c = sqrt(E / rho)``) and its points (logarithmic)
SPEED_RANGE, SPEED_POINTS = (0.002, 0.3), 20
#: the layer's thickness the table's runs use [m] (any: the factors are scale-free; this one
#: keeps the peer's default pad radius at four thicknesses)
REFERENCE_THICKNESS = 0.015
#: a storm computes a missing table only for at least this many impacts (the table's points: it then
#: costs no more than their direct runs, and serves every later storm of the material)
BUILD_MIN_IMPACTS = SIZE_POINTS * SPEED_POINTS
#: raise when the table's computation changes (the grid and the peer's resolution are in the key already)
TABLE_VERSION = 1
#: where the shipped tables live (the default scene's material): beside this module, as
#: ``inertia_table_<key>.npz``
SHIPPED = Path(__file__).resolve().parent


def mass_ratio_key(ratio: float) -> float:
    """A stone-over-pad density ratio as a table is keyed by it: six significant digits (a
    storm's stones give it back from their masses and radii with rounding noise)."""
    return float(f"{float(ratio):.6g}")


def wave_speed(young: float, density: float) -> float:
    """``c = sqrt(E / rho)`` [m/s]: the speed the table's ``v / c`` divides by."""
    return math.sqrt(float(young) / float(density))


@dataclass(frozen=True)
class InertiaTable:
    """The four inertia factors on a grid of ``log(R/h)`` x ``log(v/c)`` for one ``nu`` and mass ratio.

    Attributes
    ----------
    poisson : float
        The pad's Poisson ratio [-].
    mass_ratio : float
        Stone density over the pad's [-].
    log_size, log_speed : (p,), (q,) ndarray
        The grid's ``log(R / h)`` and ``log(v / c)``.
    factors : (4, p, q) ndarray
        Force, duration, restitution and dent factors (module docstring of
        :mod:`hailstorm.runtime.inertia.factors`); NaN where the peer could not resolve the impact.
    """

    poisson: float
    mass_ratio: float
    log_size: np.ndarray
    log_speed: np.ndarray
    factors: np.ndarray

    def lookup(self, size: Any, speed: Any) -> np.ndarray:
        """The factors at ``R / h = size`` and ``v / c = speed``, interpolated (module docstring).

        Parameters
        ----------
        size, speed : (n,) array_like
            ``R / h`` and ``v / c`` of each impact.

        Returns
        -------
        (4, n) ndarray
            NaN for an impact outside the grid (or not finite) or whose stencil holds a NaN:
            those need a direct run.
        """
        with np.errstate(invalid="ignore", divide="ignore"):  # not positive: NaN or -inf, outside the grid
            x = np.log(np.asarray(size, dtype=np.float64).ravel())
            y = np.log(np.asarray(speed, dtype=np.float64).ravel())
        out = np.full((4, x.size), np.nan)
        tol = 1e-12
        inside = (np.isfinite(x) & np.isfinite(y) & (x >= self.log_size[0] - tol) & (x <= self.log_size[-1] + tol)
                  & (y >= self.log_speed[0] - tol) & (y <= self.log_speed[-1] + tol))
        if not np.any(inside):
            return out
        ix, wx = _stencil(self.log_size, x[inside])
        iy, wy = _stencil(self.log_speed, y[inside])
        vals = self.factors[:, ix[:, :, None], iy[:, None, :]]  # (4, m, 4, 4)
        out[:, inside] = np.einsum("fmij,mi,mj->fm", vals, wx, wy)  # NaN anywhere in the stencil: NaN
        return out


def _stencil(axis: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Four grid indices around each ``x`` (one-sided at the ends) and their Lagrange weights, (m, 4) each."""
    k = np.clip(np.searchsorted(axis, x) - 2, 0, axis.size - 4)
    idx = k[:, None] + np.arange(4)
    nodes = axis[idx]
    w = np.ones_like(nodes)
    for j in range(4):
        for i in range(4):
            if i != j:
                w[:, j] *= (x - nodes[:, i]) / (nodes[:, j] - nodes[:, i])
    return idx, w


def _grid() -> tuple[np.ndarray, np.ndarray]:
    return (np.linspace(math.log(SIZE_RANGE[0]), math.log(SIZE_RANGE[1]), SIZE_POINTS),
            np.linspace(math.log(SPEED_RANGE[0]), math.log(SPEED_RANGE[1]), SPEED_POINTS))


def _key(poisson: float, mass_ratio: float, resolution: dict[str, Any]) -> str:
    from hailstorm.runtime.inertia.impact import CELLS_PER_RADIUS, STEPS_PER_CONTACT

    res = {"cells_per_radius": CELLS_PER_RADIUS, "steps_per_contact": STEPS_PER_CONTACT, **resolution}
    spec = {"poisson": repr(float(poisson)), "mass_ratio": repr(float(mass_ratio)),
            "size": [SIZE_RANGE, SIZE_POINTS], "speed": [SPEED_RANGE, SPEED_POINTS],
            "h": REFERENCE_THICKNESS, "resolution": {k: repr(float(v)) for k, v in sorted(res.items())},
            "version": TABLE_VERSION}
    return hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:20]


def build_inertia_table(poisson: float, mass_ratio: float, *, progress: bool | Callable[[int, int], None] = False,
                        **resolution: Any) -> InertiaTable:
    """Run the peer on every point of the grid (:func:`inertia_table` caches the result).

    Parameters
    ----------
    poisson, mass_ratio : float
        The material, as in :func:`inertia_table`.
    progress : bool or callable
        ``True``: a tqdm bar (on stderr); a callable is called as ``progress(done, n)``.
    **resolution
        ``cells_per_radius``, ``steps_per_contact`` of the peer
        (:func:`~hailstorm.runtime.inertia.impact.impact_inertia`).

    Returns
    -------
    InertiaTable
    """
    from hailstorm.runtime.inertia.impact import PeerResolutionError, impact_inertia

    _check(poisson, mass_ratio)
    ls, lv = _grid()
    young, pad_density = 1.0e6, 100.0  # any: the factors depend on v / c alone
    c, h = wave_speed(young, pad_density), REFERENCE_THICKNESS
    rho_s = mass_ratio * pad_density
    out = np.full((4, ls.size, lv.size), np.nan)
    n, bar = ls.size * lv.size, None
    if progress is True:
        from tqdm.auto import tqdm

        bar = tqdm(total=n, desc="inertia table (once per material)", unit="point", leave=False)
    try:
        for i, a in enumerate(ls):
            R = math.exp(a) * h
            m = rho_s * 4.0 / 3.0 * math.pi * R**3
            for j, b in enumerate(lv):
                try:
                    out[:, i, j] = impact_inertia(R, m, math.exp(b) * c, h, young, poisson, pad_density, **resolution)
                except PeerResolutionError:
                    pass
                if bar is not None:
                    bar.update(1)
                elif callable(progress):
                    progress(i * lv.size + j + 1, n)
    finally:
        if bar is not None:
            bar.close()
    return InertiaTable(float(poisson), float(mass_ratio), ls, lv, out)


def _check(poisson: float, mass_ratio: float) -> None:
    if not (-1.0 < poisson < 0.5):
        raise ValueError(f"the inertia table needs -1 < poisson < 0.5, got {poisson!r}")
    if not (math.isfinite(mass_ratio) and mass_ratio > 0):
        raise ValueError(f"the inertia table needs a positive mass ratio, got {mass_ratio!r}")


def _read(path: Path, poisson: float, mass_ratio: float) -> InertiaTable | None:
    try:
        with np.load(path) as f:
            ls, lv = np.array(f["log_size"], dtype=np.float64), np.array(f["log_speed"], dtype=np.float64)
            fac, nu, mr = np.array(f["factors"], dtype=np.float64), float(f["poisson"]), float(f["mass_ratio"])
    except (OSError, KeyError, ValueError):
        return None
    gs, gv = _grid()
    if nu != float(poisson) or mr != float(mass_ratio) or ls.shape != gs.shape or lv.shape != gv.shape \
            or not (np.allclose(ls, gs) and np.allclose(lv, gv)) or fac.shape != (4, gs.size, gv.size):
        return None
    for a in (ls, lv, fac):
        a.flags.writeable = False
    return InertiaTable(float(poisson), float(mass_ratio), ls, lv, fac)


def write_table(path: Path, table: InertiaTable) -> None:
    """Write ``table`` to ``path`` atomically (``.npz``; the folder is made)."""
    from hailstorm.runtime.bundle.atomic import replacing

    path.parent.mkdir(parents=True, exist_ok=True)
    with replacing(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, log_size=table.log_size, log_speed=table.log_speed, factors=table.factors,
                     poisson=np.float64(table.poisson), mass_ratio=np.float64(table.mass_ratio))


#: the tables read or computed in this process, by (poisson, mass ratio)
_TABLES: dict[tuple[float, float], InertiaTable] = {}


def available_table(poisson: float, mass_ratio: float) -> InertiaTable | None:
    """The inertia table of a material if it is at hand (in this process, shipped or cached on
    this machine), else None; never computes one (:func:`inertia_table` does).

    Parameters
    ----------
    poisson, mass_ratio : float
        The material, as in :func:`inertia_table`.

    Returns
    -------
    InertiaTable or None
    """
    _check(poisson, mass_ratio)
    key = (float(poisson), mass_ratio_key(mass_ratio))
    if key not in _TABLES:
        for path in (shipped_path(*key), _cached_path(*key)):
            found = _read(path, *key)
            if found is not None:
                _TABLES[key] = found
                break
    return _TABLES.get(key)


def inertia_table(poisson: float, mass_ratio: float, *, progress: bool = False) -> InertiaTable:
    """The inertia table of a material: shipped, cached on this machine, or computed now and cached
    (module docstring); kept per process.

    Parameters
    ----------
    poisson : float
        The pad's Poisson ratio, in (-1, 0.5).
    mass_ratio : float
        Stone density over the pad's (> 0).
    progress : bool
        A progress bar while the table is computed (the first time only).

    Returns
    -------
    InertiaTable
    """
    found = available_table(poisson, mass_ratio)
    if found is not None:
        return found
    key = (float(poisson), mass_ratio_key(mass_ratio))
    table = build_inertia_table(*key, progress=progress)
    try:
        write_table(_cached_path(*key), table)
    except OSError as exc:
        _log.debug("could not cache the inertia table (%s)", exc)
    _TABLES[key] = table
    return table


def shipped_path(poisson: float, mass_ratio: float) -> Path:
    """Where the package's table of a material lives (whether or not it ships one)."""
    return SHIPPED / f"inertia_table_{_key(poisson, mass_ratio_key(mass_ratio), {})}.npz"


def _cached_path(poisson: float, mass_ratio: float) -> Path:
    """Where this machine's table of a material is cached (hailstorm's cache directory)."""
    from hailstorm.runtime.bundle.stamps import default_cache_dir

    return default_cache_dir() / "inertia_table" / f"{_key(poisson, mass_ratio_key(mass_ratio), {})}.npz"


if __name__ == "__main__":  # pragma: no cover - writes the shipped table of the default scene's material
    import argparse

    from hailstorm.runtime.inertia.impact import ICE_DENSITY
    from hailstorm.runtime.inertia.pad import PAD_DENSITY

    ap = argparse.ArgumentParser(description="Write the shipped inertia table of a material (default: the "
                                             "default scene's foam and ice).")
    ap.add_argument("--poisson", type=float, default=0.35)
    ap.add_argument("--mass-ratio", type=float, default=ICE_DENSITY / PAD_DENSITY)
    args = ap.parse_args()
    ratio = mass_ratio_key(args.mass_ratio)
    path = shipped_path(args.poisson, ratio)
    write_table(path, build_inertia_table(args.poisson, ratio, progress=True))
    print(path)
