"""The near field of a pad on its rigid base: the layer's kernel at the contact's scale.

Part of the contact core (:mod:`hailstorm.runtime.contact`). The half-space near
field (:mod:`hailstorm.runtime.contact.near_field`) counts on ``D - H`` being smooth
at the mesh's scale. On a pad a dozen millimetres thick on a rigid base it is
smooth only at the pad's scale: the body's response is the half-space's plus the
layer's regular part ``G_reg(r) = (1 / (E h)) g(r / h)`` (the base's reflection,
negative: the layer is stiffer), which varies over a thickness ``h``, two 6 mm
elements. The hat loads of D sample it coarsely, so for a contact as wide as the pad
``w^T D w`` misses a share of it that the half-space's subtraction does not restore:
the layer kernel adds it back,

    ``T(w) = (1 / (E h)) [ <p, g p>  -  sum_ij w_i w_j int phi_j / a_j g(|x_i - y| / h) ]``,

the regular part's compliance of the contact's own Hertz disc ``p`` (:meth:`LayerKernel.disc`)
minus the same part on the patch's hat loads as D answers them (nodal value at ``x_i``
of vertex ``j``'s hat traction; :func:`hailstorm.runtime.compiled.near_field.layer_term`).
With it the model is ``W = w^T D w - w^T H w + c(a) + e(w) + T(w)``: the layer's own
kernel, ``H + G_reg``, is subtracted on the hat loads and added at the contact's scale.

* ``g`` is one curve per Poisson ratio (dimensional analysis: a point force ``P`` on a layer
  of thickness ``h`` bonded to a rigid base gives ``u_z = P / (E h) f(r / h)``): the axisymmetric
  solve of :mod:`hailstorm.runtime.contact.layer_solve` minus the half-space's
  ``(1 - nu^2) / (pi rho)``; smooth at 0, where the finite elements cannot carry the point
  force, it is continued by an even quartic in ``rho``. Solved once per machine (about 2 s,
  then read from hailstorm's cache directory, :func:`layer_kernel`), with the disc's share
  tabulated against ``a / h``.
* ``h`` is the local thickness under the patch (:class:`hailstorm.runtime.bundle.thickness.PadThickness`,
  a ray cast along the inward normal; the weights' mean over the patch). Where the ray
  meets nothing (an open surface) the term is 0, the half-space's model.
* Normal only: the tangential part keeps the half-space's (a layer's tangential kernel
  needs the non-axisymmetric problem; it is not built).
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import math
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from hailstorm.runtime.bundle.thickness import PadThickness
from hailstorm.runtime.compiled.near_field import layer_sum, layer_term
from hailstorm.runtime.contact.layer_solve import DUNAVANT6, DUNAVANT6_W, LAYER_MESH, layer_point_response

_log = logging.getLogger(__name__)

__all__ = ["DISC_MAX", "DISC_STEP", "LayerKernel", "LayerSurface", "hat_quadrature", "layer_correction", "layer_kernel",
           "layer_surface"]

#: the table's spacing in thicknesses, and where the finite elements' ``g`` is read from
#: (closer to the point force, within about 25 cells, the mesh's own error shows; the even
#: quartic ``c0 + c2 rho^2 + c4 rho^4`` fitted over this range continues it to 0, within 6e-5)
TABLE_STEP = 0.002
FIT_RANGE = (0.2, 0.6)

#: the disc's table: ``alpha = a / h`` from 0 to DISC_MAX in steps of DISC_STEP (wider discs are
#: integrated when asked for)
DISC_STEP, DISC_MAX = 0.01, 4.0


def _disc_points(points: int = 10, angles: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A unit Hertz disc as quadrature points and masses (summing to 1): Gauss-Jacobi in
    ``s = r^2`` (weight ``sqrt(1 - s)``, exact for the Hertz profile) times the trapezoidal rule in angle."""
    from scipy.special import roots_jacobi

    t, wt = roots_jacobi(points, 0.5, 0.0)
    s = 0.5 * (t + 1.0)
    w_s = wt / (2.0 * math.sqrt(2.0))  # int_0^1 sqrt(1 - s) f ds
    th = 2.0 * np.pi * np.arange(angles) / angles
    r = np.sqrt(s)
    xy = np.stack([np.outer(r, np.cos(th)).ravel(), np.outer(r, np.sin(th)).ravel()], axis=1)
    return xy, (3.0 / (2.0 * np.pi)) * 0.5 * np.repeat(w_s, angles) * (2.0 * np.pi / angles)


