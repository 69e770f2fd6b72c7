"""Benchmark: a compressed bundle built by streaming (``--stream``) against the dense build then its compression.

Usage::

    python tests/benchmarks/bench_stream.py                     # the default seat (6 mm, P2, hat loads), tol 1e-2
    python tests/benchmarks/bench_stream.py --mesh-size 0.0012 --order 1 --load point --routes stream
    python tests/benchmarks/bench_stream.py --out docs/_generated/stream_default_seat.txt
    python tests/benchmarks/bench_stream.py --mesh-size 0.002 --order 1 --load point --routes stream --resume

Each route is ``hailstorm precompute --tol T`` (``dense``: the dense D on disk, then its
compressed copy; ``stream``: ``--stream``) in a fresh process, into a fresh folder with an
empty cache, one after the other. Printed per route: the wall time, the process's peak
resident memory (its own ``rusage``), the largest disk the bundle's folder and its work
directory held (sampled every 0.2 s), and from the bundle's manifest the stored bytes, the
dense D's bytes, the measured column error (200 exact columns) and the solve's seconds.

``--resume`` then stops a streamed run with SIGTERM (as ``kill`` or a batch scheduler
would) at half the streamed row's wall time, runs the same command again, and prints the
blocks the rerun resumed, both runs' wall time against the uninterrupted one, and the
largest difference of 400 columns (drawn at random) from the uninterrupted bundle's.
"""

from __future__ import annotations

import sys
from pathlib import Path

# the studies (notebooks/studies) are in the repository, not in the package
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "notebooks"))

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from hailstorm.runtime.bundle.read import load as load_bundle
from studies import record

ROUTES = ("dense", "stream")


def _disk(folder: Path) -> int:
    """Bytes allocated under ``folder`` (sparse files count what they hold)."""
    total = 0
    for root, _, files in os.walk(folder):
        for f in files:
            try:
                total += os.stat(os.path.join(root, f)).st_blocks * 512
            except OSError:
                pass
    return total


#: extra options of every ``hailstorm precompute`` run (``--allow-large``: past the size estimate's refusal)
EXTRA: list[str] = []


def _command(route: str, mesh_size: float, order: int, load: str, tol: float, out: Path) -> list[str]:
    cmd = [sys.executable, "-m", "hailstorm", "precompute", "--mesh-size", str(mesh_size), "--order", str(order),
           "--load", load, "--tol", str(tol), "--out", str(out), "--quiet", *EXTRA]
    return cmd + (["--stream"] if route == "stream" else [])


def run_route(route: str, mesh_size: float, order: int, load: str, tol: float, keep: Path | None = None) -> dict:
    """One ``hailstorm precompute`` of ``route`` in a fresh process and folder: its measures
    (its bundle moved to ``keep`` if given)."""
    with tempfile.TemporaryDirectory(prefix="hailstorm-bench-stream-") as tmp:
        out = Path(tmp) / "bundle"
        cmd = _command(route, mesh_size, order, load, tol, out)
        env = dict(os.environ, HAILSTORM_CACHE=str(Path(tmp) / "cache"))
        peak_disk = 0
        done = threading.Event()

        def watch() -> None:
            nonlocal peak_disk
            while not done.wait(0.2):
                peak_disk = max(peak_disk, _disk(Path(tmp)))

        watcher = threading.Thread(target=watch, daemon=True)
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        watcher.start()
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        done.set()
        watcher.join()
        err = proc.stderr.read() if proc.stderr else ""
        if os.waitstatus_to_exitcode(status) != 0:
            raise SystemExit(f"{route}: hailstorm precompute failed: {err.strip()[-400:]}")
        peak_disk = max(peak_disk, _disk(Path(tmp)))
        manifest = json.loads((out / "manifest.json").read_text())
        if keep is not None:
            shutil.move(str(out), str(keep))
        shutil.rmtree(out, ignore_errors=True)
    comp = manifest["compliance"]
    return {"wall": wall, "rss": usage.ru_maxrss * 1024, "disk": peak_disk, "stored": comp["stored_bytes"],
            "dense": comp["dense_bytes"], "err_max": comp["error"]["max"], "err_median": comp["error"]["median"],
            "solve": manifest["timings_s"]["solve"], "shape": comp["shape"], "max_rank": comp["max_rank"],
            "n_dofs": manifest["mesh"]["n_dofs"]}


