"""Benchmark: point-contact solves through the Green's functions vs a direct FEM solve.

Usage::

    python tests/benchmarks/bench_contacts.py                 # default seat, h = 0.01 (built/cached)
    python tests/benchmarks/bench_contacts.py --gf DIR        # an existing bundle
    python tests/benchmarks/bench_contacts.py --mesh-size 0.007 --repeat 200

For s in {1, 10, 100} random contacts on contactable triangles it times
``runtime.solve_contacts`` with full-surface deformation (min / median / max
over repeats), one direct FEM saddle-point solve with the same constraints
(scipy sparse direct, clamp eliminated, the stiffness assembled beforehand and
not timed), and a Sherman-Morrison-Woodbury ``Capacitance.add`` against a fresh
``capacitance`` build. Targets: s = 100 solve + full-surface deformation
<= 1 ms median; s = 10 >= 1e4 x faster than the direct FEM solve.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from runtime.bundle import load
from runtime.contact import capacitance, solve_contacts, triangle_normals


def timeit(fn, repeat: int, warmup: int = 3) -> np.ndarray:
    """Wall-clock seconds of ``repeat`` calls of ``fn`` (after ``warmup`` calls)."""
    for _ in range(warmup):
        fn()
    out = np.empty(repeat)
    for i in range(repeat):
        t0 = time.perf_counter()
        fn()
        out[i] = time.perf_counter() - t0
    return out


def get_bundle(args) -> Path:
    if args.gf:
        return Path(args.gf)
    import precompute

    cache = Path(args.cache) if args.cache else Path(tempfile.gettempdir()) / "hailstorm-bench"
    out = cache / f"seat-h{args.mesh_size:g}-p{args.order}"
    t0 = time.perf_counter()
    path = precompute.build_bundle(out, mesh_size=args.mesh_size, order=args.order)
    print(f"bundle {path} ready in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return path


def direct_fem_setup(gf):
    """Stiffness of the bundle's own volume mesh (independent of D), clamp eliminated."""
    from precompute import fem
    from precompute.geometry import TetMesh

    order = gf.order
    clamp_tris = gf.triangles[gf.fixed[gf.triangles].all(axis=1)]
    mesh = TetMesh(np.asarray(gf.volume_points), np.asarray(gf.volume_tets),
                   {"clamp": gf.surface_nodes[clamp_tris], "top": gf.surface_nodes[gf.triangles]},
                   source="bundle")
    basis = fem.elasticity_basis(mesh, order)
    K = fem.stiffness_matrix(basis, gf.young, gf.poisson)
    clamp = fem.clamp_dofs(basis, mesh)
    free = fem.free_dofs(K.shape[0], clamp)
    return dict(basis=basis, Kff=K[free][:, free].tocsr(), free=free, ndof=K.shape[0], fem=fem)


