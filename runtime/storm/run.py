"""Running a storm from start to end: :func:`run_storm` (the loop, its frames, progress and
statistics) and the compile helper's body (:func:`warm_up_worker`).

The loop runs the steps without soft contacts many per call in compiled code
(:meth:`hailstorm.runtime.storm.driver.Storm.run_free`) and every other step through
:meth:`~hailstorm.runtime.storm.driver.Storm.step`; frames are recorded at the scene's rate
and the force history per step (:class:`~hailstorm.runtime.storm.recording.Recorder`).
"""

from __future__ import annotations

import logging
import time
from typing import Any, Callable

import numpy as np

from hailstorm.runtime.bundle.compliance import ElasticSource
from hailstorm.runtime.compiled import KERNELS
from hailstorm.runtime.storm.driver import Storm
from hailstorm.runtime.storm.estimate import StormEstimate, hit_fraction
from hailstorm.runtime.storm.recording import Frame, Recorder, StormResult, StormStats
from hailstorm.runtime.storm.scene import Scene
from hailstorm.runtime.storm.warm_helper import array_kinds

__all__ = ["run_storm", "warm_up_worker"]

_log = logging.getLogger(__name__)


def warm_up_worker(payload: dict[str, Any], names: list[str]) -> None:
    """A compile helper's body (:mod:`hailstorm.runtime.storm.warmup`): rebuild the storm of
    ``payload`` (bundle directory, memory-mapped or not, the scene's dict) and warm up
    the tasks ``names``.

    Raises
    ------
    RuntimeError
        The bundle's arrays differ in type or layout from the caller's (the kernels
        would get other argument types).
    """
    from hailstorm.runtime.bundle.read import load

    gf = load(payload["bundle"], verify=False, mmap=bool(payload["mmap"]), expand=payload.get("expand"))
    if [list(k) for k in array_kinds(gf)] != [list(k) for k in payload["kinds"]]:
        raise RuntimeError("the bundle's arrays differ from the caller's")
    Storm(gf, Scene.from_dict(payload["scene"]), spawn=False, warm=False).warm_up(names)


def run_storm(
    gf: ElasticSource,
    scene: Scene | None = None,
    *,
    progress: bool | Callable[[float, float], None] = True,
    on_frame: Callable[[Frame], None] | None = None,
    keep_frames: bool | None = None,
    allow_large: bool = False,
    estimate: StormEstimate | None = None,
) -> StormResult:
    """Run a hail storm on the seat.

    Parameters
    ----------
    gf : ElasticSource
        The bundle (:func:`hailstorm.runtime.bundle.read.load`).
    scene : Scene, optional
        Default: :meth:`Scene.default`.
    progress : bool or callable
        ``True``: a tqdm progress bar over the simulated time (on stderr); a
        callable is called as ``progress(t, duration)`` as the storm advances (after each step
        or run of compiled steps).
    on_frame : callable, optional
        Called with each :class:`Frame` as it is recorded, e.g.
        :meth:`hailstorm.runtime.output.storm_output.StormOutput.add`, which streams the frames to
        disk.
    keep_frames : bool, optional
        Keep the frames in :attr:`StormResult.frames` (memory grows with the
        duration: ~24 bytes per surface vertex and frame). Default: kept when
        no ``on_frame`` is given, else not.
    allow_large : bool
        Run even a storm whose estimate (:meth:`Scene.estimate`) exceeds the
        machine; otherwise it is refused before anything runs.
    estimate : StormEstimate, optional
        The estimate to check and announce (the command line's counts its video
        and start-up); default: the scene's on this bundle
        (:meth:`Scene.estimate` with the seat's share of the footprint).

    Returns
    -------
    StormResult
        Frames at ``scene.output.fps`` (plus the first and last instants; empty
        unless kept) and statistics (see :func:`hailstorm.runtime.output.files.summary`).

    Raises
    ------
    hailstorm.runtime.storm.scene.StormTooLarge
        The estimate exceeds the machine and ``allow_large`` is not set.
    """
    scene = Scene.default() if scene is None else scene
    keep = on_frame is None if keep_frames is None else bool(keep_frames)
    if estimate is None:
        estimate = scene.estimate(int(np.asarray(gf.vertices).shape[0]), keep_frames=keep,
                                  hit_fraction=hit_fraction(gf.vertices, gf.triangles, scene.storm.margin))
    estimate.check(allow_large=allow_large)
    _log.info("storm: %s", estimate.describe())
    for warning in scene.physical_warnings(gf.vertices):
        _log.warning("warning: %s", warning)
    setup0 = time.perf_counter()
    storm = Storm(gf, scene)
    setup = time.perf_counter() - setup0
    rec = Recorder(scene.n_steps(), scene.output.fps, on_frame, keep)
    rec.record(storm.frame())
    wall = _step_all(storm, rec, progress, scene.storm.duration)
    st = _finish(storm, gf, scene, rec, wall, setup, show_progress=progress is True)
    return StormResult(scene=scene, frames=rec.frames, stats=st, history=rec.history)


