"""The storm's stones: their per-stone arrays (growable), the spawn plan, retirement.

:class:`Stones` holds one row per stone ever spawned (ids are row numbers, in
spawn order); the arrays are the first rows of buffers that grow by doubling,
so a spawn costs O(1) per stone and the compiled kernels take the arrays in
place. :class:`SpawnPlan` draws the scene's random stones once, up front, and
hands out the ones due in each step.
"""

from __future__ import annotations

import bisect
from typing import Any, TYPE_CHECKING

import numpy as np

from hailstorm.runtime.storm.hail import stone_mass, terminal_velocity

if TYPE_CHECKING:  # annotations only
    from hailstorm.runtime.storm.scene_sections import HailSettings, StormSettings

__all__ = ["SpawnPlan", "StoneError", "Stones", "check_stones"]


class StoneError(ValueError):
    """Stones given to a storm are invalid (the message names the first bad one)."""


def _first_bad(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def check_stones(pos: Any, vel: Any, radius: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The one validation of new stones (the API's and the scene's alike).

    Parameters
    ----------
    pos : (3,) or (k, 3) array_like
        Centres [m].
    vel : (3,) or (k, 3) array_like
        Velocities [m/s] (one row for all, or one per stone).
    radius : float or (k,) array_like
        Radii [m].

    Returns
    -------
    pos, vel : (k, 3) float64 ndarray
    radius : (k,) float64 ndarray

    Raises
    ------
    StoneError
        Wrong shapes, complex or non-numeric values, a NaN or infinite position or
        velocity, or a radius that is not a finite positive number.
    """
    arrays = []
    for name, value in (("positions", pos), ("velocities", vel), ("radii", radius)):
        a = np.asarray(value)
        if a.dtype.kind not in "biuf":
            raise StoneError(f"stone {name} must be real numbers, got an array of {a.dtype}")
        arrays.append(a.astype(np.float64))
    p, v, r = arrays
    if p.ndim not in (1, 2) or p.shape[-1] != 3:
        raise StoneError(f"stone positions must have shape (3,) or (k, 3), got {p.shape}")
    p = np.atleast_2d(p)
    k = p.shape[0]
    if v.shape not in ((3,), (1, 3), (k, 3)):
        raise StoneError(f"stone velocities must have shape (3,) or ({k}, 3) for {k} stones, got {v.shape}")
    if r.shape not in ((), (1,), (k,)):
        raise StoneError(f"stone radii must be one number or {k} numbers for {k} stones, got shape {r.shape}")
    v = np.broadcast_to(v.reshape(-1, 3), (k, 3))
    r = np.broadcast_to(r.reshape(-1), (k,))
    for name, a in (("position", p), ("velocity", v)):
        bad = ~np.isfinite(a).all(axis=1)
        if bad.any():
            i = _first_bad(bad)
            raise StoneError(f"stone {i} has a non-finite {name} {a[i].tolist()}")
    bad = ~(np.isfinite(r) & (r > 0))
    if bad.any():
        i = _first_bad(bad)
        raise StoneError(f"stone {i} has radius {float(r[i])!r}; a radius must be a finite positive number [m]")
    return p, v, r

#: the per-stone arrays and the value a new stone starts with (None: given to :meth:`Stones.add`)
FIELDS: tuple[tuple[str, Any], ...] = (
    ("pos", None), ("vel", None), ("radius", None), ("mass", None), ("alive", True), ("ctri", -1),
    ("cbary", 0.0), ("cnormal", 0.0), ("gap", np.inf), ("hit", False), ("near_tri", -1), ("crad", 0.0), ("offset", 0.0),
    ("shift", 0.0), ("budget", 0.0), ("bud_u", 0.0),
)


class Stones:
    """The stones of a storm (one row per stone, alive or retired).

    Attributes
    ----------
    pos, vel : (k, 3) ndarray
        Centres [m] and velocities [m/s].
    radius, mass : (k,) ndarray
    alive : (k,) bool ndarray
    ctri : (k,) int ndarray
        Contact triangle (-1: none).
    cbary : (k, 3) ndarray
        The contact point's barycentric coordinates on ``ctri``.
    cnormal : (k, 3) ndarray
        The open contact's unit normal, set when it opens or moves: its triangle's normal,
        or on an edge or a corner of the faceted surface the direction from that closest
        point to the centre (the module notes of :mod:`hailstorm.runtime.storm.driver`,
        "Facets").
    gap : (k,) ndarray
        Last known distance to the surface minus the radius (inf: unknown).
    hit : (k,) bool ndarray
        The stone has hit the seat.
    near_tri : (k,) int ndarray
        Closest triangle at the last query.
    crad : (k,) ndarray
        Patch radius of the stone's contact (0: none yet).
    offset : (k,) ndarray
        The patch's sphere offset ``o`` of the stone's current approach or contact [m]
        (0: none): its contact surface is the sphere of radius ``radius - offset``
        (:meth:`contact_radius`; the module notes of :mod:`hailstorm.runtime.storm.driver`,
        "Patch contacts").
    shift : (k,) ndarray
        How far the anchor of the stone's open contact lies out along its normal [m]
        (0 when the contact opens): set when the contact moves to a triangle whose plane is
        nearer, so that the spring does not jump shorter (the module notes of
        :mod:`hailstorm.runtime.storm.driver`, "Facets").
    budget, bud_u : (k,) ndarray
        Broad phase: a lower bound of the distance to the seat [m] and the
        displacement bound it allows for [m] (:func:`hailstorm.runtime.compiled.near_set`).
    """

    pos: np.ndarray
    vel: np.ndarray
    radius: np.ndarray
    mass: np.ndarray
    alive: np.ndarray
    ctri: np.ndarray
    cbary: np.ndarray
    cnormal: np.ndarray
    gap: np.ndarray
    hit: np.ndarray
    near_tri: np.ndarray
    crad: np.ndarray
    offset: np.ndarray
    shift: np.ndarray
    budget: np.ndarray
    bud_u: np.ndarray

    def __init__(self, density: float) -> None:
        self.density = float(density)
        self.pos = np.zeros((0, 3))
        self.vel = np.zeros((0, 3))
        self.radius = np.zeros(0)
        self.mass = np.zeros(0)
        self.alive = np.zeros(0, dtype=bool)
        self.ctri = np.zeros(0, dtype=np.intp)
        self.cbary = np.zeros((0, 3))
        self.cnormal = np.zeros((0, 3))
        self.gap = np.zeros(0)
        self.hit = np.zeros(0, dtype=bool)
        self.near_tri = np.zeros(0, dtype=np.intp)
        self.crad = np.zeros(0)
        self.offset = np.zeros(0)
        self.shift = np.zeros(0)
        self.budget = np.zeros(0)
        self.bud_u = np.zeros(0)
        self._buffers = {name: getattr(self, name) for name, _ in FIELDS}
        self._capacity = 0
        self._live: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.pos.shape[0])

    def add(self, pos: np.ndarray, vel: np.ndarray, radius: np.ndarray) -> np.ndarray:
        """Add stones (checked by :func:`check_stones`); returns their ids.

        Raises
        ------
        StoneError
            See :func:`check_stones`.
        """
        pos, vel, radius = check_stones(pos, vel, radius)
        k = pos.shape[0]
        n = self.pos.shape[0]
        ids = np.arange(n, n + k)
        self.reserve(k)
        self.resize(n + k)
        for name, new in FIELDS:
            if new is not None:
                getattr(self, name)[n:] = new
        self.pos[n:] = pos
        self.vel[n:] = vel
        self.radius[n:] = radius
        self.mass[n:] = stone_mass(radius, self.density)
        return ids

    def reserve(self, k: int) -> None:
        """Room for ``k`` more stones in the per-stone buffers (grown by doubling: O(1) per stone)."""
        n = self.pos.shape[0]
        if n + k <= self._capacity:
            return
        cap = max(2 * self._capacity, n + k, 64)
        for name, _ in FIELDS:
            old = getattr(self, name)
            buf = np.empty((cap,) + old.shape[1:], dtype=old.dtype)
            buf[:n] = old
            self._buffers[name] = buf
        self._capacity = cap
        self.resize(n)

    def buffers(self) -> tuple[np.ndarray, ...]:
        """The per-stone buffers at their full capacity, in the order of :data:`FIELDS` (for a
        kernel that adds stones in place: :func:`hailstorm.runtime.compiled.free_steps.free_steps`;
        then :meth:`resize`)."""
        return tuple(self._buffers[name] for name, _ in FIELDS)

    def resize(self, n: int) -> None:
        """The stones are the first ``n`` rows of the buffers (after a kernel wrote new ones or
        retired some: the live ids are recomputed)."""
        for name, _ in FIELDS:
            setattr(self, name, self._buffers[name][:n])
        self._live = None

    def contact_radius(self) -> np.ndarray:
        """Radius of each stone's contact surface, ``radius - offset`` (k,) [m]: what the
        narrow phase and the contact's anchor measure the gap with."""
        return self.radius - self.offset

    def live(self) -> np.ndarray:
        """Ids of the live stones (cached until a spawn or a retirement)."""
        if self._live is None:
            self._live = np.flatnonzero(self.alive)
        return self._live

    def retire(self, ids: np.ndarray) -> None:
        """Stones ``ids`` left the seat's region."""
        self.alive[ids] = False
        self.ctri[ids] = -1
        self.offset[ids] = 0.0
        self._live = None


class SpawnPlan:
    """All random stones of a storm, drawn up front: rows (t, x, y, z, vx, vy, vz, r).

    Parameters
    ----------
    storm : StormSettings
        Count or rate, duration, margin, spawn height, wind.
    hail : HailSettings
        Radii, and the air and ice of the terminal velocity.
    lo, hi : (3,) ndarray
        The seat's bounding box.
    rng : numpy.random.Generator
    """

    def __init__(self, storm: StormSettings, hail: HailSettings, lo: np.ndarray, hi: np.ndarray,
                 rng: np.random.Generator) -> None:
        sc = storm
        wind = np.asarray(sc.wind, dtype=np.float64)
        n = sc.stones if sc.stones is not None else int(rng.poisson(sc.rate * sc.duration))
        t = np.sort(rng.random(n) * sc.duration)
        r = hail.size_distribution().sample(rng, n)
        xy = np.stack([rng.uniform(lo[0] - sc.margin, hi[0] + sc.margin, n),
                       rng.uniform(lo[1] - sc.margin, hi[1] + sc.margin, n)], axis=1)
        vt = terminal_velocity(r, cd=hail.cd, rho_air=hail.rho_air, density=hail.density)
        z0 = hi[2] + sc.spawn_height + r
        t_fall = (z0 - 0.5 * (lo[2] + hi[2])) / np.maximum(vt, 1e-9)
        xy = xy - wind[None, :2] * t_fall[:, None]  # upwind, so they land on the seat
        vel = np.column_stack([np.broadcast_to(wind[:2], (n, 2)), -vt])
        self.rows = np.column_stack([t, xy, z0, vel, r])
        self._next = 0
        #: spawn times as a plain list (one float comparison per step when nothing is due)
        self._t = self.rows[:, 0].tolist()

    @classmethod
    def empty(cls) -> "SpawnPlan":
        """No stones (a storm of stones added by hand)."""
        plan = cls.__new__(cls)
        plan.rows, plan._next, plan._t = np.zeros((0, 8)), 0, []
        return plan

    @property
    def next_row(self) -> int:
        """The first row not handed out yet."""
        return self._next

    def handed_out(self, j: int) -> None:
        """Rows up to ``j`` (excluded) were handed out (by a kernel that spawns them itself)."""
        self._next = int(j)

    def due(self, t_end: float) -> np.ndarray | None:
        """Rows of the stones due before ``t_end`` not handed out yet (None: none)."""
        j = self._next
        pt = self._t
        if j >= len(pt) or not pt[j] < t_end:
            return None  # nothing due (the times are sorted)
        k = bisect.bisect_left(pt, t_end, j)  # = np.searchsorted(rows[:, 0], t_end, side="left")
        if k <= j:
            return None
        self._next = k
        return self.rows[j:k]
