"""Where the quasi-static model holds: the dynamic FEM peer's table and the default storm's validity counts.

Usage::

    python tests/benchmarks/dynamic_peer.py                 # small grid (3 speeds x 2 radii) + the default storm
    python tests/benchmarks/dynamic_peer.py --full          # speeds 1-30 m/s x radii 2.5-12.5 mm (6 x 5)
    python tests/benchmarks/dynamic_peer.py --terminal      # each radius at its terminal speed (the default storm)
    python tests/benchmarks/dynamic_peer.py --terminal --storm-block   # and the same impacts in the storm
    python tests/benchmarks/dynamic_peer.py --no-storm      # the table only
    python tests/benchmarks/dynamic_peer.py --density 50    # another foam density [kg/m^3]

The table is :func:`hailstorm.studies.dynamic_study.main`'s: one rigid ice sphere on the
default seat's foam pad (a 15 mm disc on a rigid base), dynamic (the pad's mass,
Newmark average acceleration) against quasi-static (the same mesh without mass: the
Green's-function assumption) and Hertz's half-space impact; the last column says where
the quasi-static model is within 5 % of the dynamic one on peak force, contact duration,
rebound speed and largest dent. Then the default storm (``hailstorm storm``'s scene and
cached seat bundle, or ``--gf DIR``) and its validity keys (docs/validity.md).
"""

from __future__ import annotations

import argparse


def storm_validity(gf_path: str | None = None) -> dict:
    """The default storm's summary keys of the validity limits (and ``impacts``)."""
    import hailstorm.runtime
    from hailstorm.runtime.storm.scene import Scene, SeatSettings
    from hailstorm.runtime.storm.limits import VALIDITY_KEYS

    if gf_path is None:
        from hailstorm.precompute import build_bundle

        seat = SeatSettings.default()
        gf_path = build_bundle(None, mesh_size=seat.mesh_size, order=seat.order, load=seat.load,
                               volume_size=seat.volume_size, young=seat.young, poisson=seat.poisson, progress=False)
    res = hailstorm.runtime.run_storm(hailstorm.runtime.load(gf_path), Scene.default(), progress=False)
    return {k: res.stats[k] for k in ("hailstones", "impacts", "max_indentation_m", "max_patch_radius_m", *VALIDITY_KEYS)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--full", action="store_true", help="the whole grid (6 speeds x 5 radii)")
    ap.add_argument("--terminal", action="store_true", help="each radius at its terminal fall speed")
    ap.add_argument("--density", type=float, default=None, help="foam density [kg/m^3] (default 70)")
    ap.add_argument("--storm-block", action="store_true",
                    help="the same impacts in the storm, on a block bundle of the pad (6 mm, P2)")
    ap.add_argument("--no-storm", action="store_true", help="skip the default storm's validity counts")
    ap.add_argument("--gf", default=None, help="bundle directory of the storm (default: the default seat's)")
    args = ap.parse_args()

    from hailstorm.studies.dynamic_study import main as table

    table((["--storm"] if args.storm_block else []) + (["--full"] if args.full else []) + (["--terminal", "--radii", "0.0025", "0.005", "0.0075", "0.01", "0.0125"]
                                               if args.terminal else []) + ([] if args.density is None else ["--density", str(args.density)]))
    if not args.no_storm:
        from hailstorm.runtime.storm.limits import validity_warning

        v = storm_validity(args.gf)
        print("\ndefault storm (hailstorm storm's scene and seat): validity keys of summary.json")
        for k, x in v.items():
            print(f"  {k:<36} {x:.4g}" if isinstance(x, float) else f"  {k:<36} {x}")
        print("warning: " + (validity_warning(v) or "none"))


if __name__ == "__main__":
    main()
