"""Benchmark: the contact API on a compressed bundle read from its H-matrix against its dense expansion.

Usage::

    python tests/benchmarks/bench_hreader.py --gf DIR [--repeat 5] [--out FILE]

``DIR`` is a compressed bundle (``hailstorm precompute --tol T [--stream]``). Each reader runs in
a fresh process (``load(DIR, expand=False)``: the H-matrix's blocks; ``expand=True``: D
expanded once into the cache on first use and memory-mapped), the H-matrix reader first, in a
fresh cache that one warm-up process filled with what both read (numba's compiled kernels, the
layer kernel), never with the expansion.
Printed per reader: the first call's seconds (load, and for ``expand`` the expansion, plus
one solve), then per workload the min / median / max seconds of ``--repeat`` calls, and the
process's peak resident memory; and the largest relative difference of the forces between
the readers. Workloads, at contactable triangles drawn at random (seed 0):

* ``points s=20`` / ``points s=100``: ``solve_contacts``, sticky point contacts, with the
  full-surface displacement;
* ``spheres s=5``: ``press_spheres`` of 5 mm stones pressed 1.5 mm (Hertz patches, near field).

``--storm`` then runs the default scene's storm (``run_storm(gf, Scene.default())``) with each
reader in a fresh process, after a warm-up storm with each (the kernels compiled for both kinds
of D), in a cache holding no expansion: the wall time (load, the expansion for ``expand``, the storm), the
peak resident memory, and what the storm reports (impacts, largest force, largest dent).
"""

from __future__ import annotations

import sys
from pathlib import Path

# the studies (notebooks/studies) are in the repository, not in the package
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "notebooks"))

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from studies import record

READERS = ("hmatrix", "expand")
WORKLOADS = ("points s=20", "points s=100", "spheres s=5")


def _workload(gf, name: str) -> np.ndarray:
    """One call of workload ``name`` on ``gf``: its contact forces."""
    from hailstorm.runtime import solve_contacts
    from hailstorm.runtime.contact.hertz import press_spheres

    s = int(name.split("=")[1])
    rng = np.random.default_rng(0)
    ok = np.flatnonzero(gf.contactable[gf.triangles].all(axis=1))
    tri = rng.choice(ok, size=s, replace=False)
    bary = rng.dirichlet(np.ones(3), size=s)
    if name.startswith("points"):
        disp = np.tile([0.0, 0.0, -1e-3], (s, 1))
        return solve_contacts(gf, tri, bary, disp).forces
    return press_spheres(gf, tri, bary, np.full(s, 1.5e-3), 5e-3).normal_force


def child(gf_dir: str, reader: str, repeat: int) -> dict:
    """The measurements of one reader in this (fresh) process."""
    from hailstorm.runtime import load

    t0 = time.perf_counter()
    gf = load(gf_dir, expand=reader == "expand")
    forces = {WORKLOADS[0]: _workload(gf, WORKLOADS[0])}
    first = time.perf_counter() - t0
    times: dict[str, list[float]] = {}
    for name in WORKLOADS:
        times[name] = []
        for _ in range(repeat):
            t = time.perf_counter()
            forces[name] = _workload(gf, name)
            times[name].append(time.perf_counter() - t)
    return {"first": first, "times": times, "forces": {k: v.tolist() for k, v in forces.items()},
            "rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
            "expanded": bool(getattr(gf, "expanded", True))}


def storm_child(gf_dir: str, reader: str) -> dict:
    """The default storm with one reader in this (fresh) process."""
    from hailstorm.runtime import load, run_storm
    from hailstorm.runtime.storm.scene import Scene

    t0 = time.perf_counter()
    gf = load(gf_dir, expand=reader == "expand")
    st = run_storm(gf, Scene.default(), progress=False).stats
    return {"wall": time.perf_counter() - t0, "rss": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
            "impacts": st.impacts, "force": st.max_contact_force, "dent": st.max_indentation_m,
            "expanded": bool(getattr(gf, "expanded", True))}


