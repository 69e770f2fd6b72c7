"""First-run compile of the storm's kernels, per kernel, in a clean numba cache.

Usage (a clean cache: an empty NUMBA_CACHE_DIR, and no *.nbi / *.nbc beside the modules)::

    find runtime -name '*.nbi' -delete -o -name '*.nbc' -delete
    NUMBA_CACHE_DIR=$(mktemp -d) HAILSTORM_COMPILE_WORKERS=1 python tests/benchmarks/compile_time.py [--gf DIR] [--integrator exact]

Builds the storm of the default scene (or with ``--integrator`` / ``--patch``
changed) and runs a few steps; prints, for every kernel numba compiled, its
compile time (a kernel's own compile includes the kernels it calls that were not
compiled before it), the number of type specialisations each kernel ended with
(more than one: a second compile of the same kernel), the total, and the storm's
own per-task timing (the tasks that :mod:`hailstorm.runtime.storm.warmup` announces; wall and
this process's CPU).

Only this process's compiles are listed: with a compile helper (two usable CPUs, the
default) the helper's part is compiled in another process and only loaded here. For
the per-kernel figures and the tasks' ``seconds`` estimates (``Storm.warm_tasks``),
run with ``HAILSTORM_COMPILE_WORKERS=1``; for the parallel figure, time the whole
command (``/usr/bin/time``: the helper's CPU is counted in the children's).
"""

from __future__ import annotations

import argparse
import logging
import os
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gf", help="bundle directory (default: the default seat's, built or reused from the cache)")
    ap.add_argument("--integrator", default=None)
    ap.add_argument("--patch", default=None)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--tree", action="store_true", help="print the nesting of the compiles (who compiled what)")
    ap.add_argument("--write", action="store_true",
                    help="store the tasks' CPU seconds in runtime/storm/compile_seconds.py (the packaged estimates; "
                    "run with HAILSTORM_COMPILE_WORKERS=1 and an empty NUMBA_CACHE_DIR)")
    args = ap.parse_args()

    t_import = time.perf_counter()
    from numba.core import event

    import hailstorm.runtime
    from hailstorm.runtime.storm.scene import Scene, SeatSettings

    class CpuClock(event.Listener):
        """Records (process CPU time, event): compile seconds on a loaded machine (numba compiles in one thread)."""

        def __init__(self) -> None:
            self.buffer: list = []

        def on_start(self, ev) -> None:
            self.buffer.append((time.process_time(), ev))

        def on_end(self, ev) -> None:
            self.buffer.append((time.process_time(), ev))

    rec = CpuClock()
    event.register("numba:compile", rec)
    import_s = time.perf_counter() - t_import

    d = Scene.default().to_dict()
    if args.integrator:
        d["time"]["integrator"] = args.integrator
    if args.patch:
        d["contact"]["patch"] = args.patch
    sc = Scene.from_dict(d)
    if args.gf:
        path = args.gf
    else:
        from hailstorm.precompute import build_bundle

        seat = SeatSettings.default()
        path = build_bundle(None, mesh_size=seat.mesh_size, order=seat.order, young=seat.young, poisson=seat.poisson)
    gf = hailstorm.runtime.load(path)
    logging.basicConfig(level=logging.DEBUG, format="%(message)s")
    for name in ("numba", "matplotlib", "PIL"):
        logging.getLogger(name).setLevel(logging.WARNING)
    from hailstorm.runtime.storm.driver import Storm

    t0, c0 = time.perf_counter(), time.process_time()
    st = Storm(gf, sc)
    build, build_cpu = time.perf_counter() - t0, time.process_time() - c0
    t1 = time.perf_counter()
    for _ in range(args.steps):
        st.step()
    stepping = time.perf_counter() - t1
    starts: dict[int, tuple[str, float]] = {}
    own: list[tuple[str, float]] = []
    depth, total = 0, 0.0
    tree: list[tuple[int, str, float]] = []  # (depth, name, start) in start order; seconds filled at the end
    index: dict[int, int] = {}
    for ts, ev in rec.buffer:
        key = id(ev.data["dispatcher"]) if ev.data and "dispatcher" in ev.data else id(ev)
        name = ev.data["dispatcher"].py_func.__qualname__ if ev.data and "dispatcher" in ev.data else "?"
        if ev.is_start:
            starts[key] = (name, ts)
            index[key] = len(tree)
            tree.append((depth, name, ts))
            depth += 1
        elif key in starts:
            dt = ts - starts.pop(key)[1]
            own.append((name, dt))
            d0, n0, _ = tree[index[key]]
            tree[index.pop(key)] = (d0, n0, dt)
            depth -= 1
            if depth == 0:
                total += dt
    from numba.core.dispatcher import Dispatcher

    from hailstorm.runtime import compiled

    spec = {}
    for mod in (compiled.flight, compiled.narrow, compiled.patches, compiled.contacts, compiled.integrators,
                compiled.grid, compiled.blocks, compiled.wmatrix, compiled.point_solve, compiled.modal,
                compiled.lapack):
        for name in dir(mod):
            f = getattr(mod, name)
            if isinstance(f, Dispatcher) and f.signatures:
                spec[f"{mod.__name__.rsplit('.', 1)[1]}.{name}"] = len(f.signatures)
                if len(f.signatures) > 1:
                    print(f"{name}: " + " | ".join(str(sg) for sg in f.signatures))
    if args.tree:
        for d0, n0, sec in tree:
            if sec >= 0.2:
                print(f"{'  ' * d0}{n0} {sec:.2f} s")
    print(f"scene: integrator {sc.time.integrator}, patch {sc.contact.patch}, mode {sc.contact.mode}")
    print(f"import {import_s:.2f} s; Storm() (loads/compiles the kernels) {build:.2f} s wall, {build_cpu:.2f} s CPU; "
          f"{args.steps} steps {stepping:.2f} s")
    print(f"load average {os.getloadavg()[0]:.2f}; times below are process CPU seconds")
    print("kernel compiles (seconds, nested: a caller's time includes callees compiled with it):")
    for name, s in sorted(own, key=lambda x: -x[1]):
        print(f"  {s:7.2f}  {name}")
    top = {n for n, _ in own}
    print(f"{len(own)} compiles of {len(top)} kernels; total compile time {total:.2f} s")
    multi = {k: v for k, v in spec.items() if v > 1}
    print("kernels with more than one type specialisation:", multi or "none")
    rep = st.warm_report
    print(f"warm-up: {rep.wall:.2f} s wall; helpers: {rep.helpers or 'none'}"
          f"{' (failed)' if rep.helper_failed else ''}; per task, this process (wall / CPU s; "
          "the estimates in Storm.warm_tasks are the CPU with HAILSTORM_COMPILE_WORKERS=1):")
    for task in st.warm_tasks():
        if task.name in rep.times:
            print(f"  {rep.times[task.name]:7.2f} / {rep.cpu[task.name]:6.2f}  {task.name} (estimate {task.seconds:.0f} s)")
    if args.write:
        if rep.helpers or set(rep.compiled) != {t.name for t in st.warm_tasks()}:
            raise SystemExit("--write needs every task compiled in this process: HAILSTORM_COMPILE_WORKERS=1 and "
                             "an empty NUMBA_CACHE_DIR")
        from hailstorm.runtime.storm.warmup import write_packaged_seconds

        print("wrote", write_packaged_seconds({k: rep.cpu[k] for k in rep.compiled}))


if __name__ == "__main__":
    main()
