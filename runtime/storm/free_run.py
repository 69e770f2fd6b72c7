"""The storm's steps without soft contacts, many per call into compiled code.

While no stone presses the seat (the seat unloaded, no contact set), a step is spawning, the
broad phase, flight, the narrow phase's free part and retirement:
:func:`hailstorm.runtime.compiled.free_steps.free_steps` runs such steps back to back, with the
same kernels in the same order as :meth:`hailstorm.runtime.storm.driver.Storm.step` (the
storm fingerprints are unchanged). :class:`FreeRun` holds its arguments that do not change
over a storm and hands it the ones that do; what it returns (the state of a step left half
done when a contact opens) is a :class:`FreeResult`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from hailstorm.runtime.compiled.free_steps import ACC_FIELDS, NEAR, OPENED, free_steps
from hailstorm.runtime.storm.hail import GRAVITY, stone_mass

if TYPE_CHECKING:  # annotations only
    from hailstorm.runtime.storm.collide import Collision
    from hailstorm.runtime.storm.integrators import ContactIntegrator
    from hailstorm.runtime.storm.recording import StormStats
    from hailstorm.runtime.storm.scene import Scene
    from hailstorm.runtime.storm.seat import SeatState
    from hailstorm.runtime.storm.stones import SpawnPlan, Stones

__all__ = ["STEPS_PER_CALL", "FreeResult", "FreeRun"]

#: steps per compiled call at most: a signal is acted on between calls (a free step of the
#: default storm costs ~30 us; a storm of many stones in flight, more)
STEPS_PER_CALL = 1000

#: the kernel's accumulators that are :class:`StormStats` fields (``fell_through`` is the storm's)
STATS = frozenset(ACC_FIELDS) - {"fell_through"}


@dataclass(frozen=True)
class FreeResult:
    """What one call of :meth:`FreeRun.run` did.

    Attributes
    ----------
    steps : int
        Steps completed (their force-history rows written).
    t : float
        The time at their end (the half-done step's start).
    opened : bool
        A contact opened in the next step's free phase: that step is half done.
    near_first : bool
        (``stop_near``) Stones are near the seat in the next step: it is left after its broad
        phase and the far stones' flight.
    dropped : bool
        (``held``) The steps run dropped the released contact set the caller held: it releases it.
    live, near : (k,) int ndarray
        ``opened`` or ``near_first``: the half-done step's live and near stones.
    h, t_left : float
        ``opened``: its sub-step after the free phase, and the time of the step left before it.
    n_sub : int
        ``opened``: its sub-steps before.
    retired : (r,) int ndarray
        The stones retired by the completed steps.
    fell_through : int
        Of those, the ones below the seat, inside its footprint, that never touched it.
    """

    steps: int
    t: float
    opened: bool
    near_first: bool
    dropped: bool
    live: np.ndarray
    near: np.ndarray
    h: float
    t_left: float
    n_sub: int
    retired: np.ndarray
    fell_through: int


class FreeRun:
    """The compiled run of a storm's steps without soft contacts.

    Parameters
    ----------
    scene : Scene
    collision : Collision
        The broad and narrow phase's arrays.
    integrator : ContactIntegrator
        The sub-step sizing (adaptive implicit and symplectic).
    k_tri : ndarray or None
        The triangles' point stiffness (where the integrator sizes sub-steps by it).
    plan : SpawnPlan
    stones : Stones
        Their density (:meth:`run` gives them room for the plan's stones).
    """

    def __init__(self, scene: Scene, collision: Collision, integrator: ContactIntegrator, k_tri: np.ndarray | None,
                 plan: SpawnPlan, stones: Stones) -> None:
        self.plan = plan
        self.dt = float(scene.time.dt)
        self.plan_mass = stone_mass(plan.rows[:, 7].copy(), stones.density) if len(plan.rows) else np.zeros(0)
        ix, c = collision.index, collision
        grid = ix.grid
        self._broad = (ix.bbox[0], ix.bbox[1], ix.sample_radius, grid.lo, grid.h, grid.dims, grid.start, grid.items,
                       grid.points)
        self._narrow = (c.surface, c.toi, c.TOI_TOL, c.hmin, ix.normals, ix.corner_normals, ix.sharp_edges,
                        ix.sharp_vertices, c.soft, c.fixed, c.rigid_weight)
        self._air = (GRAVITY, c.air.wind, c.air.drag_coef, c.restitution)
        self._margin = c.margin
        e = np.zeros(0)
        sizes = bool(integrator.sizes_substeps and k_tri is not None)
        self._sizing = (sizes, int(scene.time.max_substeps), k_tri if sizes else e, scene.time.approach_fraction,
                        scene.time.rest_speed, integrator.omega_dt, integrator.kind.explicit,
                        np.zeros(0, dtype=np.int64), e, scene.contact.sticky, np.zeros((0, 3)),
                        np.array([0.0, 0.0, -GRAVITY]))
        self._scratch_size = -1

    def _scratch(self, capacity: int) -> tuple[np.ndarray, ...]:
        """The kernel's scratch arrays for ``capacity`` stones (kept while it does not change)."""
        if capacity != self._scratch_size:
            self._scratch_arrays = (np.empty(capacity, np.int64), np.empty(capacity, np.int64),
                                    np.empty(capacity, np.int64), np.empty(capacity))
            self._scratch_size = capacity
        return self._scratch_arrays

    def run(self, t: float, n_max: int, i0: int, n_steps: int, next_frame: float, history: np.ndarray,
            stones: Stones, seat: SeatState, stats: StormStats, held: bool = False,
            stop_near: bool = False) -> FreeResult:
        """Run up to ``n_max`` steps (at most :data:`STEPS_PER_CALL`) from time ``t`` (step ``i0`` of
        ``n_steps``; the frame clock ``next_frame``, the force ``history``), in place on ``stones``
        and ``stats``.

        The caller has checked that no stone presses the seat (:attr:`SeatState.loaded` false,
        no contact set, or one whose contacts were all released, ``held``: the run drops it
        where the step would, :attr:`FreeResult.dropped`; with ``stop_near`` it stops instead
        at the first step with stones near the seat); the stones' new count and the plan's
        next row are written back here.
        """
        stones.reserve(len(self.plan.rows) - self.plan.next_row)  # room for the plan's stones still to come
        buffers = stones.buffers()
        live, near, gone, _ = scratch = self._scratch(buffers[0].shape[0])
        acc = np.array([float(getattr(stats, name)) if name in STATS else 0.0 for name in ACC_FIELDS])
        use_u, cols, forces = seat.kernel_load()
        hold = np.array([bool(held)])
        status, steps, t_end, j, n, n_live, n_near, n_gone, h, t_left, n_sub = free_steps(
            int(min(n_max, STEPS_PER_CALL)), float(t), self.dt, int(i0), int(n_steps), float(next_frame), history,
            self.plan.rows, self.plan_mass, self.plan.next_row, len(stones), scratch, buffers, seat.umax_step, self._broad,
            self._narrow, self._air, self._margin, self._sizing, (seat.umax, use_u, seat.D, cols, forces),
            bool(stop_near), hold, acc)
        for name, value in zip(ACC_FIELDS, acc.tolist()):
            if name in STATS:
                setattr(stats, name, type(getattr(stats, name))(value))
        self.plan.handed_out(j)
        stones.resize(n)
        if steps:
            seat.end_step()
        opened, near_first = status == OPENED, status == NEAR
        half = opened or near_first
        return FreeResult(steps=int(steps), t=float(t_end), opened=opened, near_first=near_first,
                          dropped=bool(held) and not bool(hold[0]),
                          live=live[:n_live].copy() if half else live[:0],
                          near=near[:n_near].copy() if half else near[:0], h=float(h), t_left=float(t_left),
                          n_sub=int(n_sub), retired=gone[:n_gone].copy(),
                          fell_through=int(acc[ACC_FIELDS.index("fell_through")]))

    def warm_up(self, stones: Stones, seat: SeatState, stats: StormStats) -> None:
        """Load (or compile) the kernel with the storm loop's argument types (no step run)."""
        self.run(0.0, 0, 0, 1, np.inf, np.zeros((1, 3)), stones, seat, stats)
