"""The first-run compile (hailstorm.runtime.storm.warmup): announcement, the split among
processes, helper processes that fill numba's cache, and the clean fallback when a
helper fails."""

from __future__ import annotations

import logging
import subprocess
import sys
import textwrap

import numba
import pytest

from hailstorm.runtime.storm import warmup
from hailstorm.runtime.storm.warmup import HelperSpec, WarmTask, plan, warm_up


@pytest.fixture(autouse=True)
def _own_cache(tmp_path, monkeypatch):
    """This machine's record of compile seconds goes to a private cache directory."""
    monkeypatch.setenv("HAILSTORM_CACHE", str(tmp_path / "hs-cache"))


def _fresh_kernel():
    """A kernel numba has never seen (no cache): its first call compiles."""
    return numba.njit(lambda x: x + 1)


def test_plan_balances_and_keeps_the_first_task_here():
    tasks = [WarmTask(n, s, lambda: None) for n, s in [("a", 4), ("b", 10), ("c", 10), ("d", 10), ("e", 3), ("f", 16)]]
    parts = plan(tasks, 2)
    assert sorted(i for p in parts for i in p) == list(range(6)) and 0 in parts[0]
    loads = [sum(tasks[i].seconds for i in p) for p in parts]
    # longest-first greedy: no part exceeds the other by more than the largest task
    assert abs(loads[0] - loads[1]) <= max(t.seconds for t in tasks)
    assert plan(tasks, 1) == [list(range(6))]
    assert plan(tasks[:1], 3) == [[0]]


def test_plan_keeps_tasks_that_share_kernels_in_one_process():
    """Tasks with one ``shares`` key are planned as one unit (their common kernels compile
    once): together in a helper, or with task 0 in this process; the others still balance."""
    def tasks(shared_with_first: bool) -> list[WarmTask]:
        first = "spd" if shared_with_first else ""
        return [WarmTask("a", 4, lambda: None, first), WarmTask("b", 9, lambda: None),
                WarmTask("c", 10, lambda: None, "spd"), WarmTask("d", 9, lambda: None),
                WarmTask("e", 3, lambda: None), WarmTask("f", 7, lambda: None, "spd")]

    ts = tasks(False)
    parts = plan(ts, 2, startup=2.0)
    where = {i: k for k, p in enumerate(parts) for i in p}
    assert where[2] == where[5] == 1 and where[0] == 0
    assert sorted(i for p in parts for i in p) == list(range(6))
    # without the key the greedy split separates them (the 10 s and the 7 s task)
    plain = [WarmTask(t.name, t.seconds, t.run) for t in ts]
    loose = {i: k for k, p in enumerate(plan(plain, 2, startup=2.0)) for i in p}
    assert loose[2] != loose[5]
    ts = tasks(True)
    parts = plan(ts, 2, startup=2.0)
    assert {0, 2, 5} <= set(parts[0]) and parts[1] and not {0, 2, 5} & set(parts[1])
    assert plan(ts, 1) == [list(range(6))]


def test_a_task_that_compiles_is_announced_and_a_loaded_one_is_not(caplog):
    k = _fresh_kernel()
    k(1)  # compiled now: the task below only finds it
    fresh = _fresh_kernel()
    tasks = [WarmTask("loaded kernels", 1, lambda: k(2)), WarmTask("fresh kernels", 7, lambda: fresh(2))]
    with caplog.at_level(logging.INFO, logger="hailstorm.runtime.storm.warmup"):
        report = warm_up(tasks, None, workers=1)
    lines = [r.getMessage() for r in caplog.records]
    assert report.compiled == ["fresh kernels"] and report.helpers == []
    assert lines == [f"compiling fresh kernels [2/2] (numba, once after an install: {warmup.estimate_text(7)})..."]
    assert set(report.times) == {"loaded kernels", "fresh kernels"}