def direct_fem_solve(gf, ref, tri, bary, ubar):
    """Saddle-point [[K, C^T], [C, 0]] solve for sticky contacts; returns seat forces and u."""
    fem, basis = ref["fem"], ref["basis"]
    s = len(tri)
    dofs = fem.vertex_dofs(basis, gf.surface_nodes[gf.triangles[tri]].ravel()).reshape(s, 3, 3)
    rows = np.repeat(np.arange(3 * s).reshape(s, 1, 3), 3, axis=1)  # (k, a, d) -> row 3k + d
    vals = np.repeat(bary[:, :, None], 3, axis=2)
    C = sp.csr_matrix((vals.ravel(), (rows.ravel(), dofs.ravel())), shape=(3 * s, ref["ndof"]))[:, ref["free"]]
    A = sp.bmat([[ref["Kff"], C.T], [C, None]], format="csc")
    nf = ref["free"].size
    sol = spla.spsolve(A, np.concatenate([np.zeros(nf), ubar.ravel()]))
    return -sol[nf:].reshape(s, 3), sol[:nf]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gf", help="bundle directory (default: build the default seat)")
    ap.add_argument("--mesh-size", type=float, default=0.01)
    ap.add_argument("--order", type=int, default=1)
    ap.add_argument("--cache", help="where to build the default bundle (default: $TMPDIR/hailstorm-bench)")
    ap.add_argument("--repeat", type=int, default=100)
    ap.add_argument("--fem-repeat", type=int, default=3)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1, 10, 100])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-fem", action="store_true", help="skip the direct FEM comparison")
    ap.add_argument("--threads", type=int, default=1,
                    help="BLAS threads (default 1: the dense systems are small; 0 = library default)")
    args = ap.parse_args(argv)
    if args.threads > 0:
        try:
            from threadpoolctl import threadpool_limits

            threadpool_limits(args.threads)
        except ImportError:
            print("threadpoolctl not installed; set OMP_NUM_THREADS to limit BLAS threads", file=sys.stderr)

    gf = load(get_bundle(args), mmap=False)
    n, nc = gf.n_vertices, int(gf.contactable.sum())
    print(f"bundle: {n} surface vertices, {nc} contactable, D {gf.D.shape[0]} x {gf.D.shape[1]} "
          f"({gf.D.nbytes / 2**20:.0f} MiB), order P{gf.order}")
    tris = np.flatnonzero(gf.contactable[gf.triangles].all(axis=1))
    rng = np.random.default_rng(args.seed)
    ref = None if args.no_fem else direct_fem_setup(gf)
    if ref is not None:
        print(f"direct FEM: {ref['ndof']} dofs, {ref['free'].size} free, K nnz {ref['Kff'].nnz}")

    ms = 1e3
    header = (f"{'s':>4} {'|V|':>4} | {'solve+u(all) min/med/max [ms]':>31} | {'forces only med':>15} | "
              f"{'FEM [ms]':>9} {'ratio':>8} {'err':>8}")
    print(header)
    print("-" * len(header))
    for s in args.sizes:
        tri = rng.choice(tris, size=s, replace=s > tris.size)
        bary = rng.dirichlet([1.0, 1.0, 1.0], size=s)
        nrm = triangle_normals(gf.vertices, gf.triangles[tri])
        ubar = -1e-3 * nrm + rng.normal(scale=2e-4, size=(s, 3))
        t_full = timeit(lambda: solve_contacts(gf, tri, bary, ubar), args.repeat)
        t_forces = timeit(lambda: solve_contacts(gf, tri, bary, ubar, rows=None), args.repeat)
        V = np.unique(gf.triangles[tri]).size
        fem_col = f"{'-':>9} {'-':>8} {'-':>8}"
        if ref is not None:
            f_ref = None

            def run_fem():
                nonlocal f_ref
                f_ref, _ = direct_fem_solve(gf, ref, tri, bary, ubar)

            t_fem = timeit(run_fem, args.fem_repeat, warmup=1)
            f = solve_contacts(gf, tri, bary, ubar, rows=None).forces
            err = np.abs(f - f_ref).max() / np.abs(f_ref).max()
            fem_col = f"{np.median(t_fem) * ms:9.2f} {np.median(t_fem) / np.median(t_full):8.0f} {err:8.1e}"
        print(f"{s:4d} {V:4d} | {t_full.min() * ms:9.3f} {np.median(t_full) * ms:10.3f} {t_full.max() * ms:10.3f} | "
              f"{np.median(t_forces) * ms:15.3f} | {fem_col}")
        floor_case = (s, tri)

    if args.sizes:
        print_floor(gf, *floor_case, repeat=args.repeat)

    # Sherman-Morrison-Woodbury add vs fresh build (both followed by one force solve)
    print()
    print(f"{'s':>4} | {'SMW add+forces [ms]':>19} | {'fresh build+forces [ms]':>23} | {'gain':>6} | "
          f"{'max rel diff K':>14}")
    for s in args.sizes:
        if s < 2:
            continue
        tri = rng.choice(tris, size=s, replace=s > tris.size)
        bary = rng.dirichlet([1.0, 1.0, 1.0], size=s)
        ubar = rng.normal(scale=1e-3, size=(s, 3))
        base = capacitance(gf, tri[:-1], bary[:-1])
        caps = []

        def smw():
            c = _copy(base)
            t0 = time.perf_counter()
            c.add(int(tri[-1]), bary[-1])
            c.forces(ubar)
            dt = time.perf_counter() - t0
            caps[:] = [c]
            return dt

        t_smw = np.array([smw() for _ in range(args.repeat)])
        t_fresh = timeit(lambda: capacitance(gf, tri, bary).forces(ubar), args.repeat)
        fresh = capacitance(gf, tri, bary)
        diff = np.abs(caps[-1].K - fresh.K).max() / np.abs(fresh.K).max()
        print(f"{s:4d} | {np.median(t_smw) * ms:19.3f} | {np.median(t_fresh) * ms:23.3f} | "
              f"{np.median(t_fresh) / np.median(t_smw):6.1f} | {diff:14.1e}")
    return 0


def print_floor(gf, s: int, tri: np.ndarray, repeat: int) -> None:
    """Memory-bound floor of the full-surface deformation for the last contact set.

    ``u = D[:, cols] B f`` must read every column of D that a contacted vertex
    owns (``|cols| x n_rows x 8`` bytes): time a plain numpy ``D[:, cols] @ g``
    and a plain column copy ``D[:, cols]`` of that size (no solve, no
    gathers of D_VV), plus one full ``D @ x`` for the streaming bandwidth.
    """
    ms = 1e3
    D = np.asarray(gf.D)
    cb = np.asarray(gf.column_of)[np.unique(gf.triangles[tri])]
    cols = (3 * cb[cb >= 0][:, None] + np.arange(3)).ravel()
    g = np.random.default_rng(1).normal(size=cols.size)
    x = np.zeros(D.shape[1])
    x[cols] = g
    mb = cols.size * D.shape[0] * D.itemsize / 1e6
    t_mv = timeit(lambda: D[:, cols] @ g, repeat)
    t_cp = timeit(lambda: D[:, cols], repeat)
    t_all = timeit(lambda: D @ x, max(repeat // 5, 3))
    gbs = D.nbytes / 1e9 / np.median(t_all)
    print()
    print(f"floor (memory-bound, s = {s}: {cols.size} columns of D x {D.shape[0]} rows = {mb:.1f} MB read; "
          f"min/med/max [ms]):")
    print(f"  numpy D[:, cols] @ g  {t_mv.min() * ms:9.3f} {np.median(t_mv) * ms:10.3f} {t_mv.max() * ms:10.3f}")
    print(f"  column copy D[:, cols] {t_cp.min() * ms:8.3f} {np.median(t_cp) * ms:10.3f} {t_cp.max() * ms:10.3f}")
    print(f"  full D @ x ({D.nbytes / 1e6:.0f} MB) {t_all.min() * ms:7.3f} {np.median(t_all) * ms:10.3f} "
          f"{t_all.max() * ms:10.3f}  -> {gbs:.1f} GB/s; {mb:.1f} MB at that rate: {mb / 1e3 / gbs * ms:.3f} ms")


def _copy(cap):
    import copy

    c = copy.copy(cap)
    cap.K  # form the explicit capacitance once (as a running storm would have it)
    for name in ("tri_idx", "bary", "normals", "V", "loc", "D_VV", "W", "rigid", "_cols", "_K"):
        setattr(c, name, getattr(cap, name).copy())
    return c


if __name__ == "__main__":
    raise SystemExit(main())
