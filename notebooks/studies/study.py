"""Speed against accuracy: what each precompute knob costs and what it buys.

Every knob of the offline stage (mesh size, element order, solver and its
tolerance, storage precision, which vertices get columns, a compressed D) is
scored as one point (cost, error) of a Pareto chart.

Quantity of interest
    The displacement of the top surface under fixed *distributed* loads: a
    uniform pressure over a disc (radius ~10 mm in plan) at a few fixed spots
    of the seat (:class:`Scenario`), read by interpolation at fixed probe
    points. A distributed load has a converged limit under refinement (a point
    load does not: its displacement grows without bound as h -> 0).
Error
    Relative error of the probe displacements against a :func:`reference`
    solution (fine P2, consistent P2 load, direct solve), the worst over load
    cases: ``max_c ||U_c - U_c^ref||_F / ||U_c^ref||_F``.
What is scored
    What a *user of the bundle* gets: the pressure is lumped to the surface
    corner vertices with P1 surface shape functions (f_i = int p phi_i dA),
    u = D f, and the probes are interpolated linearly on the surface
    triangles (:func:`bundle_qoi`). So even P2 bundles are scored through
    their corner-vertex D, as the runtime uses them.
Costs
    Precompute wall time (measured: meshing + ``build_bundle``; for derived
    points the post-processing is added), memory of D [MB], and optionally
    the per-step runtime cost of :func:`hailstorm.runtime.solve_contacts`, with a
    "direct FEM re-solved per step" anchor (one sparse factorization + solve
    of the full system at that mesh).

Everything is parameterised by a ``mesher`` (mesh size -> :class:`TetMesh`)
and a :class:`Scenario`, so the tests run it on :func:`hailstorm.precompute.box_mesh`.
:func:`run_study` is what the notebook calls; it caches its results (and the
reference) as files in ``cache_dir``.

Regenerate the figure::

    python -m studies.study --out notebooks/figures/speed_vs_accuracy.png
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Sequence

import numpy as np
import scipy.sparse as sp

from hailstorm.precompute.fem import (
    DEFAULT_POISSON,
    DEFAULT_YOUNG,
    clamp_dofs,
    elasticity_basis,
    free_dofs,
    stiffness_matrix,
    vertex_dofs,
)
from hailstorm.precompute.geometry import TetMesh, boundary_triangles, mesh_default_seat
from hailstorm.precompute.greens import compliance_matrix, factorize, solver_spec
from hailstorm.precompute.pipeline import build_bundle, default_cache_dir
from hailstorm.runtime.bundle.atomic import replacing, write_text_atomic

#: Bump when the meaning of cached study results changes.
STUDY_VERSION = 1

Mesher = Callable[[float], TetMesh]


# --------------------------------------------------------------------------
# scenario: loads and probes
# --------------------------------------------------------------------------
@dataclass(frozen=True)
class LoadCase:
    """A uniform pressure on the part of the top surface inside a plan disc.

    Attributes
    ----------
    center : (float, float)
        Disc centre in plan (x, y) [m].
    radius : float
        Disc radius in plan [m].
    pressure : float
        Pressure [Pa], acting along the inward surface normal.
    """

    center: tuple[float, float]
    radius: float = 0.01
    pressure: float = 1.0e4


@dataclass(frozen=True)
class Scenario:
    """Load cases and probe points defining the quantity of interest.

    Attributes
    ----------
    loads : tuple of LoadCase
        Each load case is solved separately.
    probes : tuple of (float, float)
        Plan (x, y) positions [m]; each is read on the upward-facing surface
        triangle above it.
    min_nz : float
        Only surface triangles whose outward normal has z-component above
        this carry load and probes (the "upper side" of the solid).
    """

    loads: tuple[LoadCase, ...]
    probes: tuple[tuple[float, float], ...]
    min_nz: float = 0.5

    def key(self) -> str:
        """A stable hash of the scenario (part of every cache key)."""
        return hashlib.sha256(json.dumps(asdict(self), sort_keys=True).encode()).hexdigest()[:16]


def default_seat_scenario() -> Scenario:
    """Three 10 mm discs of 10 kPa on the default saddle, 15 probes.

    A sit bone (rear, off-centre), the middle above the clamp and the nose
    (cantilever bending); probes at the disc centres, around them, and far
    from all loads.
    """
    centers = ((0.215, 0.035), (0.150, 0.0), (0.075, 0.0))
    probes = []
    for cx, cy in centers:
        probes += [(cx, cy), (cx + 0.02, cy), (cx - 0.02, cy), (cx, cy + 0.012), (cx, cy - 0.012)]
    probes[-1] = (0.035, 0.0)  # nose tip instead of a point below the nose disc
    probes[9] = (0.250, -0.03)  # rear, far from every load
    return Scenario(tuple(LoadCase(c) for c in centers), tuple(probes))


def box_scenario(size: Sequence[float] = (0.1, 0.1, 0.05)) -> Scenario:
    """Loads and probes on the upper face z = Lz of a :func:`box_mesh` box."""
    lx, ly = float(size[0]), float(size[1])
    r = 0.2 * min(lx, ly)
    loads = (LoadCase((0.5 * lx, 0.5 * ly), r), LoadCase((0.7 * lx, 0.3 * ly), r))
    probes = tuple((a * lx, b * ly) for a, b in [(0.5, 0.5), (0.7, 0.3), (0.3, 0.7), (0.2, 0.2), (0.8, 0.8), (0.5, 0.15)])
    return Scenario(loads, probes)


# --------------------------------------------------------------------------
# surface quadrature and interpolation (P1 or P2 traces on flat triangles)
# --------------------------------------------------------------------------
def _subdivision_rule(level: int) -> tuple[np.ndarray, np.ndarray]:
    """Barycentric points (q, 3) and weights (q,) summing to 1: the 3-point
    degree-2 rule on each of the 4**level sub-triangles of the reference triangle."""
    tris = [np.eye(3)]
    for _ in range(level):
        new = []
        for t in tris:
            a, b, c = t
            ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
            new += [np.array([a, ab, ca]), np.array([ab, b, bc]), np.array([ca, bc, c]), np.array([ab, bc, ca])]
        tris = new
    base = np.array([[2 / 3, 1 / 6, 1 / 6], [1 / 6, 2 / 3, 1 / 6], [1 / 6, 1 / 6, 2 / 3]])
    lam = np.concatenate([base @ t for t in tris])
    w = np.full(lam.shape[0], 1.0 / lam.shape[0])
    return lam, w


def trace_shape(lam: np.ndarray, order: int) -> np.ndarray:
    """Lagrange shape functions of a P1 (3) or P2 (6) triangle at barycentrics ``lam`` (q, 3).

    P2 order: the three corners, then edges (0,1), (1,2), (2,0).
    """
    if order == 1:
        return lam
    l0, l1, l2 = lam.T
    return np.column_stack([
        l0 * (2 * l0 - 1), l1 * (2 * l1 - 1), l2 * (2 * l2 - 1), 4 * l0 * l1, 4 * l1 * l2, 4 * l2 * l0,
    ])


def _normals(points: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    p = points[triangles]
    cr = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area2 = np.linalg.norm(cr, axis=1)
    return cr / np.where(area2 > 0, area2, 1.0)[:, None], 0.5 * area2


def nodal_loads(
    points: np.ndarray,
    triangles: np.ndarray,
    tri_nodes: np.ndarray,
    n_nodes: int,
    load: LoadCase,
    *,
    order: int = 1,
    min_nz: float = 0.5,
    level: int = 4,
) -> np.ndarray:
    """Consistent nodal forces of a disc pressure: f_a = int p(x) N_a(x) (-n) dA.

    Parameters
    ----------
    points, triangles
        Outward surface triangles (corner indices into ``points``).
    tri_nodes
        (m, 3) for P1 or (m, 6) for P2: the node numbers of each triangle's
        shape functions (see :func:`trace_shape`), in ``range(n_nodes)``.
    load
        The disc pressure.
    order
        1 or 2.
    min_nz
        Triangles with outward normal z below this carry no load.
    level
        The indicator of the disc is integrated on 4**level sub-triangles of
        each triangle near the disc edge.

    Returns
    -------
    ndarray, shape (n_nodes, 3)
    """
    normals, areas = _normals(points, triangles)
    cx, cy = load.center
    p = points[triangles]  # (m, 3, 3)
    d = np.hypot(p[:, :, 0] - cx, p[:, :, 1] - cy)
    # plan circumradius bound: a triangle farther than that from the disc misses it
    cen = p.mean(axis=1)
    reach = np.max(np.hypot(p[:, :, 0] - cen[:, None, 0], p[:, :, 1] - cen[:, None, 1]), axis=1)
    near = (np.hypot(cen[:, 0] - cx, cen[:, 1] - cy) <= load.radius + reach) & (normals[:, 2] > min_nz)
    f = np.zeros((n_nodes, 3))
    idx = np.flatnonzero(near)
    if idx.size == 0:
        return f
    inside = np.all(d[idx] <= load.radius, axis=1)
    for sel, lev in ((idx[inside], 0), (idx[~inside], level)):
        if sel.size == 0:
            continue
        lam, w = _subdivision_rule(lev)
        x = np.einsum("qk,mkd->mqd", lam, p[sel])  # (m, q, 3)
        chi = (np.hypot(x[..., 0] - cx, x[..., 1] - cy) <= load.radius).astype(float)
        N = trace_shape(lam, order)  # (q, a)
        s = areas[sel][:, None] * np.einsum("mq,q,qa->ma", chi, w, N) * load.pressure  # (m, a)
        vec = -s[:, :, None] * normals[sel][:, None, :]  # (m, a, 3)
        np.add.at(f, tri_nodes[sel].ravel(), vec.reshape(-1, 3))
    return f


@dataclass(frozen=True)
class ProbeLocation:
    """Where the probes sit on a surface: triangle and barycentric coordinates."""

    triangle: np.ndarray  # (k,) int
    lam: np.ndarray  # (k, 3) float


def locate_probes(points: np.ndarray, triangles: np.ndarray, probes: np.ndarray, min_nz: float = 0.5) -> ProbeLocation:
    """The upward-facing triangle above each plan probe point, and its barycentrics.

    Raises
    ------
    ValueError
        If a probe lies outside every upward-facing triangle.
    """
    probes = np.asarray(probes, dtype=float).reshape(-1, 2)
    normals, _ = _normals(points, triangles)
    cand = np.flatnonzero(normals[:, 2] > min_nz)
    p = points[triangles[cand]]
    a, b, c = p[:, 0, :2], p[:, 1, :2], p[:, 2, :2]
    v0, v1 = b - a, c - a
    det = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
    tri = np.empty(probes.shape[0], dtype=np.int64)
    lam = np.empty((probes.shape[0], 3))
    for k, q in enumerate(probes):
        r = q[None, :] - a
        l1 = (r[:, 0] * v1[:, 1] - r[:, 1] * v1[:, 0]) / det
        l2 = (v0[:, 0] * r[:, 1] - v0[:, 1] * r[:, 0]) / det
        l0 = 1 - l1 - l2
        ok = np.flatnonzero((l0 >= -1e-10) & (l1 >= -1e-10) & (l2 >= -1e-10))
        if ok.size == 0:
            raise ValueError(f"probe {tuple(q)} is not above any upward-facing surface triangle")
        z = l0[ok] * p[ok, 0, 2] + l1[ok] * p[ok, 1, 2] + l2[ok] * p[ok, 2, 2]
        j = ok[np.argmax(z)]
        tri[k] = cand[j]
        lam[k] = np.clip([l0[j], l1[j], l2[j]], 0.0, 1.0)
        lam[k] /= lam[k].sum()
    return ProbeLocation(tri, lam)


# --------------------------------------------------------------------------
# quantity of interest
# --------------------------------------------------------------------------
@dataclass
class QoI:
    """Probe displacements and load work of every load case.

    Attributes
    ----------
    u : (n_loads, n_probes, 3) float ndarray
        Displacement at the probes [m].
    work : (n_loads,) float ndarray
        f . u of each load case (its compliance) [J].
    """

    u: np.ndarray
    work: np.ndarray


def relative_error(qoi: QoI | np.ndarray, ref: QoI | np.ndarray) -> float:
    """Worst relative Frobenius error of the probe displacements over load cases."""
    u = qoi.u if isinstance(qoi, QoI) else np.asarray(qoi)
    r = ref.u if isinstance(ref, QoI) else np.asarray(ref)
    num = np.linalg.norm((u - r).reshape(r.shape[0], -1), axis=1)
    den = np.linalg.norm(r.reshape(r.shape[0], -1), axis=1)
    return float(np.max(num / den))


def work_error(qoi: QoI, ref: QoI) -> float:
    """Worst relative error of the load work (compliance of the distributed load)."""
    return float(np.max(np.abs(qoi.work - ref.work) / np.abs(ref.work)))


def trace_nodes(basis, triangles: np.ndarray, order: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-triangle node numbers (3 corners, then 3 edge nodes for P2; for :func:`trace_shape`)
    and the (n_nodes, 3) dof table."""
    nv = basis.mesh.p.shape[1]
    if order == 1:
        return triangles, np.asarray(basis.nodal_dofs.T, dtype=np.int64)
    edges = np.sort(np.asarray(basis.mesh.edges.T, dtype=np.int64), axis=1)
    ke = edges[:, 0] * nv + edges[:, 1]
    srt = np.argsort(ke)
    cols = []
    for i, j in ((0, 1), (1, 2), (2, 0)):
        e = np.sort(triangles[:, [i, j]].astype(np.int64), axis=1)
        cols.append(nv + srt[np.searchsorted(ke[srt], e[:, 0] * nv + e[:, 1])])
    nodes = np.column_stack([triangles, *cols])
    table = np.concatenate([basis.nodal_dofs.T, basis.edge_dofs.T]).astype(np.int64)
    return nodes, table


