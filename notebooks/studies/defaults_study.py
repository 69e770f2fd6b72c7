"""The default discretization, chosen by measured accuracy (issue #14 item 5).

Two quantities a storm on the padded saddle depends on, at three sites of the
crown (rear, middle, nose: :data:`studies.seat_study.SITES`):

Dent
    The mean normal displacement of a 1 N load spread uniformly over a 5 mm
    disc (radius 2.5 mm in plan, along the inward normal): the load's work
    f . u, i.e. the pressure-weighted mean depth of the dent [m/N]. Also the
    depth under the disc's centre (reported, not a criterion: a 6 mm surface
    cannot resolve a 5 mm disc's centre).
Stone contact stiffness
    The capacitance k = 1 / (w^T N^T D N w) of a Hertz patch as the runtime
    builds it (:func:`hailstorm.runtime.contact.weights.patch_weights`,
    Hertz profile, along the contacted triangle's normal) for a 10 mm hailstone
    (radius 5 mm) at the peak of its impact at terminal velocity: patch radius
    :func:`stone_patch_radius` (3.8 mm on the default pad).

A setting is what a bundle user gets: surface mesh size, element order, the
load a column of D answers (``point``/``hat``) and the volume grading
(``volume_size``: finer tetrahedra under the *same* surface, which costs
precompute only). It is scored without forming D: u = D f is one direct solve
with the right-hand side a column combination stands for (f on the corner
nodes for ``point``, the hat tractions for ``hat``), read at the corner
vertices, exactly what the bundle's columns hold.

The reference is P2 with consistent loads (the disc's uniform pressure and
the patch's Hertz pressure integrated on the P2 trace), on meshes refined
around the three sites (:class:`hailstorm.precompute.geometry.Refinement`),
at a few levels: the finest is the reference and the levels before it show
its convergence and observed rate.

Run::

    python -m studies.defaults_study               # reference levels, the table, 3 timed precomputes each
    python -m studies.defaults_study --no-timing   # accuracy only (the reference ~6 min on 2 loaded cores)
    python -m studies.defaults_study --quick       # coarse reference levels, one timed run each
    python -m studies.defaults_study --frontier --reference-cache /tmp/ref.npz
        # P2 point columns on 6 ... 3.5 mm surfaces and a few variants: errors, size of D, precompute
        # wall and CPU time (2 runs each, 1 beyond --budget s), the cheapest setting within 5 %
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import math
import os
import resource
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from types import SimpleNamespace

import numpy as np

from hailstorm.precompute.fem import (
    DEFAULT_POISSON,
    DEFAULT_YOUNG,
    clamp_dofs,
    elasticity_basis,
    free_dofs,
    stiffness_matrix,
    vertex_dofs,
)
from hailstorm.precompute.geometry import (
    Refinement,
    TetMesh,
    boundary_triangles,
    default_seat_path,
    mesh_default_seat,
)
from hailstorm.precompute.greens import factorize, hat_load_matrix
from hailstorm.precompute.pipeline import build_bundle, extract_surface
from hailstorm.runtime.bundle.atomic import replacing
from hailstorm.runtime.contact.normals import triangle_normals
from hailstorm.runtime.contact.weights import patch_weights
from hailstorm.runtime.storm.hail import stone_mass, terminal_velocity
from hailstorm.runtime.contact.hertz import hertz_impact
from studies.seat_study import SITES
from studies.study import LoadCase, locate_probes, nodal_loads, trace_nodes, trace_shape

#: The dent load: 1 N uniform over a disc of this plan radius [m] (a 5 mm disc).
DENT_RADIUS = 0.0025
#: The stone of the contact stiffness: radius [m] (a 10 mm hailstone).
STONE_RADIUS = 0.005
#: Accuracy target of the default against the reference (issue #14).
TARGET = 0.05
#: The reference's levels: the size [m] around the sites, coarse to fine (the last is the reference).
REFERENCE_SIZES = (0.002, 0.0014, 0.001, 0.0007)
#: The same, coarse (``--quick``).
QUICK_REFERENCE_SIZES = (0.004, 0.0028, 0.002)

logger = logging.getLogger(__name__)


def stone_patch_radius(stone_radius: float = STONE_RADIUS, young: float = DEFAULT_YOUNG,
                       poisson: float = DEFAULT_POISSON) -> float:
    """Hertz contact radius [m] of an ice sphere at the peak of an elastic impact at terminal velocity.

    Hertz impact (Johnson, *Contact Mechanics*, §11.4): the largest indentation
    is delta = (15 m v^2 / (16 E* sqrt(R)))^(2/5) and the radius a = sqrt(R delta),
    with m the stone's mass, v its terminal velocity (default hail: ice, sphere
    drag), E* = E / (1 - nu^2) for a rigid sphere.
    """
    m = float(stone_mass(stone_radius))
    v = float(terminal_velocity(stone_radius))
    delta = hertz_impact(m, v, stone_radius, young, poisson).max_depth
    return math.sqrt(stone_radius * delta)


@dataclass(frozen=True)
class Setting:
    """A discretization of the default seat.

    Attributes
    ----------
    mesh_size : float
        Element size on the hail-facing surface [m].
    order : {1, 2}
    load : {"point", "hat"}
        What a column of D answers (``hailstorm precompute --load``).
    volume_size : float or None
        Volume grading [m] (``--volume-size``); None: none.
    """

    mesh_size: float = 0.006
    order: int = 1
    load: str = "point"
    volume_size: float | None = None

    @property
    def label(self) -> str:
        """e.g. ``P2 hat 6 mm / vol 3 mm``."""
        vol = "" if self.volume_size is None else f" / vol {self.volume_size * 1e3:g} mm"
        return f"P{self.order} {self.load} {self.mesh_size * 1e3:g} mm{vol}"

    def mesh(self) -> TetMesh:
        """The default saddle meshed for this setting."""
        return mesh_default_seat(self.mesh_size, volume_size=self.volume_size)


@dataclass
class Figures:
    """Per site (in :data:`SITES` order): dent [m/N] (mean and under the centre) and stone
    stiffness [N/m]; the solve's size and cost."""

    dent: np.ndarray
    dent_centre: np.ndarray
    stiffness: np.ndarray
    n_dofs: int
    seconds: float
    extra: dict = field(default_factory=dict)

    def errors(self, ref: "Figures") -> tuple[float, float]:
        """Worst relative error over the sites of (stiffness, dent) against ``ref``."""
        return (float(np.max(np.abs(self.stiffness / ref.stiffness - 1.0))),
                float(np.max(np.abs(self.dent / ref.dent - 1.0))))


