"""The hail storm driver: stones falling on the seat, contacts through the capacitance.

Use::

    from hailstorm.runtime.bundle import load
    from hailstorm.runtime.storm import Scene, run_storm
    gf = load("bundle/")
    scene = Scene.from_toml("scene.toml")      # or Scene.default(), Scene(duration=0.2, ...)
    result = run_storm(gf, scene, progress=True)

Algorithm of one step (``dt`` = :attr:`Scene.dt`)
-------------------------------------------------
1. Spawn the stones due in this step.
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
      advanced by :func:`hailstorm.runtime.hail.contact_step` with unilateral release.
      ``integrator = "exact"`` solves the damped linear contact dynamics in
      closed form over the whole sub-step (maximum compression and release
      located inside it), so one sub-step per step suffices whatever
      ``omega dt``; ``"implicit"``/``"symplectic"`` sub-step to ``omega_dt``
      when adaptive;
   e. the seat's state is the vertex-force vector ``B f``; the full-surface
      displacement ``u = D[:, V] B f`` is formed only for frames (:attr:`Storm.u`).
4. Retire stones that left the seat's region; record a frame if one is due.

Patch contacts (``patch = "hertz"``, the default)
-------------------------------------------------
Each soft contact spreads its force over a disc of radius ``a`` around the
contact point, with the Hertz pressure profile (consistent P1 nodal loads,
:func:`hailstorm.runtime.weights.patch_weights`); the contact prescribes the
pressure-weighted mean normal displacement of the surface under the disc
(measured from the tangent plane at the contact point), which the stone's
lowest point follows. ``patch = "none"`` gives the point contacts of the
course hint (barycentric weights on one triangle).

* Radius: ``a = hertz_radius(F_peak, R, E, nu)`` clipped to
  ``[patch_min_radius, R]``, with ``F_peak`` the peak force of the contact's
  current oscillation about its static equilibrium,
  ``F_eq + sqrt((F - F_eq)^2 + k m v_n^2)`` (``F`` the previous sub-step's
  force, ``k`` the contact's stiffness). For a new contact (``F = 0``) this is
  the impact's expected peak force, with the stiffness of the patch itself
  (one fixed-point iteration from the triangle's point stiffness). The
  estimate is nearly constant during an impact, so the disc is sized for the
  deepest dent and the contact keeps one set of weights for the whole impact.
* Rebuilds: a contact is re-weighted (and the capacitance rebuilt) only when
  its target radius grows by more than ``patch_tolerance`` (20%), or shrinks
  by more than that *once the stone rests* (oscillation amplitude below
  ``rest_speed``): re-weighting during a rebound would change the stiffness
  that the damping was tuned for (the restitution), while the damping itself
  halves the amplitude within one impact.
* Caching: a contact keeps ``(triangle, beta)`` while its stone stays over
  the triangle, so its weights are cached per stone (:func:`hailstorm.runtime.patches.cached_weights`) and
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
(``max_penetration_free_m``). A stone *in contact* overlaps the piecewise-linear
dent around its load (``max_penetration_contact_m``, also relative to the
stone's radius and as a mean over contact steps): with point contacts the
contact point follows the stone exactly, but the dent is a one-vertex spike
whose triangles tilt into the sphere's cap; a patch contact spreads the load
over the disc and the dent follows the sphere much more closely. This is a
property of the contact model (see DESIGN: vertex pressure masks), not of the
time integration.

BLAS runs single-threaded inside :func:`run_storm` (``threadpoolctl``): the
dense solves are tiny and threaded BLAS on a shared machine only adds latency.

Compiled kernels
----------------
A step's arithmetic is small; as numpy calls its cost would be the per-call
overhead of a few hundred calls on arrays of a handful of stones. Each phase
runs once, in compiled kernels (:mod:`hailstorm.runtime.compiled`, numba): the
broad phase and free flight, the queries on a uniform grid of the triangles'
samples, phases a-c of a sub-step in one kernel, the patch sizing and weights,
the capacitance blocks and the integrators' steps; the orchestration stays in
this module. The tests hold the kernels to plain statements of the same rules
(``tests/reference/``) and to independent oracles (brute-force closest points
over all triangles, analytic bounces). ``NUMBA_DISABLE_JIT=1`` runs them as
Python, for debugging.
"""

from __future__ import annotations

