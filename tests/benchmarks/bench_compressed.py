"""What a compressed D (``hailstorm precompute --tol``) costs and changes, against the dense bundle it came from.

For each tolerance: the compression's wall time, the stored and the dense bytes,
the error the bundle records (200 exact columns at random) and the worst over
*every* column, the time to load each bundle and read its D (a compressed one's
first read expands D into the cache, the later ones memory-map it), and what a user reads
off them:
``press_spheres`` forces of stones of 2.5, 5 and 12.5 mm pressed to the depth of
a Hertz impact at terminal speed (one at a time at 30 random places, and 20 at
once), dense against compressed.

    python tests/benchmarks/bench_compressed.py                    # the default seat (built or read from the cache)
    python tests/benchmarks/bench_compressed.py --gf DIR --tols 1e-2,1e-3 --out docs/_generated/compressed_default_seat.txt
"""

from __future__ import annotations

import sys
from pathlib import Path

# the studies (notebooks/studies) are in the repository, not in the package
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "notebooks"))

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from hailstorm.precompute.hmatrix import compress_bundle
from hailstorm.runtime import load
from hailstorm.runtime.contact.hertz import press_spheres
from hailstorm.runtime.storm.scene import SeatSettings
from studies import record
from studies.resolution_study import seat_bundle

#: stone radii [m] and their Hertz impact depths at terminal speed on the default seat's foam
#: (docs/_generated/resolution_seat.txt: 1.111, 2.931, 10.573 mm)
STONES = ((2.5e-3, 1.111e-3), (5e-3, 2.931e-3), (12.5e-3, 10.573e-3))
#: iterations of press_spheres' patch sizing (its default, 50, does not settle every deep 12.5 mm stone at 3 mm)
MAX_ITER = 200


def _places(gf, count: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    ok = np.flatnonzero(gf.contactable[gf.triangles].all(axis=1))
    return rng.choice(ok, size=count, replace=False), rng.dirichlet(np.ones(3), size=count)


def _forces(gf, tri, bary, radius, depth, together: bool) -> np.ndarray:
    """Normal forces of spheres pressed to ``depth``: all at once, or each on its own."""
    if together:
        return press_spheres(gf, tri, bary, np.full(len(tri), depth), radius, rows=None,
                             max_iter=MAX_ITER).normal_force
    out = np.full(len(tri), np.nan)  # NaN: the patch iteration did not settle there (left out of the errors)
    for i in range(len(tri)):
        try:
            out[i] = press_spheres(gf, tri[i:i + 1], bary[i:i + 1], [depth], radius, rows=None,
                                   max_iter=MAX_ITER).normal_force[0]
        except RuntimeError:
            pass
    return out


def _timed_load(path: Path, repeat: int = 3) -> tuple[object, list[float]]:
    """The bundle, and the wall time of each of ``repeat`` loads with the first read of D (a compressed
    bundle's first one expands D into the cache; the later ones memory-map it)."""
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        gf = load(path, verify=False)
        gf.D  # a compressed bundle expands on first use
        times.append(time.perf_counter() - t)
    return gf, times


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--gf", type=Path, default=None, help="a dense bundle (default: the default seat)")
    ap.add_argument("--tols", default="1e-2,1e-3", help="comma-separated target column errors")
    ap.add_argument("--places", type=int, default=30, help="random places per stone size")
    ap.add_argument("--out", type=Path, default=None, help="also write the output there (with its header)")
    args = ap.parse_args(argv)
    stamp = record.stamp()
    lines: list[str] = []

    def emit(text: str = "") -> None:
        print(text, flush=True)
        lines.append(text)

    src = args.gf or seat_bundle(SeatSettings.default().mesh_size).path
    dense, dense_load = _timed_load(src)
    n_rows, n_cols = dense.D.shape
    emit(f"dense bundle {src}: D {n_rows} x {n_cols} ({dense.D.nbytes / 2**20:.1f} MiB), "
         f"{dense.manifest['mesh'].get('source')}, P{dense.order}, load {dense.manifest['options'].get('load')}")
    emit(f"load (no re-hash), min/median/max of 3: dense {record.min_median_max(dense_load)} s")
    cache = Path(tempfile.mkdtemp(prefix="hailstorm-bench-cache-"))
    os.environ["HAILSTORM_CACHE"] = str(cache)  # the compressed bundles' expansions: a fresh cache, removed after
    tri, bary = _places(dense, args.places, seed=1)
    tri20, bary20 = _places(dense, 20, seed=2)
    together = STONES[:2]  # 20 stones of 12.5 mm at 10.6 mm overlap on the seat
    reference = {R: (_forces(dense, tri, bary, R, d, False),
                     _forces(dense, tri20, bary20, R, d, True) if (R, d) in together else None) for R, d in STONES}
    emit()
    emit("| tol | compress s | stored MiB | dense / stored | recorded max (200 cols) | recorded median | "
         "max over all columns | first load s | later loads s | one stone: max |dF|/F | 20 stones: max |dF|/max F |")
    emit("|---|---|---|---|---|---|---|---|---|---|---|")
    for tol in (float(t) for t in args.tols.split(",")):
        with tempfile.TemporaryDirectory(dir=Path(src).parent) as tmp:
            t0 = time.perf_counter()
            path = compress_bundle(src, Path(tmp) / "h", tol)
            seconds = time.perf_counter() - t0
            h, h_load = _timed_load(path)
            comp = h.manifest["compliance"]
            col = np.linalg.norm(np.asarray(h.D) - np.asarray(dense.D), axis=0) / np.linalg.norm(dense.D, axis=0)
            one = many = 0.0
            for R, d in STONES:
                a1, a20 = reference[R]
                one = max(one, float(np.nanmax(np.abs(_forces(h, tri, bary, R, d, False) - a1) / a1)))
                if a20 is not None:
                    many = max(many, float(np.max(np.abs(_forces(h, tri20, bary20, R, d, True) - a20))
                                           / np.abs(a20).max()))
            emit(f"| {tol:g} | {seconds:.1f} | {comp['stored_bytes'] / 2**20:.1f} | "
                 f"{comp['dense_bytes'] / comp['stored_bytes']:.1f} | {comp['error']['max']:.2e} | "
                 f"{comp['error']['median']:.2e} | {col.max():.2e} | {h_load[0]:.3f} | {record.min_median_max(h_load[1:])} | {one:.1e} | {many:.1e} |")
            del h
    shutil.rmtree(cache, ignore_errors=True)
    unsettled = sum(int(np.isnan(reference[R][0]).sum()) for R, _ in STONES)
    emit()
    if unsettled:
        emit(f"{unsettled} of {len(STONES) * args.places} single stones did not settle in {MAX_ITER} iterations "
             "on the dense bundle (left out)")
    emit(f"stones: R = {', '.join(f'{R * 1e3:g} mm at {d * 1e3:g} mm' for R, d in STONES)} (Hertz impact depths at "
         f"terminal speed); one at a time at {args.places} random places, and 20 at once (2.5 and 5 mm)")
    if args.out:
        record.write_run(args.out, record.command("python tests/benchmarks/bench_compressed.py", argv), stamp, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