class _Solver:
    """One clamped, factorized stiffness of a mesh, and the top surface's trace."""

    def __init__(self, mesh: TetMesh, order: int, young: float, poisson: float):
        t0 = time.perf_counter()
        self.mesh, self.order = mesh, order
        self.basis = elasticity_basis(mesh, order)
        K = stiffness_matrix(self.basis, young, poisson)
        self.n = K.shape[0]
        self.free = free_dofs(self.n, clamp_dofs(self.basis, mesh))
        self.fact = factorize(K.tocsr()[self.free][:, self.free], "cholmod")
        self.seconds = time.perf_counter() - t0

    def solve(self, F: np.ndarray) -> np.ndarray:
        u = np.zeros_like(F)
        u[self.free] = self.fact.solve(F[self.free])
        return u


def _sites(sites) -> np.ndarray:
    return np.array(list(sites.values()), dtype=float)


def jittered(sites, radius: float, n: int = 6) -> dict[str, np.ndarray]:
    """Each site and ``n`` points on a circle of ``radius`` around it (plan, (n + 1, 2)):
    a stone lands anywhere relative to the vertices, and a bundle's answer depends on
    where (the converged one barely does over a few millimetres)."""
    th = 2 * np.pi * np.arange(n) / n
    ring = radius * np.column_stack([np.cos(th), np.sin(th)])
    return {k: np.vstack([np.asarray(c, float), np.asarray(c, float) + ring]) for k, c in sites.items()}


