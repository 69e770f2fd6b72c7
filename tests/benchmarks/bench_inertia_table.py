"""The inertia table against direct peer runs: its interpolation error, the peer's own noise, its cost.

Usage::

    python tests/benchmarks/bench_inertia_table.py                     # 200 random points, the default storm
    python tests/benchmarks/bench_inertia_table.py --points 40 --duration 0.05
    python tests/benchmarks/bench_inertia_table.py --out docs/_generated/inertia_table.txt

Prints, for the default scene's material (foam and ice):

1. the table: where it comes from (shipped, cached or computed now) and the time to compute it
   afresh (``--rebuild``);
2. ``--points`` random points of the grid's range (uniform in ``log(R/h)`` and ``log(v/c)``,
   seed 1): the largest relative difference of each factor between the table and a direct
   run, and the peer's own noise at the same points: the direct run of the same dimensionless
   impact on a layer 3 % thicker (the factors are scale-free; what moves is the peer's mesh);
3. the default storm (``--duration``, inertia as the storm computes it): every impact's
   factors from the table against direct runs, the time of each, and the table's time against
   the storm's time stepping (target: within 1 % on every impact, at most 5 % of the stepping).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "notebooks"))

NAMES = ("force", "duration", "restitution", "dent")


def _errors(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Largest |a/b - 1| per factor over the columns where both are finite, (4,)."""
    ok = np.all(np.isfinite(a) & np.isfinite(b), axis=0)
    return np.abs(a[:, ok] / b[:, ok] - 1.0).max(axis=1, initial=0.0)


def _row(label: str, e: np.ndarray) -> str:
    return f"  {label:<34}" + "".join(f"{100 * x:>12.3f}" for x in e)


def random_points(n: int, rebuild: bool) -> None:
    from hailstorm.runtime.inertia.factors import inertia_factors
    from hailstorm.runtime.inertia.impact import ICE_DENSITY
    from hailstorm.runtime.inertia.pad import PAD_DENSITY
    from hailstorm.runtime.inertia.table import (SIZE_RANGE, SPEED_RANGE, build_inertia_table, inertia_table,
                                                 mass_ratio_key, shipped_path, wave_speed)

    nu, E, rho = 0.35, 2.0e6, PAD_DENSITY
    ratio = mass_ratio_key(ICE_DENSITY / rho)
    print(f"material: nu {nu}, pad {rho:g} kg/m^3, ice {ICE_DENSITY:g} kg/m^3 (mass ratio {ratio:g}); "
          f"shipped table: {shipped_path(nu, ratio).exists()}")
    t0 = time.perf_counter()
    table = build_inertia_table(nu, ratio) if rebuild else inertia_table(nu, ratio)
    took = time.perf_counter() - t0
    grid = table.factors.shape[1:]
    print(f"table {grid[0]} x {grid[1]} points ({'computed' if rebuild else 'read'} in {took:.2f} s), "
          f"R/h {SIZE_RANGE}, v/c {SPEED_RANGE}, NaN points {int(np.isnan(table.factors[0]).sum())}")
    rng = np.random.default_rng(1)
    s = np.exp(rng.uniform(*np.log(SIZE_RANGE), n))
    v = np.exp(rng.uniform(*np.log(SPEED_RANGE), n))
    h = 0.0123
    R, c = s * h, wave_speed(E, rho)
    m = ICE_DENSITY * 4.0 / 3.0 * math.pi * R**3
    t0 = time.perf_counter()
    direct = np.array(inertia_factors(R, m, v * c, np.full(n, h), E, nu, rho, table=False).astuple())
    t_direct = time.perf_counter() - t0
    t0 = time.perf_counter()
    tab = np.array(inertia_factors(R, m, v * c, np.full(n, h), E, nu, rho).astuple())
    t_table = time.perf_counter() - t0
    k = 1.03
    again = np.array(inertia_factors(R * k, m * k**3, v * c, np.full(n, h * k), E, nu, rho, table=False).astuple())
    print(f"\n{n} random points (seed 1): largest |table / direct - 1| [%] per factor")
    print(f"  {'':<34}" + "".join(f"{x:>12}" for x in NAMES))
    print(_row("table against direct", _errors(tab, direct)))
    print(_row("direct 3 % thicker against direct", _errors(again, direct)))
    err = np.abs(tab / direct - 1.0)
    print(f"  points beyond 1 %: {int(np.sum(np.nanmax(err, axis=0) > 0.01))} of {n}; median of the largest "
          f"factor's error {100 * float(np.nanmedian(np.nanmax(err, axis=0))):.3f} %")
    print(f"  time: direct {t_direct:.2f} s ({1e3 * t_direct / n:.1f} ms a point), table {1e3 * t_table:.2f} ms "
          f"({t_direct / max(t_table, 1e-9):.0f}x)")


def default_storm(duration: float) -> None:
    import hailstorm.runtime
    from studies.resolution_study import seat_bundle
    from hailstorm.runtime.inertia.factors import inertia_factors
    from hailstorm.runtime.storm.scene import Scene, SeatSettings

    gf = seat_bundle(SeatSettings.default().mesh_size)
    scene = Scene.default().with_(duration=duration, inertia=False)
    res = hailstorm.runtime.run_storm(gf, scene, progress=False)
    lim = res.stats.validity
    args = (lim.radius, lim.mass, lim.speed, lim.thickness, lim.young, lim.poisson, lim.pad_density)
    t0 = time.perf_counter()
    direct = inertia_factors(*args, table=False)
    t_direct = time.perf_counter() - t0
    t0 = time.perf_counter()
    tab = inertia_factors(*args)
    t_table = time.perf_counter() - t0
    d, t = np.array(direct.astuple()), np.array(tab.astuple())
    step = float(res.stats.wall_time_s)
    print(f"\nthe default storm over {duration:g} s: {lim.n} impacts, {tab.direct_runs} outside the table "
          f"(run directly); largest |table / direct - 1| [%] per factor")
    print(f"  {'':<34}" + "".join(f"{x:>12}" for x in NAMES))
    print(_row("every impact", _errors(t, d)))
    print(f"  time: direct {t_direct:.2f} s, table {1e3 * t_table:.2f} ms = {100 * t_table / step:.2f} % of the "
          f"storm's time stepping ({step:.2f} s)")


def main(argv: list[str] | None = None) -> None:
    from studies import record

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=200, help="random points of the grid's range (default 200)")
    ap.add_argument("--duration", type=float, default=0.2, help="the default storm's duration [s] (default 0.2)")
    ap.add_argument("--rebuild", action="store_true", help="compute the table afresh (and time it)")
    record.add_out_option(ap)
    argv = sys.argv[1:] if argv is None else argv
    args = ap.parse_args(argv)

    def run() -> None:
        random_points(args.points, args.rebuild)
        if args.duration > 0:
            default_storm(args.duration)

    record.run_or_record(args.out, "python tests/benchmarks/bench_inertia_table.py", argv, run)


if __name__ == "__main__":
    main()