@dataclass(frozen=True)
class LayerKernel:
    """The regular part of a layer's point-force response, ``g(rho)`` (module notes).

    Attributes
    ----------
    poisson : float
    step : float
        Spacing of ``table`` in thicknesses.
    table : ndarray
        ``g(k step)`` [-]: ``E h u_z / P`` minus the half-space's; ``1/rho`` decay past its end.
    disc_table : ndarray
        :meth:`disc_quadrature` at ``alpha = k DISC_STEP`` up to :data:`DISC_MAX`.
    """

    poisson: float
    step: float
    table: np.ndarray
    disc_table: np.ndarray

    def __call__(self, rho: Any) -> np.ndarray:
        """``g`` at ``rho = r / h`` (the compiled kernel's rule)."""
        rho = np.asarray(rho, dtype=np.float64)
        n = self.table.size
        end = (n - 1) * self.step
        x = np.minimum(rho, end) / self.step
        m = np.minimum(x.astype(np.int64), n - 2)
        f = x - m
        inside = self.table[m] * (1.0 - f) + self.table[m + 1] * f
        return np.where(rho >= end, self.table[-1] * end / np.maximum(rho, end), inside)

    def disc_quadrature(self, alpha: Any) -> np.ndarray:
        """``<p, g p>`` of a unit Hertz disc of radius ``alpha`` thicknesses, ``p = 3/(2 pi alpha^2) sqrt(1 - r^2/alpha^2)``,
        integrated (:func:`_disc_points` on both points of the pair: ten radii and 24 angles; ``g``
        is smooth, so exact to about 1e-4, tested against a plain grid)."""
        xy, m = _disc_points()
        d = np.sqrt(((xy[:, None, :] - xy[None, :, :]) ** 2).sum(-1))
        alpha = np.asarray(alpha, dtype=np.float64)
        out = np.array([m @ self(a * d) @ m for a in alpha.ravel()])
        return out.reshape(alpha.shape)

    def disc(self, alpha: Any) -> np.ndarray:
        """:meth:`disc_quadrature`, read off :attr:`disc_table` (linear between its points, which
        moves it by under 1e-5 of its value; integrated beyond its end)."""
        alpha = np.asarray(alpha, dtype=np.float64)
        out = np.interp(alpha, np.arange(self.disc_table.size) * DISC_STEP, self.disc_table)
        wide = alpha > DISC_MAX
        if np.any(wide):
            out = np.where(wide, 0.0, out)
            out[wide] = self.disc_quadrature(alpha[wide])
        return out


#: what the cached curves depend on (a change of any of them is a new file name)
_SOLVE = {**LAYER_MESH, "fit": FIT_RANGE, "step": TABLE_STEP,
          "disc": (DISC_STEP, DISC_MAX), "version": 1}


def _cache_path(poisson: float) -> Path:
    """The kernel's file in hailstorm's cache directory (``layer_kernel/<key>.npz``)."""
    from hailstorm.runtime.bundle.stamps import default_cache_dir

    key = hashlib.sha256(json.dumps({"poisson": repr(float(poisson)), **_SOLVE}, sort_keys=True).encode()).hexdigest()
    return default_cache_dir() / "layer_kernel" / f"{key[:16]}.npz"


