"""Speed against accuracy of the precompute: what a finer mesh or P2 costs and what it buys.

Usage::

    python examples/speed_vs_accuracy.py                    # 5 mesh sizes, P1 and P2, on the block
    python examples/speed_vs_accuracy.py --small            # 3 coarse sizes (seconds)
    python examples/speed_vs_accuracy.py --out plot.png     # where the plot goes (default speed_vs_accuracy.png)

On ``examples/geometries/block.geo`` it builds a bundle per mesh size and
element order (``build_bundle(reuse=False)``, timed), and measures the
quantity a stone feels: the stiffness of a Hertz patch contact (radius 4 mm,
frictionless) at the middle of the top face, ``1 / (n . W n)`` from
:func:`hailstorm.runtime.capacitance`. The error of each setting is against the
finest P2 bundle of the run (so the finest P2 point itself is not plotted).
Plots precompute seconds against that error, one line per order.

The project's full study, on the seat with an independent reference, is
``python -m studies.study`` (see the docs' "Choosing settings").
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from hailstorm import precompute, runtime

GEO = Path(__file__).resolve().parent / "geometries" / "block.geo"
PATCH_RADIUS = 0.004


def patch_stiffness(gf: runtime.GreensFunctions) -> float:
    """Normal stiffness [N/m] of a Hertz patch at the up-facing triangle nearest the top face's centre."""
    X = gf.vertices[gf.triangles]
    n = np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    lo, hi = gf.vertices.min(axis=0), gf.vertices.max(axis=0)
    centre = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2])
    up = np.flatnonzero((n[:, 2] > 0.99) & gf.contactable[gf.triangles].all(axis=1))
    t = int(up[np.argmin(np.linalg.norm(X[up, :, :2].mean(axis=1) - centre, axis=1))])
    cap = runtime.capacitance(gf, [t], [[1 / 3, 1 / 3, 1 / 3]], mode="frictionless", patch_radius=PATCH_RADIUS)
    return float(1.0 / cap.W[0, 0])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="three coarse mesh sizes (seconds)")
    ap.add_argument("--out", type=Path, default=Path("speed_vs_accuracy.png"))
    args = ap.parse_args(argv)
    sizes = [0.016, 0.011, 0.009] if args.small else [0.013, 0.009, 0.007, 0.0055, 0.0045]

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for order in (1, 2):
            for h in sizes:
                t0 = time.perf_counter()
                path = precompute.build_bundle(Path(tmp) / f"p{order}-{h}", geometry=GEO, mesh_size=h, order=order,
                                               young=5e5, poisson=0.4, reuse=False)
                seconds = time.perf_counter() - t0
                gf = runtime.load(path)
                rows.append((order, h, seconds, gf.D.nbytes / 2**20, patch_stiffness(gf)))
    reference = rows[-1][4]   # the finest P2
    print(f"{'order':>5} {'h [mm]':>7} {'precompute [s]':>15} {'D [MiB]':>8} {'k [kN/m]':>9} {'error':>7}")
    for order, h, s, mib, k in rows:
        print(f"{'P%d' % order:>5} {h * 1e3:7.1f} {s:15.2f} {mib:8.2f} {k / 1e3:9.3f} "
              f"{abs(k / reference - 1):7.1%}")

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    for order, marker in ((1, "o"), (2, "s")):
        pts = [(s, abs(k / reference - 1)) for o, h, s, mib, k in rows if o == order]
        if order == 2:
            pts = pts[:-1]    # the reference itself
        ax.loglog(*zip(*pts), marker=marker, label=f"P{order}")
    ax.set_xlabel("precompute wall time [s]")
    ax.set_ylabel("patch stiffness error vs finest P2")
    ax.set_title("block.geo: speed against accuracy")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
