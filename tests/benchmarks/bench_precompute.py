"""Benchmark: Green's-function precompute against a plain SuperLU baseline.

Both compute the same compliance D on the same seat; each repetition runs in a
fresh process so its peak memory (max RSS) is its own. Prints min/median/max
wall time per method and the speed-up of each against the baseline measured
in the same run (the machine is shared and noisy: compare ratios).

    python tests/benchmarks/bench_precompute.py --mesh-size 0.01 --order 1 --repeat 3

Methods
-------
baseline   scipy.sparse.linalg.splu once, then one solve per column (plain)
splu       the same factorization, right-hand sides in memory-bounded blocks
cholmod    CHOLMOD sparse Cholesky (cholespy), fill-reducing ordering, blocks
cholmod-N  the same in N worker processes (default: one per core when it pays)
amg        pyamg smoothed aggregation + CG per column (tol 1e-8), optional
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import tempfile
import resource
import statistics
import time

import numpy as np


def _setup(mesh_size: float, order: int):
    from hailstorm.precompute import mesh_default_seat
    from hailstorm.precompute.fem import DEFAULT_POISSON, DEFAULT_YOUNG, clamp_dofs, elasticity_basis, stiffness_matrix, vertex_dofs
    from hailstorm.precompute.pipeline import extract_surface

    mesh = mesh_default_seat(mesh_size)
    surf = extract_surface(mesh)
    basis = elasticity_basis(mesh, order)
    K = stiffness_matrix(basis, DEFAULT_YOUNG, DEFAULT_POISSON)
    fixed = clamp_dofs(basis, mesh)
    load = vertex_dofs(basis, surf.nodes[surf.contactable]).ravel()
    read = vertex_dofs(basis, surf.nodes).ravel()
    return basis, K, fixed, load, read


def _baseline(K, fixed, load, read):
    from scipy.sparse.linalg import splu

    from hailstorm.precompute.fem import free_dofs

    free = free_dofs(K.shape[0], fixed)
    where = np.full(K.shape[0], -1)
    where[free] = np.arange(free.size)
    lu = splu(K[free][:, free].tocsc())
    D = np.zeros((read.size, load.size))
    live = where[read] >= 0
    e = np.zeros(free.size)
    for k, dof in enumerate(load):
        e[:] = 0.0
        e[where[dof]] = 1.0
        D[live, k] = lu.solve(e)[where[read[live]]]
    return D


def _one(method: str, mesh_size: float, order: int, queue) -> None:
    basis, K, fixed, load, read = _setup(mesh_size, order)
    t0 = time.perf_counter()
    if method == "baseline":
        D = _baseline(K, fixed, load, read)
    else:
        from hailstorm.precompute.greens import compliance_matrix
        from hailstorm.precompute.pipeline import _rigid_modes_on_dofs

        solver, _, workers = method.partition("-")
        nn = _rigid_modes_on_dofs(basis) if solver == "amg" else None
        D = compliance_matrix(K, fixed, load, read, solver=solver, near_null=nn, tol=1e-8,
                              workers=int(workers) if workers else None)
    dt = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # MiB on Linux
    np.save(os.path.join(tempfile.gettempdir(), f"hailstorm-bench-D-{method}.npy"), D[:, :: max(1, D.shape[1] // 50)])
    queue.put((dt, rss, K.shape[0], D.shape))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--mesh-size", type=float, default=0.01)
    ap.add_argument("--order", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--methods", default="baseline,cholmod-1,cholmod")
    args = ap.parse_args()
    ctx = mp.get_context("spawn")
    results: dict[str, list] = {}
    methods = args.methods.split(",")
    for rep in range(args.repeat):
        for method in methods:  # interleaved, so drift in machine load hits all alike
            q = ctx.Queue()
            p = ctx.Process(target=_one, args=(method, args.mesh_size, args.order, q))
            p.start()
            out = q.get()
            p.join()
            results.setdefault(method, []).append(out)
    n_dofs, shape = results[methods[0]][0][2], results[methods[0]][0][3]
    print(f"default seat, mesh size {args.mesh_size} m, P{args.order}: {n_dofs} dofs, D {shape[0]} x {shape[1]}, "
          f"{args.repeat} runs each")
    base = statistics.median(r[0] for r in results.get("baseline", results[methods[0]]))
    tmp = tempfile.gettempdir()
    ref = np.load(os.path.join(tmp, f"hailstorm-bench-D-{methods[0]}.npy"))
    print(f"{'method':10s} {'min s':>8s} {'median s':>9s} {'max s':>8s} {'speed-up':>9s} {'peak MiB':>9s} {'rel. diff':>10s}")
    for method in methods:
        t = [r[0] for r in results[method]]
        mem = max(r[1] for r in results[method])
        D = np.load(os.path.join(tmp, f"hailstorm-bench-D-{method}.npy"))
        diff = np.linalg.norm(D - ref) / np.linalg.norm(ref)
        print(f"{method:10s} {min(t):8.3f} {statistics.median(t):9.3f} {max(t):8.3f} "
              f"{base / statistics.median(t):8.1f}x {mem:9.0f} {diff:10.1e}")


if __name__ == "__main__":
    main()