@dataclass
class DirectSolve:
    """A direct FEM solution of the scenario on one mesh (see :func:`direct_qoi`).

    Attributes
    ----------
    qoi : QoI
    n_dofs : int
    assemble_s, factor_s, solve_s : float
        Wall times [s]; ``factor_s + solve_s`` is the cost of re-solving the
        full FEM system once per step.
    """

    qoi: QoI
    n_dofs: int
    assemble_s: float
    factor_s: float
    solve_s: float


def direct_qoi(
    mesh: TetMesh,
    order: int,
    scenario: Scenario,
    *,
    young: float = DEFAULT_YOUNG,
    poisson: float = DEFAULT_POISSON,
) -> DirectSolve:
    """Solve the scenario's loads directly (consistent P1/P2 load, CHOLMOD).

    This is the reference (at fine P2) and the "direct FEM re-solved per
    step" anchor; it never forms D.
    """
    t0 = time.perf_counter()
    basis = elasticity_basis(mesh, order)
    K = stiffness_matrix(basis, young, poisson)
    fixed = clamp_dofs(basis, mesh)
    tris = boundary_triangles(mesh.tets)
    nodes, table = trace_nodes(basis, tris, order)
    F = np.zeros((K.shape[0], len(scenario.loads)))
    for c, load in enumerate(scenario.loads):
        f = nodal_loads(mesh.points, tris, nodes, table.shape[0], load, order=order, min_nz=scenario.min_nz)
        F[table.ravel(), c] = f.ravel()
    free = free_dofs(K.shape[0], fixed)
    Kff = sp.csr_matrix(K)[free][:, free]
    t1 = time.perf_counter()
    fact = factorize(Kff, "cholmod")
    t2 = time.perf_counter()
    U = np.zeros_like(F)
    U[free] = fact.solve(F[free])
    t3 = time.perf_counter()
    loc = locate_probes(mesh.points, tris, np.array(scenario.probes), scenario.min_nz)
    N = trace_shape(loc.lam, order)  # (k, a)
    dofs = table[nodes[loc.triangle]]  # (k, a, 3)
    u = np.einsum("ka,kacl->lkc", N, U[dofs])  # (loads, probes, 3)
    work = np.einsum("dl,dl->l", F, U)
    return DirectSolve(QoI(u, work), int(K.shape[0]), t1 - t0, t2 - t1, t3 - t2)


