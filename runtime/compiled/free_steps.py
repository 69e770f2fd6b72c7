"""Many storm steps in one call while no stone presses the seat: spawning, flight, the broad
and narrow phase, retirement.

A storm step without a soft contact (the seat unloaded, no stone pressing it) is a few small
compiled phases; called one by one from Python, the calls and the Python between them cost
more than the phases. :func:`free_steps` runs such steps back to back, exactly as
:meth:`hailstorm.runtime.storm.driver.Storm.step` does (the same kernels in the same order,
the same arithmetic: the storms' fingerprints are unchanged), until

* a stone's contact with the seat opens (the step is left half done, right after its free
  phase: the caller finishes it with the contact step, :data:`OPENED`);
* a frame is due after the step, or ``n_max`` steps are done (:data:`DONE`);
* a step starts with a stone in contact (:data:`NOT_FREE`; nothing done);
* with ``stop_near`` (a contact set the caller still holds, all its contacts released, which
  the caller's sub-step sizing reads), a stone is near the seat: the step is left after its
  broad phase and the far stones' flight (:data:`NEAR`). Without it, a held set (``held[0]``)
  is dropped where the caller's step drops it, at the first sub-step of near stones in
  which no contact opens: ``held[0]`` is set false and the caller releases its set.

Its arguments come in tuples (``stones``: the per-stone arrays in the order of
:data:`hailstorm.runtime.storm.stones.FIELDS`; ``broad``, ``narrow``, ``air``, ``sizing``: the
phases' constant arguments, see :func:`free_steps`). The statistics it keeps are
accumulated in place in one array, in the order of :data:`ACC_FIELDS`.
"""

from __future__ import annotations

import numpy as np

from hailstorm.runtime.compiled.flight import flight, near_mask, retired
from hailstorm.runtime.compiled.integrators import substep_size
from hailstorm.runtime.compiled.jit import kernel
from hailstorm.runtime.compiled.narrow import free_phase, penetration

__all__ = ["ACC_FIELDS", "DONE", "NEAR", "NOT_FREE", "OPENED", "free_steps", "free_substeps", "retire_left", "spawn_due"]

#: :func:`free_steps` ran its steps (to ``n_max``, or to a step after which a frame is due)
DONE = 0
#: a contact opened in the last step's free phase: the step is half done
OPENED = 1
#: the next step starts with a stone in contact: nothing done
NOT_FREE = 2
#: (``stop_near``) stones are near the seat: the step is left after its broad phase and far flight
NEAR = 3

#: the statistics :func:`free_steps` accumulates, in the order of its ``acc`` array
ACC_FIELDS: tuple[str, ...] = (
    "hailstones", "max_penetration_m", "max_penetration_contact_m", "max_penetration_contact_rel",
    "max_penetration_free_m", "pen_contact_sum", "pen_contact_n", "wall_contacts", "substeps", "retired",
    "fell_through", "steps",
)


@kernel
def spawn_due(t, te, plan, plan_mass, j, n, stones):  # pragma: no cover (compiled)
    """Add the plan's stones due before ``te`` (rows from ``j``) at rows ``n``, ``n + 1``, ... of
    ``stones``, each back along its path by its spawn time's lead over the step's start ``t``
    (as ``Storm.step`` and ``Stones.add`` do); returns the new ``j`` and ``n``."""
    pos, vel, radius, mass, alive, ctri, cbary, cnormal, gap, hit, near_tri, crad, offset, shift, budget, bud_u = stones
    while j < plan.shape[0] and plan[j, 0] < te:
        early = plan[j, 0] - t
        for d in range(3):
            pos[n, d] = plan[j, 1 + d] - early * plan[j, 4 + d]
            vel[n, d] = plan[j, 4 + d]
            cbary[n, d] = 0.0
            cnormal[n, d] = 0.0
        radius[n] = plan[j, 7]
        mass[n] = plan_mass[j]
        alive[n] = True
        ctri[n] = -1
        gap[n] = np.inf
        hit[n] = False
        near_tri[n] = -1
        crad[n] = 0.0
        offset[n] = 0.0
        shift[n] = 0.0
        budget[n] = 0.0
        bud_u[n] = 0.0
        n += 1
        j += 1
    return j, n