def test_nothing_is_spawned_when_nothing_compiles(monkeypatch):
    k = _fresh_kernel()
    k(1)
    started = []
    monkeypatch.setattr(warmup, "_Helper", lambda *a: started.append(a))
    report = warm_up([WarmTask("a", 1, lambda: k(1)), WarmTask("b", 1, lambda: k(3))],
                     HelperSpec("x:y", {}), workers=2)
    assert started == [] and report.helpers == [] and not report.compiled


def _module(tmp_path, body: str) -> str:
    """A module ``warmhelp_<n>`` on a path the helper inherits (this process's sys.path)."""
    name = f"warmhelp_{abs(hash(str(tmp_path))) % 10**8}"
    (tmp_path / f"{name}.py").write_text(textwrap.dedent(body))
    sys.path.insert(0, str(tmp_path))
    return name


def test_a_helper_compiles_its_tasks_into_the_cache_and_this_process_loads_them(tmp_path):
    """Two cached kernels in a fresh module: the first task compiles here and starts the
    helper, which compiles the second; this process then loads the second from the disk
    cache (no compile here), with the helper's result. (The module's cache: beside it, or
    NUMBA_CACHE_DIR if set; the helper inherits the environment.)"""
    name = _module(tmp_path, """
        import numba

        @numba.njit(cache=True)
        def first(x):
            return x * 2.0

        @numba.njit(cache=True)
        def second(x):
            return x * 3.0 + 1.0

        def worker(payload, names):
            assert names == ["second"], names
            second(payload["x"])
        """)
    try:
        mod = __import__(name)
        tasks = [WarmTask("first", 5, lambda: mod.first(1.0)), WarmTask("second", 5, lambda: mod.second(1.0))]
        report = warm_up(tasks, HelperSpec(f"{name}:worker", {"x": 1.0}), workers=2)
        assert report.helpers == [["second"]] and not report.helper_failed
        assert report.compiled == ["first"]  # "second" was loaded from the helper's cache entry
        assert mod.second.stats.cache_hits and not mod.second.stats.cache_misses
        assert mod.second(2.0) == 7.0
    finally:
        sys.path.remove(str(tmp_path))


def test_a_failing_helper_falls_back_to_compiling_here(tmp_path, caplog):
    name = _module(tmp_path, """
        def worker(payload, names):
            raise RuntimeError("helper broke on purpose")
        """)
    try:
        a, b = _fresh_kernel(), _fresh_kernel()
        tasks = [WarmTask("a", 5, lambda: a(1)), WarmTask("b", 5, lambda: b(1))]
        with caplog.at_level(logging.INFO, logger="hailstorm.runtime.storm.warmup"):
            report = warm_up(tasks, HelperSpec(f"{name}:worker", {}), workers=2)
        assert report.helpers == [["b"]] and report.helper_failed
        assert report.compiled == ["a", "b"] and b(2) == 3  # compiled here instead
        assert any("helper broke on purpose" in r.getMessage() for r in caplog.records)
    finally:
        sys.path.remove(str(tmp_path))


def test_a_helper_that_cannot_import_its_entry_falls_back(caplog):
    a, b = _fresh_kernel(), _fresh_kernel()
    tasks = [WarmTask("a", 5, lambda: a(1)), WarmTask("b", 5, lambda: b(1))]
    with caplog.at_level(logging.INFO, logger="hailstorm.runtime.storm.warmup"):
        report = warm_up(tasks, HelperSpec("no_such_module_here:worker", {}), workers=2)
    assert report.helper_failed and report.compiled == ["a", "b"]


def test_workers_from_the_environment(monkeypatch):
    monkeypatch.setenv(warmup.WORKERS_ENV, "1")
    assert warmup.compile_workers() == 1
    monkeypatch.setenv(warmup.WORKERS_ENV, "3")
    assert warmup.compile_workers() == 3
    monkeypatch.delenv(warmup.WORKERS_ENV)
    assert 1 <= warmup.compile_workers() <= 2


