"""Patch contacts in the storm: the radius of each contact's pressure disc, the per-stone
cache of its weights, and the normal stiffness of a patch or of a triangle.

The rules are in the module notes of :mod:`hailstorm.runtime.storm.driver` ("Patch
contacts"). :class:`Patches` holds what they need (the surface, the compliance, the
weights cache per stone); its inputs are the stones, the current contact set's
stones, stiffness and forces, and the statistics. The weights themselves are
:func:`hailstorm.runtime.compiled.patch_one` (the contact API's
:func:`hailstorm.runtime.contact.weights.patch_weights`, compiled); the sizing is one kernel
(:func:`hailstorm.runtime.compiled.patch_radii`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, cast

import numpy as np

from hailstorm.runtime.compiled import patch_compliance, patch_one, patch_radii
from hailstorm.runtime.compiled.sphere import impact_radius_of
from hailstorm.runtime.storm.hail import GRAVITY
from hailstorm.runtime.storm.recording import StormStats
from hailstorm.runtime.contact.weights import (PATCH_DROP, PATCH_FACING, contact_points, disc_table,
                                               triangle_index)

if TYPE_CHECKING:  # annotations only
    from hailstorm.runtime.storm.hail import Air
    from hailstorm.runtime.storm.scene_sections import ContactSettings, TimeSettings
    from hailstorm.runtime.storm.seat import SeatState
    from hailstorm.runtime.storm.stones import Stones
    from hailstorm.runtime.bundle.compliance import ElasticSource
    from hailstorm.runtime.contact.near_field import NearField

__all__ = ["Patches", "peak_radius"]

#: a stone's cached weights: (triangle, its point's key (:func:`_point`), radius, vertices, weights)
_Cached = tuple[int, bytes, float, np.ndarray, np.ndarray]


def _point(bary: np.ndarray, normal: np.ndarray) -> bytes:
    """What identifies a contact's point on its triangle in the caches: its barycentric
    coordinates and its normal (which changes only with them, where the contact opens or moves)."""
    return bary.tobytes() + normal.tobytes()


class Patches:
    """Patch radii, weights (cached per stone) and stiffness of a storm's contacts.

    Parameters
    ----------
    gf : ElasticSource
        The bundle: surface, material (``young``, ``poisson``).
    contact : ContactSettings
        ``mode``, ``patch``, ``patch_min_radius``, ``patch_tolerance``.
    time : TimeSettings
        ``rest_speed``.
    seat : SeatState
        D and its columns (read only).
    normals : (m, 3) ndarray
        Outward unit normals of the triangles.
    soft : (m,) bool ndarray
        Triangles that deform under a contact.
    air : Air
    """

    def __init__(self, gf: ElasticSource, contact: ContactSettings, time: TimeSettings, seat: SeatState, normals: np.ndarray, soft: np.ndarray,
                 air: Air) -> None:
        self.triangles = np.asarray(gf.triangles)
        self.X = np.asarray(gf.vertices, dtype=np.float64)
        self.normals = normals
        self.soft = soft
        self.seat = seat
        self.air = air
        self.contact = contact
        self.time = time
        self.e_star = float(gf.young) / (1.0 - float(gf.poisson) ** 2)
        self.enabled = contact.patch != "none"
        if self.enabled:
            self._pidx = triangle_index(gf).arrays
            self._disc = disc_table("hertz")
        self._cache: dict[int, _Cached] = {}
        self._near: dict[int, tuple[tuple[int, bytes, float], np.ndarray]] = {}
        self.gf = gf
        self._k_tri: np.ndarray | None = None
        self._none = np.zeros(0, dtype=np.int64)
        self._no_forces = np.zeros(0)

    def forget(self, ids: list[int]) -> None:
        """Stones ``ids`` are gone: drop their cached weights."""
        for j in ids:
            self._cache.pop(j, None)
            self._near.pop(j, None)

    @property
    def k_tri(self) -> np.ndarray:
        """Normal contact stiffness at the centroid of every triangle, [N/m] (0: hard), computed on first use."""
        if self._k_tri is None:
            self._k_tri = self.all_triangle_stiffness()
        return self._k_tri

    def radii(self, stones: Stones, ids: np.ndarray, tris: np.ndarray, cc_stones: np.ndarray | None,
              cc_kdiag: np.ndarray | None, lam: np.ndarray, stats: StormStats) -> np.ndarray:
        """Patch radius of each soft contact ``ids`` on triangles ``tris`` (updated in ``stones.crad``).

        The radius is the sphere's impact patch (:func:`hailstorm.runtime.contact.weights.impact_radius`;
        Hertz's radius for ``a << R``) of the contact's *peak* force, estimated
        from its current state as a linear oscillator about its static
        equilibrium: ``F_peak = F_eq + sqrt((F - F_eq)^2 + k m v_n^2)``
        (``F``: the previous sub-step's force on that contact, ``lam``, ``F_eq``: the
        stone's weight along the normal, ``k``: its stiffness, the diagonal of
        the current capacitance ``cc_kdiag`` of the set of ``cc_stones``, or the point
        stiffness of the triangle for a contact that just opened, whose ``F = 0``: the
        impact's expected peak). The estimate is (nearly) constant over one impact and
        tends to the resting force afterwards, so the patch is sized for the deepest
        dent of the impact and is not re-weighted while the force rises and
        falls. A moving contact keeps its radius until the target exceeds
        ``a (1 + tol)`` (``tol = patch_tolerance``; a falling target never shrinks it
        mid-impact); a resting one is re-sized to its target, up or down, once it is
        ``REST_TOLERANCE`` (1 %) off. A contact that opens in an engagement sized at
        its stone's first touch (:meth:`first_touch`; ``stones.offset > 0``) keeps that
        radius. One kernel
        (:func:`hailstorm.runtime.compiled.patch_radii`); the new contacts' weights at
        their first radius go to the weights cache.
        """
        if cc_stones is not None and cc_kdiag is not None and cc_stones.size and lam.size:
            cs, kd = cc_stones, cc_kdiag
        else:
            cs, kd, lam = self._none, self._no_forces, self._no_forces
        seat = self.seat
        # a stone in an engagement it was sized for (its first touch, :meth:`first_touch`) keeps
        # that radius when its contact (re)opens: the kernel sizes new contacts afresh
        if cs.size == ids.size and np.array_equal(cs, ids):  # the same set: no contact is new
            new = np.zeros(ids.size, dtype=bool)
        else:
            new = (stones.offset[ids] > 0.0) & (stones.crad[ids] > 0.0)
        if cs.size and new.any():
            known = set(cs.tolist())
            new &= np.fromiter((j not in known for j in ids.tolist()), dtype=bool, count=ids.size)
        kept = stones.crad[ids[new]].copy()
        a, resizes, a0, off, wv, ww = patch_radii(
            ids, tris, stones.mass, stones.radius, stones.vel, stones.cbary, stones.crad, stones.cnormal, GRAVITY,
            self.air.wind, self.air.drag_coef, cs, kd, lam, self.contact.sticky, self.k_tri, self.e_star,
            self.contact.patch_min_radius, self.contact.patch_tolerance, self.time.rest_speed, *self._disc, PATCH_FACING,
            PATCH_DROP, self._pidx, self.X, seat.D, seat.column_of)
        stats.patch_resizes += int(resizes)
        if new.any():
            a[new] = kept
            stones.crad[ids[new]] = kept
            a0[new] = 0.0
        for i in np.flatnonzero(a0 > 0.0).tolist():
            j = int(ids[i])
            self._cache[j] = (int(tris[i]), _point(stones.cbary[j], stones.cnormal[j]), float(a0[i]),
                              wv[off[i]:off[i + 1]], ww[off[i]:off[i + 1]])
            stats.patch_weights_computed += 1
        if a.size:
            stats.max_patch_radius_m = max(stats.max_patch_radius_m, float(a.max()))
        return a

    def first_touch(self, stones: Stones, ids: np.ndarray, tris: np.ndarray, near: NearField | None,
                    stats: StormStats) -> np.ndarray:
        """The patch radius of the impacts of stones ``ids`` that touch the seat on ``tris``
        now (updated in ``stones.crad``), before their contacts carry force.

        The sizing of a new contact (:meth:`radii`: the triangle's point stiffness, then
        the patch's own from D alone, ``a0``). With a near field, the radius then follows
        from the stiffness the contact set will have, ``k(a) = 1 / (b + c(a))``: ``c(a)`` the
        kernel's compliance of the contact's own disc, ``b = w^T D w - w^T H w`` the body's
        part (:meth:`NearField.blocks`), evaluated once, at ``a0``: the body's part is smooth
        at the contact and barely changes with the radius. The radius is the fixed point
        of ``a = a_i(F_eq + sqrt(F_eq^2 + k(a) m v_n^2))`` (:func:`peak_radius`), the
        expected peak force of a contact that just opened (``F_eq`` the weight along the
        normal), so that the radius and the sphere's offset of the impact follow from the
        stiffness its peak force sees.
        """
        a = self.radii(stones, ids, tris, None, None, self._no_forces, stats)
        if near is None or ids.size == 0:
            return a
        n = stones.cnormal[ids]
        vn = np.einsum("kd,kd->k", stones.vel[ids], n)
        m, R = stones.mass[ids], stones.radius[ids]
        f_eq = m * GRAVITY * np.clip(n[:, 2], 0.0, None)
        bary = stones.cbary[ids]
        X = contact_points(self.X, self.triangles, tris, bary)
        verts, w = self.weights(ids, tris, bary, a, n, stats)
        c = 1.0 / np.maximum(self.stiffness(verts, w, n), 1e-300)
        c = c + near.blocks(self.gf, a, verts, w, X, n, False)[:, 0, 0]
        disc = float(near.compliance(np.ones(1))[0][0])  # c(a) = disc / a
        body = c - disc / np.where(a > 0.0, a, np.inf)
        a = peak_radius(body, disc, a, f_eq, m * vn**2, R, self.e_star, self.contact.patch_min_radius)
        stones.crad[ids] = a
        if a.size:
            stats.max_patch_radius_m = max(stats.max_patch_radius_m, float(a.max()))
        return a

    def stiffness(self, verts: np.ndarray, w: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Normal stiffness ``1 / (g^T D g)`` of each patch contact alone (padded vertex
        lists and weights, :meth:`weights`), (s,) [N/m]."""
        k = np.zeros(verts.shape[0])
        for i in range(verts.shape[0]):
            c = patch_compliance(verts[i].astype(np.int64, copy=False), w[i], normals[i], self.seat.D,
                                 self.seat.column_of)
            k[i] = 1.0 / c if c > 0 else 0.0
        return k

    def weights(self, ids: np.ndarray, tris: np.ndarray, bary: np.ndarray, radius: np.ndarray,
                normals: np.ndarray, stats: StormStats) -> tuple[np.ndarray, np.ndarray]:
        """Padded (s, P) vertex lists and weights of patch contacts, cached per stone.

        A contact keeps its ``(triangle, beta)`` and normal while its stone stays over the
        triangle and its radius while the force stays within the tolerance, so
        the weights are reused until one of them changes.
        """
        out: list[tuple[np.ndarray, np.ndarray] | None] = [None] * ids.size
        todo = []
        for i, (j, t, a) in enumerate(zip(ids.tolist(), tris.tolist(), radius.tolist())):
            c = self._cache.get(j)
            if c is not None and c[0] == t and c[2] == a and c[1] == _point(bary[i], normals[i]):
                out[i] = (c[3], c[4])
            else:
                todo.append(i)
        stats.patch_weights_reused += ids.size - len(todo)
        if todo:
            stats.patch_weights_computed += len(todo)
            for i in todo:
                v, w_ = patch_one(int(tris[i]), bary[i], float(radius[i]), normals[i], 3.0, *self._disc,
                                  PATCH_FACING, PATCH_DROP, self._pidx, self.X)
                self._cache[int(ids[i])] = (int(tris[i]), _point(bary[i], normals[i]), float(radius[i]), v, w_)
                out[i] = (v, w_)
        done = cast(list[tuple[np.ndarray, np.ndarray]], out)  # every slot is filled above
        P = max(3, max((o[0].size for o in done), default=0))
        verts = np.empty((ids.size, P), dtype=np.intp)
        w = np.zeros((ids.size, P))
        for i, (v, wi) in enumerate(done):  # padding: weight-0 copies of the first vertex (weights._pad)
            verts[i, :v.size] = v
            verts[i, v.size:] = v[0]
            w[i, :v.size] = wi
        return verts, w

    def near_blocks(self, near: NearField, ids: np.ndarray, tris: np.ndarray, bary: np.ndarray, radius: np.ndarray,
                    verts: np.ndarray, w: np.ndarray, centres: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """The near-field blocks (s, p, p) of patch contacts (:meth:`NearField.blocks`), cached per
        stone with the same key as its weights (triangle, beta and normal, radius); the new ones in one call."""
        p = self.contact.contact_mode.dofs
        blocks = np.zeros((ids.size, p, p))
        keys = [(t, _point(bary[i], normals[i]), a) for i, (t, a) in enumerate(zip(tris.tolist(), radius.tolist()))]
        todo = []
        for i, j in enumerate(ids.tolist()):
            c = self._near.get(j)
            if c is not None and c[0] == keys[i]:
                blocks[i] = c[1]
            else:
                todo.append(i)
        if todo:
            new = near.blocks(self.gf, radius[todo], verts[todo], w[todo], centres[todo], normals[todo], self.contact.sticky)
            for i, b in zip(todo, new):
                self._near[int(ids[i])] = (keys[i], b)
                blocks[i] = b
        return blocks

    def triangle_stiffness(self, tris: np.ndarray) -> np.ndarray:
        """Normal contact stiffness at the centroid of triangles, [N/m].

        Used to size the sub-step *before* a contact opens (so the first
        impact step is already resolved). Hard triangles give 0. Computed for
        every soft triangle at once on first use (batched 9 x 9 blocks of D:
        one gather instead of one per triangle), then looked up.
        """
        tris = np.asarray(tris, dtype=np.intp)
        return np.where(tris >= 0, self.k_tri[tris], 0.0)

    def warm_up(self, t: int, w: np.ndarray, n: np.ndarray, stones: Stones) -> None:
        """Load (or compile) the kernels with the storm loop's argument types."""
        verts = self.triangles[[t]].astype(np.int64)
        patch_compliance(verts[0], w[0], n[0], self.seat.D, self.seat.column_of)
        if self.enabled:
            patch_one(t, w[0], self.contact.patch_min_radius, n[0], 3.0, *self._disc, PATCH_FACING, PATCH_DROP,
                      self._pidx, self.X)
            self.radii(stones, self._none.astype(np.intp), self._none.astype(np.intp), None, None,
                       self._no_forces, StormStats())

    def all_triangle_stiffness(self, chunk: int = 4096) -> np.ndarray:
        """``1 / (b^T D_tt b)`` per soft triangle, ``b = (1/3, 1/3, 1/3) kron n`` (0 elsewhere)."""
        tri = np.asarray(self.triangles, dtype=np.intp)
        out = np.zeros(tri.shape[0])
        soft = np.flatnonzero(self.soft)
        col_of = self.seat.column_of
        third = np.full(3, 1.0 / 3.0)
        for s0 in range(0, soft.size, chunk):
            t = soft[s0:s0 + chunk]
            V = tri[t]
            cb = col_of[V]
            rows = (3 * V[:, :, None] + np.arange(3)).reshape(-1, 9)
            cols = (3 * np.maximum(cb, 0)[:, :, None] + np.arange(3)).reshape(-1, 9)
            # (T, 9, 9) blocks, each column-major like gf.compliance's (same gemv sums)
            blk = np.ascontiguousarray(self.seat.entries_at(rows[:, None, :], cols[:, :, None]))  # (T, col, row)
            blk[np.repeat(cb < 0, 3, axis=1)] = 0.0  # clamped columns
            blk = blk.transpose(0, 2, 1)
            Bn = (third[None, :, None] * self.normals[t][:, None, :]).reshape(-1, 9)  # kron(1/3, n)
            w = np.matmul(np.matmul(Bn[:, None, :], blk), Bn[:, :, None])[:, 0, 0]
            out[t] = np.where(w > 0, 1.0 / np.where(w > 0, w, 1.0), 0.0)
        return out


def peak_radius(body: np.ndarray, disc: float, start: np.ndarray, f_eq: np.ndarray, mv2: np.ndarray, stone_radius: np.ndarray,
                e_star: float, a_min: float, rtol: float = 1e-12, max_iter: int = 100) -> np.ndarray:
    """The patch radius of an impact's expected peak force, with the near field: the fixed point of
    ``a = clip(a_i(F(a)), a_min, R)``.

    ``F(a) = F_eq + sqrt(F_eq^2 + k(a) m v_n^2)`` is the peak force of a linear oscillator of
    stiffness ``k(a) = 1 / (b + d / a)`` that meets the surface at the normal speed ``v_n``
    (``b`` the body's compliance beyond the kernel's, ``d / a`` the kernel's compliance of the
    Hertz disc, ``3 / (5 a E*)`` for the half-space,
    :func:`hailstorm.runtime.contact.near_field.halfspace_patch_compliance`),
    and ``a_i(F)`` the sphere's impact patch (:func:`hailstorm.runtime.contact.weights.impact_radius`:
    the disc whose linear law meets the sphere's peak force with the sphere's work; Hertz's
    ``(3 F R / (4 E*))^(1/3)`` for ``a << R``), so the fixed point's linear oscillator has the
    sphere's own peak force and depth on a half-space.
    The map contracts by about 1/6 per step (``a ~ F^(1/3)``, ``F ~ k^(1/2)``, ``k ~ a``), so
    plain iteration from ``start`` converges in a few steps. Scalar work per stone (an impact
    opens one or two contacts at a time): plain floats.

    Parameters
    ----------
    body : (s,) ndarray
        ``b`` [m/N] (may be negative: a body stiffer than the half-space; the total compliance
        is floored at 1e-300).
    disc : float
        ``d`` [m^2/N]: the kernel's compliance of a disc of radius 1 m.
    start : (s,) ndarray
        First radii [m] (> 0 where the result is wanted; 0 stays 0, a point contact).
    f_eq, mv2 : (s,) ndarray
        The weight along the normal [N] and ``m v_n^2`` [J x 2].
    stone_radius : (s,) ndarray
        ``R`` [m], the ceiling.
    e_star : float
        ``E / (1 - nu^2)`` [Pa] of Hertz's radius.
    a_min : float
        The floor [m].

    Returns
    -------
    (s,) ndarray
    """
    out = np.array(start, dtype=np.float64, copy=True)
    for i, (a, b, fe, mv, R) in enumerate(zip(out.tolist(), np.asarray(body).tolist(), np.asarray(f_eq).tolist(),
                                             np.asarray(mv2).tolist(), np.asarray(stone_radius).tolist())):
        if not a > 0.0:
            continue
        for _ in range(max_iter):
            k = 1.0 / max(b + disc / a, 1e-300)
            F = fe + math.sqrt(fe * fe + k * mv)
            a_new = max(min(impact_radius_of(F, R, e_star), R), a_min)
            done = abs(a_new - a) <= rtol * a
            a = a_new
            if done or not a > 0.0:
                break
        out[i] = a
    return out