@kernel
def free_substeps(near, dt, stones, narrow, air, sizing, seat, acc):  # pragma: no cover (compiled)
    """The sub-steps of one step of the ``near`` stones without soft contacts (``Storm._substeps``):
    each the narrow phase's free part and free flight, until the step is done or a contact
    opens. Returns ``(opened, h, t_left, n_sub)``: an opened contact's sub-step, the time left
    of the step before it and the sub-steps before it."""
    pos, vel, radius, mass, alive, ctri, cbary, cnormal, gap, hit, near_tri, crad, offset, shift, budget, bud_u = stones
    surf, toi, toi_tol, hmin, tri_normals, corner, sharp_edge, sharp_vertex, soft, fixed, rigid_weight = narrow
    g, wind, drag_coef, restitution = air
    sizes, max_substeps, k_tri, approach_fraction, rest_speed, omega_dt, symplectic, cs_none, kd_none, sticky, \
        e3_none, g3 = sizing
    umax, use_u, D, fcols, fv = seat
    t_left = dt
    n_sub = 0
    while t_left > 1e-12 * dt:
        if sizes:
            h = substep_size(near, t_left, hmin, vel, radius, mass, pos, gap, near_tri, ctri, k_tri, approach_fraction,
                             rest_speed, omega_dt, symplectic, cs_none, kd_none, sticky, e3_none, e3_none, kd_none, g3)
        else:
            h = t_left
        if n_sub >= 4 * max_substeps:
            h = t_left  # safety net: never stall
        h, walls = free_phase(near, h, toi, toi_tol, hmin, pos, vel, radius, offset, shift, ctri, cbary, cnormal, gap,
                              near_tri, surf, tri_normals, corner, sharp_edge, sharp_vertex, soft, fixed, rigid_weight,
                              umax, use_u, D, fcols, fv, g, wind, drag_coef, restitution)
        acc[7] += walls
        for q in range(near.size):
            if ctri[near[q]] >= 0:
                return True, h, t_left, n_sub
        flight(near, pos, vel, radius, h, g, wind, drag_coef)
        acc[8] += 1.0
        t_left -= h
        n_sub += 1
    return False, 0.0, 0.0, n_sub


@kernel
def retire_left(lv, lo, hi, margin, stones, gone, n_gone, acc):  # pragma: no cover (compiled)
    """Retire the live stones ``lv`` that left the seat's region (``Collision.retired``, then
    ``Stones.retire``), their ids appended to ``gone`` from ``n_gone``; counts the retired and,
    of them, those below the seat inside its footprint that never touched it. Returns the new
    ``n_gone``."""
    pos, vel, radius, mass, alive, ctri, cbary, cnormal, gap, hit, near_tri, crad, offset, shift, budget, bud_u = stones
    out = retired(lv, pos, radius, lo, hi, margin)
    for q in range(lv.size):
        if out[q]:
            i = lv[q]
            below = pos[i, 2] < lo[2] and lo[0] <= pos[i, 0] <= hi[0] and lo[1] <= pos[i, 1] <= hi[1]
            if below and not hit[i]:
                acc[10] += 1.0
            alive[i] = False
            ctri[i] = -1
            offset[i] = 0.0
            gone[n_gone] = i
            n_gone += 1
            acc[9] += 1.0
    return n_gone