def measure_setting(setting: Setting, *, mesh: TetMesh | None = None, sites=SITES, young: float = DEFAULT_YOUNG,
                    poisson: float = DEFAULT_POISSON, patch_radius: float | None = None,
                    jitter: float | None = None) -> Figures:
    """Dent and stone stiffness as a bundle of ``setting`` gives them (see the module notes).

    Each site's figure is the mean over the site and 6 points ``jitter`` [m] around it
    (default half the mesh size; 0: the site alone); ``extra["spread"]`` holds, per
    quantity, the largest relative deviation from that mean. ``mesh``: use this mesh
    instead of meshing the default seat (tests)."""
    t0 = time.perf_counter()
    mesh = setting.mesh() if mesh is None else mesh
    a_s = stone_patch_radius(young=young, poisson=poisson) if patch_radius is None else patch_radius
    jitter = 0.5 * setting.mesh_size if jitter is None else jitter
    sol = _Solver(mesh, setting.order, young, poisson)
    surface = extract_surface(mesh)
    V = mesh.points[surface.nodes]
    T = surface.triangles
    n_v = surface.nodes.size
    vdofs = vertex_dofs(sol.basis, surface.nodes)  # (n, 3)
    hat = None
    if setting.load == "hat":
        hat = hat_load_matrix(sol.basis, surface.nodes[surface.contactable], surface.areas[surface.contactable])

    def respond(f: np.ndarray) -> np.ndarray:
        """Vertex forces (n, 3) -> vertex displacements (n, 3) through the bundle's columns."""
        f = np.where(surface.contactable[:, None], f, 0.0)  # a clamped vertex has no column
        F = np.zeros(sol.n)
        if hat is None:
            F[vdofs.ravel()] = f.ravel()
        else:
            F = hat @ f[surface.contactable].ravel()
        return sol.solve(F)[vdofs]

    gf = SimpleNamespace(vertices=V, triangles=T, contactable=surface.contactable, fixed=surface.fixed)
    dent, centre, k, spread = [], [], [], {"dent": [], "stiffness": []}
    points = jittered(sites, jitter) if jitter > 0 else {n: np.asarray([c], float) for n, c in sites.items()}
    for pts in points.values():
        loc = locate_probes(V, T, pts)
        normals = triangle_normals(V, T[loc.triangle])
        verts, w = patch_weights(gf, loc.triangle, loc.lam, np.full(len(pts), a_s), normals, profile="hertz")
        d_i, c_i, k_i = [], [], []
        for i, c in enumerate(pts):
            f = nodal_loads(V, T, T, n_v, LoadCase(tuple(c), DENT_RADIUS, 1.0), order=1)
            f /= np.linalg.norm(f.sum(axis=0))
            u = respond(f)
            d_i.append(float(np.sum(f * u)))
            c_i.append(float(-normals[i] @ (loc.lam[i] @ u[T[loc.triangle[i]]])))
            fs = np.zeros((n_v, 3))
            np.add.at(fs, verts[i], -w[i][:, None] * normals[i][None, :])
            k_i.append(1.0 / float(np.sum(fs * respond(fs))))
        for name, vals, out in (("dent", d_i, dent), ("stiffness", k_i, k)):
            vals = np.asarray(vals)
            out.append(float(vals.mean()))
            spread[name].append(float(np.max(np.abs(vals / vals.mean() - 1.0))))
        centre.append(float(np.mean(c_i)))
    return Figures(np.array(dent), np.array(centre), np.array(k), int(sol.n), time.perf_counter() - t0,
                   {"n_tets": int(mesh.tets.shape[0]), "n_surface": int(n_v),
                    "n_contactable": int(surface.contactable.sum()), "patch_radius": a_s,
                    "jitter": jitter, "spread": {k_: np.array(v) for k_, v in spread.items()}})


def measure_consistent(mesh: TetMesh, order: int = 2, *, sites=SITES, young: float = DEFAULT_YOUNG,
                       poisson: float = DEFAULT_POISSON, patch_radius: float | None = None,
                       dent_radius: float = DENT_RADIUS) -> Figures:
    """Dent and stone stiffness with consistent loads (the reference's definition): the disc's
    uniform pressure (plan radius ``dent_radius``) and the patch's Hertz pressure (radius
    ``patch_radius``, default :func:`stone_patch_radius`) integrated on the element trace, the
    work F . u per newton (the pressure-weighted mean normal displacement)."""
    t0 = time.perf_counter()
    a_s = stone_patch_radius(young=young, poisson=poisson) if patch_radius is None else patch_radius
    sol = _Solver(mesh, order, young, poisson)
    tris = boundary_triangles(mesh.tets)
    topkey = set(map(tuple, np.sort(mesh.groups["top"], axis=1).tolist()))
    tris = tris[[tuple(t) in topkey for t in np.sort(tris, axis=1).tolist()]]
    nodes, table = trace_nodes(sol.basis, tris, order)
    centres = _sites(sites)
    loc = locate_probes(mesh.points, tris, centres)
    normals = triangle_normals(mesh.points, tris[loc.triangle])
    n_nodes = table.shape[0]

    def load(c, radius: float, profile: str) -> np.ndarray:
        if profile == "uniform":
            f = nodal_loads(mesh.points, tris, nodes, n_nodes, LoadCase(tuple(c), radius, 1.0), order=order)
        else:
            # Hertz p0 sqrt(1 - r^2/a^2) as a sum of uniform discs of equal pressure (Abel layering):
            # radii r_k = a sqrt(1 - t_k^2), t_k the midpoints of 32 equal steps in t = p / p0
            f = np.zeros((n_nodes, 3))
            for r in radius * np.sqrt(1.0 - ((np.arange(32) + 0.5) / 32) ** 2):
                f += nodal_loads(mesh.points, tris, nodes, n_nodes, LoadCase(tuple(c), float(r), 1.0), order=order)
        F = np.zeros(sol.n)
        F[table.ravel()] = f.ravel()
        return F / np.linalg.norm(f.sum(axis=0))

    dent, centre, k = [], [], []
    for i, c in enumerate(centres):
        F = load(c, dent_radius, "uniform")
        u = sol.solve(F)
        dent.append(float(F @ u))
        N = trace_shape(loc.lam[i:i + 1], order)[0]
        centre.append(float(-normals[i] @ (N @ u[table[nodes[loc.triangle[i]]]])))
        F = load(c, a_s, "hertz")
        k.append(1.0 / float(F @ sol.solve(F)))
    return Figures(np.array(dent), np.array(centre), np.array(k), int(sol.n), time.perf_counter() - t0,
                   {"n_tets": int(mesh.tets.shape[0]), "patch_radius": a_s})