class _SurfaceScenario:
    """A scenario mapped onto a bundle's surface: vertex forces and probe rows."""

    def __init__(self, vertices, triangles, contactable, scenario: Scenario):
        n = vertices.shape[0]
        col_of = np.full(n, -1, dtype=np.int64)
        col_of[contactable] = np.arange(int(contactable.sum()))
        forces = np.stack([
            nodal_loads(vertices, triangles, triangles, n, load, order=1, min_nz=scenario.min_nz)
            for load in scenario.loads
        ])  # (L, n, 3)
        loaded = np.flatnonzero(np.any(forces != 0, axis=(0, 2)))
        #: loaded vertices without a column in D (their force is lost)
        self.dropped = loaded[col_of[loaded] < 0]
        self.load_vertices = loaded[col_of[loaded] >= 0]
        self.forces = forces[:, self.load_vertices]  # (L, nl, 3)
        self.cols = (3 * col_of[self.load_vertices][:, None] + np.arange(3)).ravel()
        loc = locate_probes(vertices, triangles, np.array(scenario.probes), scenario.min_nz)
        self.probe_vertices = triangles[loc.triangle]  # (k, 3)
        self.lam = loc.lam
        self.probe_rows = (3 * self.probe_vertices.reshape(-1)[:, None] + np.arange(3)).ravel()
        self.work_rows = (3 * self.load_vertices[:, None] + np.arange(3)).ravel()
        self.loc = loc

    def qoi(self, D: Any) -> QoI:
        """The QoI from a compliance ``D`` (any array indexable as ``D[rows][:, cols]``)."""
        Fm = self.forces.reshape(self.forces.shape[0], -1).T  # (3 nl, L)
        if self.cols.size == 0:
            return QoI(np.zeros((Fm.shape[1], self.lam.shape[0], 3)), np.zeros(Fm.shape[1]))
        Dp = np.asarray(D[np.ix_(self.probe_rows, self.cols)], dtype=np.float64)
        up = (Dp @ Fm).reshape(self.lam.shape[0], 3, 3, -1)  # (k, corner, xyz, L)
        u = np.einsum("ka,kacl->lkc", self.lam, up)
        Dw = np.asarray(D[np.ix_(self.work_rows, self.cols)], dtype=np.float64)
        work = np.einsum("dl,dl->l", Fm, Dw @ Fm)
        return QoI(u, work)


