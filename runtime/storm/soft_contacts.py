"""The storm's soft contacts: the current contact set and one contact step of its stones.

:class:`SoftContacts` keeps the capacitance of the current set of soft contacts
(:class:`~hailstorm.runtime.storm.contact_set.ContactSet`, rebuilt when the set of
(stone, triangle[, patch radius]) changes) and the seat forces of its last step;
:meth:`SoftContacts.advance` moves the stones in contact by one sub-step through
the scene's integrator (:class:`~hailstorm.runtime.storm.integrators.ContactIntegrator`)
with unilateral release, the per-contact work in kernels
(:func:`hailstorm.runtime.compiled.contact_prep` / :func:`~hailstorm.runtime.compiled.contact_post`),
and hands the forces to the seat.
"""

from __future__ import annotations

from typing import Any, TYPE_CHECKING

import numpy as np

from hailstorm.runtime.compiled import contact_post, contact_prep
from hailstorm.runtime.compiled.narrow import DEAD_ZONE_REACH
from hailstorm.runtime.storm.hail import GRAVITY
from hailstorm.runtime.storm.limits import PAD_DENSITY, ImpactLimits

if TYPE_CHECKING:  # annotations only
    from hailstorm.runtime.storm.contact_set import ContactSet, ContactSets
    from hailstorm.runtime.storm.hail import Air
    from hailstorm.runtime.storm.integrators import ContactIntegrator
    from hailstorm.runtime.storm.patches import Patches
    from hailstorm.runtime.storm.recording import StormStats
    from hailstorm.runtime.storm.scene_sections import ContactSettings, TimeSettings
    from hailstorm.runtime.storm.seat import SeatState
    from hailstorm.runtime.storm.stones import Stones

__all__ = ["SoftContacts"]