def _run(gf_dir: Path, reader: str, repeat: int, cache: str, storm: bool = False) -> dict:
    env = dict(os.environ, HAILSTORM_CACHE=cache)
    cmd = [sys.executable, __file__, "--child", reader, "--gf", str(gf_dir), "--repeat", str(repeat)]
    out = subprocess.run(cmd + (["--storm"] if storm else []), env=env, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"{reader}: {out.stderr.strip()[-600:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gf", type=Path, required=True, help="a compressed bundle")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--out", type=Path, default=None, help="also write the output there (with its header)")
    ap.add_argument("--storm", action="store_true", help="also the default storm with each reader")
    ap.add_argument("--readers", default=",".join(READERS),
                    help="comma-separated, of hmatrix, expand (hmatrix alone: a D whose expansion does not fit)")
    ap.add_argument("--child", choices=READERS, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child is not None:
        work = storm_child if args.storm else lambda gf, r: child(gf, r, args.repeat)
        print(json.dumps(work(str(args.gf), args.child)))
        return 0
    from hailstorm.runtime import load

    readers = [r for r in args.readers.split(",") if r]
    if not readers or any(r not in READERS for r in readers):
        ap.error(f"--readers takes {', '.join(READERS)}, got {args.readers!r}")
    manifest = load(args.gf, verify=False).manifest
    if manifest.get("format_version") != 3:
        ap.error(f"{args.gf} is not a compressed bundle (format 3)")
    stamp = record.stamp()
    lines: list[str] = []

    def emit(text: str = "") -> None:
        print(text, flush=True)
        lines.append(text)

    comp = manifest["compliance"]
    emit(f"bundle: D {comp['shape'][0]} x {comp['shape'][1]}, tol {comp['tol']:g}, H-matrix "
         f"{comp['stored_bytes'] / 2**20:.1f} MiB of a {comp['dense_bytes'] / 2**30:.2f} GiB dense D "
         f"({manifest['mesh']['n_contactable']} contactable vertices)")
    emit(f"each reader in a fresh process, its cache holding no expansion of D, after a warm-up process; "
         f"{args.repeat} calls per workload: min / median / max s")
    emit()
    with tempfile.TemporaryDirectory(prefix="hailstorm-bench-hreader-") as cache:
        _run(args.gf, "hmatrix", 1, cache)  # warm-up: numba's cache, the layer kernel in this cache
        res = {r: _run(args.gf, r, args.repeat, cache) for r in readers}  # hmatrix first: no expansion yet
        if args.storm:
            for r in readers:  # warm-up: the storm's kernels compiled for both kinds of D (numba's cache)
                with tempfile.TemporaryDirectory(prefix="hailstorm-bench-hreader-warm-") as warm:
                    _run(args.gf, r, 1, warm, storm=True)
            cache2 = Path(cache) / "storm"  # a cache with no expansion again
            cache2.mkdir()
            storms = {r: _run(args.gf, r, 1, str(cache2), storm=True) for r in readers}
    emit("| reader | first call s | " + " | ".join(WORKLOADS) + " | peak memory GiB | D expanded |")
    emit("|---|---|" + "---|" * len(WORKLOADS) + "---|---|")
    for r in readers:
        m = res[r]
        cells = [f"{min(t):.3f} / {statistics.median(t):.3f} / {max(t):.3f}" for t in m["times"].values()]
        emit(f"| {r} | {m['first']:.2f} | " + " | ".join(cells) + f" | {m['rss'] / 2**30:.2f} | {m['expanded']} |")
    if len(readers) == len(READERS):
        emit()
        diffs = []
        for name in WORKLOADS:
            a, b = (np.asarray(res[r]["forces"][name]) for r in READERS)
            diffs.append(f"{name} {np.abs(a - b).max() / np.abs(b).max():.1e}")
        emit("forces, largest difference between the readers (relative to the largest force): " + ", ".join(diffs))
        ratio = [statistics.median(res["expand"]["times"][w]) / statistics.median(res["hmatrix"]["times"][w])
                 for w in WORKLOADS]
        emit("median call, expand / hmatrix: " + ", ".join(f"{w} {q:.2f}" for w, q in zip(WORKLOADS, ratio)))
    if args.storm:
        emit()
        emit("The default scene's storm (run_storm(gf, Scene.default())), each reader in a fresh process after a "
             "warm-up storm with each, in a cache holding no expansion:")
        emit()
        emit("| reader | wall s (load + storm) | peak memory GiB | impacts | largest force N | largest dent mm | "
             "D expanded |")
        emit("|---|---|---|---|---|---|---|")
        for r in readers:
            m = storms[r]
            emit(f"| {r} | {m['wall']:.1f} | {m['rss'] / 2**30:.2f} | {m['impacts']} | {m['force']:.2f} | "
                 f"{1e3 * m['dent']:.3f} | {m['expanded']} |")
    if args.out is not None:
        record.write_run(args.out, record.command("python tests/benchmarks/bench_hreader.py", argv), stamp, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
