"""A compressed compliance: ``hailstorm precompute --tol``, what ``hailstorm info`` says of it, and the same answers.

Usage::

    python examples/compressed_bundle.py            # the default seat (6 mm, P2, hat loads)
    python examples/compressed_bundle.py --small    # the seat at 12 mm, P1 (seconds)

Runs, as a user would type them (``DIR`` is ``--out``, default ``./compressed-out``)::

    hailstorm precompute --mesh-size 0.006 --load hat --out DIR/dense
    hailstorm precompute --mesh-size 0.006 --load hat --tol 1e-3 --out DIR/compressed
    hailstorm info DIR/compressed

then presses the same spheres into both bundles through the Python API and
prints the largest difference of their forces: within the tolerance, for a
bundle several times smaller on disk.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

TOL = 1e-3


def hailstorm(*args: str) -> None:
    print("$ hailstorm " + " ".join(args), flush=True)
    subprocess.run([sys.executable, "-m", "hailstorm", *args], check=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="a coarse P1 seat (seconds)")
    ap.add_argument("--out", type=Path, default=Path("compressed-out"))
    args = ap.parse_args(argv)
    seat = ["--mesh-size", "0.012", "--order", "1", "--load", "point"] if args.small else \
        ["--mesh-size", "0.006", "--load", "hat"]
    common = [*seat, "-q"]
    hailstorm("precompute", *common, "--out", str(args.out / "dense"))
    hailstorm("precompute", *common, "--tol", str(TOL), "--out", str(args.out / "compressed"))
    hailstorm("info", str(args.out / "compressed"))

    from hailstorm.runtime import load, press_spheres

    dense, compressed = load(args.out / "dense"), load(args.out / "compressed")
    comp = compressed.manifest["compliance"]
    rng = np.random.default_rng(0)
    tri = np.flatnonzero(dense.contactable[dense.triangles].all(axis=1))
    tri = rng.choice(tri, size=min(5, tri.size), replace=False)
    bary = rng.dirichlet(np.ones(3), size=tri.size)
    depth, radius = np.full(tri.size, 0.5e-3), 5e-3
    a = press_spheres(dense, tri, bary, depth, radius).normal_force
    b = press_spheres(compressed, tri, bary, depth, radius).normal_force
    diff = float(np.abs(b - a).max() / np.abs(a).max())
    print(f"D stored: {comp['stored_bytes'] / 2**20:.2f} MiB compressed against {comp['dense_bytes'] / 2**20:.2f} "
          f"MiB dense; {tri.size} spheres pressed together: forces {', '.join(f'{f:.3f}' for f in a)} N, "
          f"largest difference {diff:.1e} of the largest force (tolerance {TOL:g} per column)")
    if not diff <= TOL:
        raise SystemExit(f"the compressed bundle's forces differ by {diff:.2e}, more than {TOL:g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
