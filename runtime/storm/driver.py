"""The hail storm driver: stones falling on the seat, contacts through the capacitance
(:class:`Storm`; a storm from start to end: :func:`hailstorm.runtime.storm.run.run_storm`).

Algorithm of one step (``dt`` = ``scene.time.dt``)
-------------------------------------------------
1. Spawn the stones due in this step (each placed back along its path by its spawn
   time's lead over the step's start).
2. Broad phase by *conservative advancement*: every flying stone carries a
   lower bound of its distance to the deformed seat (``budget``: nearest
   k-d tree sample minus the sample radius, the stone radius and 1.5x the
   peak seat displacement). It is spent by what the stone can travel; only
   when it runs out is it re-measured (one vectorised k-d query for all such
   stones). Stones with budget left fly freely (vectorised ballistic + drag
   update) and are never collision-tested.
3. Near stones (budget exhausted, or in contact): one narrow-phase query per
   step on the *locally* deformed surface (k-d tree on triangle samples;
   the displacement is evaluated only at the candidate triangles' vertices,
   ``u = D[rows, cols(V)] B f``); it also records the penetration. Then
   sub-steps:

   a. closest points (reused from the step's query, or predicted from the
      previous sub-step for stones that cannot touch before the step ends);
   b. time of impact (``adaptive = true``): the sub-step ends when the first
      approaching stone reaches the tangent plane at its closest point
      (constant acceleration); the contact opens when the gap is below 1% of
      the radius and the stone is put on the surface;
      an open contact keeps its ``(t, beta)`` while the stone stays over
      the same triangle;
   c. contacts on triangles that cannot deform (all clamped, or without
      compliance columns) are a hard wall (projection + restitution);
   d. the other contacts share one capacitance (``hailstorm.runtime.contact``), rebuilt
      only when the set of (stone, triangle[, patch radius]) changes; the stones are
      advanced by the scene's integrator with unilateral release.
      ``integrator = "exact"`` solves the damped linear contact dynamics in
      closed form over the whole sub-step (maximum compression and release
      located inside it), so one sub-step per step suffices whatever
      ``omega dt``; ``"implicit"``/``"symplectic"`` sub-step to ``omega_dt``
      when adaptive;
   e. the seat's state is the vertex-force vector ``B f``; the full-surface
      displacement ``u = D[:, V] B f`` is formed only for frames (:attr:`Storm.u`).
4. Retire stones that left the seat's region; record a frame if one is due.

The parts (each with explicit inputs; this module composes them)
-----------------------------------------------------------------
* :class:`~hailstorm.runtime.storm.stones.Stones`, :class:`~hailstorm.runtime.storm.stones.SpawnPlan`
  -- the stones' arrays, spawning, retirement;
* :class:`~hailstorm.runtime.storm.seat.SeatState` -- vertex forces, displacement
  queries, peaks;
* :class:`~hailstorm.runtime.storm.collide.Collision` -- broad phase, free flight, the
  free part of a sub-step (narrow phase), penetration, retirement rule;
* :class:`~hailstorm.runtime.storm.soft_contacts.SoftContacts` -- the contact set
  (:class:`~hailstorm.runtime.storm.contact_set.ContactSets`), patch sizing
  (:class:`~hailstorm.runtime.storm.patches.Patches`) and the contact step
  (:class:`~hailstorm.runtime.storm.integrators.ContactIntegrator`);
* :mod:`~hailstorm.runtime.storm.recording` -- frames, the force history, the
  statistics (:class:`~hailstorm.runtime.storm.recording.StormStats`).

Patch contacts (``patch = "hertz"``, the default)
-------------------------------------------------
Each soft contact spreads its force over a disc of radius ``a`` around the
contact point, with the Hertz pressure profile (consistent P1 nodal loads,
:func:`hailstorm.runtime.contact.weights.patch_weights`); the contact prescribes the
pressure-weighted mean normal displacement of the surface under the disc
(measured from the tangent plane at the contact point), which lies the
sphere's offset ``o`` (:meth:`~hailstorm.runtime.storm.contact_set.ContactSets.offsets`:
the impact patch's, :func:`hailstorm.runtime.contact.weights.impact_offset`, ``a^2 / (5 R)``
on a resolved disc for ``a << R``) short of the stone's lowest point: an affine law
``F = k (delta - o)`` like :func:`hailstorm.runtime.contact.hertz.press_spheres`', through the
sphere's peak with the sphere's work (on a half-space). ``patch = "none"`` gives the point
contacts of the course hint (barycentric weights on one triangle).

* Engagement: when a stone first touches the seat
  (:meth:`~hailstorm.runtime.storm.soft_contacts.SoftContacts.engage`) its
  impact's patch is sized and its offset fixed; the contact closes again and
  the stone flies through the dead zone to its contact surface, the sphere of
  radius ``R - o`` (the narrow phase's), where the contact opens with no force.
  The stone keeps its offset, and the patch its radius, until its sphere is
  clear of the surface again (the narrow phase,
  :func:`hailstorm.runtime.compiled.free_phase`); a re-sized patch
  carries the offset along and the stone with it, keeping the spring's
  compression.

* Radius: ``a = impact_radius(F_peak, R, E, nu)`` (Hertz's radius for ``a << R``) clipped to
  ``[patch_min_radius, R]``, with ``F_peak`` the peak force of the contact's
  current oscillation about its static equilibrium,
  ``F_eq + sqrt((F - F_eq)^2 + k m v_n^2)`` (``F`` the previous sub-step's
  force, ``k`` the contact's stiffness). For a new contact (``F = 0``) this is
  the impact's expected peak force, with the stiffness of the patch itself
  (one fixed-point iteration from the triangle's point stiffness; with the
  near field, the fixed point of the radius with the body's part of the
  compliance taken at that first radius,
  :meth:`~hailstorm.runtime.storm.patches.Patches.first_touch`). The
  estimate is nearly constant during an impact, so the disc is sized for the
  deepest dent and the contact keeps one set of weights for the whole impact.
* Rebuilds: a contact is re-weighted (and the capacitance rebuilt) only when
  its target radius grows by more than ``patch_tolerance`` (20%), or, *once the
  stone rests* (oscillation amplitude below ``rest_speed``), is off by more than
  ``REST_TOLERANCE`` (1 %) either way: re-weighting during a rebound would change the stiffness
  that the damping was tuned for (the restitution), while the damping itself
  halves the amplitude within one impact.
* Caching: a contact keeps ``(triangle, beta)`` while its stone stays over
  the triangle, so its weights are cached per stone (:meth:`hailstorm.runtime.storm.patches.Patches.weights`) and
  only recomputed when the contact moves to another triangle or is resized;
  a capacitance rebuild (set change) reuses the cached weights of every other
  contact.

Adaptive sub-steps for ``"implicit"``/``"symplectic"`` (``adaptive = true``):
the sub-step is also limited so that a stone approaching the surface travels
at most ``approach_fraction * r`` per sub-step and so that ``omega dt <=
omega_dt`` for contacts that are still moving (``|v_n| > rest_speed``;
``omega = sqrt(K_kk / m)``). Resting contacts do not limit the step under the
implicit integrator (backward Euler is exact at equilibrium); under the
symplectic one every contact does (stability). The exact integrator treats a
resting contact's dashpot as acting both ways (no switching events).

Penetration: a flying stone never enters the deformed surface by more than
the contact-opening gap (1% of its radius) when ``adaptive = true``
(``max_penetration_free_m``; measured with its contact surface, whose gap a
stone in a patch's dead zone closes to within 1 % of its offset: a dent
rising under it within a sub-step can overlap it by a little more, up to
0.05 mm measured in the default storm at dt 0.5 ms and ``bench_storm.py``'s
400-stone storm). A stone *in contact* overlaps the piecewise-linear
dent around its load (``max_penetration_contact_m``, also relative to the
stone's radius and as a mean over contact steps): with point contacts the
contact point follows the stone exactly, but the dent is a one-vertex spike
whose triangles tilt into the sphere's cap; a patch contact spreads the load
over the disc and the dent follows the sphere much more closely. This is a
property of the contact model (see DESIGN: vertex pressure masks), not of the
time integration.

Facets: the seat's surface is a triangle mesh, read as the facets of a smooth
surface but at its sharp edges (more than ``CREASE_ANGLE``, 30 degrees, between
two triangles' normals: :func:`hailstorm.runtime.contact.weights.corner_normals`,
:func:`~hailstorm.runtime.storm.collide.sharp_features`). A contact's normal
(``Stones.cnormal``, :func:`hailstorm.runtime.compiled.narrow.contact_normal`)
is the smooth surface's at its contact point, the normals at its triangle's
corners interpolated, so that it turns continuously from one triangle to the
next and two contacts at one point share it; a stone over a sharp edge or
corner touches it as one: its normal is the direction from the edge to the
centre, turning from one side's normal to the other's. Measured before (the
triangle's normal): the side of an edge a stone landed on was the time of
impact's choice, and a 1 s, 2 000-stone storm on the default seat reported peak
forces of 261.6 and 258.1 N at dt 0.5 and 0.1 ms, single impacts up to 40 %
apart. The contact's spring measures the distance of the stone's centre from
the plane through its contact point at right angles to its normal, and a
facet's plane is not the seat's surface: near an edge the planes disagree, past
a convex edge whose normals differ by ``theta`` the neighbour's is nearer by
``d (1 - cos theta)`` (``d`` the centre's distance). A spring that jumped shorter
by that much during an impact would be energy from nowhere (measured before this
rule: a 5 mm stone dropped on a 0.3 rad ridge of the plate bounced with 55 %
more force and 42 % more speed than one dropped beside it; in a 1 s, 2 000-stone
storm on the default seat at dt 0.5 ms, open contacts moved triangle 342 times
in 1 047 impacts, 77 times by more than 0.2 mm of compression and up to 1.7
mm). So (:func:`hailstorm.runtime.compiled.narrow.free_phase`): a contact opens
with the stone put out along its normal by the overlap and its anchor out by the
normal's tilt from the direction to the closest point (``Stones.shift``), the
spring at its rest length; an open contact keeps its ``(t, beta)`` and normal
while the closest point of the undeformed surface lies on ``t`` (inside or on its
boundary: through a convex edge's wedge the nearer plane stays), and moves to
the closest point once it lies on another triangle, its anchor moved out if the
new plane's distance would be shorter, so that the spring never jumps shorter;
the shift lasts until the contact next opens. ``tests/runtime/storm/test_facets.py``
holds landings across a smooth and a sharp ridge to a rebound that turns
continuously with the landing point, at any dt.

BLAS runs single-threaded inside :func:`run_storm` (``threadpoolctl``): the
dense solves are tiny and threaded BLAS on a shared machine only adds latency.

Compiled kernels
----------------
A step's arithmetic is small; as numpy calls its cost would be the per-call
overhead of a few hundred calls on arrays of a handful of stones. Each phase
runs once, in compiled kernels (:mod:`hailstorm.runtime.compiled`, numba); the steps
without soft contacts run many per call (:meth:`Storm.run_free`), the others phase by
phase from this module. The tests hold the kernels to plain statements of the same
rules (``tests/reference/``) and to independent oracles (brute-force closest points,
analytic bounces). ``NUMBA_DISABLE_JIT=1`` runs them as Python, for debugging.
"""

