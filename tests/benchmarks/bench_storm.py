"""Benchmark: real-time factor of the hail storm on the default seat.

Usage::

    python tests/benchmarks/bench_storm.py                       # 2000 stones, 2 s, dt 0.5 ms, 3 repeats
    python tests/benchmarks/bench_storm.py --stones 400 --duration 0.4 --repeat 1
    python tests/benchmarks/bench_storm.py --gf DIR --configs exact,implicit,baseline
    python tests/benchmarks/bench_storm.py --configs exact-point,exact    # patch vs point contact
    python tests/benchmarks/bench_storm.py --stones 400 --duration 0.4 --repeat 1 --configs exact,baseline \
        --baseline-duration 0.1 --out docs/_generated/bench_storm.txt  # and into the docs, with a header

Each configuration runs the same storm (same seed) ``--repeat`` times and
prints RTF (simulated / wall time, video excluded) min / median / max, steps,
sub-steps, impacts, stones hit, max penetration into the deformed surface
[mm and % of r_min], max indentation, the restitution achieved by one
stone dropped on the seat's top (target 0.5) and its penetration, and the median RTF as a ratio to the
``baseline`` configuration measured in the same run (the previous default:
implicit backward Euler with adaptive omega-dt sub-steps). The baseline is
run on a shorter storm (``--baseline-duration``, same stone rate) because it
is ~50x slower; RTF is a rate, so the ratio is fair.

Target (issue): 2000 stones / 2 s / dt <= 0.5 ms at RTF >= 1 on 2 cores.

The compiled kernels are loaded (or, the first time after an install,
compiled) when the storm is built: ``setup``, not part of the RTF.

Contact model: every configuration uses the scene default ``patch = "hertz"``
(patch contacts) unless its name ends in ``-point`` (``patch = "none"``: the
previous point contacts); compare e.g. ``exact`` with ``exact-point``. The
``xpoint`` column is the median RTF of a patch configuration over its
``-point`` twin in the same run. ``pen cont`` is the largest overlap of a
stone *in contact* with the deformed surface: the dent of a point load is a
one-vertex spike whose triangles tilt into the sphere; a patch load spreads it.
"""

from __future__ import annotations

import sys
from pathlib import Path

# the studies (notebooks/studies) are in the repository, not in the package; the tests' helpers
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "notebooks"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import argparse
import os
import statistics
import sys

import numpy as np

CONFIGS = {
    # name: (integrator, adaptive); a "-point" suffix selects point contacts (patch = "none")
    "exact": ("exact", True),
    "implicit": ("implicit", False),
    "implicit-toi": ("implicit", True),
    "baseline": ("implicit", True),
}


def config(name: str) -> tuple[str, bool, str, bool]:
    """(integrator, adaptive, patch, today) of a configuration name: a ``-point`` suffix selects point
    contacts, a ``-today`` suffix the previous default seat (point-load columns, no near field)."""
    today = name.endswith("-today")
    name = name[:-6] if today else name
    base, point = (name[:-6], True) if name.endswith("-point") else (name, False)
    integ, adaptive = CONFIGS[base]
    return integ, adaptive, "none" if point else "hertz", today


def seat_drop(gf, integrator: str, adaptive: bool, dt: float, r: float = 0.005, v0: float = 9.0,
              patch: str = "hertz") -> dict:
    """One stone (no drag) hits the seat's top at v0: achieved restitution (normal exit /
    impact speed, target 0.5) and the largest penetration of that impact."""
    from hailstorm.runtime.storm.driver import Scene
    from helpers import drop_on_seat_top

    sc = Scene.from_flat(duration=0.05, stones=0, drag=False, dt=dt, integrator=integrator, adaptive=adaptive, restitution=0.5,
               patch=patch)
    st, v_in, v_out, in_one_step = drop_on_seat_top(gf, sc, int(0.02 / dt), r=r, v0=v0)
    if in_one_step:  # not measured here: no contact at a step's end
        v_in = v_out = None
    e = (v_out / v_in) if (v_in and v_out is not None) else float("nan")
    return dict(e=e, pen=st.stats["max_penetration_m"])


