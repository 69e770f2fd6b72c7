"""Your own geometry: a ``.geo`` with ``top`` and ``clamp`` groups, from the command line to a storm.

Usage::

    python examples/user_geometry.py            # mesh size 5 mm, a 0.2 s storm with its video
    python examples/user_geometry.py --small    # mesh size 10 mm, a 0.03 s storm, no video (seconds)

Runs, as a user would type them (``DIR`` is ``--out``, default ``./user-geometry-out``)::

    hailstorm precompute --geometry examples/geometries/block.geo --young 5e5 --poisson 0.4 \\
        --mesh-size H --out DIR/block-gf
    hailstorm info DIR/block-gf
    hailstorm storm --gf DIR/block-gf --duration T --stones N --out DIR/storm

``block.geo`` is a rubber block with rounded top edges: every face but the
underside is ``Physical Surface("top")``, the underside ``Physical Surface("clamp")``.
A STEP or BREP file with the same two groups, or a tetrahedral mesh (any format
meshio reads) with those cell sets, works the same way.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

GEO = Path(__file__).resolve().parent / "geometries" / "block.geo"


def hailstorm(*args: str) -> None:
    print("$ hailstorm " + " ".join(args), flush=True)
    subprocess.run([sys.executable, "-m", "hailstorm", *args], check=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="coarse mesh, short storm, no video (seconds)")
    ap.add_argument("--out", type=Path, default=Path("user-geometry-out"))
    args = ap.parse_args(argv)
    gf, storm = args.out / "block-gf", args.out / "storm"
    h, duration, stones = ("0.01", "0.03", "5") if args.small else ("0.005", "0.2", "30")
    quiet = ["-q"] if args.small else []
    hailstorm("precompute", "--geometry", str(GEO), "--young", "5e5", "--poisson", "0.4", "--mesh-size", h,
              "--out", str(gf), *quiet)
    hailstorm("info", str(gf))
    hailstorm("storm", "--gf", str(gf), "--duration", duration, "--stones", stones, "--out", str(storm),
              *quiet, *(["--no-video"] if args.small else []))
    s = json.loads((storm / "summary.json").read_text())
    print(f"summary.json: {s['hailstones']} stones, {s['impacts']} impacts, largest contact force "
          f"{s['max_contact_force']:.3g} N on a seat of {s['n_vertices']} vertices")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