def reference_mesh(size: float, *, mesh_size: float = 0.006, sites=SITES, growth: float = 0.3) -> TetMesh:
    """The saddle refined to ``size`` [m] around every site (growing by ``growth`` per metre away)."""
    refine = tuple(Refinement(float(x), float(y), size, growth) for x, y in sites.values())
    return mesh_default_seat(mesh_size, refine=refine)


@dataclass
class Convergence:
    """The reference and the levels before it."""

    sizes: list[float]
    levels: list[Figures]

    @property
    def reference(self) -> Figures:
        return self.levels[-1]

    def rates(self) -> dict[str, np.ndarray]:
        """Observed order per site from the last three levels, for dent and stiffness:
        log(|q1 - q2| / |q2 - q3|) / log(h1/h2) (levels with a constant ratio h1/h2 = h2/h3)."""
        if len(self.levels) < 3:
            return {}
        q = self.levels[-3:]
        r = self.sizes[-3] / self.sizes[-2]
        out = {}
        for name in ("dent", "stiffness"):
            a, b, c = (getattr(x, name) for x in q)
            out[name] = np.log(np.abs(a - b) / np.maximum(np.abs(b - c), 1e-300)) / np.log(r)
        return out

    def extrapolation_error(self) -> dict[str, float]:
        """Worst relative Richardson estimate of the reference's own error (rate from :meth:`rates`,
        floored at 1): |q2 - q3| / (ratio^p - 1) / |q3|."""
        rates = self.rates()
        if not rates:
            return {}
        r = self.sizes[-2] / self.sizes[-1]
        out = {}
        for name, p in rates.items():
            b, c = getattr(self.levels[-2], name), getattr(self.levels[-1], name)
            p = np.maximum(np.nan_to_num(p, nan=1.0), 1.0)
            out[name] = float(np.max(np.abs(b - c) / (r**p - 1.0) / np.abs(c)))
        return out


def converge_reference(sizes: Sequence[float] = REFERENCE_SIZES, *, sites=SITES) -> Convergence:
    """P2 with consistent loads on :func:`reference_mesh` at each size (coarse to fine)."""
    levels = [measure_consistent(reference_mesh(h, sites=sites), 2, sites=sites) for h in sizes]
    return Convergence(list(sizes), levels)


def _reference_key(sizes: Sequence[float], sites) -> dict:
    """What a cached reference must have been computed for: the levels, sites, the default seat's
    geometry (its file's hash) and gmsh's version, the defaults' material and the loads."""
    import gmsh

    return {"sizes": [float(h) for h in sizes], "sites": {k: [float(x) for x in v] for k, v in sites.items()},
            "geometry": hashlib.sha256(default_seat_path().read_bytes()).hexdigest(),
            "gmsh": str(gmsh.__version__), "young": DEFAULT_YOUNG, "poisson": DEFAULT_POISSON,
            "dent_radius": DENT_RADIUS, "patch_radius": stone_patch_radius(), "version": 1}


