"""Benchmark: the floor of a storm step -- the compiled phases alone -- against the step.

Usage::

    python tests/benchmarks/bench_step_floor.py                      # the default scene, 0.4 s, 3 repeats
    python tests/benchmarks/bench_step_floor.py --duration 1 --repeat 5 --out docs/_generated/step_floor.txt

Runs the default scene on the default seat (inertia pass off: it comes after the loop)
and times, inside the same runs, every call of a compiled kernel (numba) made from the
storm's Python code: each such call is wrapped by a timer, so the kernel's own work and
its dispatch (the unboxing of its arguments) count as "compiled"; everything else in the
loop -- numpy, LAPACK through scipy, the Python between the phases -- is "orchestration".
The compiled share is the floor a step would reach if the orchestration cost nothing
(the phases kept as they are); the ratio loop / floor is what a loop compiled end to end
could gain at most, without faster kernels.

The steps are classed by what they did: the steps without soft contacts run many per call
in compiled code (``Storm.run_free``; a call's time shared by its steps, the free phase of
a step it leaves half done included); of the steps run one by one (``Storm.step``): no
stone near the seat; near stones but no soft contact; soft contacts with the contact set
unchanged; a set that changed (a capacitance rebuild, with the patch sizing, the near field
and the engagement of new contacts). Printed per class: steps, wall time per step, the
compiled floor per step.

Min / median / max over ``--repeat`` runs (the machine is shared: wall-clock figures
are noisy; the ratios are measured within each run).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "notebooks"))

import argparse
import statistics
import time
from collections import defaultdict
from typing import Any, Callable


#: the step classes, in the order printed
CLASSES = ("no soft contact, compiled run", "no near stone", "near, no soft contact", "soft, same set", "set changed")


class KernelClock:
    """Wraps every numba dispatcher reached by name from ``hailstorm.*`` modules with a timer."""

    def __init__(self) -> None:
        self.seconds = 0.0
        self.calls = 0
        self.by_name: dict[str, float] = defaultdict(float)
        #: calls are timed only while set (inside a step)
        self.active = False
        self.count: dict[str, int] = defaultdict(int)
        self.fastest: dict[str, float] = defaultdict(lambda: float("inf"))
        self._undo: list[tuple[Any, str, Any]] = []

    def install(self) -> None:
        from numba.core.dispatcher import Dispatcher

        wrapped: dict[int, Callable] = {}
        for modname, mod in list(sys.modules.items()):
            if not modname.startswith("hailstorm.") or mod is None:
                continue
            for name, obj in list(vars(mod).items()):
                if isinstance(obj, Dispatcher):
                    if id(obj) not in wrapped:
                        wrapped[id(obj)] = self._wrap(obj, f"{obj.py_func.__module__.rsplit('.', 1)[-1]}.{obj.__name__}")
                    self._undo.append((mod, name, obj))
                    setattr(mod, name, wrapped[id(obj)])

    def uninstall(self) -> None:
        for mod, name, obj in self._undo:
            setattr(mod, name, obj)
        self._undo.clear()

    def _wrap(self, f: Any, label: str) -> Callable:
        clock = time.perf_counter

        def timed(*a: Any, **k: Any) -> Any:
            if not self.active:  # (outside the steps: the storm's set-up and warm-up)
                return f(*a, **k)
            t0 = clock()
            try:
                return f(*a, **k)
            finally:
                dt = clock() - t0
                self.seconds += dt
                self.calls += 1
                self.by_name[label] += dt
                self.count[label] += 1
                if dt < self.fastest[label]:
                    self.fastest[label] = dt

        return timed


def one_run(gf: Any, scene: Any) -> dict[str, Any]:
    """One storm run by :func:`~hailstorm.runtime.storm.run.run_storm` (its loop, frames and
    force history as always), each :meth:`Storm.step` classed and its wall and compiled time
    summed per class; ``loop``: the run's own wall time of the loop."""
    from hailstorm.runtime.storm.driver import Storm
    from hailstorm.runtime.storm.run import run_storm

    clock = KernelClock()
    wall = defaultdict(float)
    floor = defaultdict(float)
    count = defaultdict(int)
    step = Storm.step

    def timed_step(storm: Any) -> None:
        st = storm.stats
        sub0, reb0, k0 = st.substeps, st.capacitance_rebuilds, clock.seconds
        clock.active = True
        t0 = time.perf_counter()
        try:
            step(storm)
        finally:
            w = time.perf_counter() - t0
            clock.active = False
        if st.substeps == sub0:
            c = CLASSES[1]
        elif st.capacitance_rebuilds > reb0:
            c = CLASSES[4]
        elif storm.contacts.current is not None:
            c = CLASSES[3]
        else:
            c = CLASSES[2]
        wall[c] += w
        floor[c] += clock.seconds - k0
        count[c] += 1

    def timed_run_free(storm: Any, *args: Any) -> tuple[int, bool]:
        k0 = clock.seconds
        clock.active = True
        t0 = time.perf_counter()
        try:
            k, half = run_free(storm, *args)
        finally:
            w = time.perf_counter() - t0
            clock.active = False
        c = CLASSES[0]
        wall[c] += w
        floor[c] += clock.seconds - k0
        count[c] += k
        return k, half

    run_free = Storm.run_free
    clock.install()
    Storm.step = timed_step  # type: ignore[method-assign]
    Storm.run_free = timed_run_free  # type: ignore[method-assign]
    try:
        stats = run_storm(gf, scene, progress=False, on_frame=lambda f: None).stats
    finally:
        Storm.step = step  # type: ignore[method-assign]
        Storm.run_free = run_free  # type: ignore[method-assign]
        clock.uninstall()
    return dict(wall=dict(wall), floor=dict(floor), count=dict(count), sim=float(stats.sim_time_s),
                loop=float(stats.wall_time_s), calls=clock.calls, by_name=dict(clock.by_name), n_calls=dict(clock.count),
                fastest=dict(clock.fastest), stats=stats)