@kernel
def free_steps(n_max, t, dt, i0, n_steps, next_frame, history, plan, plan_mass, j, n, scratch, stones, u_bound, broad,
               narrow, air, margin, sizing, seat, stop_near, held, acc):  # pragma: no cover (compiled)
    """Storm steps without soft contacts, from time ``t`` (step index ``i0`` of ``n_steps``).

    Parameters
    ----------
    n_max : int
        Steps to run at most.
    t, dt : float
        The first step's start and the step [s].
    next_frame : float
        The frame clock (``Recorder``): the run stops after the step at whose end a frame is due.
    history : (n_steps, 3) ndarray
        The force history; each step's row ``(t, 0, 0)`` (no force) is written.
    plan, plan_mass : (p, 8), (p,) ndarray
        The spawn plan's rows ``(t, x, y, z, vx, vy, vz, r)`` and the stones' masses; ``j``
        the first row not spawned yet.
    n : int
        Stones so far; ``stones`` has room for every stone of the plan.
    scratch : tuple of 3 int ndarrays and a float ndarray, of the stones' capacity
        At return, the last step's live and near stones and the ids of the stones retired (in
        order); the near stones' contact radii.
    u_bound : float
        The seat's displacement bound of the broad phase (``SeatState.umax_step``).
    broad : tuple
        The broad phase's box and grid (``near_mask``'s ``lo, hi, sr, glo, h, dims, start, items, spts``).
    narrow, air, seat : tuple
        ``free_phase``'s ``surf, toi, toi_tol, hmin, tri_normals, corner, sharp_edge, sharp_vertex,
        soft, fixed, rigid_weight``; ``g, wind, drag_coef, restitution``; and ``umax, use_u, D,
        fcols, fv`` (the seat unloaded).
    margin : float
        Retirement's.
    sizing : tuple
        ``sizes, max_substeps, k_tri, approach_fraction, rest_speed, omega_dt, symplectic, cs, kd,
        sticky, e3, g3``: the adaptive integrators' ``substep_size`` with no contact set.
    stop_near : bool
        Leave the first step with near stones after its broad phase (:data:`NEAR`).
    held : (1,) bool ndarray
        The caller holds a released contact set; set false where its step would drop it.
    acc : (len(ACC_FIELDS),) float ndarray
        The statistics, accumulated in place.

    Returns
    -------
    status, steps, t, j, n, n_live, n_near, n_gone, h, t_left, n_sub
        :data:`DONE`, :data:`OPENED`, :data:`NOT_FREE` or :data:`NEAR`; the steps completed and the time
        at their end (an :data:`OPENED` step's start); the plan's next row, the stones'
        count; the entries of the scratch arrays; an :data:`OPENED` step's sub-step after its
        free phase, the time left of the step before it and its sub-steps before it.
    """
    live, near_out, gone, cr = scratch
    radius, ctri, offset = stones[2], stones[5], stones[12]
    lo, hi, sr, glo, gh, dims, start, items, spts = broad
    alive = stones[4]
    n_gone = np.int64(0)  # (not the literal 0: a literal argument is a second specialisation of retire_left)
    n_near = 0
    steps = 0
    # the live stones, in increasing order (as Stones.live): scanned once, then kept up to
    # date (spawned stones appended, retired ones dropped), so that a step costs what its
    # live stones do, not every stone the storm has had
    n_live = 0
    for i in range(n):
        if alive[i]:
            if ctri[i] >= 0:
                return NOT_FREE, steps, t, j, n, 0, 0, n_gone, 0.0, 0.0, 0
            live[n_live] = i
            n_live += 1
    while steps < n_max:
        j, n1 = spawn_due(t, t + dt, plan, plan_mass, j, n, stones)
        acc[0] += n1 - n
        for i in range(n, n1):
            live[n_live] = i
            n_live += 1
        n = n1
        lv = live[:n_live].copy()
        m = near_mask(lv, stones[0], stones[1], radius, ctri, stones[14], stones[15], 1.5 * u_bound, dt, air[0], lo, hi,
                      sr, glo, gh, dims, start, items, spts)
        near = lv[m]
        far = lv[~m]
        n_near = near.size
        near_out[:n_near] = near
        if far.size:
            flight(far, stones[0], stones[1], radius, dt, air[0], air[1], air[2])
            for q in range(far.size):
                stones[8][far[q]] = np.inf
                offset[far[q]] = 0.0
        if n_near and stop_near:
            return NEAR, steps, t, j, n, n_live, n_near, n_gone, 0.0, dt, 0
        if n_near:
            for q in range(n_near):
                cr[near[q]] = radius[near[q]] - offset[near[q]]  # (Stones.contact_radius)
            mp, mpc, mrc, spc, npc, mpf = penetration(near, dt, stones[0], stones[1], cr, ctri, narrow[0], seat[0],
                                                      seat[1], seat[2], seat[3], seat[4])
            acc[1] = max(acc[1], mp)
            acc[2] = max(acc[2], mpc)
            acc[3] = max(acc[3], mrc)
            acc[4] = max(acc[4], mpf)
            acc[5] += spc
            acc[6] += npc
            opened, h, t_left, n_sub = free_substeps(near, dt, stones, narrow, air, sizing, seat, acc)
            if held[0] and (not opened or n_sub > 0):  # (a sub-step without an opening: the set is dropped)
                held[0] = False
            if opened:
                return OPENED, steps, t, j, n, n_live, n_near, n_gone, h, t_left, n_sub
        n_gone0 = n_gone
        n_gone = retire_left(lv, lo, hi, margin, stones, gone, n_gone, acc)
        if n_gone > n_gone0:
            kept = 0
            for q in range(n_live):
                if alive[live[q]]:
                    live[kept] = live[q]
                    kept += 1
            n_live = kept
        u_bound = 0.0  # the seat stays unloaded (SeatState.end_step)
        t += dt
        acc[11] += 1.0
        i = i0 + steps
        history[i, 0] = t
        history[i, 1] = 0.0
        history[i, 2] = 0.0
        steps += 1
        if t >= next_frame - 1e-12 or i == n_steps - 1:
            break
    return DONE, steps, t, j, n, n_live, n_near, n_gone, 0.0, 0.0, 0