def save_convergence(conv: Convergence, path: str | os.PathLike, *, sites=SITES) -> None:
    """Write ``conv`` to ``path`` (``.npz``, atomically) with the key :func:`load_convergence` checks."""
    lv = conv.levels
    with replacing(path) as tmp:
        np.savez(tmp, key=json.dumps(_reference_key(conv.sizes, sites)),
                 dent=np.array([f.dent for f in lv]), dent_centre=np.array([f.dent_centre for f in lv]),
                 stiffness=np.array([f.stiffness for f in lv]), n_dofs=np.array([f.n_dofs for f in lv]),
                 seconds=np.array([f.seconds for f in lv]), n_tets=np.array([f.extra["n_tets"] for f in lv]),
                 patch_radius=np.array([f.extra["patch_radius"] for f in lv]))


def load_convergence(path: str | os.PathLike, sizes: Sequence[float], *, sites=SITES) -> Convergence | None:
    """The reference saved by :func:`save_convergence` at ``path``, or None if there is none or it
    was computed for other levels, sites, material or loads."""
    try:
        with np.load(path) as z:
            if json.loads(str(z["key"])) != _reference_key(sizes, sites):
                return None
            levels = [Figures(z["dent"][i], z["dent_centre"][i], z["stiffness"][i], int(z["n_dofs"][i]),
                              float(z["seconds"][i]), {"n_tets": int(z["n_tets"][i]),
                                                       "patch_radius": float(z["patch_radius"][i])})
                      for i in range(len(sizes))]
    except (OSError, KeyError, ValueError, IndexError):
        return None
    return Convergence([float(h) for h in sizes], levels)


def cached_reference(sizes: Sequence[float] = REFERENCE_SIZES, path: str | os.PathLike | None = None, *,
                     sites=SITES) -> Convergence:
    """:func:`converge_reference`, read from ``path`` if a matching one was saved there, else
    computed (minutes) and saved there (``path`` None: computed, not saved)."""
    if path is not None:
        conv = load_convergence(path, sizes, sites=sites)
        if conv is not None:
            logger.info("reference read from %s", path)
            return conv
    conv = converge_reference(sizes, sites=sites)
    if path is not None:
        save_convergence(conv, path, sites=sites)
    return conv


@dataclass
class Row:
    """One setting of the table: its cost and its errors against the reference."""

    setting: Setting
    figures: Figures
    precompute_s: list[float]
    peak_mb: float
    stiffness_error: float
    dent_error: float

    @property
    def ok(self) -> bool:
        return self.stiffness_error <= TARGET and self.dent_error <= TARGET


def precompute_cost(setting: Setting, repeats: int = 1) -> tuple[list[float], float]:
    """Wall times [s] of ``build_bundle(reuse=False)`` (meshing included) and the peak RSS of
    this process [MB] afterwards (a running maximum: measure the biggest setting last)."""
    times = []
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats):
            t = time.perf_counter()
            build_bundle(f"{tmp}/b", mesh_size=setting.mesh_size, order=setting.order, load=setting.load,
                         volume_size=setting.volume_size, reuse=False)
            times.append(time.perf_counter() - t)
    return times, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def score(settings: Sequence[Setting], ref: Figures, *, repeats: int = 1, time_it: bool = True) -> list[Row]:
    """Each setting measured against ``ref`` (and its precompute timed, unless not ``time_it``)."""
    rows = []
    for s in settings:
        fig = measure_setting(s)
        times, peak = precompute_cost(s, repeats) if time_it else ([math.nan], math.nan)
        ek, ed = fig.errors(ref)
        rows.append(Row(s, fig, times, peak, ek, ed))
    return rows


#: The settings the table compares: the old default first, then the new one.
SETTINGS = (
    Setting(0.006, 1, "point"),
    Setting(0.006, 2, "point"),
    Setting(0.006, 1, "hat"),
    Setting(0.006, 2, "hat"),
    Setting(0.006, 1, "point", 0.003),
    Setting(0.006, 2, "point", 0.0055),
    Setting(0.006, 2, "point", 0.005),
    Setting(0.006, 2, "point", 0.0045),
    Setting(0.005, 2, "point"),
)


#: The frontier (``--frontier``): P2 point columns on these surface sizes [m], no grading.
FRONTIER_SIZES = (0.006, 0.0055, 0.005, 0.0045, 0.004, 0.0035)
#: A few variants on the frontier's surfaces: finer volume under the same surface, hat columns.
FRONTIER_VARIANTS = (
    Setting(0.0055, 2, "point", 0.005),
    Setting(0.005, 2, "point", 0.0045),
    Setting(0.004, 2, "hat"),
    Setting(0.0035, 2, "hat"),
)


