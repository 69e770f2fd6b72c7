"""Refuse a foam whose energy is non-convex or whose tangent loses definiteness in a strain range.

:func:`check_stability` walks a grid of principal nominal strains ``e_a = l_a - 1`` in
``[min, max]^3`` (with the uniaxial, equibiaxial and hydrostatic paths on a finer line) and
checks at every point, in this order:

1. *convexity of the energy in the principal stretches*: the Hessian ``d^2 W / dl_a dl_b``
   positive definite (closed form);
2. *the Baker-Ericksen inequalities*: ``(tau_a - tau_b) (l_a - l_b) > 0`` (the greater principal
   stress along the greater stretch);
3. *strong ellipticity of the tangent*: the acoustic tensor ``Q_ik(n) = A_ijkl n_j n_l`` of the
   first Piola tangent positive definite for 26 directions ``n`` (cube faces, edges and corners;
   :func:`~hailstorm.precompute.foam.constitutive.piola_tangent`).

The first failure raises :class:`~hailstorm.precompute.foam.material.FoamStabilityError` naming
the test and the principal strains.
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np

__all__ = ["check_stability", "principal_hessian"]

#: grid points per principal strain, and per path
GRID, PATH = 9, 61
#: relative margin below which an eigenvalue counts as lost (round-off of the closed forms)
TOL = 1e-10


def principal_hessian(foam: Any, lam: np.ndarray) -> np.ndarray:
    """``d^2 W / dl_a dl_b`` at principal stretches ``lam`` (..., 3) -> (..., 3, 3) [Pa]."""
    lam = np.asarray(lam, dtype=np.float64)
    J = lam.prod(axis=-1)
    out = np.zeros(lam.shape + (3,))
    eye = np.eye(3)
    for m, a, b in zip(foam.mu, foam.alpha, foam.beta):
        Jab = J ** (-a * b)
        diag = (a - 1.0) * lam ** (a - 2.0) + Jab[..., None] / lam**2
        out += 2.0 * m / a * (diag[..., None] * eye + (a * b * Jab)[..., None, None] / (lam[..., :, None] * lam[..., None, :]))
    return out


def _directions() -> np.ndarray:
    n = np.array([v for v in itertools.product((-1, 0, 1), repeat=3) if any(v)], dtype=np.float64)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _points(lo: float, hi: float) -> np.ndarray:
    """Principal strains to check: the grid and the three paths (N, 3)."""
    e = np.linspace(lo, hi, GRID)
    grid = np.array(list(itertools.product(e, e, e)))
    s = np.linspace(lo, hi, PATH)
    z = np.zeros_like(s)
    paths = [np.stack([s, z, z], 1), np.stack([s, s, z], 1), np.stack([s, s, s], 1)]
    return np.concatenate([grid] + paths)


def _fail(what: str, e: np.ndarray, detail: str) -> None:
    from hailstorm.precompute.foam.ogden import FoamStabilityError

    strains = ", ".join(f"{x:+.3g}" for x in e)
    raise FoamStabilityError(f"foam refused: {what} fails at principal strains ({strains}) ({detail})")


def check_stability(foam: Any, lo: float, hi: float) -> None:
    """Raise :class:`~hailstorm.precompute.foam.material.FoamStabilityError` where the foam's energy is
    non-convex in the principal stretches, breaks Baker-Ericksen, or its tangent is not strongly
    elliptic, at principal nominal strains in ``[lo, hi]`` (module notes); return None otherwise."""
    from hailstorm.precompute.foam.constitutive import piola_tangent

    e = _points(lo, hi)
    lam = 1.0 + e
    scale = float(sum(abs(m) for m in foam.mu))
    Hs = principal_hessian(foam, lam)
    ev = np.linalg.eigvalsh(Hs)[:, 0]
    bad = np.flatnonzero(~(ev > TOL * scale))
    if bad.size:
        k = bad[np.argmin(np.abs(e[bad]).max(axis=1))]
        _fail("convexity of the energy in the principal stretches", e[k], f"least Hessian eigenvalue {ev[k]:.3g} Pa")
    tau = foam.kirchhoff(lam[:, 0], lam[:, 1], lam[:, 2])
    for a, b in ((0, 1), (0, 2), (1, 2)):
        dl = lam[:, a] - lam[:, b]
        ok = (np.abs(dl) < 1e-12) | ((tau[:, a] - tau[:, b]) * dl > -TOL * scale * np.abs(dl))
        bad = np.flatnonzero(~ok)
        if bad.size:
            k = bad[np.argmin(np.abs(e[bad]).max(axis=1))]
            _fail("the Baker-Ericksen inequality", e[k], f"tau_{a + 1} - tau_{b + 1} = {tau[k, a] - tau[k, b]:.3g} Pa")
    F = np.zeros((lam.shape[0], 3, 3))
    F[:, [0, 1, 2], [0, 1, 2]] = lam
    basis = np.zeros((9, 3, 3))
    basis[np.arange(9), np.arange(9) // 3, np.arange(9) % 3] = 1.0
    dP = piola_tangent(foam, F, basis[:, None].repeat(lam.shape[0], axis=1))  # (9, N, 3, 3): dP[E_kl]
    A = np.einsum("klmij->mijkl", dP.reshape(3, 3, lam.shape[0], 3, 3))  # A[m, i, j, k, l] = dP_ij / dF_kl
    n = _directions()
    Qac = np.einsum("mijkl,dj,dl->mdik", A, n, n)
    least = np.linalg.eigvalsh(Qac)[..., 0].min(axis=1)
    bad = np.flatnonzero(~(least > TOL * scale))
    if bad.size:
        k = bad[np.argmin(np.abs(e[bad]).max(axis=1))]
        _fail("strong ellipticity of the tangent", e[k], f"least acoustic eigenvalue {least[k]:.3g} Pa")
