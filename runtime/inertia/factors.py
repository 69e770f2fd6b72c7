"""The pad's inertia in each impact of a storm: the dynamic peer's over the quasi-static one.

The storm is quasi-static: its pad answers a contact force at once, without mass. Where an
impact is shorter than the pad's own wave period the real pad does not (``docs/validity.md``
section 2): part of the stone's momentum goes into accelerating the foam under it and into
waves, so the peak force is lower, the contact longer and the rebound slower than the
quasi-static model says. :func:`inertia_factors` measures that per impact: the impact
(stone radius, mass, normal speed at onset) is run twice on an axisymmetric pad of the local
thickness under it, of the seat's material and the scene's foam density
(:func:`hailstorm.runtime.inertia.impact.simulate_impact`, with the pad's mass and without),
and the ratios dynamic / quasi-static of peak force, contact time, rebound speed and largest
dent are the impact's **inertia factors**. The storm's own quasi-static impact times its
force factor is its dynamic estimate (``max_impact_force_dynamic_N`` in a storm's summary).

The split is multiplicative: the local pad carries the inertia, the storm its seat (its
curvature, its far field, the neighbouring contacts, its dashpot). Against the dynamic peer
on the pad the storm was measured on (``docs/validity.md``), the storm's peak forces times
these factors are within the storm's own quasi-static error.

Resolution: 8 cells per Hertz contact radius and 100 steps per Hertz contact time by
default (about 0.07 s per impact). Against 12 cells and 300 steps the factors move by at most
1.4 % at the terminal speeds on the 15 mm pad at 70 and 200 kg/m^3 (measured by hand: the
contact times and the large stones' peak forces, whose contacts spread over the nodes in
steps; ``tests/runtime/inertia/test_inertia.py`` holds the 2.5 and 5 mm stones within 1.5 %
of the studies' peer at 12 cells and 300 steps on scikit-fem's assembly).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from hailstorm.runtime.inertia.impact import PeerResolutionError, check_density, impact_inertia
from hailstorm.runtime.inertia.table import (BUILD_MIN_IMPACTS, InertiaTable, available_table, inertia_table,
                                             mass_ratio_key, wave_speed)

__all__ = ["InertiaFactors", "inertia_factors"]


@dataclass(frozen=True)
class InertiaFactors:
    """Per impact, the dynamic peer over the quasi-static peer on the local pad (:func:`inertia_factors`).

    Attributes
    ----------
    force, duration, restitution, dent : (n,) ndarray
        Peak force, contact time, rebound speed and largest dent, dynamic / quasi-static [-]
        (NaN where the impact had no local pad: the ray under it met no boundary).
    direct : (n,) bool ndarray, optional
        Which impacts were run on their own pad rather than read from the material's table
        (:mod:`hailstorm.runtime.inertia.table`: outside its grid, or not tabulated); default all.
    """

    force: np.ndarray
    duration: np.ndarray
    restitution: np.ndarray
    dent: np.ndarray
    direct: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.direct is None:
            object.__setattr__(self, "direct", np.ones(np.shape(self.force), dtype=bool))

    @property
    def impacts(self) -> int:
        """How many impacts."""
        return int(self.force.size)

    def largest_change(self) -> np.ndarray:
        """Per impact, the largest ``|factor - 1|`` of the four (NaN where none was measured), (n,)."""
        f = np.stack([self.force, self.duration, self.restitution, self.dent])
        with np.errstate(invalid="ignore"):
            return np.abs(f - 1.0).max(axis=0, initial=0.0) if f.shape[1] else np.zeros(0)

    @property
    def direct_runs(self) -> int:
        """How many impacts were run on their own pad (not read from a table)."""
        return int(np.count_nonzero(self.direct))

    def __add__(self, other: InertiaFactors) -> InertiaFactors:
        return InertiaFactors(*(np.concatenate([a, b]) for a, b in zip(self.astuple(), other.astuple())),
                              direct=np.concatenate([self.direct, other.direct]))

    def astuple(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(force, duration, restitution, dent)."""
        return self.force, self.duration, self.restitution, self.dent

    @classmethod
    def empty(cls) -> InertiaFactors:
        """No impacts."""
        return cls(*(np.zeros(0) for _ in range(4)))