import bisect
import logging
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from hailstorm.runtime import patches, soft_contacts
from hailstorm.runtime.collide import SurfaceIndex
from hailstorm.runtime.compiled import (
    capacitance_blocks,
    contact_post,
    contact_prep,
    exact_step,
    flight,
    free_phase,
    inv_spd,
    near_set,
    patch_compliance,
    patch_one,
    penetration,
    retired,
    rigid_contacts,
    substep_contacts,
    substep_damping,
    substep_size,
)
from hailstorm.runtime.compiled._jit import KERNELS
from hailstorm.runtime.compiled.grid import _surface
from hailstorm.runtime.hail import (
    _X_GRID,
    _Z_GRID,
    GRAVITY,
    stone_mass,
    terminal_velocity,
)
from hailstorm.runtime.scene import Scene, SceneError
from hailstorm.runtime.soft_contacts import ContactSet
from hailstorm.runtime.weights import PATCH_DROP, PATCH_FACING

__all__ = ["Frame", "Scene", "SceneError", "Storm", "StormResult", "run_storm"]


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
        (see :meth:`Storm.frame`): an impact lasts about a millisecond, much
        less than a frame interval, so ``displacement`` alone rarely shows
        the dents. ``None`` when not recorded.
    """

    t: float
    displacement: np.ndarray
    positions: np.ndarray
    radii: np.ndarray
    ids: np.ndarray
    contacts: int
    peak_displacement: np.ndarray | None = None


@dataclass
class StormResult:
    """What :func:`run_storm` returns: the scene, the frames and the statistics.

    ``frames`` holds the recorded frames when they were kept (``run_storm``'s
    ``keep_frames``), else it is empty: they were streamed to ``on_frame``.
    ``stats["frames"]`` counts them either way.
    """

    scene: Scene
    frames: list[Frame]
    stats: dict[str, Any]
    #: contact-force history: (time, total normal force on the seat [N], open contacts) per step
    history: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


_log = logging.getLogger(__name__)


#: seconds after which a kernel group still loading is announced as compiling
#: (loading a group from numba's on-disk cache takes milliseconds)
COMPILE_NOTICE_DELAY = 2.0


class _CompileNotice:
    """Announces a first compile: :meth:`stage` names the kernels being loaded next
    and roughly how long compiling them takes; if loading them has not finished
    after :data:`COMPILE_NOTICE_DELAY` seconds, numba is compiling and one INFO
    line says so."""

    def __init__(self) -> None:
        self._timer: threading.Timer | None = None
        self._t0 = time.perf_counter()
        self.times: dict[str, float] = {}
        self._what = ""

    def stage(self, what: str, seconds: float) -> None:
        self.done()
        self._what, self._t0 = what, time.perf_counter()
        self._timer = threading.Timer(COMPILE_NOTICE_DELAY, _log.info, args=(
            "compiling %s (numba, once after an install: about %.0f s)...", what, seconds))
        self._timer.daemon = True
        self._timer.start()

    def done(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self.times[self._what] = time.perf_counter() - self._t0
            self._timer = None

#: the per-stone arrays of a :class:`Storm` and the value a new stone starts with
#: (None: given to :meth:`Storm.add_stones`)
_STONE_FIELDS: tuple[tuple[str, Any], ...] = (
    ("pos", None), ("vel", None), ("radius", None), ("mass", None), ("alive", True), ("ctri", -1),
    ("cbary", 0.0), ("gap", np.inf), ("hit", False), ("near_tri", -1), ("crad", 0.0), ("budget", 0.0),
    ("_bud_u", 0.0),
)


class Storm:
    """A running storm (stateful). :func:`run_storm` drives one from start to end.

    Parameters
    ----------
    gf : GreensFunctions
        The bundle (:func:`hailstorm.runtime.bundle.load`).
    scene : Scene
    spawn : bool
        Spawn the scene's random stones (``False``: only stones added with
        :meth:`add_stones`, e.g. for a single drop).
    """

    def __init__(self, gf: Any, scene: Scene, *, spawn: bool = True) -> None:
        self.gf = gf
        self.scene = scene
        self.index = SurfaceIndex(gf.vertices, gf.triangles)
        self.X = np.asarray(gf.vertices, dtype=np.float64)
        self.n = self.X.shape[0]
        tri = np.asarray(gf.triangles)
        has_col = np.asarray(gf.contactable) | np.asarray(gf.fixed)
        #: triangles that deform under a contact (others are a hard wall)
        self.soft = has_col[tri].all(axis=1) & ~np.asarray(gf.fixed)[tri].all(axis=1)
        self._fixed = np.ascontiguousarray(gf.fixed, dtype=bool)
        lo, hi = self.index.bbox
        self.lo, self.hi = lo, hi
        self.g = np.array([0.0, 0.0, -GRAVITY])
        self.wind = np.asarray(scene.wind, dtype=np.float64)
        self.rng = np.random.default_rng(scene.seed)
        # stones (growable arrays)
        self.pos = np.zeros((0, 3))
        self.vel = np.zeros((0, 3))
        self.radius = np.zeros(0)
        self.mass = np.zeros(0)
        self.alive = np.zeros(0, dtype=bool)
        self.ctri = np.zeros(0, dtype=np.intp)  # contact triangle, -1 none
        self.cbary = np.zeros((0, 3))
        self.gap = np.zeros(0)  # last known distance to the surface minus radius
        self.hit = np.zeros(0, dtype=bool)
        self.near_tri = np.zeros(0, dtype=np.intp)  # closest triangle at the last query
        # patch contacts: radius of each stone's contact (0: none yet) and its cached weights
        self._patch = scene.patch != "none"
        self.crad = np.zeros(0)
        self._wcache: dict[int, tuple[int, bytes, float, np.ndarray, np.ndarray]] = {}
        self._k_tri_all: np.ndarray | None = None  # normal stiffness per triangle (lazy)
        # seat state: the contact forces at the loaded vertices; the displacement is
        # evaluated only where needed (candidate triangles, frames)
        D = gf.D
        if isinstance(D, np.memmap) and not D.flags.f_contiguous and D.nbytes <= (1 << 30):
            # column gathers D[:, cols] from a row-major memmap read the whole file each time:
            # hold a column-major copy (a no-op once bundles store D column-major)
            D = np.asfortranarray(D)
        # a plain ndarray view of a memmap (no copy): numpy.memmap's per-index overhead
        # (subclass wrapping) dominates the small gathers of the loop
        self._D = np.asarray(D)
        self._col_of = np.ascontiguousarray(gf.column_of, dtype=np.int64)
        #: the surface as the compiled kernels take it, and their "no forces"
        self._surf = _surface(self.index.grid, self.index.sample_radius, self.index.vertices, self.index.triangles)
        self._no_cols = np.zeros(0, dtype=np.int64)
        self._no_forces = np.zeros(0)
        self._no_e3 = np.zeros((0, 3))
        self._fv: np.ndarray | None = None
        self._fcols: np.ndarray | None = None
        self._u_version = 0
        self._u_cache: tuple[int, np.ndarray] = (-1, np.zeros((self.n, 3)))
        self.umax = 0.0
        self._umax_seen = 0.0
        #: per stone, its deepest dent since the previous frame and the vertex forces
        #: then: stone id -> (dent [m], D columns, vertex forces) (see :meth:`frame`)
        self._peaks: dict[int, tuple[float, np.ndarray, np.ndarray]] = {}
        self.budget = np.zeros(0)  # lower bound of each stone's distance to the seat [m]
        self._bud_u = np.zeros(0)  # the displacement bound each budget allows for [m]
        #: the per-stone arrays above are the first rows of these buffers (see :meth:`add_stones`)
        self._buffers = {name: getattr(self, name) for name, _ in _STONE_FIELDS}
        self._capacity = 0
        self._umax_step = 0.0  # largest umax in the current step
        self._live: np.ndarray | None = None
        self._far = np.zeros(0, dtype=np.intp)  # live stones that are not near (set by _near_set)
        #: time-of-impact sub-steps (adaptive) and the gap within which a contact opens [radii]
        #: compiled kernels for the step's work (:mod:`hailstorm.runtime.compiled`), or numpy
        #: quadratic drag coefficient 3 C_d rho_air / (8 rho_ice) (0: no drag), for the kernels
        self._drag_coef = 3.0 * scene.cd * scene.rho_air / (8.0 * scene.density) if scene.drag else 0.0
        if self._patch:
            from hailstorm.runtime.weights import _disc_table, _triangle_index

            self._pidx = _triangle_index(gf).arrays
            self._disc = _disc_table("hertz")
        #: the sub-steps' omega h target: symplectic Euler's explicit dashpot makes its peak force
        #: first order in omega h (-21 % at 0.2, -5 % at 0.05 on one impact), so it takes half the
        #: scene's (measured, default scene: max force 68.8 / 72.9 N at dt 0.05 / 0.5 ms with the
        #: full target, 71.93 / 71.89 N with half, for 30 % more sub-steps)
        self._omega_dt = float(scene.omega_dt) * (0.5 if scene.integrator == "symplectic" else 1.0)
        self._toi = bool(scene.adaptive)
        self._toi_tol = 0.01
        self._hmin = scene.dt / scene.max_substeps
        self.cache: ContactSet | None = None
        self.lam = np.zeros(0)
        self.t = 0.0
        self.stats: dict[str, Any] = dict(
            hailstones=0, impacts=0, stones_hit=0, max_contact_force=0.0, max_indentation_m=0.0,
            max_simultaneous_contacts=0, max_penetration_m=0.0, steps=0, substeps=0,
            capacitance_rebuilds=0, wall_contacts=0, retired=0, queries_reused=0, queries_predicted=0,
            max_penetration_contact_m=0.0, max_penetration_free_m=0.0, max_penetration_contact_rel=0.0,
            _pen_contact_sum=0.0, _pen_contact_n=0,
            patch=scene.patch, patch_weights_computed=0, patch_weights_reused=0, patch_resizes=0,
            max_patch_radius_m=0.0,
        )
        self._pending = self._plan_spawns() if spawn else np.zeros((0, 8))
        self._warm_up()
        self._next_pending = 0
        #: spawn times as a plain list (one float comparison per step when nothing is due)
        self._pending_t = self._pending[:, 0].tolist()

    def _warm_up(self) -> None:
        """Load (or compile, the first time after an install) every kernel the loop calls,
        with the loop's argument types, so that the stepping itself runs compiled code
        from its first step (loading takes ~0.3 s; compiling ~40 s, once: numba caches
        the machine code on disk). Each group of kernels that compiles says so in one
        INFO line (:class:`_CompileNotice`)."""
        none = np.zeros(0, dtype=np.intp)
        sc = self.scene
        t0 = time.perf_counter()
        notice = _CompileNotice()
        notice.stage("the storm's free-flight and broad-phase kernels", 3)
        self._fly(none, 0.0)
        retired(none, self.pos, self.radius, self.lo, self.hi, float(sc.margin))
        near_set(self.index.grid, self.index.sample_radius, self.index.bbox, none, self.pos, self.vel, self.radius,
                 self.ctri, self.budget, self._bud_u, 0.0, float(sc.dt), GRAVITY)
        notice.stage("the storm's closest-point and narrow-phase kernels", 8)
        self._free_phase(none, float(sc.dt))
        self._step_query(none, float(sc.dt))
        notice.stage("the storm's contact-set kernels", 30)
        soft = np.flatnonzero(self.soft)
        if soft.size:
            t = int(soft[0])
            verts = np.asarray(self.gf.triangles)[[t]].astype(np.int64)
            w = np.full((1, 3), 1.0 / 3.0)
            n = self.index.normals[[t]]
            rigid_contacts(verts, w, self._fixed)
            inv_spd(capacitance_blocks(verts, w, n, sc.mode == "sticky", self._D, self._col_of)[1], 1e10, 1e-10)
            patch_compliance(verts[0], w[0], n[0], self._D, self._col_of)
            if self._patch:
                patch_one(t, w[0], float(sc.patch_min_radius), n[0], 3.0, *self._disc, PATCH_FACING, PATCH_DROP,
                          self._pidx, self.X)
                patches.radii_compiled(self, none, none)
        e3, e = self._no_e3, self._no_forces
        b = np.zeros(0, dtype=bool)
        notice.stage(f"the {sc.integrator} integrator's kernels", 25 if sc.integrator == "exact" else 15)
        args = contact_prep(none, self.pos, self.vel, self.radius, self.mass, GRAVITY, self.wind, self._drag_coef,
                            e3, e3, e, e, sc.mode == "sticky", True, 1.0)
        q, a, vq, gq, _, _, acc = args
        contact_post(none, self.pos, self.vel, self.ctri, self.hit, b, e3, acc, q, a, vq, gq, e, e, b, e, e, e,
                     sc.mode == "sticky", True, 0.0, 1.0)
        one = np.ones(1)
        if sc.integrator == "exact":
            exact_step(one, one, one, one, one, 1e-4, np.eye(1), np.eye(1), np.eye(1), True, np.arange(1), one,
                       np.zeros(1, dtype=bool), 1e10, 1e-10)
        else:
            substep_contacts(one, one, one, one, one, 1e-4, np.eye(1), np.eye(1), np.eye(1), True, True,
                             np.arange(1), one, 1e10, 1e-10)
            substep_damping(one, np.eye(1), one, 0.5, 1e-4, True, _X_GRID, _Z_GRID)
            if sc.adaptive:
                self._substep_size(none, float(sc.dt))
        notice.done()
        _log.debug("storm kernels ready in %.2f s (%s)", time.perf_counter() - t0,
                   ", ".join(f"{k}: {v:.2f} s" for k, v in notice.times.items()))

    # -- stones ------------------------------------------------------------------
    def _plan_spawns(self) -> np.ndarray:
        """All random stones of the storm: rows (t, x, y, z, vx, vy, vz, r)."""
        sc, rng = self.scene, self.rng
        n = sc.stones if sc.stones is not None else int(rng.poisson(sc.rate * sc.duration))
        t = np.sort(rng.random(n) * sc.duration)
        r = sc.size_distribution().sample(rng, n)
        xy = np.stack([rng.uniform(self.lo[0] - sc.margin, self.hi[0] + sc.margin, n),
                       rng.uniform(self.lo[1] - sc.margin, self.hi[1] + sc.margin, n)], axis=1)
        vt = terminal_velocity(r, cd=sc.cd, rho_air=sc.rho_air, density=sc.density)
        z0 = self.hi[2] + sc.spawn_height + r
        t_fall = (z0 - 0.5 * (self.lo[2] + self.hi[2])) / np.maximum(vt, 1e-9)
        xy = xy - self.wind[None, :2] * t_fall[:, None]  # upwind, so they land on the seat
        vel = np.column_stack([np.broadcast_to(self.wind[:2], (n, 2)), -vt])
        return np.column_stack([t, xy, z0, vel, r])

    def add_stones(self, pos: np.ndarray, vel: np.ndarray, radius: np.ndarray) -> np.ndarray:
        """Add stones now; returns their ids."""
        pos = np.atleast_2d(np.asarray(pos, dtype=np.float64))
        vel = np.broadcast_to(np.asarray(vel, dtype=np.float64), pos.shape)
        radius = np.broadcast_to(np.asarray(radius, dtype=np.float64), (pos.shape[0],))
        k = pos.shape[0]
        n = self.pos.shape[0]
        ids = np.arange(n, n + k)
        if n + k > self._capacity:  # grow the per-stone buffers (doubling: O(1) per stone)
            cap = max(2 * self._capacity, n + k, 64)
            for name, _ in _STONE_FIELDS:
                old = getattr(self, name)
                buf = np.empty((cap,) + old.shape[1:], dtype=old.dtype)
                buf[:n] = old
                self._buffers[name] = buf
            self._capacity = cap
        for name, new in _STONE_FIELDS:
            arr = self._buffers[name][:n + k]
            setattr(self, name, arr)
            if new is not None:
                arr[n:] = new
        self.pos[n:] = pos
        self.vel[n:] = vel
        self.radius[n:] = radius
        self.mass[n:] = stone_mass(radius, self.scene.density)
        self._live = None
        self.stats["hailstones"] += k
        return ids

    def _spawn_until(self, t_end: float) -> None:
        j = self._next_pending
        pt = self._pending_t
        if j >= len(pt) or not pt[j] < t_end:
            return  # nothing due (the times are sorted)
        p = self._pending
        k = bisect.bisect_left(pt, t_end, j)  # = np.searchsorted(p[:, 0], t_end, side="left")
        if k > j:
            self.add_stones(p[j:k, 1:4], p[j:k, 4:7], p[j:k, 7])
            self._next_pending = k

    def _fly(self, idx: np.ndarray, h: float) -> None:
        """Free flight of stones ``idx`` over ``h`` (gravity and drag)."""
        flight(idx, self.pos, self.vel, self.radius, h, GRAVITY, self.wind, self._drag_coef)

    # -- the seat's displacement (only where it is needed) ---------------------------
    def _set_forces(self, cc: ContactSet | None, lam: np.ndarray, peak: np.ndarray | None = None) -> None:
        """Contact multipliers -> vertex forces; displacement bound ``umax``. ``peak``: the
        multipliers of each contact's largest force within the sub-step (default ``lam``),
        kept for the frames' peak displacement."""
        self._u_version += 1
        if cc is None or lam.size == 0 or not np.any(lam):
            self._fv = None
            self._fcols = None
            self.umax = 0.0
            if cc is not None and peak is not None and np.any(peak):
                self._track_peaks(cc, peak)  # released within the sub-step: its dent still counts
            return
        self._fv = cc.G @ lam
        self._fcols = cc.cols
        uV = (cc.DVV @ lam).reshape(-1, 3)
        # |u| peaks under the loads; 1.5x covers superposition between nearby loads
        self.umax = 1.5 * float(np.sqrt((uV**2).sum(axis=1).max())) if uV.size else 0.0
        self._umax_seen = max(self._umax_seen, self.umax)
        self._umax_step = max(self._umax_step, self.umax)
        self._track_peaks(cc, lam if peak is None else peak)

    def _track_peaks(self, cc: ContactSet, lam: np.ndarray) -> None:
        """Keep, per stone, the vertex forces of its deepest dent since the last frame.

        The dent is the largest displacement of the contact's own load at the loaded
        vertices (``D_VV G``): for fixed weights it grows with the force, and across
        a re-weighting (a patch resized) it still ranks the fields by what they show,
        which the force alone does not (a wider patch carries more force in a shallower dent).
        """
        s = cc.stones.size
        m = lam.size // s  # multipliers per contact (1 frictionless, 3 sticky)
        L = lam.reshape(-1, m)
        if m == 1:
            U = cc.DVV * L[:, 0]  # (3|V|, s): each contact's own displacement of V
        else:
            U = np.einsum("rkj,kj->rk", cc.DVV.reshape(-1, s, m), L)
        U = U.reshape(-1, 3, s)
        dent = np.sqrt((U * U).sum(axis=1).max(axis=0)) if U.size else np.zeros(s)
        peaks = self._peaks
        for k in np.flatnonzero(dent > 0.0).tolist():
            sid = int(cc.stones[k])
            prev = peaks.get(sid)
            if prev is None or dent[k] > prev[0]:
                fk = cc.G[:, m * k:m * k + m] @ L[k]
                nz = np.flatnonzero(fk)
                peaks[sid] = (float(dent[k]), cc.cols[nz], fk[nz])

    def _peak_field(self) -> np.ndarray:
        """Per vertex, the largest of the current displacement and each stone's displacement
        at its deepest dent since the previous frame (each stone's field alone: impacts rarely
        overlap within a frame, and superposing peaks of different instants would overstate)."""
        u = self.u
        if not self._peaks:
            return u
        fields = [u] + [(self._D[:, cols] @ fv).reshape(self.n, 3) for _, cols, fv in self._peaks.values()]
        F = np.stack(fields)  # (m + 1, n, 3)
        pick = np.argmax(np.einsum("mnd,mnd->mn", F, F), axis=0)
        return F[pick, np.arange(self.n)]

    def _u_at(self, verts: np.ndarray) -> np.ndarray:
        """Displacement (k, 3) of surface vertices ``verts`` under the current contact forces."""
        if self._fv is None or verts.size == 0:
            return np.zeros((verts.size, 3))
        assert self._fcols is not None  # set together with _fv (_set_forces)
        rows = (3 * verts[:, None] + np.arange(3)).ravel()
        return (self._D[np.ix_(rows, self._fcols)] @ self._fv).reshape(-1, 3)

    @property
    def u(self) -> np.ndarray:
        """Displacement (n, 3) of the whole surface (computed on demand, e.g. for frames)."""
        if self._u_cache[0] != self._u_version:
            if self._fv is None:
                u = np.zeros((self.n, 3))
            else:
                u = (self._D[:, self._fcols] @ self._fv).reshape(self.n, 3)
            self._u_cache = (self._u_version, u)
        return self._u_cache[1]

    def _substep(self, near: np.ndarray, h: float) -> float:
        """Advance the near stones by at most ``h``; returns the time actually taken
        (shorter when a stone is about to touch the seat: time of impact).

        The phases, in order (:meth:`_free_phase`): closest points, time of impact,
        contacts that open, hard walls; then soft
        contacts through the capacitance (:func:`hailstorm.runtime.soft_contacts.advance`) and free flight.
        """
        was_open = self.ctri[near] >= 0
        h = self._free_phase(near, h)
        soft = near[self.ctri[near] >= 0]
        if soft.size < near.size:
            free = near[self.ctri[near] < 0] if soft.size else near
        else:
            free = near[:0]
        if soft.size:
            soft_contacts.advance(self, near, soft, was_open, h)
        else:
            self.cache = None
            self.lam = np.zeros(0)
            self._set_forces(None, self.lam)
        if free.size:
            self._fly(free, h)
        self.stats["substeps"] += 1
        return h

    def _free_phase(self, near: np.ndarray, h: float) -> float:
        """Closest points, time of impact, contacts that open, hard walls
        (:func:`hailstorm.runtime.compiled.free_phase`). Returns the sub-step taken."""
        sc = self.scene
        use_u = self._fv is not None
        coef = self._drag_coef
        h, walls = free_phase(
            near, h, self._toi, self._toi_tol, self._hmin, self.pos, self.vel, self.radius, self.ctri, self.cbary,
            self.gap, self.near_tri, self._surf, self.index.normals, self.soft, self._fixed, self.umax, use_u,
            self._D, self._fcols if use_u else self._no_cols, self._fv if use_u else self._no_forces,
            GRAVITY, self.wind, coef, float(sc.restitution))
        self.stats["wall_contacts"] += int(walls)
        return float(h)

    def _substep_size(self, near: np.ndarray, h_left: float) -> float:
        sc = self.scene
        h = h_left
        if not sc.adaptive or sc.integrator == "exact":
            return h  # exact: no stability/accuracy limit; impacts are caught by time of impact
        hmin = sc.dt / sc.max_substeps
        cc = self.cache
        if self._k_tri_all is None:
            self._k_tri_all = patches.all_triangle_stiffness(self)
        if cc is not None and cc.stones.size:
            cs, kd, cn, cx, cr = cc.stones, cc.Kdiag, cc.normals, cc.X, cc.rest
        else:
            cs, kd, cn, cx, cr = self._no_cols, self._no_forces, self._no_e3, self._no_e3, self._no_forces
        return float(substep_size(near, float(h_left), float(hmin), self.vel, self.radius, self.mass, self.pos,
                                  self.gap, self.near_tri, self.ctri, self._k_tri_all,
                                  float(sc.approach_fraction), float(sc.rest_speed), self._omega_dt,
                                  sc.integrator == "symplectic", cs, kd, sc.mode == "sticky", cn, cx, cr, self.g))

    # -- the step ------------------------------------------------------------------
    def _near_set(self, live: np.ndarray, dt: float) -> np.ndarray:
        """Stones that may touch the seat within this step (conservative advancement).

        Every stone carries a ``budget``: a lower bound of its distance to the
        deformed surface, valid while ``|u| <= umax_i`` (the displacement bound
        it was measured with; if the seat's ``umax`` grows beyond it the budget
        shrinks by the difference). Flying stones spend it by what they can
        travel in a step; only when it runs out is the distance re-measured (a
        k-d tree query). Stones with budget left are not collision-tested.
        """
        ix = self.index
        m = near_set(ix.grid, ix.sample_radius, ix.bbox, live, self.pos, self.vel, self.radius, self.ctri,
                     self.budget, self._bud_u, 1.5 * self._umax_step, dt, GRAVITY)
        self._far = live[~m]
        return live[m]

    def _step_query(self, near: np.ndarray, dt: float) -> None:
        """One narrow-phase query per step for the near stones: the penetration of the
        deformed surface (sphere vs surface) for the statistics, kept for the first
        sub-step to reuse (free stones with this step's reach, contact stones within r;
        free stones whose predicted gap shows they cannot touch in this step are skipped)."""
        use_u = self._fv is not None
        mp, mpc, mrc, spc, npc, mpf = penetration(
            near, float(dt), self.pos, self.vel, self.radius, self.ctri, self._surf, self.umax, use_u, self._D,
            self._fcols if use_u else self._no_cols, self._fv if use_u else self._no_forces)
        st = self.stats
        st["max_penetration_m"] = max(st["max_penetration_m"], mp)
        st["max_penetration_contact_m"] = max(st["max_penetration_contact_m"], mpc)
        st["max_penetration_contact_rel"] = max(st["max_penetration_contact_rel"], mrc)
        st["max_penetration_free_m"] = max(st["max_penetration_free_m"], mpf)
        st["_pen_contact_sum"] += spc
        st["_pen_contact_n"] += int(npc)

    def step(self) -> None:
        """Advance the storm by one step ``dt``."""
        sc = self.scene
        dt = sc.dt
        self._spawn_until(self.t + dt)
        live = self._live
        if live is None:
            live = self._live = np.flatnonzero(self.alive)
        if live.size:
            near = self._near_set(live, dt)
            far = self._far
        else:
            near = far = live
        if far.size:
            self._fly(far, dt)
            self.gap[far] = np.inf
        if near.size:
            self._step_query(near, dt)
            t_left = dt
            n_sub = 0
            while t_left > 1e-12 * dt:
                h = self._substep_size(near, t_left)
                if n_sub >= 4 * self.scene.max_substeps:
                    h = t_left  # safety net: never stall
                h = self._substep(near, h)
                t_left -= h
                n_sub += 1
        elif self._fv is not None:
            self.cache = None
            self._set_forces(None, np.zeros(0))
        # retire stones that left the seat's region
        if live.size:
            gone = retired(live, self.pos, self.radius, self.lo, self.hi, float(sc.margin))
            if gone.any():
                g = live[gone]
                self.alive[g] = False
                for j in g.tolist():
                    self._wcache.pop(j, None)
                self.ctri[g] = -1
                self._live = None
                self.stats["retired"] += int(gone.sum())
        self._umax_step = self.umax
        self.t += dt
        self.stats["steps"] += 1

    def frame(self) -> Frame:
        """The current state as a :class:`Frame`.

        Its ``peak_displacement`` covers the time since the previous call (the
        start, for the first): calling this starts a new peak interval.
        """
        live = np.flatnonzero(self.alive)
        peak = self._peak_field().astype(np.float32)
        self._peaks = {}
        return Frame(t=self.t, displacement=self.u.astype(np.float32), positions=self.pos[live].copy(),
                     radii=self.radius[live].copy(), ids=live.copy(), contacts=int((self.ctri[live] >= 0).sum()),
                     peak_displacement=peak)

    def contact_forces(self) -> tuple[np.ndarray, np.ndarray]:
        """Stone ids in soft contact and the forces they apply to the seat, (s,), (s, 3)."""
        if self.cache is None or self.lam.size == 0:
            return np.zeros(0, dtype=np.intp), np.zeros((0, 3))
        cc = self.cache
        if self.scene.mode == "frictionless":
            f = self.lam[:, None] * cc.normals
        else:
            f = self.lam.reshape(-1, 3)
        keep = self.ctri[cc.stones] >= 0
        return cc.stones[keep], f[keep]


