"""A layered body, one material per volume: ``--material`` on the command line.

Usage::

    python examples/layered_materials.py            # mesh size 3 mm
    python examples/layered_materials.py --small    # mesh size 4 mm, P1 (seconds)

Both put nodes inside each layer, the same size throughout (``--coarsening 1``): a layer
one element thick is poorly resolved, and ``hailstorm precompute`` warns about it (P2 at
3 mm; P1 at 4 mm, a node layer inside the 8 mm shell).

Runs, as a user would type them::

    hailstorm precompute --geometry examples/geometries/layered.geo \\
        --material pad=0.5e6,0.3 --material shell=2e9,0.4 --mesh-size H --coarsening 1 --out DIR/layered
    hailstorm precompute --geometry examples/geometries/layered.geo \\
        --material pad=0.5e6,0.3 --material shell=0.5e6,0.3 --mesh-size H --coarsening 1 --out DIR/uniform

then loads both bundles and compares the dent under a 1 N point force at the
middle of the top face: the stiff shell under the pad makes it shallower than a
body of foam alone. The bundles go to ``--out`` (default ``./layered-out``).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

from hailstorm import runtime

GEO = Path(__file__).resolve().parent / "geometries" / "layered.geo"


def precompute(out: Path, shell: str, mesh_size: float, order: int) -> Path:
    cmd = [sys.executable, "-m", "hailstorm", "precompute", "--geometry", str(GEO), "--material", "pad=0.5e6,0.3",
           "--material", f"shell={shell}", "--mesh-size", str(mesh_size), "--coarsening", "1", "--order", str(order),
           "--out", str(out), "-q"]
    print("$ hailstorm " + " ".join(cmd[3:]))
    subprocess.run(cmd, check=True)
    return out


def centre_dent(gf: runtime.GreensFunctions) -> tuple[float, np.ndarray]:
    """Depth [m] of the dent at the contactable vertex nearest the top face's centre under 1 N down."""
    lo, hi = gf.vertices.min(axis=0), gf.vertices.max(axis=0)
    centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2]])
    cand = np.flatnonzero(gf.contactable)
    v = int(cand[np.argmin(np.linalg.norm(gf.vertices[cand] - centre, axis=1))])
    column = gf.compliance([v], [v])            # (3, 3): displacement of v per unit force at v
    return float(column[2, 2]), gf.vertices[v]   # u_z = D_zz * (-1 N): a dent of depth D_zz


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="a coarser mesh, 4 mm P1 (seconds)")
    ap.add_argument("--out", type=Path, default=Path("layered-out"))
    args = ap.parse_args(argv)
    h, order = (0.004, 1) if args.small else (0.003, 2)
    layered = runtime.load(precompute(args.out / "layered", "2e9,0.4", h, order))
    uniform = runtime.load(precompute(args.out / "uniform", "0.5e6,0.3", h, order))
    for name, gf in (("layered", layered), ("uniform", uniform)):
        mats = ", ".join(f"{m['volume']}: E = {m['young']:g} Pa, nu = {m['poisson']:g}"
                         for m in gf.manifest["materials"])
        print(f"{name}: {mats}; per tetrahedron E from {gf.tet_young.min():g} to {gf.tet_young.max():g} Pa")
    d_layered, x = centre_dent(layered)
    d_uniform, _ = centre_dent(uniform)
    print(f"1 N down at ({x[0] * 1e3:.1f}, {x[1] * 1e3:.1f}, {x[2] * 1e3:.1f}) mm: dent {d_layered * 1e3:.3f} mm "
          f"on the stiff shell, {d_uniform * 1e3:.3f} mm on foam alone ({d_layered / d_uniform:.2f}x)")
    if not d_layered < d_uniform:
        raise SystemExit("unexpected: the stiff shell did not make the dent shallower")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