class SoftContacts:
    """The storm's soft contacts (the current set, its forces) and their step.

    Parameters
    ----------
    contact : ContactSettings
        ``mode``, ``patch``.
    time : TimeSettings
        ``rest_speed``.
    sets : ContactSets
        Builds a set's capacitance.
    patches : Patches
        The patch radii (``patch = "hertz"``).
    integrator : ContactIntegrator
    seat : SeatState
        Receives the contact forces.
    air : Air
    pad_density : float
        The pad foam's density [kg/m^3], for the validity limits and the inertia factors only
        (:class:`ImpactLimits`).
    inertia : bool
        Measure the pad's inertia per impact (:meth:`ImpactLimits.inertia`).
    """

    def __init__(self, contact: ContactSettings, time: TimeSettings, sets: ContactSets, patches: Patches, integrator: ContactIntegrator,
                 seat: SeatState, air: Air, pad_density: float = PAD_DENSITY, inertia: bool = True) -> None:
        self.sets = sets
        self.patches = patches
        self.integrator = integrator
        self.seat = seat
        self.air = air
        self.contact = contact
        self.time = time
        self.patch = contact.patch != "none"
        #: the impacts' validity measures (recorded, never fed back into the contact step)
        self.limits = ImpactLimits(sets.gf, time.rest_speed, pad_density=pad_density, inertia=inertia)
        #: the current contact set (None: no soft contact) and its multipliers (the seat forces)
        self.current: ContactSet | None = None
        self.lam = np.zeros(0)
        self._no_e3 = np.zeros((0, 3))
        self._no_forces = np.zeros(0)

    def release(self) -> None:
        """No soft contact: the set and the seat's load are gone."""
        self.current = None
        self.lam = np.zeros(0)
        self.seat.set_forces(None, self.lam)

    def advance(self, stones: Stones, near: np.ndarray, soft: np.ndarray, was_open: np.ndarray, h: float,
                stats: StormStats, t: float = 0.0) -> None:
        """Advance the stones in soft contact ``soft`` (of the ``near`` stones, whose contacts
        were open at the sub-step's start where ``was_open``) by ``h`` through the
        capacitance of their contact set, with unilateral release; update the seat's
        forces and the statistics (``t``: the sub-step's start, for the impacts' records)."""
        tris = stones.ctri[soft]
        key: tuple[Any, ...]
        cc = self.current
        if self.patch:
            resizes = stats.patch_resizes
            rad = self.patches.radii(stones, soft, tris, cc.stones if cc is not None else None,
                                     cc.Kdiag if cc is not None else None, self.lam, stats)
            if cc is not None and stats.patch_resizes > resizes:
                self._follow_radius(stones, soft, tris, rad, cc, stats)
            key = tuple(zip(soft.tolist(), tris.tolist(), rad.tolist(), stones.offset[soft].tolist()))
        else:
            rad = None
            key = tuple(zip(soft.tolist(), tris.tolist()))
        # (a contact that closed and opened again on its triangle between two sub-steps has a new
        # point and normal: they are in the key)
        key += (stones.cbary[soft].tobytes() + stones.cnormal[soft].tobytes(),)
        if cc is None or cc.key != key:
            cc = self.current = self.sets.build(soft, tris, stones.cbary[soft].copy(), stones.cnormal[soft].copy(), key,
                                                stones.radius[soft].copy(), stats, rad, stones.offset[soft].copy())
        exact = self.integrator.exact
        s = soft.size
        nk = cc.normals
        q, a, vq, gq, mq, always, acc = contact_prep(
            soft, stones.pos, stones.vel, stones.radius, stones.mass, GRAVITY, self.air.wind, self.air.drag_coef,
            nk, cc.X, cc.rest - stones.shift[soft], cc.Kdiag, self.contact.sticky, exact, self.time.rest_speed)
        if self.contact.sticky:
            group, wts = np.repeat(np.arange(s), 3), nk.ravel()
        else:
            group, wts = np.arange(s), np.ones(s)
        res = self.integrator.step(cc, q, vq, a, mq, gq, h, group, wts, always)
        open_before = was_open[np.searchsorted(near, soft)]
        # the onset speed of opening contacts, before contact_post moves the stones (for the validity records)
        vin = None if open_before.all() else self.limits.onset_speed(stones.vel, soft, nk)
        impacts, fmax, indent, n_active = contact_post(
            soft, stones.pos, stones.vel, stones.ctri, stones.hit, open_before, nk, acc,
            q, a, vq, gq, res.q, res.v, res.active, res.seat_force, res.peak_seat_force, res.peak_ubar,
            self.contact.sticky, exact, h, self.time.rest_speed)
        stats.impacts += int(impacts)
        self._observe_limits(cc, soft, stones.radius[soft], stones.mass[soft], ~open_before, vin, res, stats, t, h)
        self.lam = res.seat_force
        self.seat.set_forces(cc, res.seat_force, res.peak_seat_force)
        stats.max_contact_force = max(stats.max_contact_force, float(fmax))
        if n_active:  # (the kernel's indentation is the contact surface's; the stone's own adds its offset)
            if cc.offset.any():
                indent = self._deepest(cc, res)
            stats.max_indentation_m = max(stats.max_indentation_m, float(indent))
        stats.max_simultaneous_contacts = max(stats.max_simultaneous_contacts, int(n_active))

    def _follow_radius(self, stones: Stones, soft: np.ndarray, tris: np.ndarray, rad: np.ndarray, cc: ContactSet,
                       stats: StormStats) -> None:
        """Contacts of the current set whose patch was re-sized (:meth:`Patches.radii`): the
        sphere's offset follows the new radius, and the stone moves with its contact surface
        by the change (outward when the offset shrinks), so the spring's compression, and
        with it the force but for the new stiffness, is unchanged."""
        order = np.argsort(cc.stones)
        at = np.minimum(np.searchsorted(cc.stones, soft, sorter=order), cc.stones.size - 1)
        pos = order[at]
        known = cc.stones[pos] == soft
        known[known] = cc.patch_radius[pos[known]] != rad[known]
        if not known.any():
            return
        ids, t = soft[known], tris[known]
        o = self.sets.patch_offsets(ids, t, stones.cbary[ids], stones.cnormal[ids], rad[known], stones.radius[ids],
                                    stats)
        stones.pos[ids] += (stones.offset[ids] - o)[:, None] * stones.cnormal[ids]
        stones.offset[ids] = o

    def _deepest(self, cc: ContactSet, res: Any) -> float:
        """The deepest indentation of the stones' lowest points among the contacts that carried
        force within the sub-step: the contact surface's (``-peak_ubar``) plus the sphere's offset."""
        s = cc.stones.size
        if self.contact.sticky:
            touched = res.active.reshape(s, 3).all(axis=1) | (np.abs(res.peak_seat_force.reshape(s, 3)).sum(axis=1) > 0)
            ub = np.einsum("kd,kd->k", res.peak_ubar.reshape(s, 3), cc.normals)
        else:
            touched = res.active | (res.peak_seat_force != 0.0)
            ub = res.peak_ubar
        return float((cc.offset - ub)[touched].max())

    def engage(self, stones: Stones, opened: np.ndarray, h: float, stats: StormStats) -> float:
        """Patch contacts of stones ``opened`` in this sub-step's free phase: those on a stone's
        first touch (no engagement running), size each impact's patch
        (:meth:`Patches.first_touch`) and its sphere's offset ``o``
        (:meth:`ContactSets.patch_offsets`), kept in ``stones.offset`` for the engagement. A stone
        with ``o > 0`` is not in contact yet: its contact closes again and it flies on to its
        contact surface, the sphere of radius ``R - o``, ``o`` further along the normal,
        which the sub-step (shortened from ``h``, returned) ends at or before (gravity's
        pull along the normal counted, drag's slowing not; at least the shortest sub-step,
        as the time of impact), and in which the stone moves at most
        :data:`~hailstorm.runtime.compiled.narrow.DEAD_ZONE_REACH` radii (the narrow phase's
        bound in the dead zone). Point contacts (``patch = "none"``) have no offset: ``h``
        unchanged."""
        if not self.patch:
            return h
        opened = opened[stones.offset[opened] == 0.0]
        if opened.size == 0:
            return h
        tris = stones.ctri[opened]
        n = stones.cnormal[opened]
        vn = -np.einsum("kd,kd->k", stones.vel[opened], n)  # approach speed
        a = self.patches.first_touch(stones, opened, tris, self.sets.near, stats)
        o = self.sets.patch_offsets(opened, tris, stones.cbary[opened], n, a, stones.radius[opened], stats)
        stones.offset[opened] = o
        later = o > 0.0
        if later.any():
            ids = opened[later]
            stones.ctri[ids] = -1
            stones.gap[ids] = o[later]
            w0, an = vn[later], GRAVITY * np.clip(n[later, 2], 0.0, None)  # (drag only slows it: never past)
            den = w0 + np.sqrt(w0 * w0 + 2.0 * an * o[later])
            t = np.where(den > 0.0, 2.0 * o[later] / np.where(den > 0.0, den, 1.0), np.inf)
            speed = np.maximum(np.linalg.norm(stones.vel[ids], axis=1), 1e-12)
            t = np.minimum(t, DEAD_ZONE_REACH * stones.radius[ids] / speed)  # (as the narrow phase's)
            h = min(h, max(float(t.min()), self.time.min_substep))
        return h

    def _observe_limits(self, cc: ContactSet, soft: np.ndarray, radius: np.ndarray, mass: np.ndarray,
                        opening: np.ndarray, vin: np.ndarray | None, res: Any, stats: StormStats, t: float,
                        h: float) -> None:
        """Hand the sub-step's per-contact peaks to the validity measures (:class:`ImpactLimits`),
        with the touched rule of :func:`hailstorm.runtime.compiled.contact_post`."""
        stats.validity = self.limits
        ids = soft.tolist()
        if not self.limits.watching(ids, vin is not None):
            return
        s = soft.size
        if self.contact.sticky:
            act = res.active.reshape(s, 3).all(axis=1)
            f = np.maximum(np.linalg.norm(res.seat_force.reshape(s, 3), axis=1),
                           np.linalg.norm(res.peak_seat_force.reshape(s, 3), axis=1))
            touched = (act | (np.linalg.norm(res.peak_seat_force.reshape(s, 3), axis=1) > 0.0)).tolist()
            indent = (cc.offset - np.einsum("kd,kd->k", res.peak_ubar.reshape(s, 3), cc.normals)).tolist()
            force = f.tolist()
        else:
            act, seat, peak = res.active.tolist(), res.seat_force.tolist(), res.peak_seat_force.tolist()
            touched = [a or p != 0.0 for a, p in zip(act, peak)]
            indent = (cc.offset - res.peak_ubar).tolist()
            force = [max(abs(f), abs(p)) for f, p in zip(seat, peak)]
        self.limits.observe(ids, radius.tolist(), mass.tolist(), cc.tris.tolist(), cc.bary.tolist(), opening.tolist(),
                            None if vin is None else vin.tolist(), touched, indent, force, t, h)

    def forces(self, ctri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Stone ids in soft contact and the forces they apply to the seat, (s,), (s, 3)
        (``ctri``: the stones' contact triangles, -1 where released)."""
        cc = self.current
        if cc is None or self.lam.size == 0:
            return np.zeros(0, dtype=np.intp), np.zeros((0, 3))
        f = self.lam.reshape(-1, 3) if self.contact.sticky else self.lam[:, None] * cc.normals
        keep = ctri[cc.stones] >= 0
        return cc.stones[keep], f[keep]

    def warm_up(self, stones: Stones) -> None:
        """Load (or compile) the contact step's kernels with the storm loop's argument types."""
        none = np.zeros(0, dtype=np.intp)
        e3, e = self._no_e3, self._no_forces
        b = np.zeros(0, dtype=bool)
        q, a, vq, gq, _, _, acc = contact_prep(none, stones.pos, stones.vel, stones.radius, stones.mass, GRAVITY,
                                               self.air.wind, self.air.drag_coef, e3, e3, e, e, self.contact.sticky, True,
                                               1.0)
        contact_post(none, stones.pos, stones.vel, stones.ctri, stones.hit, b, e3, acc, q, a, vq, gq, e, e, b, e, e,
                     e, self.contact.sticky, True, 0.0, 1.0)