def resume_run(reference: Path, wall: float, mesh_size: float, order: int, load: str, tol: float) -> dict:
    """A streamed run stopped by SIGTERM at ``wall / 2`` s, then run again: what it resumed, both
    runs' wall time, and the largest relative column difference from the bundle at ``reference``
    (400 columns drawn at random, seed 1)."""
    with tempfile.TemporaryDirectory(prefix="hailstorm-bench-resume-") as tmp:
        out = Path(tmp) / "bundle"
        cmd = _command("stream", mesh_size, order, load, tol, out)
        env = dict(os.environ, HAILSTORM_CACHE=str(Path(tmp) / "cache"))
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        try:
            proc.wait(timeout=wall / 2)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGTERM)
            proc.wait()
        first = time.perf_counter() - t0
        t1 = time.perf_counter()
        rerun = subprocess.run(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        second = time.perf_counter() - t1
        if rerun.returncode != 0:
            raise SystemExit(f"resume: the rerun failed: {rerun.stderr.strip()[-400:]}")
        stats = json.loads((out / "manifest.json").read_text())["solve_stats"]
        a, b = load_bundle(reference).hmatrix, load_bundle(out).hmatrix
        cols = np.random.default_rng(1).choice(a.shape[1], size=min(400, a.shape[1]), replace=False)
        A, B = a.columns(cols), b.columns(cols)
        diff = float((np.linalg.norm(A - B, axis=0) / np.linalg.norm(A, axis=0)).max())
    return {"stopped_at": first, "first_rc": proc.returncode, "resumed": stats["blocks_resumed"],
            "blocks": stats["blocks"], "rerun": second, "diff": diff}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mesh-size", type=float, default=0.006)
    ap.add_argument("--order", type=int, default=2)
    ap.add_argument("--load", choices=("point", "hat"), default="hat")
    ap.add_argument("--tol", type=float, default=1e-2)
    ap.add_argument("--routes", default=",".join(ROUTES), help=f"comma-separated, of {', '.join(ROUTES)}")
    ap.add_argument("--coarsening", type=float, default=None,
                    help="pass --coarsening C (the volume's elements grow to C mesh sizes away from the top)")
    ap.add_argument("--allow-large", action="store_true",
                    help="pass --allow-large (past the size estimate's refusal)")
    ap.add_argument("--keep", type=Path, default=None,
                    help="move the streamed bundle there (a new path) instead of deleting it")
    ap.add_argument("--resume", action="store_true",
                    help="also stop a streamed run with SIGTERM halfway and rerun it (needs the stream route)")
    ap.add_argument("--out", type=Path, default=None, help="also write the output there (with its header)")
    args = ap.parse_args(argv)
    routes = [r for r in args.routes.split(",") if r]
    if not routes or any(r not in ROUTES for r in routes):
        ap.error(f"--routes takes {', '.join(ROUTES)}, got {args.routes!r}")
    if (args.resume or args.keep is not None) and "stream" not in routes:
        ap.error("--resume and --keep need the stream route")
    if args.keep is not None and args.keep.exists():
        ap.error(f"--keep {args.keep}: exists (a new path is needed)")
    EXTRA[:] = (["--allow-large"] if args.allow_large else []) + \
        ([] if args.coarsening is None else ["--coarsening", str(args.coarsening)])
    stamp = record.stamp()
    lines: list[str] = []

    def emit(text: str = "") -> None:
        print(text, flush=True)
        lines.append(text)

    options = " ".join([f"--mesh-size {args.mesh_size} --order {args.order} --load {args.load} --tol {args.tol:g}",
                        *EXTRA, "[--stream]"])
    emit(f"hailstorm precompute {options}, each in a fresh process and folder")
    emit()
    emit("| route | D rows x columns | dofs | wall s | solve s | peak memory GiB | peak disk GiB | stored MiB | "
         "dense GiB | max rank | column error max (200 cols) | median |")
    emit("|---|---|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(prefix="hailstorm-bench-stream-keep-") as kept:
        reference = Path(kept) / "stream"
        for route in routes:
            m = run_route(route, args.mesh_size, args.order, args.load, args.tol,
                          keep=reference if route == "stream" and (args.resume or args.keep) else None)
            emit(f"| {route} | {m['shape'][0]} x {m['shape'][1]} | {m['n_dofs']:,} | {m['wall']:.1f} | "
                 f"{m['solve']:.1f} | {m['rss'] / 2**30:.2f} | {m['disk'] / 2**30:.2f} | {m['stored'] / 2**20:.1f} | "
                 f"{m['dense'] / 2**30:.2f} | {m['max_rank']} | {m['err_max']:.2e} | {m['err_median']:.2e} |")
            if route == "stream":
                wall = m["wall"]
        if args.resume:
            r = resume_run(reference, wall, args.mesh_size, args.order, args.load, args.tol)
            emit()
            emit("A streamed run stopped by SIGTERM halfway, then the same command again:")
            emit()
            emit("| stopped at s | exit | blocks resumed | rerun s | both runs / uninterrupted | "
                 "column difference from uninterrupted (400 cols) |")
            emit("|---|---|---|---|---|---|")
            emit(f"| {r['stopped_at']:.1f} | {r['first_rc']} | {r['resumed']} of {r['blocks']} | {r['rerun']:.1f} | "
                 f"{(r['stopped_at'] + r['rerun']) / wall:.2f} | {r['diff']:.1e} |")
        if args.keep is not None:
            shutil.move(str(reference), str(args.keep))
    if args.out is not None:
        record.write_run(args.out, record.command("python tests/benchmarks/bench_stream.py", argv), stamp, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