def inertia_factors(radius: Any, mass: Any, speed: Any, thickness: Any, young: float, poisson: float,
                    density: float, *, progress: bool | Callable[[int, int], None] = False, table: bool = True,
                    **resolution: Any) -> InertiaFactors:
    """The inertia factors of many impacts: read from the material's table where it holds them,
    :func:`impact_inertia` for the others.

    Parameters
    ----------
    radius, mass, speed, thickness : (n,) array_like
        Per impact: the stone's radius [m] and mass [kg], its normal speed at onset [m/s],
        the local pad's thickness [m] (not finite: no local pad, NaN factors; so too an
        impact whose contact the local pad cannot resolve at 4 times the cells per radius,
        :class:`~hailstorm.runtime.inertia.impact.PeerResolutionError`: a storm's statistics
        count NaN factors as 1).
    young, poisson : float
        The pad's material [Pa], [-].
    density : float
        The pad foam's density [kg/m^3] (> 0).
    progress : bool or callable
        ``True``: a tqdm bar over the direct runs (on stderr; and over the table's points the
        first time a material's table is computed); a callable is called as
        ``progress(done, n)`` after each direct run.
    table : bool
        Interpolate in the material's table of factors (:func:`hailstorm.runtime.inertia.table.inertia_table`:
        shipped for the default scene's material, else computed once per material and cached,
        when there are at least ``BUILD_MIN_IMPACTS`` impacts to measure) where the impact lies in
        its grid; False: every impact directly. A non-default ``resolution`` runs every impact directly.
    **resolution
        ``pad_radius``, ``cells_per_radius``, ``steps_per_contact`` (:func:`impact_inertia`).

    Returns
    -------
    InertiaFactors
    """
    check_density("pad", density)
    if not (-1.0 < poisson < 0.5):
        raise ValueError(f"inertia_factors needs -1 < poisson < 0.5, got {poisson!r}")
    R, m, v, h = (np.asarray(a, dtype=np.float64).ravel() for a in (radius, mass, speed, thickness))
    if not (R.size == m.size == v.size == h.size):
        raise ValueError(f"inertia_factors: radius, mass, speed and thickness differ in length "
                         f"({R.size}, {m.size}, {v.size}, {h.size})")
    out = np.full((4, R.size), np.nan)
    padded = np.isfinite(h) & (h > 0)
    direct = padded.copy()
    if table and not resolution and np.any(padded):
        tab, of = _tabulated(R, m, h, density, poisson, progress is True)
        if tab is not None:
            got = tab.lookup(R[of] / h[of], v[of] / wave_speed(young, density))
            hit = np.all(np.isfinite(got), axis=0)
            out[:, of[hit]] = got[:, hit]
            direct[of[hit]] = False
    todo = np.flatnonzero(direct)
    bar = None
    if progress is True and todo.size:
        from tqdm.auto import tqdm

        bar = tqdm(total=todo.size, desc="pad inertia", unit="impact", leave=False)
    try:
        for i, k in enumerate(todo):
            try:
                out[:, k] = impact_inertia(R[k], m[k], v[k], h[k], young, poisson, density, **resolution)
            except PeerResolutionError:  # a contact the local pad cannot resolve: not measured (NaN)
                pass
            if bar is not None:
                bar.update(1)
            elif callable(progress):
                progress(i + 1, todo.size)
    finally:
        if bar is not None:
            bar.close()
    return InertiaFactors(*out, direct=direct)


def _tabulated(R: np.ndarray, m: np.ndarray, h: np.ndarray, density: float, poisson: float,
               progress: bool) -> tuple[InertiaTable | None, np.ndarray]:
    """The material's table for the impacts' stones (those of the most common density) and
    which impacts on a pad it may serve; (None, empty) when no stone density is shared."""
    rho_s = m / (4.0 / 3.0 * math.pi * R**3)
    ok = np.isfinite(h) & (h > 0) & np.isfinite(rho_s) & (rho_s > 0)
    if not np.any(ok):
        return None, np.zeros(0, dtype=np.int64)
    ratio = mass_ratio_key(float(np.median(rho_s[ok])) / density)
    of = np.flatnonzero(ok & np.isclose(rho_s / density, ratio, rtol=1e-6, atol=0.0))
    tab = available_table(poisson, ratio)
    if tab is None and of.size >= BUILD_MIN_IMPACTS:  # worth computing once for this material
        tab = inertia_table(poisson, ratio, progress=progress)
    return tab, of