@dataclass
class HatCompliance:
    """A compliance D whose column (j, d) answers a *traction* spread over the
    hat function of vertex j (see :func:`hat_traction_compliance`).

    Same layout as a bundle's D: rows are every surface vertex (x, y, z),
    columns the contactable vertices.
    """

    D: np.ndarray
    vertices: np.ndarray
    triangles: np.ndarray
    contactable: np.ndarray
    seconds: float
    n_dofs: int


def hat_traction_compliance(
    mesh: TetMesh,
    order: int,
    *,
    young: float = DEFAULT_YOUNG,
    poisson: float = DEFAULT_POISSON,
    contact_group: str = "top",
    block: int = 32,
) -> HatCompliance:
    """D with "vertex pressure mask" columns (James & Pai): column (j, d) is
    the response to the traction e_d phi_j / a_j, phi_j the P1 hat function of
    surface vertex j and a_j = int phi_j its lumped area, loaded consistently
    for the element order. One newton in total, like a bundle column.

    For P1 this differs from the bundle's unit nodal force only by the
    surface mass matrix; for P2 it is the difference between a consistent
    load and a point force on a corner node (on which a P2 corner-only D
    performs badly for distributed loads). ``seconds`` is the measured wall
    time of the whole computation (surface, assembly, factorization, solves),
    without meshing.
    """
    from hailstorm.precompute.greens import hat_load_matrix
    from hailstorm.precompute.pipeline import extract_surface

    t0 = time.perf_counter()
    surface = extract_surface(mesh, contact_group)
    basis = elasticity_basis(mesh, order)
    K = stiffness_matrix(basis, young, poisson)
    contact_nodes = surface.nodes[surface.contactable]
    loads = hat_load_matrix(basis, contact_nodes, surface.areas[surface.contactable])
    D = compliance_matrix(K, clamp_dofs(basis, mesh), vertex_dofs(basis, contact_nodes).ravel(),
                          vertex_dofs(basis, surface.nodes).ravel(), loads=loads, block_columns=block)
    return HatCompliance(D, mesh.points[surface.nodes], surface.triangles, surface.contactable,
                         time.perf_counter() - t0, int(K.shape[0]))


def bundle_qoi(gf: Any, scenario: Scenario, D: Any = None) -> QoI:
    """The QoI as a bundle user gets it: P1-lumped pressure, u = D f, P1 probes.

    Parameters
    ----------
    gf
        A loaded bundle (:func:`hailstorm.runtime.load`).
    scenario
        Loads and probes.
    D
        Replace the bundle's compliance by this matrix of the same shape
        (a float32 copy, a low-rank approximation...).
    """
    s = _SurfaceScenario(gf.vertices, gf.triangles, gf.contactable, scenario)
    return s.qoi(gf.D if D is None else D)


# --------------------------------------------------------------------------
# the reference
# --------------------------------------------------------------------------
@dataclass
class Reference:
    """The fine solution errors are measured against.

    Attributes
    ----------
    qoi : QoI
    mesh_size : float
    order : int
    n_dofs : int
    seconds : float
        Wall time of meshing and solving it.
    self_error : float or None
        Relative difference to the same order one mesh size coarser
        (``check_size``): an estimate of the reference's own error; errors
        well below it are not resolved.
    """

    qoi: QoI
    mesh_size: float
    order: int
    n_dofs: int
    seconds: float
    self_error: float | None = None


def reference(
    scenario: Scenario,
    *,
    mesher: Mesher = mesh_default_seat,
    mesh_size: float = 0.004,
    order: int = 2,
    check_size: float | None = None,
    young: float = DEFAULT_YOUNG,
    poisson: float = DEFAULT_POISSON,
    cache_dir: str | os.PathLike | None = None,
) -> Reference:
    """Solve (or load from ``cache_dir``) the reference QoI.

    The cache key covers the mesh content, order, material and scenario.

    Parameters
    ----------
    scenario
        Loads and probes.
    mesher
        Mesh size -> :class:`TetMesh` (default: the saddle).
    mesh_size, order
        The reference discretization (default P2 at 4 mm).
    check_size
        If given, also solve at this (coarser) size to estimate the
        reference's own error.
    cache_dir
        Directory for ``reference-<key>.npz``; ``None``: no caching.
    """
    t0 = time.perf_counter()
    mesh = mesher(mesh_size)
    t_mesh = time.perf_counter() - t0
    key = hashlib.sha256(json.dumps({
        "v": STUDY_VERSION, "mesh": mesh.content_hash(), "order": order, "young": young, "poisson": poisson,
        "scenario": scenario.key(), "check": check_size,
    }, sort_keys=True).encode()).hexdigest()[:16]
    path = None if cache_dir is None else Path(cache_dir) / f"reference-{key}.npz"
    if path is not None and path.is_file():
        z = np.load(path)
        se = float(z["self_error"])
        return Reference(QoI(z["u"], z["work"]), float(z["mesh_size"]), int(z["order"]), int(z["n_dofs"]),
                         float(z["seconds"]), None if math.isnan(se) else se)
    sol = direct_qoi(mesh, order, scenario, young=young, poisson=poisson)
    seconds = t_mesh + sol.assemble_s + sol.factor_s + sol.solve_s
    self_error = None
    if check_size is not None:
        coarse = direct_qoi(mesher(check_size), order, scenario, young=young, poisson=poisson)
        self_error = relative_error(coarse.qoi, sol.qoi)
    ref = Reference(sol.qoi, float(mesh_size), int(order), sol.n_dofs, seconds, self_error)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        with replacing(path) as tmp:
            np.savez(tmp, u=ref.qoi.u, work=ref.qoi.work, mesh_size=ref.mesh_size, order=ref.order,
                     n_dofs=ref.n_dofs, seconds=ref.seconds, self_error=np.nan if self_error is None else self_error)
    return ref


