"""What ``--coarsening`` buys and costs on the default seat: the volume's size, the factor's, and the pad's
compliance under smooth loads.

For each coarsening C (the volume's elements grow to C mesh sizes away from the top): the mesh's
vertices (on the top and in all), the free dofs, nnz(L) of the stiffness' Cholesky factor
(:func:`hailstorm.precompute.greens.cholesky_nnz`: the minimum-degree ordering the supernodal solver
uses) and its time, and the pad's compliance under three Gaussian pressures (``sigma`` 4 mm, normal
to the plan, at the rear, middle and nose) as the load-weighted mean dent per newton, by a direct
solve; relative to the first coarsening in the list. The loads are smooth, so the top meshes of the
different runs (gmsh meshes each anew) need not match vertex for vertex.

``python -m studies.coarsening_study [--mesh-size 0.0015] [--order 1] [--coarsenings 2.5,5,10]``
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from studies import record

__all__ = ["LOAD_SIGMA", "PLAN_POINTS", "coarsening_row", "main"]

#: where the Gaussian loads are centred on the seat's plan [m]: rear, middle, nose
PLAN_POINTS = ((0.20, 0.0), (0.12, 0.0), (0.04, 0.0))
#: the Gaussian loads' standard deviation [m]
LOAD_SIGMA = 0.004


def coarsening_row(mesh_size: float, coarsening: float, order: int = 1, young: float = 2e6,
                   poisson: float = 0.35) -> dict[str, float | list[float]]:
    """The default seat meshed at ``mesh_size`` with ``coarsening``: its counts, its factor's nnz(L) and
    seconds, and its compliance [m/N] under each of :data:`PLAN_POINTS`' Gaussian loads."""
    from hailstorm.precompute import fem
    from hailstorm.precompute.geometry import mesh_default_seat
    from hailstorm.precompute.greens import cholesky_nnz, lumped_areas
    from hailstorm.precompute.pipeline import extract_surface

    mesh = mesh_default_seat(mesh_size, coarsening=coarsening, order=order, allow_large=True)
    surface = extract_surface(mesh)
    basis = fem.elasticity_basis(mesh, order)
    K = fem.stiffness_matrix(basis, young, poisson).tocsr()
    fixed = fem.clamp_dofs(basis, mesh)
    free = fem.free_dofs(K.shape[0], fixed)
    t0 = time.perf_counter()
    nnz = cholesky_nnz(K[free][:, free])
    t_factor = time.perf_counter() - t0
    nodes = surface.nodes[surface.contactable]
    plan = mesh.points[nodes]
    areas = lumped_areas(mesh.points[surface.nodes], surface.triangles)[surface.contactable]
    z = fem.vertex_dofs(basis, nodes)[:, 2]
    F = np.zeros((K.shape[0], len(PLAN_POINTS)))
    weights = []
    for k, (x, y) in enumerate(PLAN_POINTS):
        w = np.exp(-((plan[:, 0] - x) ** 2 + (plan[:, 1] - y) ** 2) / (2 * LOAD_SIGMA**2)) * areas
        w /= w.sum()
        F[z, k] = -w  # 1 N down in all
        weights.append(w)
    u = fem.solve_direct(K, F, fixed)
    return {"coarsening": coarsening, "top": int(mesh.group_vertices("top").size), "points": int(mesh.points.shape[0]),
            "dofs": int(free.size), "nnz_L": nnz, "factor_s": t_factor,
            "compliance": [float(-(weights[k] @ u[z, k])) for k in range(len(PLAN_POINTS))]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m studies.coarsening_study", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mesh-size", type=float, default=0.0015, help="the top's mesh size [m] (default 0.0015)")
    ap.add_argument("--order", type=int, choices=(1, 2), default=1)
    ap.add_argument("--coarsenings", default="2.5,5,10", help="comma-separated (default 2.5,5,10)")
    ap.add_argument("--out", type=Path, default=None, help="also write the output there (with its header)")
    args = ap.parse_args(argv)
    try:
        cs = [float(c) for c in args.coarsenings.split(",") if c]
    except ValueError:
        ap.error(f"--coarsenings takes numbers, got {args.coarsenings!r}")
    if not cs:
        ap.error("--coarsenings: none given")

    def run() -> None:
        print(f"default seat at {args.mesh_size * 1e3:g} mm, P{args.order}; Gaussian loads (sigma "
              f"{LOAD_SIGMA * 1e3:g} mm) at the rear, middle and nose; compliance relative to C = {cs[0]:g}")
        print()
        print("| C | top vertices | vertices | free dofs | nnz(L) | factor s | compliance um/N rear / middle / nose "
              "| relative |")
        print("|---|---|---|---|---|---|---|---|")
        base = None
        for c in cs:
            r = coarsening_row(args.mesh_size, c, args.order)
            comp = np.array(r["compliance"])
            base = comp if base is None else base
            print(f"| {c:g} | {r['top']:,} | {r['points']:,} | {r['dofs']:,} | {r['nnz_L']:,} | {r['factor_s']:.1f} | "
                  + " / ".join(f"{1e6 * v:.3f}" for v in comp) + " | "
                  + " / ".join(f"{100 * v:+.1f} %" for v in comp / base - 1) + " |", flush=True)

    if args.out is None:
        run()
    else:
        record.whole_output(args.out, "python -m studies.coarsening_study", sys.argv[1:] if argv is None
                            else argv, run)
    return 0


if __name__ == "__main__":
    sys.exit(main())