from __future__ import annotations

import logging
from typing import Callable

import numpy as np

from hailstorm.runtime.storm.collide import Collision, SurfaceIndex
from hailstorm.runtime.compiled import closest_points
from hailstorm.runtime.bundle.compliance import ElasticSource
from hailstorm.runtime.storm.contact_set import ContactSet, ContactSets
from hailstorm.runtime.storm.hail import GRAVITY, Air
from hailstorm.runtime.storm.free_run import FreeResult, FreeRun
from hailstorm.runtime.storm.integrators import ContactIntegrator
from hailstorm.runtime.storm.patches import Patches
from hailstorm.runtime.storm.recording import Frame, StormResult, StormStats
from hailstorm.runtime.storm.scene import Scene, SceneError
from hailstorm.runtime.storm.seat import SeatState
from hailstorm.runtime.storm.soft_contacts import SoftContacts
from hailstorm.runtime.storm.stone_collisions import StoneCollisions
from hailstorm.runtime.storm.stones import SpawnPlan, StoneError, Stones, check_stones
from hailstorm.runtime.storm.warm_helper import helper_spec
from hailstorm.runtime.storm.warmup import WarmReport, WarmTask, measured_seconds, warm_up

__all__ = ["Frame", "Scene", "SceneError", "Storm", "StormResult", "StormStats"]

