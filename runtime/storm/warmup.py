"""The storm's first-run compile: its kernels warmed up in tasks, some in a helper process.

numba compiles a kernel on its first call and caches the machine code on disk
(``cache=True``), so every later process only loads it (milliseconds). The first
run after an install compiles them all: about 50 s of CPU for the default storm (its exact
integrator's kernels about half of it; measured by ``tests/benchmarks/compile_time.py`` on
2026-12-06: 54 s, the exact integrator's 27 s, the compiled free steps' 6 s), nearly all in
numba's own single-threaded compiler. :func:`warm_up` runs a list
of :class:`WarmTask` (each loads or compiles a few kernels with the storm loop's
argument types) and, as soon as a task turns out to compile (numba's
``numba:compile`` event: a cache miss), starts helper processes that compile the
tasks planned for them while this process compiles its own; it then waits for
them and runs their tasks itself, which now only load what the helpers cached.
Tasks that share kernels (:attr:`WarmTask.shares`) stay in one process so that those
compile once. Measured when the compile was about twice as long (``tests/benchmarks/compile_helper.py``,
docs/performance.md): a cold default storm took 67.4 s of wall time with the helper against
95.8 s in one process (medians of three pairs on two cores, ratio 0.64-0.74; 13 % more CPU
in all), the exact integrator's task alone setting the helper's time.

A helper rebuilds the same storm from the bundle's directory and the scene (so
that its kernels get exactly this process's argument types) through the
``entry`` the caller names (``"module:function"``, called with the payload
dict). If a helper cannot start, fails or times out, this process simply
compiles its tasks too (the result is the same; only slower). Nothing is
spawned when every kernel is cached, under ``NUMBA_DISABLE_JIT=1``, or with
``HAILSTORM_COMPILE_WORKERS=1``.

A task's seconds are measured, never typed in (:func:`measured_seconds`): each cold
compile records its CPU seconds in ``compile_seconds.json`` in hailstorm's cache
directory (this machine's figures, used by the next compile, e.g. after an
upgrade); before any compile on this machine, the packaged measurement
(:mod:`hailstorm.runtime.storm.compile_seconds`, written by
``tests/benchmarks/compile_time.py --write``). The announcement states a range
scaled by the machine's load (:func:`estimate_text`): numba compiles on one
thread, so a loaded machine stretches the wall time.
"""

from __future__ import annotations

import json
import logging
import math
import os
import pickle
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numba
from numba.core import event

__all__ = ["RECORD_NAME", "WORKERS_ENV", "HelperSpec", "WarmReport", "WarmTask", "compile_workers", "estimate_text",
           "load_factor", "measured_seconds", "plan", "record_seconds", "run_helper", "warm_up",
           "write_packaged_seconds"]

_log = logging.getLogger(__name__)

#: environment variable: processes that compile at most (``1``: no helper; default: the usable CPUs, at most 2)
WORKERS_ENV = "HAILSTORM_COMPILE_WORKERS"
#: a helper that has not finished after this many times its planned seconds (and 60 s) is stopped
HELPER_TIMEOUT_FACTOR = 10.0
#: CPU seconds a helper spends before it compiles (interpreter, imports, the storm rebuilt; measured ~1.5 s idle,
#: ~3 s at load ~3: its CPU less its tasks' in a fresh venv)
HELPER_STARTUP = 3.0


@dataclass(frozen=True)
class WarmTask:
    """A few kernels loaded (or compiled) together.

    Attributes
    ----------
    name : str
        What they are, for the announcement (``"the narrow-phase kernels"``).
    seconds : float or None
        CPU seconds their first compile takes in a fresh process, measured
        (:func:`measured_seconds`), or None when never measured; plans the split and is announced.
    run : callable
        Calls the kernels with the storm loop's argument types.
    shares : str
        Tasks with the same non-empty ``shares`` call kernels in common (numba compiles
        a kernel's callees with it, once per process): :func:`plan` keeps them in one
        process, in their order, so that the common kernels compile once, and the
        ``seconds`` of the later ones leave them out.
    """

    name: str
    seconds: float | None
    run: Callable[[], None]
    shares: str = ""


@dataclass(frozen=True)
class HelperSpec:
    """How a helper process rebuilds the caller's kernels' argument types.

    Attributes
    ----------
    entry : str
        ``"module:function"``; the helper imports it and calls ``function(payload, names)``
        with ``names`` the task names to warm up.
    payload : dict
        Picklable inputs of ``entry`` (e.g. the bundle's path and the scene's dict).
    """

    entry: str
    payload: dict[str, Any]