def _step_all(storm: Storm, rec: Recorder, progress: bool | Callable[[float, float], None], duration: float) -> float:
    """:func:`run_storm`'s loop: every step of ``storm``, its frames and force history into
    ``rec``, the progress shown; returns the loop's wall time (the frames' sink excluded)."""
    bar = None
    if progress is True:
        from tqdm.auto import tqdm

        bar = tqdm(total=float(duration), desc="hail storm", unit="s sim", leave=False,
                   bar_format="{l_bar}{bar}| {n:.3g}/{total:.3g} s simulated [{elapsed}<{remaining}]")
    from threadpoolctl import threadpool_limits

    limiter = threadpool_limits(1)  # small dense solves: threaded BLAS only adds overhead
    wall0, sink0 = time.perf_counter(), rec.sink_time
    shown = 0.0
    try:
        i = 0
        while i < rec.n_steps:
            # the steps without soft contacts in compiled code, many per call; then one step here
            k, half_done = storm.run_free(rec.n_steps - i, i, rec.n_steps, rec.next_frame, rec.history)
            if k:
                i += k
                if rec.frame_due(storm.t, i - 1):
                    rec.record(storm.frame())
            if half_done or k == 0:
                storm.step()  # (finishes the half-done step)
                rec.forces(i, storm.t, storm.contact_forces()[1])
                if rec.frame_due(storm.t, i):
                    rec.record(storm.frame())
                i += 1
            if bar is not None:
                if storm.t - shown >= 0.002 * duration or i == rec.n_steps:
                    bar.update(min(storm.t, duration) - shown)
                    shown = min(storm.t, duration)
            elif callable(progress):
                progress(storm.t, duration)
    finally:
        wall = time.perf_counter() - wall0 - (rec.sink_time - sink0)
        limiter.restore_original_limits()
        if bar is not None:
            bar.close()
    return wall


def _finish(storm: Storm, gf: ElasticSource, scene: Scene, rec: Recorder, wall: float, setup: float,
            show_progress: bool) -> StormStats:
    """:func:`run_storm`'s end: the inertia pass (with a progress bar if ``show_progress``), the warning of
    stones that passed through, and the statistics completed."""
    st, stones = storm.stats, storm.stones
    inertia0 = time.perf_counter()
    if st.validity is not None and st.validity.measure_inertia:  # the pad's inertia per impact (a local peer each)
        st.validity.inertia(progress=show_progress)
    st.inertia_time_s = time.perf_counter() - inertia0
    through = storm.passed_through_warning()
    if through is not None:
        _log.warning("warning: %s", through)
    st.stones_hit = int(stones.hit.sum())
    # the one-time compile (a warm-up that compiled: the first run after an install) apart from the setup
    warm = storm.warm_report
    compile_s = float(warm.wall) if warm is not None and warm.compiled else 0.0
    st.sim_time_s, st.wall_time_s, st.backend = float(storm.t), float(wall), KERNELS
    st.setup_time_s, st.compile_time_s = max(float(setup) - compile_s, 0.0), compile_s
    st.real_time_factor = float(storm.t / wall) if wall > 0 else float("inf")
    st.seed, st.dt, st.integrator = scene.storm.seed, scene.time.dt, scene.time.integrator
    st.mode, st.restitution = scene.contact.mode, scene.contact.restitution
    st.n_vertices, st.n_triangles = int(storm.n), int(len(gf.triangles))
    st.resting_at_end = int((stones.ctri[stones.alive] >= 0).sum())
    st.frames, st.output_time_s = rec.n_frames, float(rec.sink_time)
    return st
