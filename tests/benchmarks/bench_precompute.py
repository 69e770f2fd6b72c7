"""Benchmark: the Green's-function precompute (solvers, Dask workers, resume after kill -9).

Every repetition runs in a fresh process, so that its peak memory (max RSS) is
its own; configurations are interleaved so that drift in the machine's load
hits all alike. Prints min/median/max and ratios against the first
configuration measured in the same run, and the load average before and after
(the reference machine is shared: compare ratios, not seconds).

    # in-memory solvers against a plain SuperLU baseline
    python tests/benchmarks/bench_precompute.py solvers --mesh-size 0.006 --repeat 3
    # the CLI end to end: serial (supernodal; CHOLMOD) against a local Dask cluster of 1 and 2 workers
    python tests/benchmarks/bench_precompute.py dask --mesh-size 0.003 --repeat 3 --configs serial,cholmod,workers-1,workers-2
    # kill -9 at ~50 % of the blocks, rerun: work and wall time against an uninterrupted run
    python tests/benchmarks/bench_precompute.py resume --mesh-size 0.003 --repeat 2

Solver methods (``solvers``)
----------------------------
baseline   scipy.sparse.linalg.splu once, then one solve per column (plain)
splu       the same factorization, blocked right-hand sides
supernodal the default solver (hailstorm.precompute.supernodal): pruned supernodal solves
cholmod    CHOLMOD sparse Cholesky (cholespy), fill-reducing ordering, blocks
cholmod-N  the same on a local Dask cluster of N processes
amg        pyamg smoothed aggregation + CG per column (tol 1e-8), optional
pardiso    MKL PARDISO (pypardiso, not a project dependency: ``pip install pypardiso``),
           supernodal LLᵀ, METIS ordering, no iterative refinement, blocks of 128
           columns: the supernodal multi-right-hand-side floor (``MKL_NUM_THREADS``
           decides its threads)

``dask`` also prints the sparse triangular-solve bound of the serial runs
(``serial``: the default supernodal solver; ``cholmod``: ``--solver cholmod``):
a full forward and backward solve per column, 4 nnz(L) operations, at the
machine's dense matrix-multiply rate (measured here, both cores), or L
streamed once per batch of right-hand sides (4 for cholespy's simplicial
solve) at the measured copy bandwidth, the larger, against the solve time
achieved. ``solvers --bound`` prints each method's time against the FLOP term.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import resource
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

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


def _pardiso(K, fixed, load, read, batch: int = 128):
    """D by MKL PARDISO's supernodal Cholesky (SPD, mtype 2), ``batch`` right-hand sides per solve."""
    import pypardiso
    import scipy.sparse as sp

    from hailstorm.precompute.greens import column_problem

    problem = column_problem(K, fixed, load, read)
    upper = sp.triu(problem.Kff, format="csr")
    upper.sort_indices()
    solver = pypardiso.PyPardisoSolver(mtype=2)
    for i, v in ((1, 1), (2, 2), (8, 0), (18, -1), (19, -1)):  # own iparm, METIS, no refinement, report nnz(L)
        solver.set_iparm(i, v)
    solver.factorize(upper)
    print(f"pardiso: nnz(L) {solver.iparm[17]:,}", file=sys.stderr)
    n_rows, ncols = problem.shape
    live = np.flatnonzero(problem.read_pos >= 0)
    D = np.zeros((n_rows, ncols), order="F")
    for s in range(0, ncols, batch):
        e = min(ncols, s + batch)
        rhs = np.zeros((upper.shape[0], e - s), order="F")
        rhs[problem.load_pos[s:e], np.arange(e - s)] = 1.0
        D[live, s:e] = solver.solve(upper, rhs)[problem.read_pos[live]]
    return D