@dataclass
class WarmReport:
    """What :func:`warm_up` did.

    Attributes
    ----------
    compiled : list of str
        Tasks that compiled at least one kernel in this process.
    helpers : list of list of str
        Tasks given to each helper process started.
    helper_failed : bool
        A helper failed or timed out (its tasks were compiled here).
    times : dict
        Wall seconds per task in this process (a helper's task: its load after the wait).
    cpu : dict
        This process's CPU seconds per task.
    wall : float
        Wall seconds in all (the wait for helpers included).
    """

    compiled: list[str] = field(default_factory=list)
    helpers: list[list[str]] = field(default_factory=list)
    helper_failed: bool = False
    times: dict[str, float] = field(default_factory=dict)
    cpu: dict[str, float] = field(default_factory=dict)
    wall: float = 0.0


def compile_workers() -> int:
    """Processes the first compile may use: ``HAILSTORM_COMPILE_WORKERS`` if set (at
    least 1), else the CPUs this process may run on, at most 2 (the storm's tasks do
    not split evenly further)."""
    raw = os.environ.get(WORKERS_ENV, "").strip()
    if raw:
        try:
            return max(1, int(raw))
        except ValueError:
            _log.warning("warning: %s=%r is not an integer; using 1", WORKERS_ENV, raw)
            return 1
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    return max(1, min(2, cpus))


def plan(tasks: Sequence[WarmTask], workers: int, startup: float = HELPER_STARTUP) -> list[list[int]]:
    """Split task indices among ``workers`` processes (longest first, each to the least
    loaded; a helper starts loaded with ``startup`` seconds); list 0 is this process's
    and holds task 0 (the first one run). Tasks with the same ``shares`` go together
    (to the process of task 0 if it is one of them). Task order within each list is
    the given order."""
    loads = [0.0] + [startup] * (max(1, workers) - 1)
    parts: list[list[int]] = [[] for _ in loads]
    units: dict[object, list[int]] = {}
    for i, task in enumerate(tasks):
        units.setdefault(task.shares or i, []).append(i)
    weight = _weights(tasks)
    order = sorted(units.values(), key=lambda u: (0 not in u, -sum(weight[i] for i in u)))
    for unit in order:
        w = 0 if 0 in unit else min(range(len(loads)), key=lambda k: (loads[k], k))
        parts[w].extend(unit)
        loads[w] += sum(weight[i] for i in unit)
    return [sorted(p) for p in parts if p or p is parts[0]]