def run_storm(
    gf: Any,
    scene: Scene | None = None,
    *,
    progress: bool | Callable[[float, float], None] = True,
    on_frame: Callable[[Frame], None] | None = None,
    keep_frames: bool | None = None,
    allow_large: bool = False,
) -> StormResult:
    """Run a hail storm on the seat.

    Parameters
    ----------
    gf : GreensFunctions
        The bundle (:func:`hailstorm.runtime.bundle.load`).
    scene : Scene, optional
        Default: :meth:`Scene.default`.
    progress : bool or callable
        ``True``: a tqdm progress bar over the simulated time (on stderr); a
        callable is called as ``progress(t, duration)`` after every step.
    on_frame : callable, optional
        Called with each :class:`Frame` as it is recorded, e.g.
        :meth:`hailstorm.runtime.output.StormOutput.add`, which streams the frames to
        disk.
    keep_frames : bool, optional
        Keep the frames in :attr:`StormResult.frames` (memory grows with the
        duration: ~24 bytes per surface vertex and frame). Default: kept when
        no ``on_frame`` is given, else not.
    allow_large : bool
        Run even a storm whose estimate (:meth:`Scene.estimate`) exceeds the
        machine; otherwise it is refused before anything runs.

    Returns
    -------
    StormResult
        Frames at ``scene.fps`` (plus the first and last instants; empty
        unless kept) and statistics (see :func:`hailstorm.runtime.output.summary`).

    Raises
    ------
    hailstorm.runtime.scene.StormTooLarge
        The estimate exceeds the machine and ``allow_large`` is not set.
    """
    scene = Scene.default() if scene is None else scene
    keep = on_frame is None if keep_frames is None else bool(keep_frames)
    estimate = scene.estimate(int(np.asarray(gf.vertices).shape[0]), keep_frames=keep)
    estimate.check(allow_large=allow_large)
    _log.info("storm: %s", estimate.describe())
    for warning in scene.physical_warnings(gf.vertices):
        _log.warning("warning: %s", warning)
    setup0 = time.perf_counter()
    storm = Storm(gf, scene)
    setup = time.perf_counter() - setup0
    n_steps = scene.n_steps()
    frame_dt = 1.0 / scene.fps
    frames: list[Frame] = []
    n_frames = 0
    sink_time = 0.0  # spent in on_frame (writing files): not the storm's wall time

    def record() -> None:
        nonlocal n_frames, sink_time
        f = storm.frame()
        n_frames += 1
        if on_frame is not None:
            t0 = time.perf_counter()
            on_frame(f)
            sink_time += time.perf_counter() - t0
        if keep:
            frames.append(f)

    record()
    next_frame = frame_dt
    history = np.zeros((n_steps, 3))
    bar = None
    if progress is True:
        from tqdm.auto import tqdm

        bar = tqdm(total=float(scene.duration), desc="hail storm", unit="s sim", leave=False,
                   bar_format="{l_bar}{bar}| {n:.3g}/{total:.3g} s simulated [{elapsed}<{remaining}]")
    from threadpoolctl import threadpool_limits

    limiter = threadpool_limits(1)  # small dense solves: threaded BLAS only adds overhead
    wall0, sink0 = time.perf_counter(), sink_time
    shown = 0.0
    try:
        for i in range(n_steps):
            storm.step()
            _, f = storm.contact_forces()
            history[i] = (storm.t, float(np.linalg.norm(f, axis=1).sum()) if f.size else 0.0, f.shape[0])
            if storm.t >= next_frame - 1e-12 or i == n_steps - 1:
                record()
                next_frame += frame_dt
            if bar is not None:
                if storm.t - shown >= 0.002 * scene.duration or i == n_steps - 1:
                    bar.update(min(storm.t, scene.duration) - shown)
                    shown = min(storm.t, scene.duration)
            elif callable(progress):
                progress(storm.t, scene.duration)
    finally:
        wall = time.perf_counter() - wall0 - (sink_time - sink0)
        limiter.restore_original_limits()
        if bar is not None:
            bar.close()
    st = storm.stats
    st["stones_hit"] = int(storm.hit.sum())
    n_pen, pen_sum = st.pop("_pen_contact_n"), st.pop("_pen_contact_sum")
    st["mean_penetration_contact_m"] = pen_sum / n_pen if n_pen else 0.0
    st.update(
        sim_time_s=float(storm.t), wall_time_s=float(wall), setup_time_s=float(setup), backend=KERNELS,
        real_time_factor=float(storm.t / wall) if wall > 0 else float("inf"),
        seed=scene.seed, dt=scene.dt, integrator=scene.integrator, mode=scene.mode,
        restitution=scene.restitution, n_vertices=int(storm.n), n_triangles=int(len(gf.triangles)),
        resting_at_end=int((storm.ctri[storm.alive] >= 0).sum()), frames=n_frames, output_time_s=float(sink_time),
    )
    return StormResult(scene=scene, frames=frames, stats=st, history=history)
