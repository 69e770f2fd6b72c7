"""Where the quasi-static model holds: the dynamic FEM peer's table and the default storm's validity counts.

Usage::

    python tests/benchmarks/dynamic_peer.py                 # small grid (3 speeds x 2 radii) + the default storm
    python tests/benchmarks/dynamic_peer.py --full          # speeds 1-30 m/s x radii 2.5-12.5 mm (6 x 5)
    python tests/benchmarks/dynamic_peer.py --terminal      # each radius at its terminal speed (the default storm)
    python tests/benchmarks/dynamic_peer.py --limit --no-storm   # the grid at 70 and 200 kg/m^3 by the storm's t_c/T
    python tests/benchmarks/dynamic_peer.py --terminal --storm-block   # and the same impacts in the storm
    python tests/benchmarks/dynamic_peer.py --full --speeds 30 --storm-block --no-storm   # 30 m/s, every radius
    python tests/benchmarks/dynamic_peer.py --no-storm      # the table only
    python tests/benchmarks/dynamic_peer.py --density 50    # another foam density [kg/m^3]
    python tests/benchmarks/dynamic_peer.py --no-table      # the default storm's validity counts only
    python tests/benchmarks/dynamic_peer.py --full --no-storm --plot notebooks/figures/dynamic_peer.png
                                                            # and the chart of where the table is within 5 %
    python tests/benchmarks/dynamic_peer.py --full --no-storm --out docs/_generated/dynamic_peer_full.txt
                                                            # and the printed output into a file, with a header

The table is :func:`studies.dynamic_study.main`'s: one rigid ice sphere on the
default seat's foam pad (a 15 mm disc on a rigid base), dynamic (the pad's mass,
Newmark average acceleration) against quasi-static (the same mesh without mass: the
Green's-function assumption) and Hertz's half-space impact; the last column says where
the quasi-static model is within 5 % of the dynamic one on peak force, contact duration,
rebound speed and largest dent. Then the default storm (``hailstorm storm``'s scene and
cached seat bundle, or ``--gf DIR``), its validity keys (docs/validity.md) and their
spread over its impacts, with the pad's inertia factors of its impacts (the scene's
70 kg/m^3, and 200).

``--out FILE`` writes what the run prints to FILE as well (the measured output docs/
includes from docs/_generated/): first the line ``$ <command>`` (this script's command
line without ``--out``), then one with the UTC date, the code's commit (``git rev-parse
--short HEAD``, and the tracked files outside docs/ that differ from it) and the load
average before the run, then the output, and last the run's wall time and the load
average after it. The file is written whole at the end (a temporary file in the same
folder, then ``os.replace``): a run that fails leaves an earlier file as it was.
"""

from __future__ import annotations

import sys
from pathlib import Path

# the studies (notebooks/studies) are in the repository, not in the package
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "notebooks"))

import argparse
import sys

from studies import record


def run_default_storm(gf_path: str | None = None, duration: float | None = None):
    """The default storm (the packaged scene; ``duration``: shortened) on ``gf_path`` (default: the
    default seat's bundle, built or reused from the cache like ``hailstorm storm`` does); its result."""
    import hailstorm.runtime
    from hailstorm.runtime.storm.scene import Scene, SeatSettings

    if gf_path is None:
        from hailstorm.precompute import build_bundle

        seat = SeatSettings.default()
        gf_path = build_bundle(None, mesh_size=seat.mesh_size, order=seat.order, load=seat.load,
                               volume_size=seat.volume_size, young=seat.young, poisson=seat.poisson, progress=False)
    scene = Scene.default() if duration is None else Scene.default().with_(duration=duration)
    return hailstorm.runtime.run_storm(hailstorm.runtime.load(gf_path), scene, progress=False)


def _validity_keys(stats) -> dict:
    from hailstorm.runtime.storm.limits import VALIDITY_KEYS

    return {k: stats[k] for k in ("hailstones", "impacts", "max_indentation_m", "max_patch_radius_m", *VALIDITY_KEYS,
                                  "wall_time_s", "inertia_time_s")}


def storm_validity(gf_path: str | None = None) -> dict:
    """The default storm's summary keys of the validity limits (and ``impacts``)."""
    return _validity_keys(run_default_storm(gf_path).stats)


