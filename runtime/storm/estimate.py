"""What a storm will cost before it runs: :class:`StormEstimate` and its measured rates.

The stepping time of a storm is set by its impacts, not by its stones in flight:
on the default seat a stone in free flight costs ~1e-7 s per step (the compiled
flight and broad phase), a step with no stone near the seat ~7 us, and each
impact (its approach, the contact's sub-steps, its capacitance and patches, its
release) about 3.5 ms, nearly independent of ``dt`` (the sub-steps adapt) and of
the storm's duration (stones retire after their bounce: a default storm holds
~345 stones at a time from ~0.4 s on, whatever its duration). Impacts that
overlap in time cost more each (the contact set grows): by the factor
``1 + s / CROWD_CONTACTS`` where ``s`` is the mean number of stones near the seat
at once. The frames cost ~0.8 us per surface vertex each (the one-file ParaView series and
the video) and the pad's inertia, read impact by impact from the material's table
after the storm, :data:`INERTIA_SECONDS_PER_IMPACT` each (a material without a table
computes it once, in about 30-60 s, not counted: it is announced with a progress bar).

How many stones hit: the seat's share of the spawn footprint
(:func:`hit_fraction`); before the bundle is read, 1 (an upper bound: the
default seat takes 0.54 of its footprint).

The rates were measured on this project's 2-core test machine with the default
seat (1659 surface vertices), under a load of ~1.5 (``docs/performance.md``,
"Estimates"; ``tests/benchmarks/bench_estimate.py`` prints the estimate beside the
measured wall time).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hailstorm.runtime.resources import available_memory
from hailstorm.runtime.storm.errors import StormTooLarge

__all__ = ["BYTES_PER_STEP", "BYTES_PER_STONE", "CROWD_CONTACTS", "DISK_BYTES_FIXED", "DISK_BYTES_PER_VERTEX", "FLIGHT_SECONDS_PER_STONE_STEP",
           "FRAME_SECONDS_PER_VERTEX", "IMPACT_SECONDS", "INERTIA_SECONDS_PER_IMPACT", "MAX_SECONDS", "MAX_STEPS",
           "MEMORY_FRACTION", "NEAR_TIME", "STARTUP_SECONDS", "STEP_SECONDS", "STONE_LIFETIME", "VIDEO_FRAMES", "VIDEO_SECONDS_PER_FRAME", "StormEstimate", "count_text", "duration_text",
           "hit_fraction", "size_text"]


#: above this many steps a storm is refused without ``allow_large`` (hours of stepping)
MAX_STEPS = 10_000_000
#: above this estimated wall time [s] (stepping, frames, inertia) a storm is refused without ``allow_large``
MAX_SECONDS = 3600.0
#: a storm may hold at most this fraction of the available memory without ``allow_large``
MEMORY_FRACTION = 0.8
#: memory per stone over the run [bytes]: the spawn plan (64) and the per-stone state
#: (~160), which grows by doubling (x2), rounded up
BYTES_PER_STONE = 512
#: memory per step [bytes]: the contact-force history (time, force, contacts)
BYTES_PER_STEP = 24
#: disk per frame and surface vertex [bytes], by ParaView series: ``"vtu"``, the seat's VTU (measured
#: ~60 on the default seat, zlib-compressed float64 fields and the triangles); ``"vtkhdf"``, the one
#: file (``bench_series.py``: 22.2 kB a frame of the 30 s default storm, stones included, ~13 per
#: vertex); rounded up
DISK_BYTES_PER_VERTEX: dict[str, int] = {"vtu": 80, "vtkhdf": 16}
#: disk of a storm's outputs whatever its frames [bytes], by series: the one file's fixed part
#: (its datasets' first chunks; measured ~0.2 MB on a small seat)
DISK_BYTES_FIXED: dict[str, int] = {"vtu": 0, "vtkhdf": 256 * 1024}
#: wall time of one expected impact's stepping [s]: measured 3.0-3.7 ms per impact on the default
#: seat (the default storm over 1, 3 and 10 s, at dt 0.2 and 0.5 ms, 300 and 2 000 stones per
#: second), per impact that :func:`hit_fraction` expects (0.47 of the stones; 0.54 hit, the
#: stones' radius widening the seat) 4 ms
IMPACT_SECONDS = 4e-3
#: how long a stone that hits stays near the seat [s] (approach, contact, release): ~2 ms
#: (68 % of the default storm's steps have a stone near the seat at 540 impacts per second)
NEAR_TIME = 2e-3
#: stones near the seat at once that double an impact's cost (measured: 3 000 stones landing
#: within 0.05 s, ~58 at once, cost 14 ms per impact against 3.5 ms alone)
CROWD_CONTACTS = 19.0
#: wall time of one stone's step in free flight [s] (the compiled flight and broad phase)
FLIGHT_SECONDS_PER_STONE_STEP = 1e-7
#: wall time of a step with no stone near the seat [s] (5 000 steps of one stone: 0.036 s)
STEP_SECONDS = 7e-6
#: how long a stone lives, spawn to retirement [s]: a default storm holds ~345 stones at
#: 1 000 stones per second from ~0.4 s on
STONE_LIFETIME = 0.35
#: wall time of a frame per surface vertex [s]: the one-file series (``bench_estimate.py``: 9.9 s for
#: the 7 501 frames of a 30 s default storm, 1.3 ms a frame; the ``.vtu`` series of ``--series vtu``
#: costs about 8 ms a frame, ~5e-6 per vertex, not counted)
FRAME_SECONDS_PER_VERTEX = 0.8e-6
#: wall time of the pad's inertia per expected impact [s], read from the material's table
#: (:mod:`hailstorm.runtime.inertia.table`; ``bench_inertia_table.py``: ~0.5 ms for 99 impacts,
#: with the impact records' thickness rays ~1 ms in all; an impact off the table's grid is re-run
#: on its pad, ~0.08 s, rare in the default scene)
INERTIA_SECONDS_PER_IMPACT = 2e-5
#: wall time of rendering one frame of the video [s] (``storm.mp4``, after the storm: the default
#: storm over 0.5 s, 126 frames in ~5.3 s)
VIDEO_SECONDS_PER_FRAME = 0.042
#: the video's frames at most (:func:`hailstorm.runtime.output.animation.write_animation`'s ``max_frames``:
#: a long storm's video is evenly subsampled)
VIDEO_FRAMES = 100
#: wall time of a warm start [s]: imports, the bundle, the compiled kernels from numba's cache
#: (``hailstorm storm --duration 0.001 --no-video``: 3.5 s)
STARTUP_SECONDS = 3.5
#: the seat's share of the footprint assumed before the bundle is read (an upper bound)
UNKNOWN_HIT_FRACTION = 1.0


def size_text(n: float) -> str:
    """A byte count for a message: ``"3.5 MiB"``."""
    for unit, k in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20)):
        if n >= k:
            return f"{n / k:.3g} {unit}"
    return f"{n / 2**10:.3g} KiB"


def count_text(n: float) -> str:
    """A count for a message: ``12,345`` up to a trillion, else ``1.23e+300``."""
    return f"{int(n):,}" if n < 1e12 else f"{float(n):.3g}"


def duration_text(seconds: float) -> str:
    """``seconds`` in the largest fitting unit: "3.5 h", "12 min", "40 s"."""
    for unit, k in (("days", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if seconds >= k:
            return f"{seconds / k:.3g} {unit}"
    return f"{seconds:.3g} s"


def hit_fraction(vertices: np.ndarray, triangles: np.ndarray, margin: float) -> float:
    """The share of the spawn footprint that the seat covers seen from above.

    Parameters
    ----------
    vertices : (n, 3) array
        The seat's surface vertices [m].
    triangles : (m, 3) int array
        Its triangles, outward-oriented.
    margin : float
        The spawn footprint is the seat's xy bounding box grown by this [m]
        (``[storm] margin``).

    Returns
    -------
    float
        The projected area of the upward-facing triangles over the footprint's
        area, in [0, 1]: the fraction of vertically falling stones that hit.
    """
    X = np.asarray(vertices, dtype=np.float64)
    T = np.asarray(triangles, dtype=np.int64)
    e1, e2 = X[T[:, 1]] - X[T[:, 0]], X[T[:, 2]] - X[T[:, 0]]
    nz = 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])  # projected signed area of each triangle
    lo, hi = X[:, :2].min(axis=0) - margin, X[:, :2].max(axis=0) + margin
    box = float(np.prod(hi - lo))
    return float(min(1.0, nz[nz > 0].sum() / box)) if box > 0 else 1.0


@dataclass(frozen=True)
class StormEstimate:
    """What a storm will cost, before it runs (:meth:`hailstorm.runtime.storm.scene.Scene.estimate`).

    Attributes
    ----------
    steps : int
        Time steps (``duration / dt``; sub-steps come on top).
    stones : int
        Hailstones (the exact count, or the mean of the Poisson rate).
    frames : int
        Recorded frames.
    memory_bytes : int
        Memory the run holds beyond the bundle (stones, the per-step history,
        frames if kept in memory).
    disk_bytes : int or None
        Size of the written outputs (None: the surface size was not given).
    duration : float
        Simulated time [s].
    dt : float
        Time step [s].
    n_vertices : int or None
        Surface vertices (None: not known yet; the frames' time is then not counted).
    hit_fraction : float
        Share of the stones that hit the seat (:func:`hit_fraction`; 1 before the
        bundle is read).
    inertia : bool
        The pad's inertia is measured per impact after the storm.
    video : bool
        The frames are rendered into a video after the storm.
    startup : bool
        Count a warm start (:data:`STARTUP_SECONDS`: what the command line adds).
    from_rate : bool
        ``stones`` is the mean of a rate's Poisson count (announced as ``~N stones``: the storm
        draws its own number), not an exact count.

    Notes
    -----
    The estimated wall time (:attr:`seconds`) is the sum of

    * stepping: ``impacts * IMPACT_SECONDS * (1 + s / CROWD_CONTACTS)`` with
      ``impacts = stones * hit_fraction`` and ``s = impacts / duration * NEAR_TIME``
      the stones near the seat at once, plus ``steps * STEP_SECONDS`` and the
      stones' flight, ``stones * min(duration, STONE_LIFETIME) / dt *
      FLIGHT_SECONDS_PER_STONE_STEP``;
    * frames: ``frames * n_vertices * FRAME_SECONDS_PER_VERTEX``, and
      ``min(frames, VIDEO_FRAMES) * VIDEO_SECONDS_PER_FRAME`` with a video;
    * inertia: ``impacts * INERTIA_SECONDS_PER_IMPACT`` when it is measured;
    * with ``startup``, a warm start, :data:`STARTUP_SECONDS`.

    A first run's precompute and compile are not included (they are announced
    on their own, and do not grow with the storm).
    """

    steps: int
    stones: int
    frames: int
    memory_bytes: int
    disk_bytes: int | None = None
    duration: float = 0.0
    dt: float = 0.0
    n_vertices: int | None = None
    hit_fraction: float = UNKNOWN_HIT_FRACTION
    inertia: bool = False
    video: bool = False
    startup: bool = False
    from_rate: bool = False

    @property
    def impacts(self) -> float:
        """Expected impacts: ``stones * hit_fraction``."""
        return float(self.stones) * float(self.hit_fraction)

    @property
    def near_at_once(self) -> float:
        """Mean stones near the seat at once: impacts per simulated second times :data:`NEAR_TIME`."""
        return self.impacts / max(float(self.duration), NEAR_TIME) * NEAR_TIME

    @property
    def stepping_seconds(self) -> float:
        """Estimated wall time of the time stepping [s] (see the class notes)."""
        flight = float(self.stones) * min(float(self.duration), STONE_LIFETIME) / max(float(self.dt), 1e-300)
        return (self.impacts * IMPACT_SECONDS * (1.0 + self.near_at_once / CROWD_CONTACTS)
                + float(self.steps) * STEP_SECONDS + flight * FLIGHT_SECONDS_PER_STONE_STEP)

    @property
    def frame_seconds(self) -> float:
        """Estimated wall time of writing the frames [s] (0 when the surface size is not known)."""
        files = 0.0 if self.n_vertices is None else float(self.frames) * self.n_vertices * FRAME_SECONDS_PER_VERTEX
        return files + (float(min(self.frames, VIDEO_FRAMES)) * VIDEO_SECONDS_PER_FRAME if self.video else 0.0)

    @property
    def inertia_seconds(self) -> float:
        """Estimated wall time of the pad's inertia pass [s]."""
        return self.impacts * INERTIA_SECONDS_PER_IMPACT if self.inertia else 0.0

    @property
    def seconds(self) -> float:
        """Estimated wall time of the storm [s]: stepping, frames and inertia, and the start-up if
        counted (see the class notes)."""
        return (self.stepping_seconds + self.frame_seconds + self.inertia_seconds
                + (STARTUP_SECONDS if self.startup else 0.0))

    def describe(self) -> str:
        """One line: steps, stones, frames, memory (and disk), and the estimated time with its parts."""
        stones = ("~" if self.from_rate else "") + count_text(self.stones)
        text = (f"{count_text(self.steps)} steps, {stones} stones, {count_text(self.frames)} frames, "
                f"~{size_text(self.memory_bytes)} of memory")
        if self.disk_bytes is not None:
            text += f", ~{size_text(self.disk_bytes)} on disk"
        return text + f", about {duration_text(self.seconds)}{self._parts()}"

    def _parts(self) -> str:
        parts = [("start-up", STARTUP_SECONDS if self.startup else 0.0), ("stepping", self.stepping_seconds),
                 ("frames", self.frame_seconds), ("inertia", self.inertia_seconds)]
        shown = [f"{name} {duration_text(s)}" for name, s in parts if s > 0]
        return f" ({', '.join(shown)})" if len(shown) > 1 else ""

    def check(self, *, allow_large: bool = False) -> None:
        """Refuse a storm that exceeds the machine.

        Raises
        ------
        StormTooLarge
            More than :data:`MAX_STEPS` steps, more memory than
            :data:`MEMORY_FRACTION` of the available memory, or an estimated wall
            time above :data:`MAX_SECONDS`; not raised with ``allow_large`` (the
            CLI's ``--allow-large``).
        """
        if allow_large:
            return
        avail = available_memory()
        if avail is not None and self.memory_bytes > MEMORY_FRACTION * avail:
            raise StormTooLarge(f"the storm needs an estimated {size_text(self.memory_bytes)} of memory "
                                f"({self.describe()}); a storm may use at most {MEMORY_FRACTION:.0%} of the "
                                f"memory available ({size_text(avail)} available now, so at most "
                                f"{size_text(MEMORY_FRACTION * avail)}); lower the duration, the rate or the frame "
                                "rate, or pass --allow-large (allow_large=True)")
        if self.steps > MAX_STEPS:
            raise StormTooLarge(f"the storm has {count_text(self.steps)} steps ({self.describe()}), more than "
                                f"{MAX_STEPS:,} (hours of computing); raise dt or lower the duration, "
                                "or pass --allow-large (allow_large=True)")
        if self.seconds > MAX_SECONDS:
            crowd = (f", {self.near_at_once:.3g} stones near the seat at once" if self.near_at_once > 1 else "")
            raise StormTooLarge(f"the storm would take an estimated {duration_text(self.seconds)}{self._parts()} "
                                f"({count_text(self.impacts)} impacts expected of {count_text(self.stones)} stones"
                                f"{crowd}), more than {duration_text(MAX_SECONDS)}; lower the stones, the rate or "
                                "the duration, or pass --allow-large (allow_large=True)")

