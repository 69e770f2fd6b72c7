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
* a step starts with a stone in contact (:data:`NOT_FREE`; nothing done).

The statistics it keeps are accumulated in place in one array, indexed by the ``ACC_*``
constants (the caller reads them into and back from its statistics).
"""

from __future__ import annotations

import numpy as np

from hailstorm.runtime.compiled.flight import flight, near_mask, retired
from hailstorm.runtime.compiled.integrators import substep_size
from hailstorm.runtime.compiled.jit import kernel
from hailstorm.runtime.compiled.narrow import free_phase, penetration

__all__ = ["ACC_FIELDS", "DONE", "NOT_FREE", "OPENED", "free_steps"]

#: :func:`free_steps` ran its steps (to ``n_max``, or to a step after which a frame is due)
DONE = 0
#: a contact opened in the last step's free phase: the step is half done
OPENED = 1
#: the next step starts with a stone in contact: nothing done
NOT_FREE = 2

#: the statistics :func:`free_steps` accumulates, in the order of its ``acc`` array
ACC_FIELDS: tuple[str, ...] = (
    "hailstones", "max_penetration_m", "max_penetration_contact_m", "max_penetration_contact_rel",
    "max_penetration_free_m", "pen_contact_sum", "pen_contact_n", "wall_contacts", "substeps", "retired",
    "fell_through", "steps",
)


@kernel
def free_steps(n_max, t, dt, i0, n_steps, next_frame, history, plan, plan_mass, j, n, live, near_out, gone, cr,
               pos, vel, radius, mass, alive, ctri, cbary, cnormal, gap, hit, near_tri, crad, offset, shift, budget,
               bud_u, u_bound, lo, hi, sample_radius, glo, gh, dims, start, items, spts, surf, toi, toi_tol, hmin,
               tri_normals, corner, sharp_edge, sharp_vertex, soft, fixed, rigid_weight, umax, use_u, D, fcols, fv, g,
               wind, drag_coef, restitution, margin, sizes, max_substeps, k_tri, approach_fraction, rest_speed,
               omega_dt, symplectic, cs_none, kd_none, sticky, e3_none, g3, acc):  # pragma: no cover (compiled)
    """Storm steps without soft contacts, from time ``t`` (step index ``i0`` of ``n_steps``).

    Parameters
    ----------
    n_max : int
        Steps to run at most.
    t, dt : float
        The first step's start and the step [s].
    next_frame : float
        The frame clock (:class:`hailstorm.runtime.storm.recording.Recorder`): the run stops
        after the step at whose end a frame is due.
    history : (n_steps, 3) ndarray
        The force history; each step's row ``(t, 0, 0)`` (no force) is written.
    plan, plan_mass : (p, 8), (p,) ndarray
        The spawn plan's rows ``(t, x, y, z, vx, vy, vz, r)`` and the stones' masses; ``j``
        the first row not spawned yet.
    n : int
        Stones so far; the stones' arrays (``pos`` ... ``bud_u``, :data:`hailstorm.runtime.storm.stones.FIELDS`)
        have room for every stone of the plan (new ones are written at ``n``, ``n + 1``, ...).
    live, near_out, gone : int ndarray
        Scratch of the stones' capacity: at return, the last step's live and near stones, and
        the ids of the stones retired (in order).
    cr : float ndarray
        Scratch of the stones' capacity (the near stones' contact radii).
    u_bound : float
        The seat's displacement bound of the broad phase (the previous step's, ``SeatState.umax_step``).
    lo, hi ... spts
        The broad phase's box and grid (:func:`hailstorm.runtime.compiled.flight.near_set`).
    surf ... restitution
        The narrow phase's arguments (:func:`hailstorm.runtime.compiled.narrow.free_phase`;
        the seat unloaded: ``umax`` 0, ``use_u`` false, ``fcols``, ``fv`` empty; ``g`` the
        gravity's magnitude).
    margin : float
        Retirement (:func:`hailstorm.runtime.compiled.flight.retired`).
    sizes ... g3
        The sub-step sizing of the adaptive integrators (``sizes``;
        :func:`hailstorm.runtime.compiled.integrators.substep_size` with no contact set; ``g3``
        the gravity vector), and the safety net of ``4 max_substeps`` sub-steps.
    acc : (len(ACC_FIELDS),) float ndarray
        The statistics, accumulated in place.

    Returns
    -------
    status : int
        :data:`DONE`, :data:`OPENED` or :data:`NOT_FREE`.
    steps : int
        Steps completed.
    t : float
        Time at the end of the last completed step (an :data:`OPENED` step's start).
    j, n : int
        The plan's next row and the stones' count.
    n_live, n_near, n_gone : int
        Entries of ``live``, ``near_out`` and ``gone``.
    h, t_left : float
        :data:`OPENED`: the half-done step's sub-step (after its free phase) and the time
        left of the step before it.
    n_sub : int
        :data:`OPENED`: the sub-steps of the step before the half-done one.
    """
    n_plan = plan.shape[0]
    n_gone = 0
    n_live = 0
    n_near = 0
    steps = 0
    while steps < n_max:
        te = t + dt
        # 1. spawn: each stone back along its path by its spawn time's lead over the step's start
        while j < n_plan and plan[j, 0] < te:
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
            acc[0] += 1.0
        n_live = 0
        for i in range(n):
            if alive[i]:
                if ctri[i] >= 0:
                    return NOT_FREE, steps, t, j, n, 0, 0, n_gone, 0.0, 0.0, 0
                live[n_live] = i
                n_live += 1
        lv = live[:n_live].copy()
        # 2. broad phase; the far stones fly
        m = near_mask(lv, pos, vel, radius, ctri, budget, bud_u, 1.5 * u_bound, dt, g, lo, hi, sample_radius, glo,
                      gh, dims, start, items, spts)
        n_near = 0
        for q in range(n_live):
            if m[q]:
                n_near += 1
        n_far = n_live - n_near
        near = np.empty(n_near, np.int64)
        far = np.empty(n_far, np.int64)
        a = 0
        b = 0
        for q in range(n_live):
            if m[q]:
                near[a] = lv[q]
                near_out[a] = lv[q]
                a += 1
            else:
                far[b] = lv[q]
                b += 1
        if n_far:
            flight(far, pos, vel, radius, dt, g, wind, drag_coef)
            for q in range(n_far):
                gap[far[q]] = np.inf
                offset[far[q]] = 0.0
        # 3. near stones: penetration statistics, then the sub-steps' free phase and flight
        if n_near:
            for q in range(n_near):
                cr[near[q]] = radius[near[q]] - offset[near[q]]  # (Stones.contact_radius)
            mp, mpc, mrc, spc, npc, mpf = penetration(near, dt, pos, vel, cr, ctri, surf, umax, use_u, D, fcols, fv)
            acc[1] = max(acc[1], mp)
            acc[2] = max(acc[2], mpc)
            acc[3] = max(acc[3], mrc)
            acc[4] = max(acc[4], mpf)
            acc[5] += spc
            acc[6] += npc
            t_left = dt
            n_sub = 0
            while t_left > 1e-12 * dt:
                if sizes:
                    h = substep_size(near, t_left, hmin, vel, radius, mass, pos, gap, near_tri, ctri, k_tri,
                                     approach_fraction, rest_speed, omega_dt, symplectic, cs_none, kd_none, sticky,
                                     e3_none, e3_none, kd_none, g3)
                else:
                    h = t_left
                if n_sub >= 4 * max_substeps:
                    h = t_left  # safety net: never stall
                h, walls = free_phase(near, h, toi, toi_tol, hmin, pos, vel, radius, offset, shift, ctri, cbary,
                                      cnormal, gap, near_tri, surf, tri_normals, corner, sharp_edge, sharp_vertex,
                                      soft, fixed, rigid_weight, umax, use_u, D, fcols, fv, g, wind, drag_coef,
                                      restitution)
                acc[7] += walls
                for q in range(n_near):
                    if ctri[near[q]] >= 0:
                        return OPENED, steps, t, j, n, n_live, n_near, n_gone, h, t_left, n_sub
                flight(near, pos, vel, radius, h, g, wind, drag_coef)
                acc[8] += 1.0
                t_left -= h
                n_sub += 1
        # 4. retirement
        out = retired(lv, pos, radius, lo, hi, margin)
        for q in range(n_live):
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