def impact_spread(stats) -> list[str]:
    """Per impact of a storm (its statistics' validity records): min, median and max of the
    stone radius, ``a/R``, the estimated strain, ``delta/h`` and the local thickness."""
    import numpy as np

    from hailstorm.runtime.storm.limits import contact_time_ratio, peak_strain
    from studies.dynamic_study import LIMIT_DENSITIES

    rec = stats.validity
    if rec is None or rec.n == 0:
        return ["per impact: no impacts"]
    dh, aR, eps = rec.ratios()
    tr = rec.time_ratios()
    hertz = peak_strain(aR, np.zeros_like(aR), rec.poisson)
    rows = [("stone radius R [mm]", 1e3 * np.array(rec.radius)), ("normal speed v [m/s]", np.array(rec.speed)),
            ("a / R", aR), ("estimated peak strain", eps), ("delta / h", dh),
            (f"t_c / T at {rec.pad_density:g} kg/m^3", tr), ("local thickness h [mm]", 1e3 * rec.thickness)]
    lines = [f"{f'per impact ({rec.n} impacts):':<26} {'min':>10} {'median':>8} {'max':>8}"]
    for name, x in rows:
        lines.append(f"  {name:<24} {x.min():10.3g} {np.median(x):8.3g} {x.max():8.3g}")
    lines.append(f"  the strain is Hertz's term ((2/pi)(1-2nu)/(1-nu) a/R) in {int((hertz >= dh).sum())} of "
                 f"{rec.n} impacts, the layer's (delta/h) in the others")
    fac = rec.inertia() if rec.measure_inertia else None
    if fac is not None:
        for name, x in (("inertia: peak force", fac.force), ("inertia: contact time", fac.duration),
                        ("inertia: rebound speed", fac.restitution), ("inertia: dent", fac.dent)):
            lines.append(f"  {name + ' x':<24} {np.nanmin(x):10.3g} {np.nanmedian(x):8.3g} {np.nanmax(x):8.3g}")
    limit = rec.limits.contact_time
    for rho in LIMIT_DENSITIES:
        t = contact_time_ratio(rec.mass, rec.radius, rec.speed, rec.thickness, rec.young, rec.poisson, rho)
        ok = np.array(rec.radius)[t >= limit]
        lines.append(f"  with the pad at {rho:g} kg/m^3: {int((t < limit).sum())} of {rec.n} impacts below t_c/T "
                     f"{limit:g}" + (f" (the smallest stone within it: R = {1e3 * ok.min():.1f} mm)" if ok.size else ""))
    if fac is None:
        return lines
    from hailstorm.runtime.inertia import inertia_factors

    F = np.array(rec.force)
    for rho in LIMIT_DENSITIES:
        f = fac if rho == rec.pad_density else inertia_factors(rec.radius, rec.mass, rec.speed, rec.thickness,
                                                                rec.young, rec.poisson, rho)
        change = f.largest_change()
        beyond = change > rec.limits.inertia
        within = np.array(rec.radius)[~beyond]
        smallest = f"; the smallest stone within it: R = {1e3 * within.min():.1f} mm" if within.size else ""
        lines.append(f"  the pad's inertia at {rho:g} kg/m^3: {int(beyond.sum())} of {rec.n} impacts changed by more "
                     f"than {100 * rec.limits.inertia:g} % (the largest change {100 * np.nanmax(change):.1f} %"
                     f"{smallest})")
        lines.append(f"    peak force x{np.nanmin(f.force):.3f}-{np.nanmax(f.force):.3f}; the largest impact "
                     f"{np.nanmax(F * np.where(np.isfinite(f.force), f.force, 1.0)):.1f} N dynamic against "
                     f"{F.max():.1f} N quasi-static; rebound x{np.nanmin(f.restitution):.3f}-"
                     f"{np.nanmax(f.restitution):.3f}")
    return lines


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--full", action="store_true", help="the whole grid (6 speeds x 5 radii)")
    ap.add_argument("--terminal", action="store_true", help="each radius at its terminal fall speed")
    ap.add_argument("--limit", action="store_true",
                    help="the whole grid at 70 and 200 kg/m^3 sorted by the storm's contact-time measure t_c/T")
    ap.add_argument("--density", type=float, default=None, help="foam density [kg/m^3] (default 70)")
    ap.add_argument("--speeds", type=float, nargs="+", default=None, help="impact speeds [m/s] (instead of the grid's)")
    ap.add_argument("--storm-block", action="store_true",
                    help="the same impacts in the storm, on a block bundle of the pad (6 mm, P2)")
    ap.add_argument("--no-storm", action="store_true", help="skip the default storm's validity counts")
    ap.add_argument("--no-table", action="store_true", help="skip the peer's table (the default storm's counts only)")
    ap.add_argument("--gf", default=None, help="bundle directory of the storm (default: the default seat's)")
    ap.add_argument("--duration", type=float, default=None, help="the storm's simulated time [s] (default: the scene's)")
    ap.add_argument("--plot", default=None, metavar="PATH", help="chart the table's rows into PATH (PNG)")
    ap.add_argument("--corrections", action="store_true",
                    help="also what a one-number correction matched to the peak force would predict")
    record.add_out_option(ap)
    args = ap.parse_args(argv)
    if args.no_table and args.no_storm:
        ap.error("--no-table and --no-storm leave nothing to run")

    return record.run_or_record(args.out, "python tests/benchmarks/dynamic_peer.py", argv, lambda: _run(args))


def _run(args: argparse.Namespace) -> int:
    from studies.dynamic_study import main as table

    if not args.no_table:
        table((["--storm"] if args.storm_block else []) + (["--full"] if args.full else [])
              + (["--limit"] if args.limit else [])
              + (["--terminal", "--radii", "0.0025", "0.005", "0.0075", "0.01", "0.0125"] if args.terminal else [])
              + ([] if args.density is None else ["--density", str(args.density)])
              + ([] if args.speeds is None else ["--speeds", *map(str, args.speeds)])
              + ([] if args.plot is None else ["--plot", args.plot])
              + (["--corrections"] if args.corrections else []))
    if not args.no_storm:
        from hailstorm.runtime.storm.limits import validity_warning

        stats = run_default_storm(args.gf, args.duration).stats
        v = _validity_keys(stats)
        seat = "the default seat" if args.gf is None else f"the bundle {args.gf}"
        print(f"\ndefault storm (hailstorm storm's scene, on {seat}): validity keys of summary.json")
        for k, x in v.items():
            print(f"  {k:<36} {x:.4g}" if isinstance(x, float) else f"  {k:<36} {x}")
        print("\n".join(impact_spread(stats)))
        print("warning: " + (validity_warning(v) or "none"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