@pytest.mark.slow
def test_the_storm_helper_fills_the_cache_with_the_parents_types(tmp_path, seat_bundle):
    """A cold storm build with two compile processes: every task the helper had is then
    loaded here without a compile (the helper rebuilt the storm with the same argument
    types), and a second process loads everything (a cold cache: slow)."""
    code = """
import json, sys
from hailstorm.runtime import load
from hailstorm.runtime.storm.scene import Scene
from hailstorm.runtime.storm.driver import Storm
st = Storm(load(sys.argv[1]), Scene.default())
r = st.warm_report
print(json.dumps({"compiled": r.compiled, "helpers": r.helpers, "failed": r.helper_failed}))
"""
    import json
    import os

    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"), HAILSTORM_COMPILE_WORKERS="2")
    out = subprocess.run([sys.executable, "-c", code, str(seat_bundle)], env=env, check=True,
                         capture_output=True, text=True).stdout
    first = json.loads(out.strip().splitlines()[-1])
    assert first["helpers"] and not first["failed"]
    helped = {n for part in first["helpers"] for n in part}
    assert not helped & set(first["compiled"]), first
    out = subprocess.run([sys.executable, "-c", code, str(seat_bundle)], env=env, check=True,
                         capture_output=True, text=True).stdout
    second = json.loads(out.strip().splitlines()[-1])
    assert second == {"compiled": [], "helpers": [], "failed": False}


def test_estimates_are_ranges_scaled_by_the_load(monkeypatch):
    """An estimate is a range from the measured CPU seconds to twice them stretched by the load
    (the load average and this process over the usable CPUs, at least 1); unmeasured says so."""
    assert warmup.estimate_text(9.0, 1.0) == "about 9-18 s"
    assert warmup.estimate_text(9.0, 2.5) == "about 9-45 s at the current load (x2.5)"
    assert warmup.estimate_text(9.0, 0.3) == "about 9-18 s"  # an idle machine is no faster than the CPU
    assert warmup.estimate_text(None) == "time not measured yet"
    monkeypatch.setattr(warmup.os, "getloadavg", lambda: (6.0, 0.0, 0.0))
    monkeypatch.setattr(warmup.os, "sched_getaffinity", lambda pid: {0, 1})
    assert warmup.load_factor() == 3.5  # (6 + this process) / 2 CPUs
    assert warmup.estimate_text(2.0) == "about 2-14 s at the current load (x3.5)"


def test_the_seconds_are_measured_at_a_compile_and_recorded(monkeypatch):
    """A task that compiles records its CPU seconds in this machine's record; the next estimate of
    that task is that measurement, before it the packaged one, and none for a task never measured."""
    from hailstorm.runtime.storm import compile_seconds

    monkeypatch.setattr(compile_seconds, "CPU_S", {"fresh kernels": 3.5})
    assert warmup.measured_seconds("fresh kernels") == 3.5  # packaged
    assert warmup.measured_seconds("other kernels") is None
    fresh = _fresh_kernel()
    report = warm_up([WarmTask("fresh kernels", warmup.measured_seconds("fresh kernels"), lambda: fresh(2))], None,
                     workers=1)
    assert report.compiled == ["fresh kernels"]
    assert warmup.measured_seconds("fresh kernels") == pytest.approx(report.cpu["fresh kernels"], abs=1e-3)
    assert warmup.measured_seconds("other kernels") is None
    # a task never measured is planned with the median of the measured ones
    ts = [WarmTask("a", 4.0, lambda: None), WarmTask("b", None, lambda: None), WarmTask("c", 10.0, lambda: None)]
    assert warmup._weights(ts) == [4.0, 10.0, 10.0]


def test_the_storm_tasks_take_their_seconds_from_the_measurements(monkeypatch):
    """No task's seconds is typed in: every storm task asks :func:`measured_seconds`."""
    from helpers import plate_gf

    from hailstorm.runtime.storm.scene import Scene
    from hailstorm.runtime.storm import driver

    asked = []
    monkeypatch.setattr(driver, "measured_seconds", lambda name: asked.append(name) or 1.25)
    st = driver.Storm(plate_gf(), Scene.from_flat(duration=0.01, stones=2, seed=1), warm=False)
    tasks = st.warm_tasks()
    assert sorted(t.name for t in tasks) == sorted(asked) and {t.seconds for t in tasks} == {1.25}