# --------------------------------------------------------------------------
# study points
# --------------------------------------------------------------------------
@dataclass
class StudyPoint:
    """One knob setting: its costs and its error.

    Attributes
    ----------
    knob : str
        The family ("P1 mesh", "P2 mesh", "AMG tol", "float32", "region",
        "low rank", "direct FEM/step").
    label : str
        The setting ("h=10 mm", "tol=1e-06", "rank 50"...).
    precompute_s : float
        Precompute wall time [s] (NaN for the direct-FEM anchor, which
        precomputes nothing).
    memory_mb : float
        Memory of D [MB] (NaN for the anchor).
    error : float
        Relative QoI error against the reference.
    step_s : float or None
        Runtime cost per step [s]: :func:`hailstorm.runtime.solve_contacts` with one
        contact per load case, or one factor + solve for the anchor.
    params : dict
        The knob values (mesh_size, order, solver, tol, rank...).
    extra : dict
        Secondary measures: ``work_error``, ``error_vs_parent`` (error caused
        by the knob alone), ``d_error`` (relative Frobenius error of D),
        ``n_columns``, ``n_dofs``...
    """

    knob: str
    label: str
    precompute_s: float
    memory_mb: float
    error: float
    step_s: float | None = None
    params: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        """A JSON-ready dict."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "StudyPoint":
        """Inverse of :meth:`to_dict`."""
        return cls(**d)


@dataclass
class Built:
    """A bundle built by :func:`build_config` and what it cost."""

    gf: Any
    path: Path
    seconds: float
    mesh_s: float
    n_dofs: int
    memory_mb: float


def build_config(
    workdir: str | os.PathLike,
    *,
    mesher: Mesher,
    mesh_size: float,
    order: int = 1,
    solver: str = "cholmod",
    tol: float = 1e-10,
    mesh: TetMesh | None = None,
    contact_group: str = "top",
    name: str | None = None,
) -> Built:
    """Mesh (unless ``mesh`` is given) and build a bundle, timing both.

    The bundle is always recomputed (``reuse=False``): the point is the time.
    """
    t0 = time.perf_counter()
    if mesh is None:
        mesh = mesher(mesh_size)
    t1 = time.perf_counter()
    name = name or f"h{mesh_size:g}-p{order}-{solver}" + (f"-{tol:g}" if solver_spec(solver).uses_tol else "") + f"-{contact_group}"
    path = build_bundle(Path(workdir) / name, mesh=mesh, mesh_size=mesh_size, order=order, solver=solver, tol=tol,
                        contact_group=contact_group, reuse=False)
    t2 = time.perf_counter()
    from hailstorm.runtime import load

    gf = load(path, verify=False, mmap=False)
    return Built(gf, path, t2 - t0, t1 - t0, int(gf.manifest["mesh"]["n_dofs"]), gf.D.nbytes / 1e6)


def step_time(gf: Any, scenario: Scenario, *, repeats: int = 7, depth: float = 1e-3) -> float:
    """Median wall time of one :func:`hailstorm.runtime.solve_contacts` call with one
    sticky contact at each load centre, pressed ``depth`` into the surface."""
    from hailstorm.runtime import solve_contacts

    centers = np.array([ld.center for ld in scenario.loads])
    loc = locate_probes(gf.vertices, gf.triangles, centers, scenario.min_nz)
    normals, _ = _normals(gf.vertices, gf.triangles)
    disp = -depth * normals[loc.triangle]
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        solve_contacts(gf, loc.triangle, loc.lam, disp)
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def _point(knob, label, built: Built, qoi: QoI, ref: Reference, *, step=None, params=None, extra=None) -> StudyPoint:
    ex = {"work_error": work_error(qoi, ref.qoi), "n_columns": int(built.gf.D.shape[1]), "n_dofs": built.n_dofs}
    ex.update(extra or {})
    return StudyPoint(knob, label, built.seconds, built.memory_mb, relative_error(qoi, ref.qoi), step,
                      params or {}, ex)


def study_discretization(
    mesh_sizes: Iterable[float],
    orders: Iterable[int],
    scenario: Scenario,
    ref: Reference,
    workdir: str | os.PathLike,
    *,
    mesher: Mesher = mesh_default_seat,
    with_steps: bool = True,
    with_direct: bool = True,
) -> list[StudyPoint]:
    """Mesh size x element order, CHOLMOD, float64, every top vertex contactable.

    With ``with_direct``, also the "direct FEM/step" anchor at each P1 mesh
    (same error as the P1 bundle, cost = one factor + solve per step).
    """
    out = []
    for order in orders:
        for h in mesh_sizes:
            b = build_config(workdir, mesher=mesher, mesh_size=h, order=order)
            q = bundle_qoi(b.gf, scenario)
            step = step_time(b.gf, scenario) if with_steps else None
            out.append(_point(f"P{order} mesh", f"h={h * 1e3:g} mm", b, q, ref, step=step,
                              params={"mesh_size": h, "order": order}))
            if with_direct and order == 1:
                d = direct_qoi(mesher(h), 1, scenario, young=b.gf.young, poisson=b.gf.poisson)
                out.append(StudyPoint("direct FEM/step", f"h={h * 1e3:g} mm", math.nan, math.nan,
                                      relative_error(d.qoi, ref.qoi), d.factor_s + d.solve_s,
                                      {"mesh_size": h, "order": 1}, {"n_dofs": d.n_dofs}))
    return out


def study_hat_columns(
    mesh_sizes: Iterable[float],
    orders: Iterable[int],
    scenario: Scenario,
    ref: Reference,
    *,
    mesher: Mesher = mesh_default_seat,
) -> list[StudyPoint]:
    """Like :func:`study_discretization`, but with hat-traction columns
    (:func:`hat_traction_compliance`), computed in this module: the same
    number of solves, a different right-hand side. Knob "P<k> hat columns"."""
    out = []
    for order in orders:
        for h in mesh_sizes:
            t = time.perf_counter()
            mesh = mesher(h)
            t_mesh = time.perf_counter() - t
            hc = hat_traction_compliance(mesh, order)
            q = _SurfaceScenario(hc.vertices, hc.triangles, hc.contactable, scenario).qoi(hc.D)
            out.append(StudyPoint(f"P{order} hat columns", f"h={h * 1e3:g} mm", t_mesh + hc.seconds, hc.D.nbytes / 1e6,
                                  relative_error(q, ref.qoi), None, {"mesh_size": h, "order": order},
                                  {"work_error": work_error(q, ref.qoi), "n_columns": int(hc.D.shape[1]),
                                   "n_dofs": hc.n_dofs}))
    return out


def study_solver(
    mesh_size: float,
    order: int,
    tols: Iterable[float],
    scenario: Scenario,
    ref: Reference,
    workdir: str | os.PathLike,
    *,
    mesher: Mesher = mesh_default_seat,
) -> list[StudyPoint]:
    """AMG-preconditioned CG at each tolerance against CHOLMOD on one mesh.

    ``extra["error_vs_parent"]`` is the QoI error relative to the CHOLMOD bundle
    (the solver's own error); ``extra["d_error"]`` the relative Frobenius error of D.
    """
    mesh = mesher(mesh_size)
    base = build_config(workdir, mesher=mesher, mesh=mesh, mesh_size=mesh_size, order=order)
    qb = bundle_qoi(base.gf, scenario)
    Db = np.asarray(base.gf.D)
    out = [_point("CHOLMOD", f"P{order} h={mesh_size * 1e3:g} mm", base, qb, ref,
                  params={"mesh_size": mesh_size, "order": order, "solver": "cholmod"})]
    for tol in tols:
        b = build_config(workdir, mesher=mesher, mesh=mesh, mesh_size=mesh_size, order=order, solver="amg", tol=tol)
        q = bundle_qoi(b.gf, scenario)
        d_err = float(np.linalg.norm(np.asarray(b.gf.D) - Db) / np.linalg.norm(Db))
        out.append(_point("AMG tol", f"tol={tol:.0e}", b, q, ref,
                          params={"mesh_size": mesh_size, "order": order, "solver": "amg", "tol": tol},
                          extra={"error_vs_parent": relative_error(q, qb), "d_error": d_err}))
    return out


def study_precision(built: Built, scenario: Scenario, ref: Reference) -> list[StudyPoint]:
    """D stored in float32 instead of float64 (half the memory)."""
    D64 = np.asarray(built.gf.D)
    t = time.perf_counter()
    D32 = D64.astype(np.float32)
    dt = time.perf_counter() - t
    q64 = bundle_qoi(built.gf, scenario)
    q32 = bundle_qoi(built.gf, scenario, D=D32)
    d_err = float(np.linalg.norm(D32.astype(np.float64) - D64) / np.linalg.norm(D64))
    h, order = built.gf.manifest["options"]["mesh_size"], built.gf.order
    return [StudyPoint("float32", f"P{order} h={h * 1e3:g} mm", built.seconds + dt, D32.nbytes / 1e6,
                       relative_error(q32, ref.qoi), None, {"mesh_size": h, "order": order, "dtype": "float32"},
                       {"error_vs_parent": relative_error(q32, q64), "d_error": d_err,
                        "work_error": work_error(q32, ref.qoi)})]


def _region_mesh(mesh: TetMesh, centers: np.ndarray, radius: float) -> TetMesh:
    top = mesh.groups["top"]
    cen = mesh.points[top].mean(axis=1)[:, :2]
    d = np.min(np.linalg.norm(cen[:, None, :] - centers[None, :, :], axis=2), axis=1)
    groups = dict(mesh.groups)
    groups["region"] = top[d <= radius]
    return TetMesh(mesh.points, mesh.tets, groups, mesh.source)


def study_region(
    mesh_size: float,
    order: int,
    radii: Iterable[float],
    scenario: Scenario,
    ref: Reference,
    workdir: str | os.PathLike,
    *,
    mesher: Mesher = mesh_default_seat,
) -> list[StudyPoint]:
    """"Only what the scene needs": columns only for top vertices within a plan
    distance ``radius`` of a load centre (the part of the seat hail can reach
    in the scene). Cost scales with the columns; a region that misses part of
    a load drops that force (``extra["dropped_vertices"]``)."""
    mesh = mesher(mesh_size)
    centers = np.array([ld.center for ld in scenario.loads])
    out = []
    for r in radii:
        rm = _region_mesh(mesh, centers, r)
        if rm.groups["region"].size == 0:
            continue
        b = build_config(workdir, mesher=mesher, mesh=rm, mesh_size=mesh_size, order=order, contact_group="region",
                         name=f"h{mesh_size:g}-p{order}-region{r:g}")
        s = _SurfaceScenario(b.gf.vertices, b.gf.triangles, b.gf.contactable, scenario)
        out.append(_point("region", f"r={r * 1e3:g} mm", b, s.qoi(b.gf.D), ref,
                          params={"mesh_size": mesh_size, "order": order, "radius": r},
                          extra={"dropped_vertices": int(s.dropped.size)}))
    return out


def low_rank(D: np.ndarray, rank: int, *, method: str = "svd", oversample: int = 10, power: int = 2,
             seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Factors (L, R) with D ~= L @ R, L (m, k), R (k, n).

    ``method="svd"``: truncated SVD (optimal in the 2- and Frobenius norms).
    ``method="randomized"``: Halko-Martinsson-Tropp range finder with
    ``power`` subspace iterations (cheaper for large D).
    """
    D = np.asarray(D, dtype=np.float64)
    k = int(min(rank, *D.shape))
    if method == "svd":
        U, s, Vt = np.linalg.svd(D, full_matrices=False)
        return U[:, :k] * s[:k], Vt[:k]
    if method == "randomized":
        rng = np.random.default_rng(seed)
        p = min(k + oversample, min(D.shape))
        Q, _ = np.linalg.qr(D @ rng.standard_normal((D.shape[1], p)))
        for _ in range(power):
            Q, _ = np.linalg.qr(D.T @ Q)
            Q, _ = np.linalg.qr(D @ Q)
        U, s, Vt = np.linalg.svd(Q.T @ D, full_matrices=False)
        return (Q @ U[:, :k]) * s[:k], Vt[:k]
    raise ValueError(f"unknown low-rank method {method!r}; choose 'svd' or 'randomized'")


def study_low_rank(built: Built, ranks: Iterable[int], scenario: Scenario, ref: Reference, *,
                   method: str = "svd") -> list[StudyPoint]:
    """D compressed to rank k: memory (m + n) k doubles, error vs reference.

    ``extra["d_error"]`` is ||D - D_k||_F / ||D||_F; ``extra["error_vs_parent"]``
    the QoI error relative to the uncompressed bundle.
    """
    D = np.asarray(built.gf.D, dtype=np.float64)
    s = _SurfaceScenario(built.gf.vertices, built.gf.triangles, built.gf.contactable, scenario)
    q0 = s.qoi(D)
    nD = np.linalg.norm(D)
    h, order = built.gf.manifest["options"]["mesh_size"], built.gf.order
    out = []
    if method == "svd":
        t = time.perf_counter()
        U, sv, Vt = np.linalg.svd(D, full_matrices=False)
        t_svd = time.perf_counter() - t
    for k in ranks:
        t = time.perf_counter()
        if method == "svd":
            k = int(min(k, sv.size))
            L, R = U[:, :k] * sv[:k], Vt[:k]
            dt = t_svd
        else:
            L, R = low_rank(D, k, method=method)
            dt = time.perf_counter() - t
        Dk = L @ R
        q = s.qoi(Dk)
        out.append(StudyPoint("low rank", f"rank {L.shape[1]}", built.seconds + dt, (L.nbytes + R.nbytes) / 1e6,
                              relative_error(q, ref.qoi), None,
                              {"mesh_size": h, "order": order, "rank": int(L.shape[1]), "method": method},
                              {"d_error": float(np.linalg.norm(D - Dk) / nD), "error_vs_parent": relative_error(q, q0),
                               "work_error": work_error(q, ref.qoi), "full_rank": int(min(D.shape))}))
    return out


# --------------------------------------------------------------------------
# Pareto front and the chart
# --------------------------------------------------------------------------
def _get(p: Any, name: str, pos: int) -> float:
    if isinstance(p, StudyPoint):
        v = getattr(p, name)
    elif isinstance(p, dict):
        v = p[name]
    else:
        v = p[pos]
    return math.nan if v is None else float(v)


def pareto_front(points: Sequence[Any], cost: str = "precompute_s", error: str = "error") -> list[int]:
    """Indices of the non-dominated points, by increasing cost.

    A point is dominated if another is no worse in both cost and error and
    strictly better in one. Points with a NaN cost or error are ignored.

    Parameters
    ----------
    points
        :class:`StudyPoint` objects, dicts, or ``(cost, error)`` pairs.
    cost, error
        Attribute/key names for StudyPoints and dicts.
    """
    ce = [(_get(p, cost, 0), _get(p, error, 1), i) for i, p in enumerate(points)]
    ce = [t for t in ce if not (math.isnan(t[0]) or math.isnan(t[1]))]
    ce.sort(key=lambda t: (t[0], t[1]))
    front, best = [], math.inf
    for c, e, i in ce:
        if e < best:
            front.append(i)
            best = e
    return front


_STYLE = {
    "P1 mesh": ("o", "C0"), "P2 mesh": ("s", "C1"), "CHOLMOD": ("D", "C7"), "AMG tol": ("^", "C2"),
    "float32": ("v", "C3"), "region": ("P", "C4"), "low rank": ("X", "C5"), "direct FEM/step": ("*", "k"),
}


def plot_speed_vs_accuracy(results: Sequence[StudyPoint], path: str | os.PathLike | None = None, *,
                           reference_error: float | None = None, dpi: int = 80):
    """Three log-log panels (precompute time, memory of D, runtime per step)
    against error, every knob labelled, the Pareto front of each panel drawn.

    Returns the matplotlib figure; saves it to ``path`` if given.
    """
    import matplotlib
    import matplotlib.pyplot as plt
    import matplotlib.ticker  # noqa: F401

    pts = list(results)
    axes_spec = [("precompute_s", "precompute wall time [s]"), ("memory_mb", "memory of D [MB]"),
                 ("step_s", "runtime cost per step [s]")]
    fig, axes = plt.subplots(1, 3, figsize=(15, 5), sharey=True)
    for ax, (attr, xlabel) in zip(axes, axes_spec):
        seen = set()
        for p in pts:
            x = _get(p, attr, 0)
            if math.isnan(x) or x <= 0 or not (p.error > 0):
                continue
            marker, color = _STYLE.get(p.knob, ("o", "C9"))
            ax.loglog(x, p.error, marker, color=color, ms=7, alpha=0.85,
                      label=None if p.knob in seen else p.knob)
            seen.add(p.knob)
            ax.annotate(p.label, (x, p.error), fontsize=6, xytext=(3, 2), textcoords="offset points")
        valid = [p for p in pts if _get(p, attr, 0) > 0 and p.error > 0]
        front = pareto_front(valid, cost=attr)
        if front:
            fx = [_get(valid[i], attr, 0) for i in front]
            fy = [valid[i].error for i in front]
            ax.step(fx, fy, where="post", color="0.3", lw=1.2, ls="--", label="Pareto front")
        if reference_error:
            ax.axhline(reference_error, color="0.6", lw=0.8, ls=":", label="reference's own error")
        ax.set_xlabel(xlabel)
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.grid(True, which="both", alpha=0.25)
        ax.legend(fontsize=7, loc="best")
    axes[0].set_ylabel("relative error of top-surface displacement\n(disc loads, vs fine P2 reference)")
    fig.tight_layout()
    if path is not None:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=dpi)
    return fig