@dataclass
class Cost:
    """Precompute cost of one setting: per ``build_bundle`` run, the wall time [s], the CPU time of
    this process and its children [s] (all threads; the machine's load does not inflate it) and
    the 1-minute load average as the run ended; the peak RSS of this process afterwards [MB]."""

    wall: list[float]
    cpu: list[float]
    load: list[float]
    peak_mb: float

    @staticmethod
    def summary(values: Sequence[float]) -> str:
        """``min/median/max`` of ``values`` (one value: itself)."""
        v = np.asarray(values, float)
        if v.size == 1:
            return f"{v[0]:.1f}"
        return f"{v.min():.1f}/{np.median(v):.1f}/{v.max():.1f}"


def _cpu_seconds() -> float:
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def precompute_timings(setting: Setting, repeats: int = 2, *, budget: float = math.inf,
                       mesh: TetMesh | None = None) -> Cost:
    """Time ``build_bundle(reuse=False)`` of ``setting`` (meshing included) ``repeats`` times, or
    fewer: no further run once one took longer than ``budget`` [s] of wall time. ``mesh``: build
    this mesh instead of meshing the default seat (tests)."""
    wall, cpu, load = [], [], []
    kw = (dict(mesh=mesh) if mesh is not None else
          dict(mesh_size=setting.mesh_size, volume_size=setting.volume_size))
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(max(repeats, 1)):
            t, c = time.perf_counter(), _cpu_seconds()
            build_bundle(f"{tmp}/b", order=setting.order, load=setting.load, reuse=False, **kw)
            wall.append(time.perf_counter() - t)
            cpu.append(_cpu_seconds() - c)
            load.append(os.getloadavg()[0])
            if wall[-1] > budget:
                break
    return Cost(wall, cpu, load, resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)


@dataclass
class FrontierRow:
    """One setting of the frontier: its signed errors per site against the reference, and its costs.

    ``consistent``: the signed (dent, stiffness) errors of P2 with the reference's consistent loads on
    the same mesh (what the mesh itself allows; the rest of the setting's error is the columns' load).
    """

    setting: Setting
    figures: Figures
    dent_error: np.ndarray
    stiffness_error: np.ndarray
    cost: Cost | None = None
    consistent: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def ok(self) -> bool:
        """Both site-mean errors within :data:`TARGET` at every site."""
        return bool(np.max(np.abs(self.dent_error)) <= TARGET and np.max(np.abs(self.stiffness_error)) <= TARGET)

    @property
    def spread(self) -> float:
        """The largest landing-position spread (dent or stiffness, any site)."""
        return float(max(np.max(v) for v in self.figures.extra["spread"].values()))

    @property
    def n_contactable(self) -> int:
        """Columns of D (the runtime's cost grows with it; D is 3 n_surface x 3 n_contactable)."""
        return int(self.figures.extra["n_contactable"])


def frontier(settings: Sequence[Setting], ref: Figures, *, sites=SITES, meshes: dict | None = None,
             young: float = DEFAULT_YOUNG, poisson: float = DEFAULT_POISSON,
             consistent: bool = False) -> list[FrontierRow]:
    """Accuracy of each setting against ``ref`` (signed, per site; no timing: see :func:`time_frontier`).
    ``meshes``: setting -> mesh to use instead of meshing the default seat (tests). ``consistent``:
    also P2 with consistent loads on each setting's mesh (:func:`measure_consistent`, once per mesh)."""
    rows = []
    split: dict = {}
    for s in settings:
        mesh = (meshes or {}).get(s)
        mesh = s.mesh() if mesh is None else mesh
        fig = measure_setting(s, mesh=mesh, sites=sites, young=young, poisson=poisson)
        rows.append(FrontierRow(s, fig, fig.dent / ref.dent - 1.0, fig.stiffness / ref.stiffness - 1.0))
        if consistent:
            key = mesh.content_hash()
            if key not in split:
                c = measure_consistent(mesh, 2, sites=sites, young=young, poisson=poisson,
                                       patch_radius=fig.extra["patch_radius"])
                split[key] = (c.dent / ref.dent - 1.0, c.stiffness / ref.stiffness - 1.0)
            rows[-1].consistent = split[key]
        logger.info("%s: dent %s, stiffness %s", s.label, np.round(100 * rows[-1].dent_error, 1),
                    np.round(100 * rows[-1].stiffness_error, 1))
    return rows


