"""Benchmark: point-contact solves through the Green's functions vs a direct FEM solve.

Usage::

    python tests/benchmarks/bench_contacts.py                 # default seat, h = 0.01 (built/cached)
    python tests/benchmarks/bench_contacts.py --gf DIR        # an existing bundle
    python tests/benchmarks/bench_contacts.py --mesh-size 0.007 --repeat 200
    python tests/benchmarks/bench_contacts.py --gf DIR --dtype-only   # float32 D against float64, alone

For s in {1, 10, 100} random contacts on contactable triangles it times
``hailstorm.runtime.solve_contacts`` with full-surface deformation (min / median / max
over repeats),
one direct FEM saddle-point solve with the same constraints and loads (hat loads
on a hat-load bundle; scipy sparse direct, clamp eliminated, the stiffness
assembled beforehand and not timed; ``err``: the largest force difference over
the largest force, which on a hat-load bundle is what the contact solves'
symmetric part of ``W`` changes, docs/verification.md, "reciprocity"), and a Sherman-Morrison-Woodbury ``Capacitance.add`` against a fresh
``capacitance`` build. Targets: s = 100 solve + full-surface deformation
<= 1 ms median; s = 10 >= 1e4 x faster than the direct FEM solve.

Last (``--dtype float32``, the default; ``--dtype none`` skips it): the same
solves on a float32 copy of the bundle (:func:`hailstorm.runtime.bundle.read.convert_bundle`,
in a temporary directory), timed interleaved with the float64 ones in the same
run, and the float32 results' error against float64.
"""

from __future__ import annotations

import sys
from pathlib import Path

# the studies (notebooks/studies) are in the repository, not in the package
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "notebooks"))

import argparse
import itertools
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from hailstorm.runtime.bundle.read import load
from hailstorm.runtime.bundle.write import convert_bundle
from hailstorm.runtime.compiled import vertex_block
from hailstorm.runtime.contact import capacitance, solve_contacts, triangle_normals


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


def random_contacts(gf, tris: np.ndarray, rng: np.random.Generator, s: int, sets: int | None = None):
    """``s`` random contacts on the triangles ``tris`` pressed ~1 mm in: (tri, bary, ubar);
    ``ubar`` is (s, 3), or (sets, s, 3) for several prescriptions of the same set."""
    tri = rng.choice(tris, size=s, replace=s > tris.size)
    bary = rng.dirichlet([1.0, 1.0, 1.0], size=s)
    nrm = triangle_normals(gf.vertices, gf.triangles[tri])
    shape = (s, 3) if sets is None else (sets, s, 3)
    return tri, bary, -1e-3 * nrm + rng.normal(scale=2e-4, size=shape)