def main(argv: list[str] | None = None) -> None:
    from studies import record

    argv = sys.argv[1:] if argv is None else list(argv)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gf", help="bundle directory (default: the default seat, built or reused from the cache)")
    ap.add_argument("--duration", type=float, default=0.4)
    ap.add_argument("--repeat", type=int, default=3)
    record.add_out_option(ap)
    args = ap.parse_args(argv)
    record.run_or_record(args.out, "python tests/benchmarks/bench_step_floor.py", argv, lambda: run(args))


def run(args: argparse.Namespace) -> None:
    """The runs of ``args`` and their table."""
    import hailstorm.runtime
    from hailstorm.runtime.storm.scene import Scene, SeatSettings

    if args.gf:
        gf = hailstorm.runtime.load(args.gf)
    else:
        from studies.resolution_study import seat_bundle

        gf = seat_bundle(SeatSettings.default().mesh_size)
    d = Scene.default().to_dict()
    d["storm"]["duration"] = float(args.duration)
    d["validity"]["inertia"] = False
    scene = Scene.from_dict(d)
    runs = [one_run(gf, scene) for _ in range(args.repeat)]
    st = runs[-1]["stats"]
    print(f"default scene, {args.duration:g} s simulated, dt {scene.time.dt * 1e3:g} ms, {st.hailstones} stones, "
          f"{st.impacts} impacts, {st.capacitance_rebuilds} capacitance rebuilds; {args.repeat} runs, one BLAS thread")
    print(f"{'steps':24s} {'count':>6s} {'wall/step [us]':>16s} {'floor/step [us]':>16s} {'share of steps':>14s}"
          "   (median over runs; floor = the compiled kernels' calls)")
    total = [sum(r["wall"].values()) for r in runs]
    for c in CLASSES:
        n = runs[-1]["count"].get(c, 0)
        if not n:
            continue
        w = statistics.median(r["wall"].get(c, 0.0) for r in runs) / n * 1e6
        f = statistics.median(r["floor"].get(c, 0.0) for r in runs) / n * 1e6
        share = statistics.median(r["wall"].get(c, 0.0) / t for r, t in zip(runs, total))
        print(f"{c:24s} {n:6d} {w:16.0f} {f:16.0f} {share:14.0%}")
    loop = [r["loop"] for r in runs]  # the run's own: steps, force history, frames
    fl = [sum(r["floor"].values()) for r in runs]
    rtf = [r["sim"] / t for r, t in zip(runs, loop)]
    ratio = [t / f for t, f in zip(loop, fl)]
    floor_rtf = [r["sim"] / f for r, f in zip(runs, fl)]

    def mmm(x: list[float], fmt: str) -> str:
        return " / ".join(format(v, fmt) for v in (min(x), statistics.median(x), max(x)))

    print(f"loop (steps and frames): real-time factor {mmm(rtf, '.2f')} (min / median / max)")
    print(f"floor (compiled kernels alone): real-time factor {mmm(floor_rtf, '.2f')}; "
          f"loop / floor {mmm(ratio, '.2f')}; {runs[-1]['calls'] / max(st.steps, 1):.0f} kernel calls per step")
    last = runs[-1]
    names = sorted(last["by_name"].items(), key=lambda kv: -kv[1])
    top = sum(last["floor"].values())
    # the fastest call of a kernel is its dispatch (unboxing its arguments) plus the least work: a
    # lower bound of what the call costs before any arithmetic, which a loop compiled end to end saves
    dispatch = sum(last["fastest"][k] * last["n_calls"][k] for k, _ in names)
    print(f"of the floor, the calls at their fastest call's cost (~ dispatch: the arguments unboxed): "
          f"{dispatch / top:.0%}")
    print(f"{'kernel (last run)':40s} {'calls':>7s} {'share':>6s} {'mean [us]':>10s} {'fastest [us]':>13s}")
    for k, v in names[:12]:
        n = last["n_calls"][k]
        print(f"{k:40s} {n:7d} {v / top:6.0%} {v / n * 1e6:10.1f} {last['fastest'][k] * 1e6:13.1f}")


if __name__ == "__main__":
    main()