def time_frontier(rows: Sequence[FrontierRow], *, repeats: int = 2, budget: float = math.inf,
                  all_rows: bool = False, meshes: dict | None = None) -> None:
    """Fill each row's :class:`Cost` (:func:`precompute_timings`), cheapest surface first: the rows
    without volume grading in point columns, and any other that meets the target (``all_rows``:
    every row). A row costlier than ``budget`` gets one run."""
    for r in sorted(rows, key=lambda r: (r.n_contactable, r.figures.n_dofs)):
        plain = r.setting.load == "point" and r.setting.volume_size is None
        if all_rows or plain or r.ok:
            r.cost = precompute_timings(r.setting, repeats, budget=budget, mesh=(meshes or {}).get(r.setting))
            logger.info("%s: precompute %s s wall, %s s CPU, load %s", r.setting.label, Cost.summary(r.cost.wall),
                        Cost.summary(r.cost.cpu), Cost.summary(r.cost.load))


def cheapest(rows: Sequence[FrontierRow]) -> FrontierRow | None:
    """The cheapest row that meets the target: the fewest columns of D (the runtime's cost), then the
    lowest median precompute CPU time (untimed rows last); None if no row does."""
    ok = [r for r in rows if r.ok]
    if not ok:
        return None
    return min(ok, key=lambda r: (r.n_contactable, np.median(r.cost.cpu) if r.cost else math.inf))


def format_frontier(rows: Sequence[FrontierRow]) -> str:
    """The frontier as text: errors per site (rear / middle / nose), spread, size of D, precompute cost."""
    lines = [f"{'setting':<24}{'dent err %':>18}{'stiffness err %':>18}{'consistent d / k %':>26}"
             f"{'spread %':>10}{'surface':>9}"
             f"{'columns':>9}{'dofs':>8}{'wall s':>17}{'CPU s':>17}{'load':>14}{'peak MB':>9}  5 %"]
    for r in rows:
        c = r.cost
        de = "/".join(f"{100 * x:+.0f}" for x in r.dent_error)
        ke = "/".join(f"{100 * x:+.0f}" for x in r.stiffness_error)
        ce = ("  ".join("/".join(f"{100 * x:+.0f}" for x in e) for e in r.consistent) if r.consistent else "-")
        timing = (f" {Cost.summary(c.wall):>16} {Cost.summary(c.cpu):>16} {Cost.summary(c.load):>13}{c.peak_mb:>9.0f}"
                  if c else f"{'-':>17}{'-':>17}{'-':>14}{'-':>9}")
        lines.append(f"{r.setting.label:<24}{de:>18}{ke:>18}{ce:>26}{100 * r.spread:>10.0f}"
                     f"{r.figures.extra['n_surface']:>9d}{r.n_contactable:>9d}{r.figures.n_dofs:>8d}{timing}"
                     f"  {'yes' if r.ok else 'no'}")
    best = cheapest(rows)
    if best is None:
        lines.append(f"no setting meets {TARGET:.0%} on both dent and stiffness at every site")
    else:
        cost = f"precompute {Cost.summary(best.cost.wall)} s wall" if best.cost else "not timed"
        lines.append(f"cheapest within {TARGET:.0%}: {best.setting.label} ({best.n_contactable} columns, {cost})")
    narrow = [r for r in rows if r.spread < TARGET]
    if narrow:
        lines.append(f"landing-position spread under {TARGET:.0%} from: "
                     + ", ".join(r.setting.label for r in narrow))
    else:
        lines.append(f"landing-position spread under {TARGET:.0%}: none of these")
    return "\n".join(lines)


def format_convergence(conv: Convergence) -> str:
    """The reference's levels, rates and own-error estimate as text."""
    names = list(SITES)
    lines = ["reference: P2, consistent loads, refined around the sites",
             "dent [um/N] and stone stiffness k [kN/m] at " + ", ".join(names),
             "size [mm]     dofs  " + " ".join(f"{n:>7}" for n in names) + "    " + " ".join(f"{n:>7}" for n in names)]
    for h, f in zip(conv.sizes, conv.levels):
        lines.append(f"{h * 1e3:>8.2f} {f.n_dofs:>8d}  " + " ".join(f"{x * 1e6:>7.2f}" for x in f.dent) +
                     "    " + " ".join(f"{x / 1e3:>7.3f}" for x in f.stiffness))
    for name, p in conv.rates().items():
        lines.append(f"observed rate ({name}): " + ", ".join(f"{n} {v:.2f}" for n, v in zip(names, p)))
    for name, e in conv.extrapolation_error().items():
        lines.append(f"reference's own error ({name}, Richardson): {e:.2%}")
    return "\n".join(lines)