def get_bundle(args) -> Path:
    if args.gf:
        return Path(args.gf)
    import hailstorm.precompute
    cache = Path(args.cache) if args.cache else Path(tempfile.gettempdir()) / "hailstorm-bench"
    out = cache / f"seat-h{args.mesh_size:g}-p{args.order}"
    t0 = time.perf_counter()
    path = hailstorm.precompute.build_bundle(out, mesh_size=args.mesh_size, order=args.order)
    print(f"bundle {path} ready in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return path


def direct_fem_setup(gf):
    """Stiffness of the bundle's own volume mesh (independent of D), clamp eliminated."""
    from hailstorm.precompute import fem
    from hailstorm.precompute.geometry import TetMesh

    order = gf.order
    clamp_tris = gf.triangles[gf.fixed[gf.triangles].all(axis=1)]
    mesh = TetMesh(np.asarray(gf.volume_points), np.asarray(gf.volume_tets),
                   {"clamp": gf.surface_nodes[clamp_tris], "top": gf.surface_nodes[gf.triangles]},
                   source="bundle")
    basis = fem.elasticity_basis(mesh, order)
    K = fem.stiffness_matrix(basis, gf.young, gf.poisson)
    clamp = fem.clamp_dofs(basis, mesh)
    free = fem.free_dofs(K.shape[0], clamp)
    hat = None
    if gf.manifest["options"].get("load") == "hat":  # the bundle's columns answer hat loads: so do the FEM's forces
        from hailstorm.precompute.greens import hat_load_matrix

        cv = gf.contact_vertices
        hat = hat_load_matrix(basis, gf.surface_nodes[cv], gf.areas[cv]).tocsc()
    return dict(basis=basis, Kff=K[free][:, free].tocsr(), free=free, ndof=K.shape[0], fem=fem, hat=hat)


def saddle_matrix(gf, ref, tri, bary):
    """The FEM saddle-point matrix [[K, L], [C, 0]] of sticky contacts (CSC): ``C`` the contact points'
    displacement (the vertices' nodal values, weighted by ``bary``), ``L`` where their forces act: ``C^T``
    (unit forces at the vertices) on a point-load bundle, the same weights of the vertices' consistent hat
    loads (:func:`hailstorm.precompute.greens.hat_load_matrix`) on a hat-load bundle, as its columns."""
    fem, basis = ref["fem"], ref["basis"]
    s = len(tri)
    verts = gf.triangles[tri]
    dofs = fem.vertex_dofs(basis, gf.surface_nodes[verts].ravel()).reshape(s, 3, 3)
    rows = np.repeat(np.arange(3 * s).reshape(s, 1, 3), 3, axis=1)  # (k, a, d) -> row 3k + d
    vals = np.repeat(bary[:, :, None], 3, axis=2)
    C = sp.csr_matrix((vals.ravel(), (rows.ravel(), dofs.ravel())), shape=(3 * s, ref["ndof"]))[:, ref["free"]]
    if ref["hat"] is None:
        return sp.bmat([[ref["Kff"], C.T], [C, None]], format="csc")
    # column 3i + d: sum over the triangle's corners a of bary[i, a] times the hat load (vertex a, direction d)
    hcols = (3 * gf.column_of[verts][:, :, None] + np.arange(3)).transpose(0, 2, 1)  # (s, d, a)
    W = sp.csc_matrix((np.repeat(bary[:, None, :], 3, axis=1).ravel(), (hcols.ravel(), np.repeat(np.arange(3 * s), 3))),
                      shape=(ref["hat"].shape[1], 3 * s))
    L = (ref["hat"] @ W)[ref["free"]]
    return sp.bmat([[ref["Kff"], L], [C, None]], format="csc")


def direct_fem_solve(gf, ref, tri, bary, ubar):
    """Saddle-point [[K, C^T], [C, 0]] solve for sticky contacts; returns seat forces and u."""
    A = saddle_matrix(gf, ref, tri, bary)
    nf, s = ref["free"].size, len(tri)
    sol = spla.spsolve(A, np.concatenate([np.zeros(nf), ubar.ravel()]))
    return -sol[nf:].reshape(s, 3), sol[:nf]


def main(argv=None) -> int:
    from studies import record

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
    ap.add_argument("--dtype", default="float32", choices=["float32", "none"],
                    help="also time the solves on a copy of the bundle with D in this type (default float32)")
    ap.add_argument("--dtype-only", action="store_true", help="only the float32 against float64 section")
    ap.add_argument("--threads", type=int, default=1,
                    help="BLAS threads (default 1: the dense systems are small; 0 = library default)")
    record.add_out_option(ap)
    args = ap.parse_args(argv)
    return record.run_or_record(args.out, "python tests/benchmarks/bench_contacts.py",
                                sys.argv[1:] if argv is None else list(argv), lambda: run(args))


def run(args: argparse.Namespace) -> int:
    """The sections of ``args``, printed."""
    if args.threads > 0:
        try:
            from threadpoolctl import threadpool_limits

            threadpool_limits(args.threads)
        except ImportError:
            print("threadpoolctl not installed; set OMP_NUM_THREADS to limit BLAS threads", file=sys.stderr)

    path = get_bundle(args)
    gf = load(path, mmap=False)
    n, nc = gf.n_vertices, int(gf.contactable.sum())
    print(f"bundle: {n} surface vertices, {nc} contactable, D {gf.D.shape[0]} x {gf.D.shape[1]} "
          f"{gf.dtype} ({gf.D.nbytes / 2**20:.0f} MiB), order P{gf.order}")
    tris = np.flatnonzero(gf.contactable[gf.triangles].all(axis=1))
    if args.dtype_only:
        print_dtype(path, gf, tris, args)
        return 0
    rng = np.random.default_rng(args.seed)
    ref = None if args.no_fem else direct_fem_setup(gf)
    if ref is not None:
        print(f"direct FEM: {ref['ndof']} dofs, {ref['free'].size} free, K nnz {ref['Kff'].nnz}")

    ms = 1e3
    header = (f"{'s':>4} {'|V|':>4} | {'solve+u(all) min/med/max [ms]':>31} | {'forces only med':>15} | "
              f"{'FEM [ms]':>9} {'ratio':>8} {'ratio f':>8} {'err':>8}")
    print(header)
    print("-" * len(header))
    for s in args.sizes:
        tri, bary, ubar = random_contacts(gf, tris, rng, s)
        V = np.unique(gf.triangles[tri]).size
        t_fem = f_ref = None
        if ref is not None:

            def run_fem():
                nonlocal f_ref
                f_ref, _ = direct_fem_solve(gf, ref, tri, bary, ubar)

            t_fem = np.median(timeit(run_fem, args.fem_repeat, warmup=1))
        t_full = timeit(lambda: solve_contacts(gf, tri, bary, ubar), args.repeat)
        t_forces = timeit(lambda: solve_contacts(gf, tri, bary, ubar, rows=None), args.repeat)
        fem_col = f"{'-':>9} {'-':>8} {'-':>8} {'-':>8}"
        if t_fem is not None:
            f = solve_contacts(gf, tri, bary, ubar, rows=None).forces
            err = np.abs(f - f_ref).max() / np.abs(f_ref).max()
            fem_col = (f"{t_fem * ms:9.2f} {t_fem / np.median(t_full):8.0f} "
                       f"{t_fem / np.median(t_forces):8.0f} {err:8.1e}")
        print(f"{s:4d} {V:4d} | {t_full.min() * ms:9.3f} {np.median(t_full) * ms:10.3f} "
              f"{t_full.max() * ms:10.3f} | {np.median(t_forces) * ms:15.3f} | {fem_col}")
        floor_case = (s, tri, bary, t_full)
        floor_ubar = ubar

    if args.sizes:
        refs = print_floor(gf, *floor_case, repeat=args.repeat)
        print_phases(gf, floor_case[1], floor_case[2], floor_ubar, refs, repeat=args.repeat)
        print_steady(gf, ref, tris, args)

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
    if args.dtype != "none":
        print_dtype(path, gf, tris, args)
    return 0


def timeit_pair(fa, fb, repeat: int, warmup: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Wall-clock seconds of ``repeat`` calls of each of ``fa`` and ``fb``, interleaved
    (a, b, b, a, ...: a load change on the host hits both alike)."""
    for _ in range(warmup):
        fa(), fb()
    ta, tb = np.empty(repeat), np.empty(repeat)
    for i in range(repeat):
        for f, t in ((fa, ta), (fb, tb)) if i % 2 == 0 else ((fb, tb), (fa, ta)):
            t0 = time.perf_counter()
            f()
            t[i] = time.perf_counter() - t0
    return ta, tb


def print_dtype(path: Path, gf, tris: np.ndarray, args) -> None:
    """D stored as float32 against float64: the same solves, their times and the rounding's effect.

    For each s: fresh solves with full-surface u (sticky bilateral point contacts,
    the one-call kernel) and the steady-state ``forces`` + ``surface_displacement``
    of a kept capacitance, timed interleaved on both bundles; then the largest
    relative error of the float32 forces and u against float64 (max-norm, relative
    to the largest float64 value) for sticky bilateral, frictionless unilateral and
    patch contacts, and the condition number of W.
    """
    ms = 1e3
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        p32 = convert_bundle(path, Path(tmp) / "f32", args.dtype)
        t_conv = time.perf_counter() - t0
        g32 = load(p32, mmap=False)
        b64, b32 = (path / "compliance.npy").stat().st_size, (p32 / "compliance.npy").stat().st_size
        cast = g32.manifest["dtype_cast"]
        print()
        print(f"D as {args.dtype} (convert_bundle {t_conv:.1f} s): compliance.npy {b64 / 2**20:.1f} -> "
              f"{b32 / 2**20:.1f} MiB on disk, D in memory {gf.D.nbytes / 2**20:.1f} -> {g32.D.nbytes / 2**20:.1f} MiB; "
              f"rounding of D: max abs {cast['max_abs_error']:.2e} m/N, {cast['max_rel_error']:.2e} of max |D|")
        rng = np.random.default_rng(args.seed + 2)
        print(f"{'s':>4} | {'fresh f64 min/med/max [ms]':>27} | {'fresh f32':>27} | {'ratio med':>9} "
              f"{'ratio min':>9} | {'steady f64 med':>14} {'f32 med':>8} {'ratio':>6}")
        cases = []
        for s in args.sizes:
            tri, bary, ubar = random_contacts(gf, tris, rng, s)
            cases.append((s, tri, bary, ubar))
            ta, tb = timeit_pair(lambda: solve_contacts(gf, tri, bary, ubar),
                                 lambda: solve_contacts(g32, tri, bary, ubar), args.repeat)
            caps = []
            for g in (gf, g32):
                c = capacitance(g, tri, bary)
                c.keep_response()
                caps.append(c)
            sa, sb = timeit_pair(lambda: caps[0].surface_displacement(caps[0].forces(ubar)),
                                 lambda: caps[1].surface_displacement(caps[1].forces(ubar)), args.repeat)
            print(f"{s:4d} | {ta.min() * ms:8.3f} {np.median(ta) * ms:8.3f} {ta.max() * ms:9.3f} | "
                  f"{tb.min() * ms:8.3f} {np.median(tb) * ms:8.3f} {tb.max() * ms:9.3f} | "
                  f"{np.median(tb) / np.median(ta):9.2f} {tb.min() / ta.min():9.2f} | "
                  f"{np.median(sa) * ms:14.4f} {np.median(sb) * ms:8.4f} {np.median(sb) / np.median(sa):6.2f}")
        print()
        print(f"{'s':>4} {'cond W':>9} | max rel error of float32 (forces / u): {'sticky':>19} | "
              f"{'frictionless unil.':>19} | {'patch (r = 4 mm)':>19}")
        for s, tri, bary, ubar in cases:
            errs = []
            for kw in ({}, dict(mode="frictionless", unilateral=True), dict(patch_radius=0.004)):
                a, b = solve_contacts(gf, tri, bary, ubar, **kw), solve_contacts(g32, tri, bary, ubar, **kw)
                errs.append((np.abs(b.forces - a.forces).max() / np.abs(a.forces).max(),
                             np.abs(b.surface_displacement - a.surface_displacement).max()
                             / np.abs(a.surface_displacement).max()))
            cond = np.linalg.cond(capacitance(gf, tri, bary).W)
            print(f"{s:4d} {cond:9.3g} | {'':>38} " + " | ".join(f"{ef:9.2e} {eu:9.2e}" for ef, eu in errs))


def print_steady(gf, ref, tris: np.ndarray, args) -> None:
    """Steady state: one contact set, new prescribed displacements on every call.

    The capacitance is factorised once and its full-surface response kept
    (:meth:`Capacitance.keep_response`, timed as ``setup``); each call is then
    ``forces`` (two triangular solves) and ``surface_displacement`` (one
    product with the kept response). The FEM counterpart factorises its saddle
    point matrix once (SuperLU) and back-substitutes per call.
    """
    ms = 1e3
    rng = np.random.default_rng(args.seed + 1)
    print()
    print("steady state (contact set unchanged, new displacements each call; min/med/max [ms]):")
    header = (f"{'s':>4} | {'setup':>7} | {'forces + u(all)':>26} | {'forces only':>26} | "
              f"{'FEM factor':>10} {'FEM solve':>9} | {'FEM solve / (f+u)':>17} | {'FEM fresh / forces':>18}")
    print(header)
    print("-" * len(header))
    for s in args.sizes:
        tri, bary, ubars = random_contacts(gf, tris, rng, s, sets=16)
        t0 = time.perf_counter()
        cap = capacitance(gf, tri, bary)
        cap.keep_response()
        t_setup = time.perf_counter() - t0
        it = itertools.count()  # a new prescription on every call (cycling through 16)

        def step():
            f = cap.forces(ubars[next(it) % 16])
            return f, cap.surface_displacement(f)

        def forces_only():
            return cap.forces(ubars[next(it) % 16])

        t_fu = timeit(step, args.repeat)
        t_f = timeit(forces_only, args.repeat)
        fem = "-"
        if ref is not None:
            A = saddle_matrix(gf, ref, tri, bary)
            nf = ref["free"].size
            t_fac = timeit(lambda: spla.splu(A), max(args.fem_repeat, 1), warmup=0)
            lu = spla.splu(A)
            rhs = np.zeros(A.shape[0])

            def fem_step():
                rhs[nf:] = ubars[next(it) % 16].ravel()
                return lu.solve(rhs)

            t_fs = timeit(fem_step, max(args.repeat // 10, 3), warmup=1)
            t_fresh = np.median(t_fac) + np.median(t_fs)
            fem = (f"{np.median(t_fac) * ms:10.2f} {np.median(t_fs) * ms:9.3f} | "
                   f"{np.median(t_fs) / np.median(t_fu):16.0f}x | {t_fresh / np.median(t_f):17.0f}x")
        print(f"{s:4d} | {t_setup * ms:7.2f} | {t_fu.min() * ms:8.4f} {np.median(t_fu) * ms:8.4f} {t_fu.max() * ms:8.4f} | "
              f"{t_f.min() * ms:8.4f} {np.median(t_f) * ms:8.4f} {t_f.max() * ms:8.4f} | {fem}")


@numba.njit(nogil=True)
def line_sum(x: np.ndarray, idx: np.ndarray) -> float:  # pragma: no cover (compiled)
    """Sum of ``x[idx]`` (one double of each cache line, ``idx`` ascending): the least work that
    touches those lines once each, scattered, in address order. A reference read for
    :func:`print_floor`, not library code."""
    a0 = a1 = a2 = a3 = 0.0
    n = idx.size // 4
    for i in range(n):
        a0 += x[idx[4 * i]]
        a1 += x[idx[4 * i + 1]]
        a2 += x[idx[4 * i + 2]]
        a3 += x[idx[4 * i + 3]]
    for i in range(4 * n, idx.size):
        a0 += x[idx[i]]
    return a0 + a1 + a2 + a3


@numba.njit(fastmath=True, nogil=True)
def stream_sum(x: np.ndarray) -> float:  # pragma: no cover (compiled)
    """Sum of a contiguous 1-D array, read as eight contiguous streams at once: the least
    work that reads every byte once, with as many reads in flight as the solve's product
    (eight columns of D per pass). A reference read for :func:`print_floor`, not library code."""
    n = x.size // 8
    a0 = a1 = a2 = a3 = a4 = a5 = a6 = a7 = 0.0
    for i in range(n):
        a0 += x[i]
        a1 += x[n + i]
        a2 += x[2 * n + i]
        a3 += x[3 * n + i]
        a4 += x[4 * n + i]
        a5 += x[5 * n + i]
        a6 += x[6 * n + i]
        a7 += x[7 * n + i]
    for i in range(8 * n, x.size):
        a0 += x[i]
    return a0 + a1 + a2 + a3 + a4 + a5 + a6 + a7


def print_floor(gf, s: int, tri: np.ndarray, bary: np.ndarray, t_fresh: np.ndarray, repeat: int) -> dict:
    """Lower bound of an exact (float64) solve + full-surface deformation for the last contact set.

    Whatever the algorithm, three costs cannot be avoided:

    * (a) the deformation ``u = D[:, cols] B f`` reads every column of D that a
      contacted vertex owns (``|cols| x n_rows x 8`` bytes). The fastest one core
      reads that many bytes of D is the faster of one BLAS product (one thread) and a
      compiled sum (:func:`stream_sum`) over a *contiguous* block of D of the same
      size, warm in cache (as it is when the benchmark repeats one contact set);
    * (b) the forces need ``W = B^T D_VV B``: its entries lie scattered over the same
      columns, so at least the cache lines holding ``D_VV`` are read (counted
      here, at the rate of (a));
    * (c) the Cholesky factorisation of W (``3s x 3s``), at the benchmark's BLAS threads,
      of a Fortran-ordered W (LAPACK copies its input with a plain memcpy). Until issue
      12's third round (c) factorised the C-ordered W, whose copy into LAPACK's order is a
      transpose (0.05-0.1 ms at m = 300): more work than the solve does, and no longer a
      lower bound once the solve's factor skipped that transpose.

    Their sum is printed as the floor, next to a plain numpy ``D[:, cols] @ g``,
    a column copy ``D[:, cols]`` and the cold streaming bandwidth of a full ``D @ x``,
    and the fresh solve's times ``t_fresh`` (solve + full-surface u of this set) as a
    ratio to it: from the medians, and from the minima (less sensitive to a loaded host).

    One core, because the solve is serial: its kernels are single-threaded and the
    benchmark pins BLAS to ``--threads`` (default 1) for it. The product (a') of the
    same block with every BLAS thread, and the ratio to the floor built on it, are
    printed too: the bound of a parallel solve (before issue 12's second round the
    floor used (a'), so it bounded a program the benchmark does not run).

    (b) counts D_VV's cache lines at the streaming rate of (a): a bound no scattered
    read reaches. Beside it, (b'') touches each of those lines once, in address order,
    with a compiled sum of one double per line (no output written): the least a
    scattered read of D_VV costs on this machine, and what the solve's
    ``(D_VV G)^T`` kernel is to be compared with (it reads each line once per
    contact that uses its column and writes ``3s x 3|V|`` doubles). The floor itself
    keeps (b).

    Returns the medians of (a), (b), (b'') and (c) [s] for :func:`print_phases`.
    """
    import os

    import scipy.linalg as sla
    from threadpoolctl import threadpool_limits

    ms = 1e3
    D = np.asarray(gf.D)
    V = np.unique(gf.triangles[tri])
    cb = np.asarray(gf.column_of)[V]
    cols = (3 * cb[cb >= 0][:, None] + np.arange(3)).ravel()
    g = np.random.default_rng(1).normal(size=cols.size)
    x = np.zeros(D.shape[1])
    x[cols] = g
    mb = cols.size * D.shape[0] * D.itemsize / 1e6
    t_mv = timeit(lambda: D[:, cols] @ g, repeat)
    t_cp = timeit(lambda: D[:, cols], repeat)
    t_all = timeit(lambda: D @ x, max(repeat // 5, 3))
    gbs = D.nbytes / 1e9 / np.median(t_all)
    # the contiguous block of D with the same number of columns (same bytes)
    f_order = D.flags.f_contiguous
    block = D[:, :cols.size] if f_order else D[:cols.size, :]
    gb = g if f_order else np.random.default_rng(1).normal(size=D.shape[1])
    flat = block.ravel(order="K")  # the block's memory, in order (a view)
    with threadpool_limits(limits=1, user_api="blas"):
        t_blas1 = timeit(lambda: block @ gb, repeat)
    t_sum = timeit(lambda: stream_sum(flat), repeat)
    with threadpool_limits(limits=os.cpu_count() or 1, user_api="blas"):
        t_par = timeit(lambda: block @ gb, repeat)
    # (a): the faster reference read on one core, by median (its minimum for the minima's floor)
    t_blk = t_blas1 if np.median(t_blas1) <= np.median(t_sum) else t_sum
    a_min = min(t_blas1.min(), t_sum.min())
    # cache lines of D that hold D_VV (the live contacted vertices' rows of those columns)
    rows = (3 * V[:, None] + np.arange(3)).ravel()
    if f_order:
        offs = cols[None, :].astype(np.int64) * D.shape[0] + rows[:, None]
    else:
        offs = rows[:, None].astype(np.int64) * D.shape[1] + cols[None, :]
    line_ids = np.unique(offs.ravel() * D.itemsize // 64)
    lines = line_ids.size
    flat_D = D.ravel(order="K")
    first = np.maximum(line_ids * (64 // D.itemsize), 0).astype(np.int64)  # a double in each line
    t_lines = timeit(lambda: line_sum(flat_D, first), repeat)
    extra = lines * 64 / block.nbytes  # (b) in units of (a)
    rate = block.nbytes / np.median(t_blk)  # bytes/s of the serial reference read
    t_vv = lines * 64 / rate
    t_gather = None
    if f_order:  # the same cache lines as scattered reads, in one compiled loop
        t_gather = timeit(lambda: vertex_block(V, D.T, gf.column_of), repeat)
    W = capacitance(gf, tri, bary).W
    # W.T is W (symmetric) in Fortran order: LAPACK's input copy is a memcpy, as in SPDFactor
    # (on the C-ordered W, cho_factor adds a transposing copy the solve does not make)
    t_chol = timeit(lambda: sla.cho_factor(W.T, check_finite=False), repeat)
    floor = np.median(t_blk) * (1.0 + extra) + np.median(t_chol)
    floor_min = a_min * (1.0 + extra) + t_chol.min()
    floor_par = np.median(t_par) * (1.0 + extra) + np.median(t_chol)
    floor_par_min = t_par.min() * (1.0 + extra) + t_chol.min()
    print()
    print(f"floor (s = {s}: {cols.size} columns of D x {D.shape[0]} rows = {mb:.1f} MB read; min/med/max [ms]):")
    print(f"  numpy D[:, cols] @ g  {t_mv.min() * ms:9.3f} {np.median(t_mv) * ms:10.3f} {t_mv.max() * ms:10.3f}")
    print(f"  column copy D[:, cols] {t_cp.min() * ms:8.3f} {np.median(t_cp) * ms:10.3f} {t_cp.max() * ms:10.3f}")
    print(f"  full D @ x ({D.nbytes / 1e6:.0f} MB, cold) {t_all.min() * ms:7.3f} {np.median(t_all) * ms:10.3f} "
          f"{t_all.max() * ms:10.3f}  -> {gbs:.1f} GB/s")
    print(f"  (a) contiguous block of D, same {mb:.1f} MB, one core, warm: BLAS product "
          f"{t_blas1.min() * ms:.3f} {np.median(t_blas1) * ms:.3f} {t_blas1.max() * ms:.3f}, "
          f"compiled sum {t_sum.min() * ms:.3f} {np.median(t_sum) * ms:.3f} {t_sum.max() * ms:.3f}"
          f"  -> {rate / 1e9:.1f} GB/s")
    print(f"  (b) D_VV: {lines} cache lines ({lines * 64 / 1e6:.1f} MB) at that rate: {t_vv * ms:.3f}")
    print(f"  (b'') the same lines touched once each, scattered, in address order (compiled, one core): "
          f"{t_lines.min() * ms:.3f} {np.median(t_lines) * ms:.3f} {t_lines.max() * ms:.3f}")
    print(f"  (c) Cholesky of W ({W.shape[0]} x {W.shape[0]}): "
          f"{t_chol.min() * ms:.3f} {np.median(t_chol) * ms:.3f} {t_chol.max() * ms:.3f}")
    print(f"  lower bound (a) + (b) + (c), medians: {floor * ms:.3f} ms (exact float64 D, one core, on this machine)")
    print(f"  fresh solve + u(all) / floor: medians {np.median(t_fresh) / floor:.2f} "
          f"({np.median(t_fresh) * ms:.3f} / {floor * ms:.3f} ms), minima {t_fresh.min() / floor_min:.2f} "
          f"({t_fresh.min() * ms:.3f} / {floor_min * ms:.3f} ms)")
    print(f"  (a') the block's BLAS product on {os.cpu_count()} threads: {t_par.min() * ms:.3f} "
          f"{np.median(t_par) * ms:.3f} {t_par.max() * ms:.3f}; floor on it {floor_par * ms:.3f} ms, "
          f"fresh solve / it: medians {np.median(t_fresh) / floor_par:.2f}, minima {t_fresh.min() / floor_par_min:.2f} "
          f"({t_fresh.min() * ms:.3f} / {floor_par_min * ms:.3f} ms)")
    if t_gather is not None:
        print(f"  (b') the same D_VV as scattered reads (compiled vertex_block), measured: "
              f"{t_gather.min() * ms:.3f} {np.median(t_gather) * ms:.3f} {t_gather.max() * ms:.3f}"
              f"  -> (a) + (b') + (c) = {(np.median(t_blk) + np.median(t_gather) + np.median(t_chol)) * ms:.3f} ms")
    return {"a": float(np.median(t_blk)), "b": t_vv, "b''": float(np.median(t_lines)), "c": float(np.median(t_chol))}


def print_phases(gf, tri: np.ndarray, bary: np.ndarray, ubar: np.ndarray, refs: dict, repeat: int) -> None:
    """The fresh solve of :func:`print_floor`'s contact set (bilateral sticky point contacts,
    full-surface u: the general path above ``POINT_FAST_MAX``), phase by phase.

    Each repetition runs the phases of one solve in order (validation, V and the column
    dofs, ``Y = (D_VV G)^T``, ``W``, the rigid test, the factor with its condition test,
    the force solve, ``B f``, ``u = D[:, V] B f``, ``B^T u_V``) and then the whole
    :func:`solve_contacts`; min / median / max of each, beside the floor term it is to be
    compared with (``print_floor``'s medians).
    """
    from hailstorm.runtime.compiled import blocks, wmatrix
    from hailstorm.runtime.bundle.compliance import apply_columns, column_dofs, kernel_columns
    from hailstorm.runtime.contact.policy import POINT_FAST_MAX, SPDFactor, is_rigid
    from hailstorm.runtime.contact.validate import check_contacts, check_mode, check_patch
    from hailstorm.runtime.contact.weights import interpolate, locate, vertex_forces

    names = ["validation", "V, column dofs", "Y = (D_VV G)^T", "W = G^T Y^T", "rigid test",
             "factor + condition", "force solve", "B f", "u(all) = D[:, V] B f", "B^T u_V", "sum of the phases",
             "solve_contacts"]
    floors = {"Y = (D_VV G)^T": ("(b'')", refs["b''"]), "factor + condition": ("(c)", refs["c"]),
              "u(all) = D[:, V] B f": ("(a)", refs["a"])}
    T = np.empty((repeat + 3, len(names)))
    clock = time.perf_counter
    for i in range(repeat + 3):
        t = [clock()]
        check_mode("sticky")
        tt, b, _ = check_contacts(gf, tri, bary, None, need_normals=False)
        check_patch(None, tt.size, "hertz")
        u = np.asarray(ubar, dtype=np.float64)
        np.isfinite(u).all()
        t.append(clock())
        pv = gf.triangles[tt]
        V, loc = locate(pv)
        cols = column_dofs(gf, V)
        w = np.ascontiguousarray(b, dtype=np.float64)
        nrm = np.zeros((tt.size, 3))
        t.append(clock())
        Y = blocks.constraint_rows(kernel_columns(gf), gf.column_of, V, loc, w, nrm, True)
        t.append(clock())
        W = wmatrix.contact_compliance(Y, loc, w, nrm, True)
        t.append(clock())
        is_rigid(gf.fixed, pv, w).any()
        t.append(clock())
        F = SPDFactor(W, symmetric=True)
        t.append(clock())
        f = F.solve(u.reshape(-1)).reshape(-1, 3)
        t.append(clock())
        g = vertex_forces(V.size, loc, w, f)
        t.append(clock())
        uall = apply_columns(gf, cols, g.reshape(-1), None)
        t.append(clock())
        interpolate(uall[V], loc, w)
        t.append(clock())
        t0 = clock()
        solve_contacts(gf, tri, bary, ubar)
        t1 = clock()
        d = np.diff(t)
        T[i] = np.concatenate([d, [t[-1] - t[0], t1 - t0]])
    T = T[3:] * 1e3
    print()
    print(f"the fresh solve above, phase by phase (perf_counter, {repeat} repeats; min / med / max [ms]):")
    if tri.size <= POINT_FAST_MAX:
        print(f"  (s <= POINT_FAST_MAX = {POINT_FAST_MAX}: solve_contacts takes the one-call compiled path, "
              "not these phases of the general one)")
    for j, name in enumerate(names):
        col = T[:, j]
        fl = floors.get(name)
        extra = f"   {fl[0]} {fl[1] * 1e3:.3f}: {np.median(col) / (fl[1] * 1e3):.2f}x" if fl else ""
        print(f"  {name:22s} {col.min():8.3f} {np.median(col):8.3f} {col.max():8.3f}{extra}")


def _copy(cap):
    import copy

    c = copy.copy(cap)
    cap.K  # form the explicit capacitance once (as a running storm would have it)
    cap.D_VV  # gathered on first use
    for name, value in vars(cap).items():  # every array the updates replace
        if isinstance(value, np.ndarray):
            setattr(c, name, value.copy())
    return c


if __name__ == "__main__":
    raise SystemExit(main())