def _read_cached(path: Path, poisson: float) -> LayerKernel | None:
    try:
        with np.load(path) as f:
            table, discs, nu = np.array(f["table"], dtype=np.float64), np.array(f["disc"], dtype=np.float64), float(f["poisson"])
    except (OSError, KeyError, ValueError):
        return None
    n_disc = int(round(DISC_MAX / DISC_STEP)) + 1
    if nu != float(poisson) or discs.shape != (n_disc,) or table.ndim != 1 or table.size < 2 \
            or not (np.all(np.isfinite(table)) and np.all(np.isfinite(discs))):
        return None
    table.flags.writeable = False
    discs.flags.writeable = False
    return LayerKernel(poisson=float(poisson), step=TABLE_STEP, table=table, disc_table=discs)


@functools.lru_cache(maxsize=4)
def layer_kernel(poisson: float) -> LayerKernel:
    """The layer kernel of a Poisson ratio: solved once per machine (about 2 s; module notes), then
    read from hailstorm's cache directory (``layer_kernel/``, written atomically; a cache that cannot
    be read or written is passed by) and kept per process.

    Raises
    ------
    ValueError
        ``poisson`` outside (-1, 0.5).
    """
    if not (-1.0 < poisson < 0.5):
        raise ValueError(f"layer_kernel needs -1 < poisson < 0.5, got {poisson!r}")
    path = _cache_path(poisson)
    cached = _read_cached(path, poisson)
    if cached is not None:
        return cached
    kern = _solve_kernel(float(poisson))
    try:
        from hailstorm.runtime.bundle.atomic import replacing

        path.parent.mkdir(parents=True, exist_ok=True)
        with replacing(path) as tmp:
            with open(tmp, "wb") as f:
                np.savez(f, table=kern.table, disc=kern.disc_table, poisson=np.float64(poisson))
    except OSError as exc:
        _log.debug("could not cache the layer kernel (%s)", exc)
    return kern


def _solve_kernel(poisson: float) -> LayerKernel:
    """:func:`layer_kernel`'s solve."""
    r, uz = layer_point_response(float(poisson))
    g = uz - (1.0 - poisson**2) / (np.pi * np.where(r > 0, r, np.inf))
    fit = (r >= FIT_RANGE[0]) & (r <= FIT_RANGE[1])
    even = np.polyfit(r[fit] ** 2, g[fit], 2)
    far = r >= FIT_RANGE[0]
    grid = np.arange(0.0, r[-1] * 0.8, TABLE_STEP)  # the far rim's own free edge left out
    table = np.interp(grid, r[far], g[far])
    near = grid < FIT_RANGE[0]
    table[near] = np.polyval(even, grid[near] ** 2)
    table.flags.writeable = False
    bare = LayerKernel(poisson=float(poisson), step=TABLE_STEP, table=table, disc_table=np.zeros(1))
    discs = bare.disc_quadrature(np.arange(0.0, DISC_MAX + DISC_STEP / 2, DISC_STEP))
    discs.flags.writeable = False
    return LayerKernel(poisson=float(poisson), step=TABLE_STEP, table=table, disc_table=discs)