# --------------------------------------------------------------------------
# the whole study (what the notebook runs)
# --------------------------------------------------------------------------
@dataclass
class StudySettings:
    """Every parameter of :func:`run_study`; :meth:`small` for tests/CI."""

    mesh_sizes: tuple[float, ...] = (0.02, 0.015, 0.01, 0.008, 0.006)
    p2_mesh_sizes: tuple[float, ...] = (0.02, 0.015, 0.01, 0.008, 0.006)
    hat_mesh_sizes: tuple[float, ...] = (0.02, 0.015, 0.01, 0.008, 0.006)
    reference_size: float = 0.004
    reference_check_size: float | None = 0.005
    solver_mesh: tuple[float, int] = (0.01, 2)
    amg_tols: tuple[float, ...] = (1e-4, 1e-6, 1e-8)
    base_mesh: tuple[float, int] = (0.008, 2)
    region_radii: tuple[float, ...] = (0.02, 0.04, 0.07)
    ranks: tuple[int, ...] = (10, 30, 100, 300, 1000)

    @classmethod
    def small(cls) -> "StudySettings":
        """Coarse meshes only: the whole study in well under a minute."""
        return cls(mesh_sizes=(0.02, 0.015), p2_mesh_sizes=(0.02,), hat_mesh_sizes=(0.02,), reference_size=0.01,
                   reference_check_size=None, solver_mesh=(0.02, 1), amg_tols=(1e-4, 1e-8), base_mesh=(0.02, 1),
                   region_radii=(0.03,), ranks=(10, 100))


