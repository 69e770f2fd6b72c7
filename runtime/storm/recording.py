"""What a storm records: frames, the contact-force history and the statistics.

* :class:`Frame` -- one recorded instant (surface displacement, stones);
* :class:`StormStats` -- the statistics as a typed record, updated by the storm's
  parts while it runs and completed by :func:`hailstorm.runtime.storm.run.run_storm`;
  it reads like the mapping it replaces (``stats["impacts"]``, ``dict(stats)``,
  the keys of ``hailstorm-storm.json`` and ``summary.json``);
* :class:`Recorder` -- frames at the scene's rate (kept and/or streamed) and the
  per-step force history;
* :class:`StormResult` -- what :func:`~hailstorm.runtime.storm.run.run_storm` returns.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Any, Callable, TYPE_CHECKING

import numpy as np

from hailstorm.runtime.storm.limits import VALIDITY_KEYS, summarise

if TYPE_CHECKING:  # annotations only
    from hailstorm.runtime.storm.scene import Scene
    from hailstorm.runtime.storm.limits import ImpactLimits

__all__ = ["Frame", "Recorder", "StormResult", "StormStats"]


@dataclass
class Frame:
    """One recorded instant.

    Attributes
    ----------
    t : float
        Time [s].
    displacement : (n, 3) float32 ndarray
        Surface displacement [m].
    positions : (k, 3) ndarray
        Centres of the live stones [m].
    radii : (k,) ndarray
    ids : (k,) int ndarray
        Stone ids (spawn order).
    contacts : int
        Open contacts.
    peak_displacement : (n, 3) float32 ndarray or None
        Per vertex, the largest displacement seen since the previous frame
        (see :meth:`hailstorm.runtime.storm.driver.Storm.frame`): an impact lasts about a
        millisecond, much less than a frame interval, so ``displacement`` alone
        rarely shows the dents. ``None`` when not recorded.
    forces : (k, 3) ndarray or None
        Per live stone (the rows of ``positions``), the force it applies to
        the seat at the frame's instant [N] (zero when not in soft contact);
        ``np.linalg.norm(forces, axis=1).sum()`` is the total contact force of
        :attr:`StormResult.history` at this instant. ``None`` when not recorded.
    """

    t: float
    displacement: np.ndarray
    positions: np.ndarray
    radii: np.ndarray
    ids: np.ndarray
    contacts: int
    peak_displacement: np.ndarray | None = None
    forces: np.ndarray | None = None


#: fields of :class:`StormStats` that are accumulators, not statistics (not among its keys)
_ACCUMULATORS = ("pen_contact_sum", "pen_contact_n", "validity")


@dataclass(eq=False)
class StormStats(Mapping):
    """The statistics of a storm (every key and its unit: the documentation, "Outputs").

    The parts of the storm update the counters while it runs; :func:`run_storm`
    fills the run's figures (times, scene values) at the end. As a mapping its
    keys are the fields in this order, less the accumulators of the mean
    penetration in contact (``pen_contact_sum``, ``pen_contact_n``), plus
    ``mean_penetration_contact_m``, and less the impacts' validity records
    (``validity``, :class:`~hailstorm.runtime.storm.limits.ImpactLimits`), plus the
    validity keys computed from them when read (after ``max_patch_radius_m``;
    :data:`~hailstorm.runtime.storm.limits.VALIDITY_KEYS`: impacts beyond each
    limit, the worst values, the limits; docs/validity.md).
    """

    hailstones: int = 0
    impacts: int = 0
    stones_hit: int = 0
    max_contact_force: float = 0.0
    max_indentation_m: float = 0.0
    max_simultaneous_contacts: int = 0
    max_penetration_m: float = 0.0
    steps: int = 0
    substeps: int = 0
    capacitance_rebuilds: int = 0
    wall_contacts: int = 0
    #: collisions between stones (``[hail] collisions``) and the largest force of one [N]
    stone_collisions: int = 0
    max_stone_collision_force_N: float = 0.0
    retired: int = 0
    max_penetration_contact_m: float = 0.0
    max_penetration_free_m: float = 0.0
    max_penetration_contact_rel: float = 0.0
    patch: str = "hertz"
    patch_weights_computed: int = 0
    patch_weights_reused: int = 0
    patch_resizes: int = 0
    max_patch_radius_m: float = 0.0
    #: sum of the non-negative overlaps of stones in contact [m] and their count (steps x stones)
    pen_contact_sum: float = 0.0
    pen_contact_n: int = 0
    #: the impacts' validity measures (set by the storm's soft contacts); the validity keys read them
    validity: ImpactLimits | None = None
    # the run (filled by run_storm)
    sim_time_s: float = 0.0
    wall_time_s: float = 0.0
    setup_time_s: float = 0.0
    compile_time_s: float = 0.0
    backend: str = "numba"
    real_time_factor: float = 0.0
    seed: int = 0
    dt: float = 0.0
    integrator: str = ""
    mode: str = ""
    restitution: float = 0.0
    n_vertices: int = 0
    n_triangles: int = 0
    resting_at_end: int = 0
    frames: int = 0
    output_time_s: float = 0.0
    #: the wall time of the impacts' inertia factors [s] (after the storm, not in ``wall_time_s``)
    inertia_time_s: float = 0.0

    @property
    def mean_penetration_contact_m(self) -> float:
        """Mean overlap of a stone in contact with the deformed surface [m] (0: none)."""
        return self.pen_contact_sum / self.pen_contact_n if self.pen_contact_n else 0.0

    def validity_summary(self) -> dict[str, float | int]:
        """The validity keys and their values (:func:`hailstorm.runtime.storm.limits.summarise`)."""
        if self.validity is None:
            return summarise(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0))
        return self.validity.summary()

    def _keys(self) -> list[str]:
        names = [f.name for f in dataclasses.fields(self) if f.name not in _ACCUMULATORS]
        i = names.index("sim_time_s")
        names = names[:i] + ["mean_penetration_contact_m"] + names[i:]
        j = names.index("max_patch_radius_m") + 1
        return names[:j] + list(VALIDITY_KEYS) + names[j:]

    def __getitem__(self, key: str) -> Any:
        if key in VALIDITY_KEYS:
            return self.validity_summary()[key]
        if key not in self._keys():
            raise KeyError(key)
        return getattr(self, key)

    def items(self) -> Any:
        """(key, value) pairs (the validity keys computed once for the lot)."""
        validity = self.validity_summary()
        return [(k, validity[k] if k in validity else getattr(self, k)) for k in self._keys()]

    def __iter__(self) -> Iterator[str]:
        return iter(self._keys())

    def __len__(self) -> int:
        return len(self._keys())

    def __repr__(self) -> str:
        return f"StormStats({', '.join(f'{k}={v!r}' for k, v in self.items())})"


@dataclass
class StormResult:
    """What :func:`run_storm` returns: the scene, the frames and the statistics.

    ``frames`` holds the recorded frames when they were kept (``run_storm``'s
    ``keep_frames``), else it is empty: they were streamed to ``on_frame``.
    ``stats["frames"]`` counts them either way.
    """

    scene: Scene
    frames: list[Frame]
    stats: StormStats
    #: contact-force history: (time, total normal force on the seat [N], open contacts) per step
    history: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


class Recorder:
    """Frames at ``fps`` (plus the first and last instants) and the per-step force history.

    Parameters
    ----------
    n_steps : int
    fps : float
    on_frame : callable, optional
        Called with each frame as it is recorded (the time it takes is
        ``sink_time``, not the storm's).
    keep : bool
        Keep the frames in :attr:`frames`.
    """

    def __init__(self, n_steps: int, fps: float, on_frame: Callable[[Frame], None] | None, keep: bool) -> None:
        self.frame_dt = 1.0 / fps
        self.next_frame = self.frame_dt
        self.on_frame = on_frame
        self.keep = keep
        self.frames: list[Frame] = []
        self.n_frames = 0
        self.sink_time = 0.0
        self.n_steps = n_steps
        self.history = np.zeros((n_steps, 3))

    def record(self, frame: Frame) -> None:
        self.n_frames += 1
        if self.on_frame is not None:
            t0 = time.perf_counter()
            self.on_frame(frame)
            self.sink_time += time.perf_counter() - t0
        if self.keep:
            self.frames.append(frame)

    def frame_due(self, t: float, i: int) -> bool:
        """After step ``i`` (time ``t``): is a frame due? (Advances the frame clock.)"""
        if t >= self.next_frame - 1e-12 or i == self.n_steps - 1:
            self.next_frame += self.frame_dt
            return True
        return False

    def forces(self, i: int, t: float, f: np.ndarray) -> None:
        """Step ``i``'s contact forces on the seat ``f`` (s, 3)."""
        self.history[i] = (t, float(np.linalg.norm(f, axis=1).sum()) if f.size else 0.0, f.shape[0])