def hat_quadrature(X: np.ndarray, T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Quadrature of each vertex's hat traction ``phi_j / a_j`` over its fan (degree 4 in the product).

    Returns
    -------
    ptr : (n + 1,) int64
        CSR: vertex ``j``'s points are ``pts[ptr[j]:ptr[j + 1]]``.
    pts : (q, 3) float64
    w : (q,) float64
        ``int phi_j / a_j f ~ sum w f(pts)``; each vertex's weights sum to 1 (``a_j`` is its fan's).
    """
    X = np.asarray(X, dtype=np.float64)
    T = np.asarray(T, dtype=np.int64)
    area = 0.5 * np.linalg.norm(np.cross(X[T[:, 1]] - X[T[:, 0]], X[T[:, 2]] - X[T[:, 0]]), axis=1)
    pts = np.einsum("qc,tcd->tqd", DUNAVANT6, X[T])  # (m, 6, 3)
    # corner c of triangle t owns its 6 points with weight rule_w * area * lambda_c
    own = np.concatenate([T[:, c] for c in range(3)])
    pw = np.concatenate([(DUNAVANT6_W * DUNAVANT6[:, c])[None, :] * area[:, None] for c in range(3)])  # (3m, 6)
    pp = np.concatenate([pts] * 3)
    order = np.argsort(own, kind="stable")
    n = X.shape[0]
    ptr = np.zeros(n + 1, dtype=np.int64)
    np.add.at(ptr, own + 1, 6)
    ptr = np.cumsum(ptr)
    w = pw[order].ravel()
    total = np.add.reduceat(w, ptr[:-1][np.diff(ptr) > 0]) if w.size else np.zeros(0)
    norm = np.ones(n)
    norm[np.diff(ptr) > 0] = total
    w = w / np.repeat(norm, np.diff(ptr))
    return ptr, np.ascontiguousarray(pp[order].reshape(-1, 3)), np.ascontiguousarray(w)


@dataclass
class LayerSurface:
    """A bundle's surface as the layer kernel reads it (:func:`layer_surface`).

    Attributes
    ----------
    X : (n, 3) float64
        Vertices.
    hat_ptr, hat_pts, hat_w : ndarray
        :func:`hat_quadrature`.
    thick : (n,) float64
        The local thickness under every contactable vertex (:class:`~hailstorm.runtime.bundle.thickness.PadThickness`),
        cast once (NaN elsewhere): what the patches read.
    """

    X: np.ndarray
    hat_ptr: np.ndarray
    hat_pts: np.ndarray
    hat_w: np.ndarray
    thick: np.ndarray


_SURFACES: "weakref.WeakKeyDictionary[Any, LayerSurface]" = weakref.WeakKeyDictionary()


def layer_surface(gf: Any) -> LayerSurface:
    """The :class:`LayerSurface` of a bundle, built once per bundle (``vertices``, outward ``triangles``)."""
    try:
        return _SURFACES[gf]
    except (KeyError, TypeError):
        pass
    X = np.ascontiguousarray(gf.vertices, dtype=np.float64)
    thick = np.full(X.shape[0], np.nan)
    soft = np.flatnonzero(np.asarray(gf.contactable))
    thick[soft] = PadThickness(gf)(soft)
    out = LayerSurface(X, *hat_quadrature(X, np.asarray(gf.triangles)), thick=thick)
    try:
        _SURFACES[gf] = out
    except TypeError:  # pragma: no cover - not weak-referenceable
        pass
    return out


def layer_correction(kernel: LayerKernel, surface: LayerSurface, young: float, radius: np.ndarray,
                     verts: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The layer's term ``T(w)`` of each patch contact [m/N], (s,) (module notes).

    Parameters
    ----------
    kernel : LayerKernel
    surface : LayerSurface
    young : float
        The pad's Young's modulus [Pa].
    radius : (s,) ndarray
        The contacts' Hertz radii ``a`` [m] (> 0).
    verts, weights : (s, P) ndarray
        Padded patch vertex lists and their consistent loads (weight 0: padding).
    """
    verts = np.ascontiguousarray(verts, dtype=np.int64)
    weights = np.ascontiguousarray(weights, dtype=np.float64)
    radius = np.ascontiguousarray(radius, dtype=np.float64)
    out = layer_term(verts, weights, radius, surface.thick, surface.X, surface.hat_ptr, surface.hat_pts,
                     surface.hat_w, kernel.table, kernel.step, kernel.disc_table, DISC_STEP, float(young))
    wide = np.flatnonzero(np.isnan(out))
    for k in wide:  # a disc wider than the table: integrated
        w = weights[k]
        h = float((w * surface.thick[verts[k]]).sum() / w.sum())
        S = layer_sum(verts[k:k + 1], weights[k:k + 1], surface.X, surface.hat_ptr, surface.hat_pts, surface.hat_w,
                      np.array([1.0 / h]), kernel.table, kernel.step)[0]
        out[k] = (float(kernel.disc(np.array([radius[k] / h]))[0]) * w.sum() ** 2 - S) / (young * h)
    return out
