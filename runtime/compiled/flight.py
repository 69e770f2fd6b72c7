"""Stones in flight: free flight with drag, the broad phase (conservative advancement)
and retirement.

Plain statements of the same rules (the tests' oracles): ``tests/reference/flight_ref.py``.
"""

from __future__ import annotations

import math

import numpy as np

from hailstorm.runtime.compiled.jit import kernel
from hailstorm.runtime.compiled.grid import SampleGrid, nearest_sample

__all__ = ["flight", "near_mask", "near_set", "retired"]


@kernel
def flight(idx, pos, vel, radius, h, g, wind, drag_coef):  # pragma: no cover (compiled)
    """Free flight of stones ``idx`` over ``h``, in place: gravity ``g`` [m/s^2] plus,
    if ``drag_coef > 0``, quadratic drag ``-(drag_coef / r) |v - wind| (v - wind)``
    (``drag_coef = 3 C_d rho_air / (8 rho_ice)``), taken constant over the step as
    ``tests/reference/flight_ref.free_flight_ref`` does."""
    a = np.empty(3)
    for q in range(idx.size):
        i = idx[q]
        a[0] = 0.0; a[1] = 0.0; a[2] = -g
        if drag_coef > 0.0:
            w0 = vel[i, 0] - wind[0]; w1 = vel[i, 1] - wind[1]; w2 = vel[i, 2] - wind[2]
            c = drag_coef / radius[i] * math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
            a[0] -= c * w0; a[1] -= c * w1; a[2] -= c * w2
        for d in range(3):
            pos[i, d] += h * vel[i, d] + 0.5 * h * h * a[d]
            vel[i, d] += h * a[d]


@kernel
def drag_dot(i, vel, radius, nrm, g, wind, drag_coef):  # pragma: no cover (compiled)
    """``accel . nrm`` of stone i in flight (gravity + drag)."""
    a0 = 0.0; a1 = 0.0; a2 = -g
    if drag_coef > 0.0:
        w0 = vel[i, 0] - wind[0]; w1 = vel[i, 1] - wind[1]; w2 = vel[i, 2] - wind[2]
        c = drag_coef / radius[i] * math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        a0 -= c * w0; a1 -= c * w1; a2 -= c * w2
    return a0 * nrm[0] + a1 * nrm[1] + a2 * nrm[2]


@kernel
def near_mask(live, pos, vel, radius, ctri, budget, bud_u, U, dt, g, lo, hi, sr,
              glo, h, dims, start, items, spts):  # pragma: no cover (compiled)
    """:func:`near_set`'s kernel, its grid's arrays unpacked (``lo``, ``hi``: the seat's bounding
    box; ``sr``: the sample radius; ``glo`` ... ``spts``: :class:`SampleGrid`'s arrays)."""
    n = live.size
    near = np.zeros(n, np.bool_)
    for q in range(n):
        i = live[q]
        sp = math.sqrt(vel[i, 0] * vel[i, 0] + vel[i, 1] * vel[i, 1] + vel[i, 2] * vel[i, 2])
        travel = sp * dt + g * dt * dt + 1e-4
        inc = U - bud_u[i]
        if inc > 0.0:
            budget[i] -= inc
            bud_u[i] = U
        if ctri[i] >= 0:
            budget[i] = -np.inf
            near[q] = True
            continue
        if budget[i] <= travel:
            o2 = 0.0
            for d in range(3):
                o = max(max(lo[d] - pos[i, d], pos[i, d] - hi[d]), 0.0)
                o2 += o * o
            lb = math.sqrt(o2) - sr - radius[i] - U - 1e-4
            if lb <= travel:
                d0 = nearest_sample(pos[i], glo, h, dims, start, items, spts)
                lb = d0 - sr - radius[i] - U - 1e-4
            budget[i] = lb
            bud_u[i] = U
        if budget[i] <= travel:
            near[q] = True
        else:
            budget[i] -= travel
    return near


def near_set(grid: SampleGrid, sample_radius: float, bbox: tuple[np.ndarray, np.ndarray], live: np.ndarray,
             pos: np.ndarray, vel: np.ndarray, radius: np.ndarray, ctri: np.ndarray, budget: np.ndarray,
             bud_u: np.ndarray, U: float, dt: float, gravity: float) -> np.ndarray:
    """The storm's broad phase : mask of the ``live``
    stones that may touch the seat within ``dt``. Updates ``budget`` and ``bud_u``
    in place. Every stone carries a ``budget``, a lower bound of its distance to the
    deformed surface valid while ``|u| <= bud_u`` (when the bound ``U`` grows beyond
    it the budget shrinks by the difference); flying stones spend it by what they can
    travel in a step, and only when it runs out is the distance re-measured (the
    bounding box, else the nearest sample). Stones in contact are near."""
    return near_mask(live, pos, vel, radius, ctri, budget, bud_u, float(U), float(dt), float(gravity),
                     bbox[0], bbox[1], float(sample_radius), grid.lo, grid.h, grid.dims, grid.start,
                     grid.items, grid.points)


@kernel
def retired(live, pos, radius, lo, hi, margin):  # pragma: no cover (compiled)
    """Mask of the ``live`` stones that left the seat's region (compiled rule of
    ``Storm.step``): below the seat by ``margin``, or beyond its footprint grown by
    ``2 margin + r`` while below its top."""
    out = np.zeros(live.size, np.bool_)
    for q in range(live.size):
        i = live[q]
        r = radius[i]
        outside = False
        for d in range(2):
            if pos[i, d] < lo[d] - 2.0 * margin - r or pos[i, d] > hi[d] + 2.0 * margin + r:
                outside = True
        out[q] = pos[i, 2] < lo[2] - margin or (outside and pos[i, 2] < hi[2])
    return out