_log = logging.getLogger(__name__)


class Storm:
    """A running storm (stateful): the parts composed; :func:`run_storm` drives one from start to end.

    Parameters
    ----------
    gf : ElasticSource
        The bundle (:func:`hailstorm.runtime.bundle.read.load`).
    scene : Scene
    spawn : bool
        Spawn the scene's random stones (``False``: only stones added with
        :meth:`add_stones`, e.g. for a single drop).
    warm : bool
        Load (or, the first time, compile) the kernels now (:meth:`warm_up`);
        ``False``: later, e.g. on first use.

    Attributes
    ----------
    stones : Stones
    seat : SeatState
    collision : Collision
    contacts : SoftContacts
    stats : StormStats
    warm_report : WarmReport or None
        What the kernels' warm-up did (None with ``warm=False``).
    t : float
        Simulated time [s].
    """

    def __init__(self, gf: ElasticSource, scene: Scene, *, spawn: bool = True, warm: bool = True) -> None:
        self.gf = gf
        self.scene = scene
        hail, contact = scene.hail, scene.contact
        air = Air.of(scene.storm.wind, hail.drag, hail.cd, hail.rho_air, hail.density)
        self.g = np.array([0.0, 0.0, -GRAVITY])
        self.stones = Stones(hail.density)
        self.seat = SeatState(gf)
        self.collision = Collision(gf, scene, air)
        normals = self.collision.index.normals
        self.patches = Patches(gf, contact, scene.time, self.seat, normals, self.collision.soft, air)
        sets = ContactSets(gf, contact, normals, self.patches)
        self.integrator = ContactIntegrator(scene.time, contact)
        self.contacts = SoftContacts(contact, scene.time, sets, self.patches, self.integrator, self.seat, air,
                                     scene.validity.pad_density, scene.validity.inertia)
        self.stats = StormStats(patch=contact.patch)
        #: collisions between stones (None: off, ``[hail] collisions``)
        self.stone_collisions = StoneCollisions(contact.restitution) if hail.collisions else None
        self.t = 0.0
        #: stones retired below the seat inside its footprint without ever touching it
        self.fell_through = 0
        self.plan = SpawnPlan(scene.storm, hail, self.collision.lo, self.collision.hi,
                              np.random.default_rng(scene.storm.seed)) if spawn else SpawnPlan.empty()
        #: the compiled run of the steps without soft contacts (:meth:`run_free`; None: every step
        #: through :meth:`step`, as with stones that collide with each other)
        self.free: FreeRun | None = None
        self._pending: FreeResult | None = None
        if self.stone_collisions is None:
            self.free = FreeRun(scene, self.collision, self.integrator, self._k_tri(), self.plan, self.stones)
        self.warm_report: WarmReport | None = self.warm_up() if warm else None

    def step(self) -> None:
        """Advance the storm by one step ``dt`` (or finish the step :meth:`run_free` left half done)."""
        pending, self._pending = self._pending, None
        if pending is not None:
            self._finish_free(pending)
            return
        live, pos0, near = self._begin_step()
        if near.size:
            self._substeps(near, self.scene.time.dt, 0)
        elif self.seat.loaded:
            self.contacts.release()
        self._end_step(live, pos0)

    def _begin_step(self) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
        """A step's spawning, broad phase, far stones' flight and penetration statistics;
        returns the live stones, their positions at the step's start (for the stone pairs,
        else None) and the near stones."""
        dt, st, stones, seat = self.scene.time.dt, self.stats, self.stones, self.seat
        due = self.plan.due(self.t + dt)
        if due is not None:  # the plan's stones start above the seat: Stones.add's check is the one they need
            # each at its own spawn time: at the step's start it is still that far back along its
            # (steady, terminal) path, so that where and when it lands does not depend on dt
            early = (due[:, 0] - self.t)[:, None]
            st.hailstones += stones.add(due[:, 1:4] - early * due[:, 4:7], due[:, 4:7], due[:, 7]).size
        live = stones.live()
        pos0 = stones.pos.copy() if self.stone_collisions is not None else None  # (the step's paths start here)
        near, far = self.collision.near_set(stones, live, dt, seat.umax_step) if live.size else (live, live)
        if far.size:
            self.collision.fly(stones, far, dt)
            stones.gap[far] = np.inf
            stones.offset[far] = 0.0  # (far from the seat: any engagement is over)
        if near.size:
            self.collision.penetration(stones, near, dt, seat, st)
        return live, pos0, near

    def _substeps(self, near: np.ndarray, t_left: float, n_sub: int) -> None:
        """The near stones' sub-steps over the ``t_left`` left of the step (``n_sub`` taken)."""
        dt = self.scene.time.dt
        while t_left > 1e-12 * dt:
            h = self.integrator.substep_size(self.stones, near, t_left, self.contacts.current, self._k_tri(), self.g)
            if n_sub >= 4 * self.scene.time.max_substeps:
                h = t_left  # safety net: never stall
            t_left -= self._substep(near, h, self.t + (dt - t_left))
            n_sub += 1

    def _end_step(self, live: np.ndarray, pos0: np.ndarray | None) -> None:
        """A step's stone pairs, retirement and clock."""
        st, stones = self.stats, self.stones
        pairs = self.stone_collisions
        if pairs is not None and pos0 is not None:
            pairs.resolve(stones, live, pos0, self.scene.time.dt, st)
        gone = self.collision.retired(stones, live) if live.size else live
        if gone.size:
            self.fell_through += self.collision.fell_through(stones, gone)
            stones.retire(gone)
            self.patches.forget(gone.tolist())
            st.retired += int(gone.size)
        self.seat.end_step()
        self.t += self.scene.time.dt
        st.steps += 1

    def run_free(self, n_max: int, i0: int, n_steps: int, next_frame: float, history: np.ndarray) -> tuple[int, bool]:
        """Run up to ``n_max`` steps in compiled code while no stone presses the seat
        (:class:`~hailstorm.runtime.storm.free_run.FreeRun`): the same steps as :meth:`step`.

        ``i0`` is the next step's index of ``n_steps``; ``next_frame`` the frame clock (the run
        stops after a step at whose end a frame is due) and ``history`` the force history
        (:class:`~hailstorm.runtime.storm.recording.Recorder`), whose rows of the steps run
        here are written. Returns the steps completed, and whether the next one is left half
        done for :meth:`step` to finish (:class:`~hailstorm.runtime.storm.free_run.FreeResult`).
        ``(0, False)``: nothing done (a stone presses the seat, stones collide with each
        other, or a step is half done: :meth:`step`).
        """
        if self.free is None or self._pending is not None or self.seat.loaded:
            return 0, False
        held = self.contacts.current is not None  # (a released set: dropped where the step would)
        res = self.free.run(self.t, n_max, i0, n_steps, next_frame, history, self.stones, self.seat, self.stats,
                            held=held, stop_near=held and self.integrator.sizes_substeps)
        if res.dropped:
            self.contacts.release()
        self.t = res.t
        self.fell_through += res.fell_through
        if res.retired.size:
            self.patches.forget(res.retired.tolist())
        half = res.opened or res.near_first
        if half:
            self._pending = res
        return res.steps, half

    def _finish_free(self, res: FreeResult) -> None:
        """The step :meth:`run_free` left half done, finished as :meth:`step` would (from its
        contact step, or from its penetration statistics)."""
        dt = self.scene.time.dt
        if res.near_first:
            self.collision.penetration(self.stones, res.near, dt, self.seat, self.stats)
            self._substeps(res.near, dt, 0)
            self._end_step(res.live, None)
            return
        was_open = np.zeros(res.near.size, dtype=bool)  # (no contact was open in a compiled step)
        t_left = res.t_left - self._after_free_phase(res.near, res.h, was_open, self.t + (dt - res.t_left))
        self._substeps(res.near, t_left, res.n_sub + 1)
        self._end_step(res.live, None)

    def passed_through_warning(self) -> str | None:
        """A sentence when stones passed through the seat's footprint and none touched
        it (0 impacts that are no physics: a step or a terminal speed too large for the
        seat's thickness), else None."""
        if self.fell_through == 0 or self.stones.hit.any():
            return None
        sc = self.scene
        return (f"{self.fell_through:,} stones passed through the seat's footprint and none touched the seat "
                f"(0 impacts): they crossed it within one step; lower dt ([time] dt = {sc.time.dt:g} s) or check "
                f"the drag ([hail] cd = {sc.hail.cd:g}: a small cd gives a large terminal speed)")

    def _k_tri(self) -> np.ndarray | None:
        """The triangles' point stiffness when the integrator sizes sub-steps by it (computed once)."""
        return self.patches.k_tri if self.integrator.sizes_substeps else None

    def _substep(self, near: np.ndarray, h: float, t0: float = 0.0) -> float:
        """Advance the near stones by at most ``h``; returns the time actually taken
        (shorter when a stone is about to touch the seat: time of impact): the free
        phase (closest points, time of impact, contacts that open, hard walls), then the
        soft contacts through their capacitance and free flight of the others."""
        was_open = self.stones.ctri[near] >= 0
        h = self.collision.free_phase(self.stones, near, h, self.seat, self.stats)
        return self._after_free_phase(near, h, was_open, t0)

    def _after_free_phase(self, near: np.ndarray, h: float, was_open: np.ndarray, t0: float) -> float:
        """A sub-step's contacts after its free phase (which took ``h``; ``was_open``: the near
        stones' contacts open before it): engagement, the soft contacts' step, flight."""
        stones = self.stones
        in_contact = stones.ctri[near] >= 0
        opened = in_contact & ~was_open
        if self.patches.enabled and opened.any():
            h = self.contacts.engage(stones, near[opened], h, self.stats)
            in_contact = stones.ctri[near] >= 0
        soft = near[in_contact]
        free = near[~in_contact] if soft.size else near
        if soft.size:
            self.contacts.advance(stones, near, soft, was_open, h, self.stats, t0)
        else:
            self.contacts.release()
        if free.size:
            self.collision.fly(stones, free, h)
        self.stats.substeps += 1
        return h

    def warm_tasks(self) -> list[WarmTask]:
        """The kernels the loop calls, in tasks that load (or compile) them with the loop's
        argument types; only those of this scene (integrator, patch model). Each task's
        ``seconds`` is its cold compile CPU in a fresh process, measured
        (:func:`hailstorm.runtime.storm.warmup.measured_seconds`; more wall time on a loaded machine)."""
        sc, stones, col = self.scene.time, self.stones, self.collision
        dt = float(sc.dt)
        soft = np.flatnonzero(col.soft)
        t = int(soft[0]) if soft.size else -1
        third = np.full((1, 3), 1.0 / 3.0)
        # each task's seconds: measured (this machine's last compile, else the packaged measurement of
        # tests/benchmarks/compile_time.py --write); no two tasks share a kernel (the contact set's are
        # the contact API's blocks of D, the integrators' SPD inverse is theirs alone)
        def task(name: str, run: Callable[[], None]) -> WarmTask:
            return WarmTask(name, measured_seconds(name), run)

        tasks = [
            task("the free-flight and broad-phase kernels", lambda: col.warm_up_flight(stones, dt)),
            task("the narrow-phase kernels", lambda: col.warm_up_narrow(stones, self.seat, dt)),
            task("the contact-step kernels", lambda: self.contacts.warm_up(stones)),
            task(f"the {sc.integrator} integrator's kernels",
                 lambda: self.integrator.warm_up(stones, self._k_tri(), self.g, dt)),
        ]
        free = self.free
        if free is not None:
            tasks.append(task("the free-steps kernel", lambda: free.warm_up(self.stones, self.seat, self.stats)))
        if self.stone_collisions is not None:
            pairs = self.stone_collisions
            tasks.append(task("the stone-collision kernels", lambda: pairs.warm_up(stones)))
        if t >= 0:
            tasks.insert(2, task("the contact-set kernels", lambda: self.contacts.sets.warm_up(t)))
            tasks.insert(3, task("the patch kernels" if self.patches.enabled else "the patch-compliance kernel",
                                 lambda: self.patches.warm_up(t, third, col.index.normals[[t]], stones)))
        return tasks

    def warm_up(self, names: list[str] | None = None) -> WarmReport:
        """Load (or compile, the first time after an install) every kernel the loop calls,
        with the loop's argument types, so that the stepping runs compiled code from its
        first step (loading takes ~0.3 s; compiling takes a while, once: numba caches the
        machine code on disk). A task that compiles says so in one INFO line; when one
        does, a helper process compiles part of the tasks in parallel
        (:func:`hailstorm.runtime.storm.warmup.warm_up`; the helper rebuilds this storm from the
        bundle's directory, :func:`hailstorm.runtime.storm.run.warm_up_worker`).

        Parameters
        ----------
        names : list of str, optional
            Only these tasks (:meth:`warm_tasks` names), all here (a helper's part).
        """
        tasks = self.warm_tasks()
        if names is not None:
            tasks = [task for task in tasks if task.name in names]
        helper = None if names is not None else helper_spec(self.gf, self.scene)
        report = warm_up(tasks, helper) if helper is not None else warm_up(tasks, None, workers=1)
        if report.compiled:
            _log.info("storm kernels compiled in %.1f s (%s); later runs load them", report.wall,
                      f"{len(report.helpers) + 1} processes" if report.helpers else "1 process")
        _log.debug("storm kernels ready in %.2f s (%s)", report.wall,
                   ", ".join(f"{k}: {v:.2f} s" for k, v in report.times.items()))
        return report

    # -- the public face (stones, seat, contacts) -----------------------------------
    def add_stones(self, pos: np.ndarray, vel: np.ndarray, radius: np.ndarray) -> np.ndarray:
        """Add stones now; returns their ids.

        Parameters
        ----------
        pos : (3,) or (k, 3) array_like
            Centres [m].
        vel : (3,) or (k, 3) array_like
            Velocities [m/s].
        radius : float or (k,) array_like
            Radii [m].

        Raises
        ------
        hailstorm.runtime.storm.stones.StoneError
            Bad shapes or values (:func:`~hailstorm.runtime.storm.stones.check_stones`),
            a stone whose centre lies inside the seat (below its surface), or one whose
            body overlaps it by more than ``Collision.TOI_TOL`` of its radius.
        """
        pos, vel, radius = check_stones(pos, vel, radius)  # normalised for the seat test (Stones.add checks again)
        self._check_outside(pos, radius)
        ids = self.stones.add(pos, vel, radius)
        self.stats.hailstones += ids.size
        return ids

    def _check_outside(self, pos: np.ndarray, radius: np.ndarray) -> None:
        """Refuse stones whose centre is inside the (undeformed) seat (the closest surface
        point's triangle normal points away from the centre), or whose body overlaps it by
        more than the contact's opening gap (``Collision.TOI_TOL`` radii). Only stones
        within a radius of the seat's footprint and not a radius above its top are looked
        at (the spawn plan's stones start above it and do not come through here)."""
        ix = self.collision.index
        lo, hi = ix.bbox
        r = np.broadcast_to(radius, (pos.shape[0],))
        footprint = ((pos[:, :2] >= lo[:2] - r[:, None]) & (pos[:, :2] <= hi[:2] + r[:, None])).all(axis=1)
        inbox = np.flatnonzero(footprint & (pos[:, 2] - r <= hi[2]))
        if inbox.size == 0:
            return
        reach = 2.0 * (float(np.linalg.norm(hi - lo)) + np.abs(pos[inbox, 2] - lo[2])) + 1e-9
        tri, _, point, _ = closest_points(ix.grid, ix.sample_radius, ix.vertices, ix.triangles, pos[inbox], reach)
        found = tri >= 0
        side = np.full(inbox.size, np.inf)
        side[found] = np.einsum("ij,ij->i", pos[inbox][found] - point[found], ix.normals[tri[found]])
        scale = float(np.linalg.norm(hi - lo))
        inside = side < -1e-12 * scale
        if inside.any():
            i = int(np.flatnonzero(inside)[0])
            raise StoneError(f"stone {int(inbox[i])} at {pos[inbox[i]].tolist()} starts inside the seat "
                             f"({-side[i]:.3g} m below its surface); place stones above the surface")
        gap = np.full(inbox.size, np.inf)
        gap[found] = np.linalg.norm(pos[inbox][found] - point[found], axis=1) - r[inbox][found]
        over = gap < -self.collision.TOI_TOL * r[inbox]
        if over.any():
            i = int(np.flatnonzero(over)[0])
            raise StoneError(f"stone {int(inbox[i])} of radius {float(r[inbox[i]]):.3g} m at {pos[inbox[i]].tolist()} "
                             f"overlaps the seat by {-gap[i]:.3g} m; place stones at least their radius above "
                             "the surface")

    def frame(self) -> Frame:
        """The current state as a :class:`Frame`.

        Its ``peak_displacement`` covers the time since the previous call (the
        start, for the first): calling this starts a new peak interval.
        """
        stones = self.stones
        live = np.flatnonzero(stones.alive)
        peak = self.seat.peak_field().astype(np.float32)
        forces = np.zeros((live.size, 3))
        ids, f = self.contact_forces()
        np.add.at(forces, np.searchsorted(live, ids), f)  # stones in contact are live
        return Frame(t=self.t, displacement=self.seat.u.astype(np.float32), positions=stones.pos[live].copy(),
                     radii=stones.radius[live].copy(), ids=live.copy(),
                     contacts=int((stones.ctri[live] >= 0).sum()), peak_displacement=peak, forces=forces)

    def contact_forces(self) -> tuple[np.ndarray, np.ndarray]:
        """Stone ids in soft contact and the forces they apply to the seat, (s,), (s, 3)."""
        return self.contacts.forces(self.stones.ctri)

    @property
    def u(self) -> np.ndarray:
        """Displacement (n, 3) of the whole surface (computed on demand, e.g. for frames)."""
        return self.seat.u

    @property
    def index(self) -> SurfaceIndex:
        """The surface's index (samples, grid, triangle normals, bounding box)."""
        return self.collision.index

    @property
    def soft(self) -> np.ndarray:
        """Triangles that deform under a contact (others are a hard wall)."""
        return self.collision.soft

    @property
    def cache(self) -> ContactSet | None:
        """The current contact set."""
        return self.contacts.current

    @property
    def lam(self) -> np.ndarray:
        """The current contact set's multipliers (seat forces)."""
        return self.contacts.lam

    @property
    def n(self) -> int:
        """Surface vertices."""
        return self.seat.n

    @property
    def lo(self) -> np.ndarray:
        return self.collision.lo

    @property
    def hi(self) -> np.ndarray:
        return self.collision.hi


def _stone_array(name: str) -> property:
    return property(lambda self: getattr(self.stones, name),
                    doc=f"The stones' ``{name}`` (:class:`~hailstorm.runtime.storm.stones.Stones`).")


for _name in ("pos", "vel", "radius", "mass", "alive", "ctri", "cbary", "gap", "hit", "near_tri", "crad", "budget"):
    setattr(Storm, _name, _stone_array(_name))
