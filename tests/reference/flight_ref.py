"""Free flight, the plain way: the oracle of :func:`hailstorm.runtime.compiled.flight`."""

from __future__ import annotations

import numpy as np

from hailstorm.runtime.storm.hail import GRAVITY


def free_flight_ref(
    pos: np.ndarray,
    vel: np.ndarray,
    dt: float,
    *,
    accel: np.ndarray | None = None,
    g: float = GRAVITY,
) -> tuple[np.ndarray, np.ndarray]:
    """Advance stones in free flight by ``dt``.

    Exact for gravity alone (constant acceleration); an extra acceleration
    (drag) is taken as constant over the step.

    Returns
    -------
    pos, vel : (k, 3) ndarray
        New arrays (inputs are not modified).
    """
    a = np.zeros_like(vel)
    a[:, 2] -= g
    if accel is not None:
        a = a + accel
    return pos + dt * vel + 0.5 * dt * dt * a, vel + dt * a


def drag_ref(vel: np.ndarray, radius: np.ndarray, wind: np.ndarray, drag_coef: float) -> np.ndarray:
    """Quadratic drag ``-(drag_coef / r) |v - wind| (v - wind)`` (0 when ``drag_coef`` is 0)."""
    w = vel - wind
    return -(drag_coef / radius)[:, None] * np.linalg.norm(w, axis=1, keepdims=True) * w


def near_set_ref(live: np.ndarray, pos: np.ndarray, vel: np.ndarray, radius: np.ndarray, ctri: np.ndarray,
                 budget: np.ndarray, bud_u: np.ndarray, U: float, dt: float, samples: np.ndarray,
                 sample_radius: float, bbox: tuple[np.ndarray, np.ndarray],
                 g: float = GRAVITY) -> np.ndarray:
    """The broad phase by conservative advancement, in numpy (the storm's rule; the
    oracle of :func:`hailstorm.runtime.compiled.near_set`): mask of the ``live`` stones
    that may touch the seat within ``dt``; ``budget``/``bud_u`` updated in place.

    Every stone carries a ``budget``, a lower bound of its distance to the deformed
    surface valid while ``|u| <= bud_u``; when the displacement bound ``U`` grows beyond
    it the budget shrinks by the difference. A flying stone spends it by what it can
    travel in the step; when it runs out the distance is re-measured: the bounding box
    bound, else the nearest sample (here by brute force over all samples). Stones in
    contact are near, and their budget is spent (-inf).
    """
    v = vel[live]
    travel = np.sqrt(np.einsum("ij,ij->i", v, v)) * dt + g * dt * dt + 1e-4
    inc = U - bud_u[live]
    if np.any(inc > 0):
        budget[live] -= np.clip(inc, 0.0, None)
        bud_u[live] = np.maximum(bud_u[live], U)
    b = budget[live]
    incontact = ctri[live] >= 0
    chk = (b <= travel) & ~incontact
    budget[live[incontact]] = -np.inf
    if chk.any():
        check = live[chk]
        p = pos[check]
        out = np.maximum(np.maximum(bbox[0] - p, p - bbox[1]), 0.0)
        lb = np.sqrt(np.einsum("ij,ij->i", out, out)) - sample_radius - radius[check] - U - 1e-4
        kd = lb <= travel[chk]
        if kd.any():
            d = np.linalg.norm(p[kd][:, None, :] - samples[None, :, :], axis=2).min(axis=1)
            lb[kd] = d - sample_radius - radius[check[kd]] - U - 1e-4
        budget[check] = lb
        bud_u[check] = U
        b = budget[live]
    near = (b <= travel) | incontact
    far = live[~near]
    budget[far] -= travel[~near]
    return near


def retired_ref(live: np.ndarray, pos: np.ndarray, radius: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                margin: float) -> np.ndarray:
    """Mask of the ``live`` stones that left the seat's region: below it by ``margin``, or
    beyond its footprint grown by ``2 margin + r`` while below its top."""
    p = pos[live]
    r = radius[live][:, None]
    return (p[:, 2] < lo[2] - margin) | np.any(
        (p[:, :2] < lo[:2] - 2 * margin - r) | (p[:, :2] > hi[:2] + 2 * margin + r), axis=1) & (p[:, 2] < hi[2])