def format_table(rows: Sequence[Row]) -> str:
    """The settings table as text."""
    lines = [f"{'setting':<26}{'precompute s (min/med/max)':>28}{'peak MB':>9}{'dofs':>8}"
             f"{'stiffness err':>15}{'dent err':>10}{'centre err':>12}  within 5 %"]
    for r in rows:
        t = np.array(r.precompute_s)
        ts = f"{t.min():.1f}/{np.median(t):.1f}/{t.max():.1f}"
        lines.append(f"{r.setting.label:<26}{ts:>28}{r.peak_mb:>9.0f}{r.figures.n_dofs:>8d}"
                     f"{r.stiffness_error:>15.1%}{r.dent_error:>10.1%}{r.figures.extra.get('centre_error', math.nan):>12.1%}"
                     f"  {'yes' if r.ok else 'no'}")
    return "\n".join(lines)


def _sizes_mm(text: str) -> tuple[float, ...]:
    try:
        sizes = tuple(float(x) * 1e-3 for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a comma-separated list of sizes in mm: {text!r}") from None
    if not sizes or min(sizes) <= 0:
        raise argparse.ArgumentTypeError(f"sizes must be positive: {text!r}")
    return sizes


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="coarse reference levels, no timing repeats")
    ap.add_argument("--repeats", type=int, default=None,
                    help="precompute runs per setting (min/median/max; default 3, --frontier 2)")
    ap.add_argument("--no-timing", action="store_true", help="accuracy only (no build_bundle runs)")
    ap.add_argument("--reference-cache", metavar="FILE.npz", default=None,
                    help="read the reference from this file if it holds the same levels, else compute and save it")
    ap.add_argument("--frontier", action="store_true",
                    help="P2 point columns over surface sizes (and a few variants): cheapest within 5 %%")
    ap.add_argument("--sizes", type=_sizes_mm, default=FRONTIER_SIZES, metavar="MM,MM,...",
                    help="--frontier: surface sizes [mm] (default 6,5.5,5,4.5,4,3.5)")
    ap.add_argument("--no-variants", action="store_true", help="--frontier: the plain P2 point rows only")
    ap.add_argument("--no-consistent", action="store_true",
                    help="--frontier: skip P2 with consistent loads on each setting's mesh")
    ap.add_argument("--budget", type=float, default=150.0, metavar="S",
                    help="--frontier: no repeat of a precompute that took more than S seconds (default 150)")
    args = ap.parse_args(argv)
    if args.reference_cache is not None:
        folder = os.path.dirname(os.path.abspath(args.reference_cache))
        if not os.path.isdir(folder) or not os.access(folder, os.W_OK):
            print(f"defaults_study: cannot write the reference cache in {folder}", file=sys.stderr)
            return 3
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    if args.frontier:
        logger.setLevel(logging.INFO)
    t0 = time.perf_counter()
    conv = cached_reference(QUICK_REFERENCE_SIZES if args.quick else REFERENCE_SIZES, args.reference_cache)
    print(format_convergence(conv), flush=True)
    ref = conv.reference
    print(f"\nstone: radius {STONE_RADIUS * 1e3:g} mm, Hertz patch radius {ref.extra['patch_radius'] * 1e3:.2f} mm; "
          f"dent: 1 N over a {2e3 * DENT_RADIUS:g} mm disc")
    if args.frontier:
        settings = [Setting(h, 2, "point") for h in args.sizes]
        settings += [] if args.no_variants else [v for v in FRONTIER_VARIANTS if v not in settings]
        rows = frontier(settings, ref, consistent=not args.no_consistent)
        print("errors rear/middle/nose of the site means; consistent: P2 with the reference's loads on the same "
              "mesh; spread: largest over the landing positions", flush=True)
        print(format_frontier(rows), flush=True)
        if not args.no_timing:
            time_frontier(rows, repeats=1 if args.quick else (args.repeats or 2), budget=args.budget)
            print(format_frontier(rows))
        print(f"({time.perf_counter() - t0:.0f} s)")
        return 0
    rows = score(SETTINGS, ref, repeats=1 if args.quick else (args.repeats or 3), time_it=not args.no_timing)
    for r in rows:
        r.figures.extra["centre_error"] = float(np.max(np.abs(r.figures.dent_centre / ref.dent_centre - 1.0)))
    print(format_table(rows))
    print(f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