@dataclass
class StudyResults:
    """The output of :func:`run_study`."""

    points: list[StudyPoint]
    reference: dict
    settings: dict

    def table(self) -> list[dict]:
        """Rows (knob, label, precompute_s, memory_mb, error, step_s) for display."""
        return [{k: getattr(p, k) for k in ("knob", "label", "precompute_s", "memory_mb", "error", "step_s")}
                for p in self.points]


def run_study(
    settings: StudySettings | None = None,
    *,
    small: bool = False,
    cache_dir: str | os.PathLike | None = None,
    recompute: bool = False,
    mesher: Mesher = mesh_default_seat,
    scenario: Scenario | None = None,
) -> StudyResults:
    """Run every knob (or load the cached results) and return the points.

    Parameters
    ----------
    settings
        Knob values; default :class:`StudySettings` (``small=True``:
        :meth:`StudySettings.small`).
    cache_dir
        Where the reference, the bundles and ``study-<key>.json`` live
        (default ``default_cache_dir() / "study"``).
    recompute
        Ignore cached study results (the reference stays cached).
    mesher, scenario
        The seat and its loads (default: the saddle and
        :func:`default_seat_scenario`).
    """
    settings = settings or (StudySettings.small() if small else StudySettings())
    scenario = scenario or default_seat_scenario()
    cache = Path(cache_dir) if cache_dir is not None else default_cache_dir() / "study"
    cache.mkdir(parents=True, exist_ok=True)
    key = hashlib.sha256(json.dumps({"v": STUDY_VERSION, "settings": asdict(settings), "scenario": scenario.key(),
                                     "mesher": getattr(mesher, "__qualname__", repr(mesher))},
                                    sort_keys=True).encode()).hexdigest()[:16]
    res_path = cache / f"study-{key}.json"
    if res_path.is_file() and not recompute:
        d = json.loads(res_path.read_text())
        return StudyResults([StudyPoint.from_dict(p) for p in d["points"]], d["reference"], d["settings"])

    ref = reference(scenario, mesher=mesher, mesh_size=settings.reference_size,
                    check_size=settings.reference_check_size, cache_dir=cache)
    pts: list[StudyPoint] = []
    with tempfile.TemporaryDirectory(dir=cache) as work:
        pts += study_discretization(settings.mesh_sizes, (1,), scenario, ref, work, mesher=mesher)
        pts += study_discretization(settings.p2_mesh_sizes, (2,), scenario, ref, work, mesher=mesher)
        pts += study_hat_columns(settings.hat_mesh_sizes, (2,), scenario, ref, mesher=mesher)
        h, o = settings.solver_mesh
        pts += study_solver(h, o, settings.amg_tols, scenario, ref, work, mesher=mesher)
        h, o = settings.base_mesh
        base = build_config(work, mesher=mesher, mesh_size=h, order=o, name="base")
        pts += study_precision(base, scenario, ref)
        pts += study_low_rank(base, settings.ranks, scenario, ref)
        pts += study_region(h, o, settings.region_radii, scenario, ref, work, mesher=mesher)
    out = StudyResults(pts, {**asdict(ref), "qoi": None}, asdict(settings))
    write_text_atomic(res_path, json.dumps({"points": [p.to_dict() for p in pts], "reference": out.reference,
                                            "settings": out.settings}, indent=1, default=_json_default))
    return out


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(type(o))


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m studies.study [--small] [--recompute] [--out PNG] [--cache DIR]``."""
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--small", action="store_true", help="coarse settings (seconds)")
    ap.add_argument("--recompute", action="store_true", help="ignore cached study results")
    ap.add_argument("--out", default="notebooks/figures/speed_vs_accuracy.png")
    ap.add_argument("--cache", default=None, help="cache directory (default: <hailstorm cache>/study)")
    a = ap.parse_args(argv)
    res = run_study(small=a.small, cache_dir=a.cache, recompute=a.recompute)
    import matplotlib

    matplotlib.use("Agg")
    plot_speed_vs_accuracy(res.points, a.out, reference_error=res.reference.get("self_error"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