def main(argv: list[str] | None = None) -> None:
    from studies import record

    argv = sys.argv[1:] if argv is None else list(argv)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gf", help="bundle directory (default: the default seat of the scene's [seat], built or reused from the cache)")
    ap.add_argument("--today-gf", help="bundle of the '-today' configurations (default: the default seat with point-load "
                                       "columns, the previous default; run with near_field = 'none')")
    ap.add_argument("--stones", type=int, default=2000)
    ap.add_argument("--duration", type=float, default=2.0)
    ap.add_argument("--dt", type=float, default=5e-4)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--configs", default="exact-point,exact,baseline-point,baseline")
    ap.add_argument("--baseline-duration", type=float, default=0.2)
    record.add_out_option(ap)
    args = ap.parse_args(argv)
    record.run_or_record(args.out, "python tests/benchmarks/bench_storm.py", argv, lambda: run(args))


def run(args: argparse.Namespace) -> None:
    """The configurations of ``args``, one line each, and the notes."""

    import hailstorm.runtime
    from hailstorm.runtime.storm.driver import Scene
    from hailstorm.runtime.storm.run import run_storm

    from hailstorm.precompute import build_bundle
    from hailstorm.runtime.storm.scene import SeatSettings

    seat = SeatSettings.default()

    def default_seat(load: str) -> str:
        return str(build_bundle(None, mesh_size=seat.mesh_size, order=seat.order, load=load, young=seat.young,
                                poisson=seat.poisson))

    path = args.gf or default_seat(seat.load)
    gf = hailstorm.runtime.load(path)
    today_gf = None
    rows = []
    base_rtf = None
    for name in args.configs.split(","):
        integ, adaptive, patch, today = config(name)
        body = gf
        if today:
            if today_gf is None:
                today_gf = hailstorm.runtime.load(args.today_gf or default_seat("point"))
            body = today_gf
        base = name.removesuffix("-today").removesuffix("-point")
        d = Scene.default().to_dict()
        dur, stones, dt = args.duration, args.stones, args.dt
        if base == "baseline":
            dur = min(dur, args.baseline_duration)
            stones = max(1, int(round(args.stones * dur / args.duration)))
            dt = 2e-4  # the previous default scene's step
        d["storm"].update(stones=stones, duration=dur, seed=args.seed)
        d["time"].update(dt=dt, adaptive=adaptive, integrator=integ)
        d["contact"].update(patch=patch, near_field="none" if today else "auto")
        sc = Scene.from_dict(d)
        rtf, setup, st = [], [], None
        for _ in range(args.repeat if base != "baseline" else 1):
            res = run_storm(body, sc, progress=False)
            st = res.stats
            rtf.append(st["real_time_factor"])
            setup.append(st["setup_time_s"])
            assert all(np.isfinite(f.displacement).all() and np.isfinite(f.positions).all() for f in res.frames)
        drop = seat_drop(body, integ, adaptive, dt, patch=patch)
        st = dict(st, drop_e=drop["e"], drop_pen=drop["pen"], setup=statistics.median(setup))
        med = statistics.median(rtf)
        if base == "baseline" and (base_rtf is None or patch == "none"):
            base_rtf = med  # the previous default: implicit, point contacts (if run)
        rows.append((name, integ, adaptive, patch, stones, dur, dt, min(rtf), med, max(rtf), st))
    r_min = Scene.default().hail.r_min
    print(f"bundle {path}: {gf.n_vertices} surface vertices, D {gf.D.shape}"
          + (f"; '-today' configurations on {today_gf.path}" if today_gf is not None else ""))
    point_rtf = {r[0][:-6]: r[8] for r in rows if r[0].endswith("-point")}
    hdr = (f"{'config':25s} {'integr.':10s} {'adapt':5s} {'patch':5s} {'stones':>6s} {'T[s]':>5s} {'dt[ms]':>6s} "
           f"{'RTF min':>8s} {'median':>8s} {'max':>8s} {'xbase':>7s} {'xpoint':>7s} {'setup[s]':>8s} "
           f"{'steps':>6s} {'substeps':>8s} "
           f"{'impacts':>7s} {'hit':>5s} {'pen[mm]':>8s} {'pen/rmin':>8s} {'indent[mm]':>10s} "
           f"{'pen free':>8s} {'pen cont':>8s} {'drop e':>7s} {'drop pen[mm]':>12s}")
    print(hdr)
    for name, integ, adaptive, patch, stones, dur, dt, lo, med, hi, st in rows:
        ratio = f"{med / base_rtf:7.1f}" if base_rtf else "    n/a"
        pr = f"{med / point_rtf[name]:7.2f}" if name in point_rtf and point_rtf[name] else "    n/a"
        print(f"{name:25s} {integ:10s} {str(adaptive):5s} {patch:5s} {stones:6d} {dur:5.2f} {dt * 1e3:6.2f} "
              f"{lo:8.3f} {med:8.3f} {hi:8.3f} {ratio} {pr} {st['setup']:8.2f} {st['steps']:6d} {st['substeps']:8d} "
              f"{st['impacts']:7d} {st['stones_hit']:5d} {st['max_penetration_m'] * 1e3:8.3f} "
              f"{st['max_penetration_m'] / r_min:8.1%} {st['max_indentation_m'] * 1e3:10.3f} "
              f"{st.get('max_penetration_free_m', float('nan')) * 1e3:8.3f} "
              f"{st.get('max_penetration_contact_m', float('nan')) * 1e3:8.3f} "
              f"{st['drop_e']:7.3f} {st['drop_pen'] * 1e3:12.4f}")
    print("pen: max overlap of a sphere with the deformed surface [mm]; 'pen free' for flying stones,")
    print("     'pen cont' for stones in contact (the dent around a point load tilts into the sphere)")
    print("patch: 'hertz' = patch contacts (Hertz disc), 'none' = point contacts; xpoint = median RTF / '-point' twin")
    for name, *_, st in rows:
        if st.get("patch", "none") != "none":
            print(f"  {name}: capacitance rebuilds {st['capacitance_rebuilds']}, patch weights computed "
                  f"{st['patch_weights_computed']} / reused {st['patch_weights_reused']}, resizes {st['patch_resizes']}, "
                  f"largest patch radius {st['max_patch_radius_m'] * 1e3:.2f} mm")
    today_rtf = {r[0].removesuffix("-today"): r for r in rows if r[0].endswith("-today")}
    for name, *_, lo, med, hi, st in rows:
        if name in today_rtf:
            t = today_rtf[name]
            print(f"  {name} against {name}-today (same run): median RTF {med:.3f} / {t[8]:.3f} = {med / t[8]:.2f}x "
                  f"(min {lo:.3f} / {t[7]:.3f}, max {hi:.3f} / {t[9]:.3f}); impacts {st['impacts']} / {t[10]['impacts']}, "
                  f"max force {st['max_contact_force']:.1f} / {t[10]['max_contact_force']:.1f} N")
    print("setup: building the storm (index, spawn plan, loading the compiled kernels), not in the RTF")
    print("drop: one 5 mm stone at 9 m/s onto the seat's top, no drag; restitution target 0.5")
    print(f"load average during the run: {os.getloadavg()[0]:.2f} (2-core machine; RTF is wall-clock)")


if __name__ == "__main__":
    main()
