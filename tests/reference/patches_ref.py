"""The storm's patch sizing, the plain way: the oracle of :func:`hailstorm.runtime.compiled.patch_radii`.

A soft contact's patch radius is the sphere's impact patch of its *peak* force (the sphere's
contact radius times the patch's ratio, :func:`reference.sphere_ref.impact_patch_ref`), estimated
from its state as a linear oscillator about its static equilibrium:
``F_peak = F_eq + sqrt((F - F_eq)^2 + k m v_n^2)``. A known contact (in the previous
set) takes ``k`` from the set's capacitance and ``F`` from its force; a new one
takes the triangle's point stiffness, then once more the stiffness of that patch
alone (one fixed-point iteration). A contact keeps its radius until the target
leaves the band ``[a / (1 + tol), a (1 + tol)]``; it grows at once, and once the stone
rests it follows the target to ``REST_TOLERANCE`` (both ways).
"""

from __future__ import annotations

from typing import Callable

import numpy as np

from hailstorm.runtime.contact.sphere_patch import sphere_radius
from reference.sphere_ref import impact_patch_ref
from hailstorm.runtime.compiled.patches import REST_TOLERANCE


def patch_radii_ref(ids: np.ndarray, tris: np.ndarray, mass: np.ndarray, radius: np.ndarray, vel: np.ndarray,
                    accel: np.ndarray, crad: np.ndarray, cnormal: np.ndarray, cc_stones: np.ndarray | None,
                    K: np.ndarray | None, lam: np.ndarray, sticky: bool, k_tri: np.ndarray,
                    patch_stiffness: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray],
                    young: float, poisson: float, min_radius: float, tolerance: float,
                    rest_speed: float) -> tuple[np.ndarray, int]:
    """Radii (s,) of contacts ``ids`` on ``tris`` and the number of resized known contacts.

    ``accel``: (s, 3) non-contact acceleration of the stones; ``crad``: their current
    radii; ``cnormal``: the stones' contact normals; ``patch_stiffness(ids, tris, a, n)``: the
    normal stiffness of patches.
    """
    m, R = mass[ids], radius[ids]
    n = cnormal[ids]
    vn = np.einsum("ij,ij->i", vel[ids], n)
    gn = np.einsum("ij,ij->i", accel, n)
    f_eq = m * np.clip(-gn, 0.0, None)
    k = np.zeros(ids.size)
    f = np.zeros(ids.size)
    known = np.zeros(ids.size, dtype=bool)
    if cc_stones is not None and K is not None and cc_stones.size and lam.size:
        for i, j in enumerate(ids.tolist()):
            hit = np.flatnonzero(cc_stones == j)
            if hit.size:
                known[i], c = True, int(hit[0])
                if sticky:
                    k[i] = np.diag(K).reshape(-1, 3)[c] @ n[i] ** 2
                    f[i] = abs(lam.reshape(-1, 3)[c] @ n[i])
                else:
                    k[i], f[i] = np.diag(K)[c], abs(lam[c])

    def radius_for(kk: np.ndarray, sel: np.ndarray) -> np.ndarray:
        kk = np.clip(kk, 0.0, None)
        fp = f_eq[sel] + np.sqrt((f[sel] - f_eq[sel]) ** 2 + kk * m[sel] * vn[sel] ** 2)
        x = sphere_radius(fp, R[sel], young, poisson) / np.where(R[sel] > 0, R[sel], 1.0)
        a_t = R[sel] * np.array([impact_patch_ref(v) if v > 0 else 0.0 for v in x.tolist()])
        return np.maximum(np.clip(a_t, min_radius, R[sel]), min_radius)

    target = np.zeros(ids.size)
    if known.any():
        target[known] = radius_for(k[known], known)
    nw = ~known
    if nw.any():
        a0 = radius_for(k_tri[tris[nw]], nw)
        a1 = radius_for(patch_stiffness(ids[nw], tris[nw], a0, n[nw]), nw)
        target[nw] = np.where((a1 > a0 * (1.0 + tolerance)) | (a1 * (1.0 + tolerance) < a0), a1, a0)
    cur = np.where(known, crad[ids], 0.0)
    tol = 1.0 + tolerance
    amp = np.sqrt((f - f_eq) ** 2 / np.maximum(np.clip(k, 0.0, None) * m, 1e-300) + vn * vn)
    resting = known & (amp < rest_speed)
    resize = (cur <= 0.0) | (target > cur * tol) | (resting & (np.abs(target - cur) > REST_TOLERANCE * cur))
    return np.where(resize, target, cur), int((resize & (cur > 0.0)).sum())