def _one(method: str, mesh_size: float, order: int, queue) -> None:
    basis, K, fixed, load, read = _setup(mesh_size, order)
    t0 = time.perf_counter()
    if method == "baseline":
        D = _baseline(K, fixed, load, read)
    elif method == "pardiso":
        D = _pardiso(K, fixed, load, read)
    else:
        from hailstorm.precompute.greens import compliance_matrix
        from hailstorm.precompute.fem import rigid_modes_on_dofs

        solver, _, workers = method.partition("-")
        nn = rigid_modes_on_dofs(basis) if solver == "amg" else None
        D = compliance_matrix(K, fixed, load, read, solver=solver, near_null=nn, tol=1e-8,
                              workers=int(workers) if workers else None)
    dt = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # MiB on Linux
    np.save(os.path.join(tempfile.gettempdir(), f"hailstorm-bench-D-{method}.npy"), D[:, :: max(1, D.shape[1] // 50)])
    queue.put((dt, rss, K.shape[0], D.shape))


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def _mmm(t: list[float]) -> str:
    return f"{min(t):8.2f} {statistics.median(t):9.2f} {max(t):8.2f}"


def solvers(args) -> None:
    ctx = mp.get_context("spawn")
    results: dict[str, list] = {}
    methods = args.methods.split(",")
    print(f"load average before: {_load()}")
    for rep in range(args.repeat):
        for method in methods:  # interleaved, so drift in machine load hits all alike
            q = ctx.Queue()
            p = ctx.Process(target=_one, args=(method, args.mesh_size, args.order, q))
            p.start()
            out = q.get()
            p.join()
            results.setdefault(method, []).append(out)
    print(f"load average after: {_load()}")
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
        print(f"{method:10s} {_mmm(t)} {base / statistics.median(t):8.1f}x {mem:9.0f} {diff:10.1e}")
    if args.bound:
        from hailstorm.precompute.greens import cholesky_nnz, column_problem

        gflops, _ = _machine_rates()
        _, K, fixed, load, read = _setup(args.mesh_size, args.order)
        nnz = cholesky_nnz(column_problem(K, fixed, load, read).Kff)
        t_flop = 4.0 * nnz * shape[1] / (gflops * 1e9)
        print(f"FLOP bound: nnz(L) {nnz:,} (proxy), 4 nnz(L) per column at the dense multiply rate "
              f"{gflops:.1f} GFLOP/s = {t_flop:.2f} s; median time (factorization included) / bound: "
              + ", ".join(f"{m} {statistics.median(r[0] for r in results[m]) / t_flop:.1f}x" for m in methods)
              + f"; load average {_load()}")


# --------------------------------------------------------------------------- the CLI end to end

def _cli(out: Path, mesh_size: float, extra: list[str], cache: Path) -> subprocess.Popen:
    env = {**os.environ, "HAILSTORM_CACHE": str(cache)}
    cmd = [sys.executable, "-m", "hailstorm", "precompute", "--mesh-size", str(mesh_size), "--out", str(out),
           "--force", "-q", *extra]
    return subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _finish(p: subprocess.Popen, t0: float) -> tuple[float, float]:
    """Wait for ``p``; its wall time and peak RSS [MiB] (this child, via wait4)."""
    _, status, usage = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    if p.returncode != 0:
        raise SystemExit(f"precompute failed ({p.returncode}): {p.stderr.read() if p.stderr else ''}")
    return time.perf_counter() - t0, usage.ru_maxrss / 1024


def _stats(out: Path) -> dict:
    return json.loads((out / "manifest.json").read_text())["solve_stats"]


def _machine_rates() -> tuple[float, float]:
    """Dense matrix-multiply rate [GFLOP/s] (both cores) and copy bandwidth [GB/s] of this machine."""
    a = np.random.default_rng(0).random((2000, 2000))
    best = min(_timed(lambda: a @ a) for _ in range(3))
    big = np.ones(2**27 // 8 * 4)  # 512 MiB
    dst = np.empty_like(big)
    bw = 2 * big.nbytes / min(_timed(lambda: np.copyto(dst, big)) for _ in range(3)) / 1e9
    return 2 * 2000**3 / best / 1e9, bw


def _timed(f) -> float:
    t = time.perf_counter()
    f()
    return time.perf_counter() - t


def _bound(stats: dict, gflops: float, bandwidth: float) -> str:
    """The run's triangular solves against the sparse triangular-solve bound: a full forward and
    backward solve per column (4 nnz(L)) at the dense multiply rate, or L streamed once per
    batch of right-hand sides (value + index, both sweeps) at the copy bandwidth, the larger."""
    if "nnz_L" not in stats:
        return ""
    cols = stats["columns_solved"]
    # right-hand sides per pass over L: cholespy's factor is simplicial (it sets CHOLMOD_SIMPLICIAL),
    # which CHOLMOD solves at most 4 at a time whatever the block width
    batch = 4 if stats.get("solver", "cholmod") == "cholmod" else stats.get("batch", 4)
    full = stats.get("full_solve_flops", stats["solve_flops"])
    t_flop = full / (gflops * 1e9)
    t_mem = 2 * 12 * stats["nnz_L"] * (cols / batch) / (bandwidth * 1e9)
    achieved = stats["solve_s"] - stats["factor_s"]
    return (f"nnz(L) {stats['nnz_L']:,}; triangular solves {stats['solve_flops'] / 1e9:.0f} GFLOP done "
            f"({100 * stats['solve_flops'] / full:.0f} % of 4 nnz(L) per column) in {achieved:.1f} s "
            f"({stats['solve_gflop_per_s']:.2f} GFLOP/s); bound max(4 nnz(L) per column at {gflops:.0f} GFLOP/s "
            f"= {t_flop:.1f} s, L streamed per batch of {batch} at {bandwidth:.0f} GB/s = {t_mem:.1f} s): "
            f"achieved = {achieved / max(t_flop, t_mem):.2f}x the bound")


#: CLI arguments of each ``dask`` configuration
_CONFIGS = {"serial": [], "cholmod": ["--solver", "cholmod"]}


def dask(args) -> None:
    configs = args.configs.split(",")
    work = Path(tempfile.mkdtemp(prefix="hailstorm-bench-"))
    gflops, bw = _machine_rates()
    print(f"machine: dense multiply {gflops:.1f} GFLOP/s, copy {bw:.1f} GB/s; load average before: {_load()}")
    res: dict[str, list] = {c: [] for c in configs}
    try:
        for rep in range(args.repeat):
            for c in configs:
                extra = (_CONFIGS[c] if c in _CONFIGS else ["--workers", c.split("-")[1]]) + args.cli
                out = work / c
                t0 = time.perf_counter()
                wall, rss = _finish(_cli(out, args.mesh_size, extra, work / "cache"), t0)
                st = _stats(out)
                res[c].append((wall, st["solve_s"], st["factor_s"], st["first_block_s"] if "first_block_s" in st else None,
                               rss, st))
                print(f"  {c} run {rep + 1}: wall {wall:.1f} s, solve {st['solve_s']:.1f} s, load {_load()}", flush=True)
        print(f"load average after: {_load()}")
        st0 = res[configs[0]][0][5]
        print(f"default seat, mesh size {args.mesh_size} m{' ' + ' '.join(args.cli) if args.cli else ''}: "
              f"{st0['blocks']} blocks, {st0['columns_solved']} columns; "
              f"{args.repeat} runs each")
        base = statistics.median(r[1] for r in res[configs[0]])
        print(f"{'config':10s} {'wall min':>8s} {'median':>9s} {'max':>8s} | {'solve min':>8s} {'median':>9s} {'max':>8s} "
              f"{'speed-up':>9s} {'per block s':>11s} {'peak MiB':>9s}")
        for c in configs:
            wall = [r[0] for r in res[c]]
            solve = [r[1] for r in res[c]]
            per_block = statistics.median(r[1] / r[5]["blocks_solved"] for r in res[c])
            print(f"{c:10s} {_mmm(wall)} | {_mmm(solve)} {base / statistics.median(solve):8.2f}x "
                  f"{per_block:11.3f} {max(r[4] for r in res[c]):9.0f}")
        ref = np.load(work / configs[0] / "compliance.npy", mmap_mode="r")
        for c in configs[1:]:
            other = np.load(work / c / "compliance.npy", mmap_mode="r")
            print(f"{c}: max |D - D_{configs[0]}| / max |D| = {float(np.abs(other - ref).max() / np.abs(ref).max()):.1e}")
        for c in ("serial", "cholmod"):
            if c in res:
                runs = sorted(res[c], key=lambda r: r[1])
                print(f"{c} (median run): " + _bound(runs[len(runs) // 2][5], gflops, bw))
    finally:
        shutil.rmtree(work, ignore_errors=True)


def resume(args) -> None:
    """kill -9 a run when ~half its blocks are on disk, rerun, compare with an uninterrupted run."""
    work = Path(tempfile.mkdtemp(prefix="hailstorm-bench-"))
    print(f"load average before: {_load()}")
    rows = []
    try:
        for rep in range(args.repeat):
            out = work / "full"
            t0 = time.perf_counter()
            full, _ = _finish(_cli(out, args.mesh_size, [], work / "cache"), t0)
            n_blocks = _stats(out)["blocks"]
            shutil.rmtree(out)
            out = work / "killed"
            records = work / ".killed.work" / "blocks"
            t0 = time.perf_counter()
            p = _cli(out, args.mesh_size, [], work / "cache")
            while True:
                done = len(list(records.glob("*.json"))) if records.is_dir() else 0
                if done >= n_blocks // 2 or p.poll() is not None:
                    break
                time.sleep(0.05)
            os.kill(p.pid, signal.SIGKILL)
            p.wait()
            first = time.perf_counter() - t0
            kept = len(list(records.glob("*.json")))
            t1 = time.perf_counter()
            second, _ = _finish(_cli(out, args.mesh_size, [], work / "cache"), t1)
            st = _stats(out)
            solved = st["blocks_solved"]
            # work: blocks solved before the kill (kept + the one in flight, lost) plus after
            total_blocks = kept + 1 + solved
            rows.append((full, first, second, kept, solved, n_blocks, total_blocks / n_blocks, (first + second) / full))
            print(f"  run {rep + 1}: uninterrupted {full:.1f} s; killed at {first:.1f} s with {kept}/{n_blocks} blocks "
                  f"on disk; rerun {second:.1f} s solving {solved} blocks (resumed {st['blocks_resumed']}); "
                  f"load {_load()}", flush=True)
            shutil.rmtree(out, ignore_errors=True)
        print(f"load average after: {_load()}")
        work_ratio = [r[6] for r in rows]
        wall_ratio = [r[7] for r in rows]
        print(f"work (blocks solved, both runs) / uninterrupted: min {min(work_ratio):.3f} median "
              f"{statistics.median(work_ratio):.3f} max {max(work_ratio):.3f}")
        print(f"wall (killed run + rerun) / uninterrupted:      min {min(wall_ratio):.3f} median "
              f"{statistics.median(wall_ratio):.3f} max {max(wall_ratio):.3f}  (both include meshing and assembly twice)")
    finally:
        shutil.rmtree(work, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="mode", required=True)
    for name in ("solvers", "dask", "resume"):
        p = sub.add_parser(name)
        p.add_argument("--mesh-size", type=float, default=0.01 if name == "solvers" else 0.003)
        p.add_argument("--repeat", type=int, default=3)
        if name == "solvers":
            p.add_argument("--order", type=int, default=1)
            p.add_argument("--methods", default="baseline,cholmod")
            p.add_argument("--bound", action="store_true",
                           help="also print each method's time against the FLOP bound of its triangular solves")
        if name == "dask":
            p.add_argument("--configs", default="serial,workers-1,workers-2")
            p.add_argument("--order", type=int, choices=(1, 2), default=None,
                           help="element order passed to the CLI (default: the CLI's, P2)")
    args = ap.parse_args()
    args.cli = [] if getattr(args, "order", None) is None else ["--order", str(args.order)]
    {"solvers": solvers, "dask": dask, "resume": resume}[args.mode](args)


if __name__ == "__main__":
    main()