def _weights(tasks: Sequence[WarmTask]) -> list[float]:
    """Each task's planning weight: its measured seconds, or (never measured) the median of the
    measured ones (1 s when none is)."""
    known = sorted(t.seconds for t in tasks if t.seconds is not None)
    fill = known[len(known) // 2] if known else 1.0
    return [t.seconds if t.seconds is not None else fill for t in tasks]


#: this machine's record of the tasks' measured compile seconds, in hailstorm's cache directory
RECORD_NAME = "compile_seconds.json"


def _record_path() -> Any:
    from hailstorm.runtime.bundle.stamps import default_cache_dir

    return default_cache_dir() / RECORD_NAME


def _read_record() -> dict[str, float]:
    try:
        data = json.loads(_record_path().read_text())
        return {str(k): float(v) for k, v in data.get("cpu_s", {}).items() if math.isfinite(float(v)) and v > 0}
    except (OSError, ValueError, TypeError, AttributeError):
        return {}


def measured_seconds(name: str) -> float | None:
    """CPU seconds of task ``name``'s cold compile in one process: this machine's last measured
    compile (:func:`record_seconds`), else the packaged measurement
    (:data:`hailstorm.runtime.storm.compile_seconds.CPU_S`), else None (never measured)."""
    from hailstorm.runtime.storm.compile_seconds import CPU_S

    here = _read_record()
    return here.get(name, CPU_S.get(name))


def record_seconds(cpu: dict[str, float]) -> None:
    """Merge the measured CPU seconds of tasks that compiled into this machine's record
    (written atomically; a record that cannot be written is skipped, said at debug level)."""
    if not cpu:
        return
    from hailstorm.runtime.bundle.atomic import write_text_atomic

    data = _read_record()
    data.update({k: round(float(v), 3) for k, v in cpu.items()})
    try:
        path = _record_path()
        path.parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(path, json.dumps({"cpu_s": data}, indent=1, sort_keys=True) + "\n")
    except OSError as exc:
        _log.debug("could not record the compile seconds (%s)", exc)


def write_packaged_seconds(cpu: dict[str, float]) -> Any:
    """Write the packaged measurement :mod:`hailstorm.runtime.storm.compile_seconds` (merged with
    what it holds): for ``tests/benchmarks/compile_time.py --write``. Returns its path."""
    from pathlib import Path

    from hailstorm.runtime.bundle.atomic import write_text_atomic
    from hailstorm.runtime.storm.compile_seconds import CPU_S

    data = dict(CPU_S)
    data.update({k: round(float(v), 2) for k, v in cpu.items()})
    try:
        load = os.getloadavg()[0]
    except OSError:
        load = float("nan")
    body = "".join(f"    {k!r}: {v!r},\n" for k, v in sorted(data.items()))
    text = ('"""Measured CPU seconds of each storm warm-up task\'s cold compile in one process (generated: do not\n'
            "edit; ``NUMBA_CACHE_DIR=$(mktemp -d) HAILSTORM_COMPILE_WORKERS=1 python tests/benchmarks/compile_time.py\n"
            f"--write [--integrator NAME]``; last written {time.strftime('%Y-%m-%d')} at load {load:.1f} on "
            f"{os.cpu_count()} CPUs).\n\n"
            "The fallback of :func:`hailstorm.runtime.storm.warmup.measured_seconds` before a machine has\n"
            'measured its own.\n"""\n\n'
            f"CPU_S: dict[str, float] = {{\n{body}}}\n")
    path = Path(__file__).with_name("compile_seconds.py")
    write_text_atomic(path, text)
    return path


def load_factor() -> float:
    """How much longer than its CPU seconds a compile takes now: the 1-minute load average plus
    this process, over the CPUs it may use, at least 1 (numba compiles on one thread)."""
    try:
        load = os.getloadavg()[0]
    except OSError:  # not available here
        return 1.0
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    return max(1.0, (load + 1.0) / max(cpus, 1))


def estimate_text(seconds: float | None, factor: float | None = None) -> str:
    """The announced estimate of a compile of ``seconds`` CPU seconds: a range from the CPU
    seconds (a process may still get a whole core on a loaded machine) to twice the CPU
    seconds stretched by the load (:func:`load_factor`): ``"about 9-18 s"`` on an idle machine.
    The load average predicts the stretch poorly both ways: 60 CPU s took 559 s of wall at
    load 7.4 on 2 CPUs (9.3x, factor 4.2), while a fresh install's compile at factor 3.2 ran
    at its CPU seconds (35.5 s of wall for 32 CPU s in two processes). Or ``"time not measured
    yet"``."""
    if seconds is None:
        return "time not measured yet"
    f = load_factor() if factor is None else max(1.0, float(factor))
    return f"about {seconds:.0f}-{2 * seconds * f:.0f} s" + (f" at the current load (x{f:.1f})" if f > 1.05 else "")


class _MissWatch(event.Listener):
    """Calls ``on_miss`` at every start of a numba compile (a kernel not in the cache)."""

    def __init__(self, on_miss: Callable[[], None]) -> None:
        self.on_miss = on_miss

    def on_start(self, ev: event.Event) -> None:
        self.on_miss()

    def on_end(self, ev: event.Event) -> None:
        pass


_BOOT = (
    "import pickle, sys\n"
    "msg = pickle.load(sys.stdin.buffer)\n"
    "sys.path[:] = msg['path']\n"
    "from hailstorm.runtime.storm.warmup import run_helper\n"
    "run_helper(msg)\n"
)


def run_helper(msg: dict[str, Any]) -> None:
    """A helper process's body: import ``msg["entry"]`` and call it with
    ``(msg["payload"], msg["names"])``."""
    module, _, func = msg["entry"].partition(":")
    import importlib

    getattr(importlib.import_module(module), func)(msg["payload"], list(msg["names"]))


class _Helper:
    """One helper process compiling some tasks (its stderr kept in a temporary file)."""

    def __init__(self, spec: HelperSpec, names: list[str], seconds: float) -> None:
        self.names = names
        self.timeout = max(60.0, HELPER_TIMEOUT_FACTOR * seconds)
        self.err = tempfile.TemporaryFile()
        msg = {"path": list(sys.path), "entry": spec.entry, "payload": spec.payload, "names": names}
        self.proc = subprocess.Popen([sys.executable, "-c", _BOOT], stdin=subprocess.PIPE,
                                     stdout=subprocess.DEVNULL, stderr=self.err)
        assert self.proc.stdin is not None
        try:
            self.proc.stdin.write(pickle.dumps(msg))
            self.proc.stdin.close()
        except OSError:  # it died at once; wait() reports it
            pass
        self.t0 = time.perf_counter()

    def wait(self) -> bool:
        """Wait for it; True if it finished its tasks."""
        try:
            rc = self.proc.wait(timeout=max(1.0, self.timeout - (time.perf_counter() - self.t0)))
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            _log.info("compile helper (%s) timed out; compiling its kernels here", ", ".join(self.names))
            self.err.close()
            return False
        if rc != 0:
            self.err.seek(0)
            lines = self.err.read().decode(errors="replace").strip().splitlines()
            _log.info("compile helper (%s) failed (exit %d: %s); compiling its kernels here", ", ".join(self.names),
                      rc, lines[-1] if lines else "no message")
        self.err.close()
        return rc == 0


def warm_up(tasks: Sequence[WarmTask], helper: HelperSpec | None = None, *, workers: int | None = None) -> WarmReport:
    """Run ``tasks``; if one compiles and ``helper`` is given, compile in parallel.

    Parameters
    ----------
    tasks : sequence of WarmTask
    helper : HelperSpec, optional
        How a helper process rebuilds the tasks (None: everything here).
    workers : int, optional
        Processes in all (default :func:`compile_workers`).

    Returns
    -------
    WarmReport

    Notes
    -----
    Each task that compiles says so in one INFO line, with its place in the
    sequence and its measured seconds; a started helper is announced with the
    tasks it compiles.
    """
    t_all = time.perf_counter()
    report = WarmReport()
    n_workers = workers if workers is not None else compile_workers()
    can_help = helper is not None and n_workers > 1 and len(tasks) > 1 and not numba.config.DISABLE_JIT
    parts = plan(tasks, n_workers if can_help else 1)
    weight = _weights(tasks)
    mine, others = parts[0], parts[1:]
    helpers: list[_Helper] = []
    state = {"current": "", "announced": set(), "step": 0, "spawned": False}
    total = len(tasks)

    def on_miss() -> None:
        name = state["current"]
        if name and name not in state["announced"]:
            state["announced"].add(name)
            report.compiled.append(name)
            _log.info("compiling %s [%d/%d] (numba, once after an install: %s)...", name, state["step"],
                      total, estimate_text(next(t.seconds for t in tasks if t.name == name)))
        if can_help and not state["spawned"]:
            state["spawned"] = True
            for part in others:
                names = [tasks[i].name for i in part]
                secs = sum(weight[i] for i in part)
                try:
                    helpers.append(_Helper(helper, names, secs))  # type: ignore[arg-type]
                except OSError as exc:
                    _log.info("cannot start a compile helper (%s); compiling here", exc)
                    report.helper_failed = True
                    continue
                report.helpers.append(names)
                _log.info("compiling %s in a helper process, in parallel (%s)...", ", ".join(names), estimate_text(secs))

    def run(i: int) -> None:
        task = tasks[i]
        state["current"], state["step"] = task.name, state["step"] + 1
        t0, c0 = time.perf_counter(), time.process_time()
        task.run()
        report.times[task.name] = time.perf_counter() - t0
        report.cpu[task.name] = time.process_time() - c0
        state["current"] = ""

    watch = _MissWatch(on_miss)
    event.register("numba:compile", watch)
    try:
        for i in mine:
            run(i)
        for h in helpers:
            if not h.wait():
                report.helper_failed = True
        for part in others:
            for i in part:
                run(i)
    finally:
        event.unregister("numba:compile", watch)
        for h in helpers:  # an exception above: do not leave a helper behind
            if h.proc.poll() is None:
                h.proc.kill()
                h.proc.wait()
    report.wall = time.perf_counter() - t_all
    # this machine's measurement, for the next compile's plan and announcement (a helper records its own)
    record_seconds({name: report.cpu[name] for name in report.compiled if name in report.cpu})
    return report
