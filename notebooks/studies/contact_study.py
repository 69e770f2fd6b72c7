"""Contact studies: mesh dependence of point vs patch contacts, degenerate contacts, locking.

Three importable studies (tested in ``tests/test_contact_study.py``, charted
in ``notebooks/mesh_dependence.ipynb``):

:func:`contact_stiffness_vs_mesh`
    Effective normal stiffness ``k`` of one stone at fixed points of the seat
    against the mesh size, for a point contact (force on one triangle's
    vertices) and a patch contact (force spread over a Hertz pressure disc of
    fixed physical radius, :func:`hailstorm.runtime.contact.weights.patch_weights`). A point
    load on an elastic body is singular (Boussinesq: ``u ~ 1/r``), so the
    point stiffness keeps falling as the mesh is refined (like ``h`` on a
    half-space); the patch stiffness converges.
:func:`degenerate_contacts`
    Coincident, nearly coincident, clamped and conflicting contacts: the
    condition number of ``W = B^T D B`` and what the solver does with it
    (:attr:`hailstorm.runtime.contact.Capacitance.exact`, rigid flags, the force split).
:func:`locking_vs_poisson`
    Tip deflection of a cantilever with P1 and P2 tetrahedra as
    ``nu -> 0.5``: P1 locks (volumetric and in bending), P2 much less.

and the stability study (charted in ``notebooks/stability.ipynb``):

:func:`stability_map`
    One stone in contact, advanced by :func:`hailstorm.runtime.storm.hail.contact_step`
    exactly as the storm does, for every (stiffness, mass, time step):
    bounded or diverged (energy growth), against the predicted explicit
    limit :func:`predicted_dt_limit` ``dt = 2 / omega``;
    :func:`measure_dt_limit` finds the measured limit by bisection.

The committed figures are regenerated with::

    python -m studies.contact_study --out notebooks/figures/mesh_dependence.png
    python -m studies.contact_study stability --out notebooks/figures/stability.png

(``--small`` for the coarse levels / a small grid only). Bundles are cached under
``<hailstorm cache>/contact_study`` (see :func:`hailstorm.precompute.default_cache_dir`),
so a second run only re-reads them. Scripts that call these functions must be
guarded by ``if __name__ == "__main__":`` (the offline stage may spawn worker
processes).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from hailstorm.precompute.geometry import TetMesh, box_mesh
from hailstorm.precompute.pipeline import build_bundle, default_cache_dir
from hailstorm.runtime.bundle.read import load as load_bundle
from hailstorm.runtime.contact import capacitance, hertz_radius, solve_contacts, triangle_normals
from hailstorm.runtime.contact.validate import Mode
from hailstorm.runtime.storm.hail import Integrator

__all__ = [
    "SEAT_POINTS",
    "StiffnessStudy",
    "contact_stiffness",
    "contact_stiffness_vs_mesh",
    "degenerate_contacts",
    "locate_points",
    "locking_vs_poisson",
    "measure_dt_limit",
    "plot_stability_map",
    "plot_stiffness_vs_mesh",
    "predicted_dt_limit",
    "seat_contact_stiffness",
    "separation_sweep",
    "StabilityMap",
    "stability_map",
]

#: Fixed probe points (x, y) on the default saddle's top [m]: the saddle's
#: rear (wide, sit bones) is at large x, the nose at small x, the clamp
#: underneath 0.12 < x < 0.205.
SEAT_POINTS: dict[str, tuple[float, float]] = {
    "sit bone": (0.22, 0.035),
    "above clamp": (0.16, 0.0),
    "nose": (0.05, 0.0),
}
#: Default mesh levels of the stiffness study [m] (gmsh fails to mesh the
#: saddle's clamp group at 4 and 4.5 mm with the current geometry).
MESH_SIZES = (0.015, 0.01, 0.008, 0.006, 0.0055, 0.005)
SMALL_MESH_SIZES = (0.015, 0.01, 0.008)
#: The stone and load that set the default (fixed, physical) patch: a 4 cm
#: hailstone pressing with 100 N (a ~20 m/s impact of ~30 g stopping in a
#: few ms) on the default seat (E = 2 MPa, nu = 0.35) gives a ~ 8.7 mm.
STONE_RADIUS = 0.02
LOAD = 100.0


def study_cache_dir() -> Path:
    """Where this module's bundles live: ``<hailstorm cache>/contact_study``."""
    return default_cache_dir() / "contact_study"


# --------------------------------------------------------------------------
# locating points and measuring stiffness
# --------------------------------------------------------------------------
def locate_points(gf: Any, xy: Sequence[Sequence[float]], *, min_nz: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """Contact triangle and barycentric coordinates of the top surface under points (x, y).

    A vertical ray from above hits the upward-facing (``n_z > min_nz``)
    triangles whose vertices all own a column of D; the highest hit wins.

    Returns
    -------
    tri : (p,) int ndarray
    bary : (p, 3) float ndarray

    Raises
    ------
    ValueError
        If a point lies off the (contactable, upward-facing) top surface.
    """
    X = np.asarray(gf.vertices, dtype=np.float64)
    T = np.asarray(gf.triangles)
    n = triangle_normals(X, T)
    ok = (n[:, 2] > min_nz) & (gf.contactable | gf.fixed)[T].all(axis=1)
    P = X[T[ok]]
    idx = np.flatnonzero(ok)
    v0 = P[:, 1, :2] - P[:, 0, :2]
    v1 = P[:, 2, :2] - P[:, 0, :2]
    det = v0[:, 0] * v1[:, 1] - v0[:, 1] * v1[:, 0]
    tris, barys = [], []
    for x, y in np.asarray(xy, dtype=np.float64).reshape(-1, 2):
        v2 = np.array([x, y]) - P[:, 0, :2]
        with np.errstate(divide="ignore", invalid="ignore"):
            l1 = (v2[:, 0] * v1[:, 1] - v2[:, 1] * v1[:, 0]) / det
            l2 = (v0[:, 0] * v2[:, 1] - v0[:, 1] * v2[:, 0]) / det
        inside = np.isfinite(l1) & np.isfinite(l2) & (l1 >= -1e-12) & (l2 >= -1e-12) & (l1 + l2 <= 1 + 1e-12)
        if not inside.any():
            raise ValueError(f"point ({x:g}, {y:g}) is not above the contactable top surface")
        b = np.stack([1.0 - l1 - l2, l1, l2], axis=1)
        z = np.einsum("ka,ka->k", b, P[:, :, 2])
        j = np.flatnonzero(inside)[np.argmax(z[inside])]
        bj = np.clip(b[j], 0.0, None)
        tris.append(idx[j])
        barys.append(bj / bj.sum())
    return np.asarray(tris, dtype=np.intp), np.asarray(barys)


def contact_stiffness(gf: Any, tri: Any, bary: Any, *, patch_radius: Any = None, mode: Mode = "frictionless",
                      profile: str = "hertz") -> np.ndarray:
    """Effective normal stiffness of single contacts (one at a time), [N/m].

    ``mode="frictionless"``: ``k = 1 / (n^T W n)`` (the stone only pushes
    along the normal, the storm's default); ``mode="sticky"``: ``k = n^T K n``
    with ``K = W^-1`` the 3x3 capacitance. ``k = 0`` at rigid (clamped)
    contacts is reported as ``inf``.
    """
    tri = np.asarray(tri, dtype=np.intp).reshape(-1)
    bary = np.asarray(bary, dtype=np.float64).reshape(-1, 3)
    a = np.broadcast_to(np.asarray(0.0 if patch_radius is None else patch_radius, dtype=np.float64), tri.shape)
    out = np.empty(tri.size)
    for k in range(tri.size):
        cap = capacitance(gf, tri[k:k + 1], bary[k:k + 1], mode=mode,
                          patch_radius=None if a[k] == 0 else float(a[k]), patch_profile=profile)
        if cap.rigid[0]:
            out[k] = np.inf
            continue
        n = cap.normals[0]
        out[k] = float(cap.K[0, 0]) if mode == "frictionless" else float(n @ cap.K @ n)
    return out


@dataclass
class StiffnessStudy:
    """Result of :func:`contact_stiffness_vs_mesh`.

    Attributes
    ----------
    mesh_sizes : (L,) float ndarray
        Mesh size of each level [m], coarse to fine.
    n_vertices : (L,) int ndarray
        Surface vertices of each level.
    points : list of str
        Probe names.
    k_point, k_patch : (L, p) float ndarray
        Normal stiffness of a point / patch contact [N/m].
    patch_radius : float
        The fixed patch radius [m].
    order : int
        Element order of the bundles.
    k_control : (L, p) float ndarray or None
        Stiffness of a wide patch (radius ``control_radius``): a control
        whose change between levels is the bulk discretisation and geometry
        error alone (no contact singularity at all).
    control_radius : float or None
    """

    mesh_sizes: np.ndarray
    n_vertices: np.ndarray
    points: list[str]
    k_point: np.ndarray
    k_patch: np.ndarray
    patch_radius: float
    order: int = 1
    k_control: np.ndarray | None = None
    control_radius: float | None = None
    extra: dict = field(default_factory=dict)

    def rel_change(self, which: str = "patch") -> np.ndarray:
        """``|k_l - k_{l-1}| / k_l`` between consecutive levels, (L-1, p); which: point, patch, control."""
        k = {"patch": self.k_patch, "point": self.k_point, "control": self.k_control}[which]
        if k is None:
            raise ValueError("no control patch in this study (control_radius=None)")
        return np.abs(np.diff(k, axis=0)) / np.abs(k[1:])

    def table(self) -> str:
        """A plain-text table (one row per level, point | patch per probe)."""
        ctl = self.k_control is not None
        cols = ["point", "patch"] + (["wide"] if ctl else [])
        ks = [self.k_point, self.k_patch] + ([self.k_control] if self.k_control is not None else [])
        wide = ""
        if ctl:
            assert self.control_radius is not None  # set together with k_control
            wide = f", wide patch a = {self.control_radius * 1e3:.0f} mm (control)"
        head = f"{'h [mm]':>7} {'verts':>6} | " + " | ".join(
            " ".join(f"{c:>8}" for c in cols) for _ in self.points)
        title = " | ".join(f"{p:^{9 * len(cols) - 1}}" for p in self.points)
        lines = [f"P{self.order}: k [kN/m]; point contact, patch a = {self.patch_radius * 1e3:.2f} mm" + wide,
                 f"{'':>14} | {title}", head]
        for i, h in enumerate(self.mesh_sizes):
            cells = " | ".join(" ".join(f"{k[i, j] / 1e3:8.4g}" for k in ks) for j in range(len(self.points)))
            lines.append(f"{h * 1e3:7.3g} {int(self.n_vertices[i]):6d} | {cells}")
        if len(self.mesh_sizes) > 1:
            ch = [self.rel_change(w)[-1] for w in ("point", "patch", "control")[:len(cols)]]
            cells = " | ".join(" ".join(f"{100 * c[j]:7.1f}%" for c in ch) for j in range(len(self.points)))
            lines.append(f"{'last change':>14} | {cells}")
        return "\n".join(lines)


def contact_stiffness_vs_mesh(
    mesh_sizes: Sequence[float] = MESH_SIZES,
    *,
    points: Mapping[str, Sequence[float]] | None = None,
    patch_radius: float | None = None,
    load: float = LOAD,
    stone_radius: float = STONE_RADIUS,
    order: int = 1,
    mesh: Callable[[float], TetMesh] | None = None,
    young: float | None = None,
    poisson: float | None = None,
    cache_dir: str | os.PathLike | None = None,
    mode: Mode = "frictionless",
    profile: str = "hertz",
    control_radius: float | None = 0.02,
) -> StiffnessStudy:
    """Normal contact stiffness of point and patch contacts against the mesh size.

    Parameters
    ----------
    mesh_sizes
        Mesh levels [m] (coarse to fine).
    points
        Name -> (x, y) of the probes on the top surface (default
        :data:`SEAT_POINTS`); located on each level by :func:`locate_points`.
    patch_radius
        Fixed physical patch radius [m]; default the Hertz radius of a rigid
        sphere of ``stone_radius`` pressed with ``load`` on the material
        (:func:`hailstorm.runtime.contact.sphere_patch.hertz_radius`).
    order
        Element order of the bundles.
    mesh
        ``h -> TetMesh`` (e.g. ``lambda h: box_mesh((0.1, 0.1, 0.05), h)``);
        default the saddle meshed by gmsh at ``h``.
    young, poisson
        Material (default: the offline stage's defaults).
    cache_dir
        Where to build/reuse bundles (default :func:`study_cache_dir`;
        reuse is keyed on the full cache key).
    mode, profile
        See :func:`contact_stiffness`.
    control_radius
        Radius [m] of a wide control patch (``None``: skip); its change
        between levels measures the bulk discretisation and geometry error.

    Returns
    -------
    StiffnessStudy
    """
    from hailstorm.precompute.fem import DEFAULT_POISSON, DEFAULT_YOUNG

    young = DEFAULT_YOUNG if young is None else float(young)
    poisson = DEFAULT_POISSON if poisson is None else float(poisson)
    points = dict(SEAT_POINTS if points is None else points)
    if patch_radius is None:
        patch_radius = float(hertz_radius(load, stone_radius, young, poisson))
    cache = Path(study_cache_dir() if cache_dir is None else cache_dir)
    tag = "seat" if mesh is None else "mesh"
    kp, ka, kc, nv = [], [], [], []
    for h in mesh_sizes:
        out = cache / f"{tag}-P{order}-h{h * 1e3:g}mm"  # reuse is keyed on everything that changes D
        kw: dict[str, Any] = dict(order=order, young=young, poisson=poisson)
        path = build_bundle(out, mesh_size=h, **kw) if mesh is None else build_bundle(out, mesh=mesh(h), **kw)
        gf = load_bundle(path)
        tri, bary = locate_points(gf, list(points.values()))
        kp.append(contact_stiffness(gf, tri, bary, mode=mode))
        ka.append(contact_stiffness(gf, tri, bary, patch_radius=patch_radius, mode=mode, profile=profile))
        if control_radius is not None:
            kc.append(contact_stiffness(gf, tri, bary, patch_radius=control_radius, mode=mode, profile=profile))
        nv.append(gf.n_vertices)
    return StiffnessStudy(np.asarray(mesh_sizes, dtype=float), np.asarray(nv), list(points), np.asarray(kp),
                          np.asarray(ka), float(patch_radius), order,
                          k_control=np.asarray(kc) if kc else None, control_radius=control_radius)


def plot_stiffness_vs_mesh(studies: StiffnessStudy | Sequence[StiffnessStudy], path: str | os.PathLike | None = None,
                           *, dpi: int = 90):
    """Chart: normal stiffness against mesh size, point (dashed, open) vs patch (solid), one panel per study.

    Each probe is normalised by its patch stiffness on the finest level of
    its study, so all probes share one axis. Returns the figure; saves a
    small PNG (about 9 x 3.6 in at ``dpi``) if ``path`` is given.
    """
    import matplotlib.pyplot as plt  # (headless: matplotlib falls back to Agg by itself)

    studies = [studies] if isinstance(studies, StiffnessStudy) else list(studies)
    fig, axes = plt.subplots(1, len(studies), figsize=(4.6 * len(studies), 3.6), sharey=True, squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for ax, st in zip(axes[0], studies):
        ref = st.k_patch[-1]
        for j, name in enumerate(st.points):
            c = colors[j % len(colors)]
            ax.plot(st.mesh_sizes * 1e3, st.k_point[:, j] / ref[j], ls="--", marker="o", mfc="none", color=c,
                    alpha=0.8)
            ax.plot(st.mesh_sizes * 1e3, st.k_patch[:, j] / ref[j], ls="-", marker="o", color=c, label=name)
        ax.invert_xaxis()
        ax.set_xlabel("mesh size h [mm] (finer to the right)")
        ax.set_title(f"P{st.order}: point (dashed) vs patch a = {st.patch_radius * 1e3:.1f} mm (solid)", fontsize=9)
        ax.grid(True, alpha=0.3)
    axes[0, 0].set_ylabel("k / k(patch, finest h)")
    axes[0, 0].legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    if path is not None:
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(path, dpi=dpi)
    return fig


# --------------------------------------------------------------------------
# degenerate contacts
# --------------------------------------------------------------------------
def _free_top_triangle(gf: Any) -> int:
    """An upward-facing triangle with all vertices contactable, nearest the middle of the top."""
    X = np.asarray(gf.vertices)
    T = np.asarray(gf.triangles)
    n = triangle_normals(X, T)
    ok = np.flatnonzero((n[:, 2] > 0.5) & gf.contactable[T].all(axis=1))
    if ok.size == 0:
        raise ValueError("no upward-facing contactable triangle")
    c = X[T[ok]].mean(axis=1)
    mid = c[:, :2].mean(axis=0)
    return int(ok[np.argmin(np.linalg.norm(c[:, :2] - mid, axis=1))])


def _cond(W: np.ndarray) -> float:
    if W.size == 0:
        return float("nan")
    lam = np.linalg.eigvalsh(0.5 * (W + W.T))
    return float("inf") if lam[0] <= 0 else float(lam[-1] / lam[0])


def degenerate_contacts(gf: Any, *, depth: float = 1e-3, mode: Mode = "frictionless",
                        patch_radius: float | None = None) -> list[dict]:
    """What the solver does with degenerate contact sets.

    Cases (all pressing ``depth`` along the inward normal unless stated):
    one contact (reference); two coincident contacts; two contacts ``1e-9``
    and ``1e-3`` apart in barycentric coordinates (nearly duplicate); two
    coincident contacts with conflicting prescriptions (one pressing, one
    pulling); a contact on a fully clamped triangle (with a free one); a
    contact on a partly clamped triangle whose weight is all on clamped
    vertices (rigid as a point contact; a patch around it reaches free
    vertices and is not).

    Returns
    -------
    list of dict
        ``case``, ``s``, ``cond_W`` (2-norm condition number of the live
        ``W``, ``inf`` if singular), ``exact`` (Cholesky vs pseudo-inverse),
        ``rigid`` (flags), ``fn`` (normal force on the seat per contact [N]),
        ``fn_total`` and ``fn_ref`` (the single contact's normal force).
    """
    T = np.asarray(gf.triangles)
    t = _free_top_triangle(gf)
    b = np.array([0.2, 0.5, 0.3])
    n = triangle_normals(gf.vertices, T[[t]])[0]
    u = -depth * n
    kw: dict[str, Any] = dict(mode=mode, patch_radius=patch_radius)

    def run(name, tri, bary, ubar):
        tri = np.asarray(tri, dtype=np.intp)
        bary = np.asarray(bary, dtype=np.float64)
        ubar = np.asarray(ubar, dtype=np.float64)
        cap = capacitance(gf, tri, bary, **kw)
        live = cap.live_dofs
        sol = solve_contacts(gf, tri, bary, ubar, rows=None, **kw)
        fn = np.einsum("ki,ki->k", sol.forces, cap.normals)
        return dict(case=name, s=int(tri.size), cond_W=_cond(cap.W[np.ix_(live, live)]), exact=bool(cap.exact),
                    rigid=cap.rigid.tolist(), fn=fn.tolist(), fn_total=float(fn.sum()))

    rows = [run("single contact", [t], [b], [u])]
    f_ref = rows[0]["fn_total"]
    rows.append(run("coincident pair", [t, t], [b, b], [u, u]))
    for d in (1e-9, 1e-3):
        b2 = b + np.array([d, -d, 0.0])
        rows.append(run(f"pair {d:g} apart (bary)", [t, t], [b, b2], [u, u]))
    rows.append(run("coincident, conflicting", [t, t], [b, b], [u, -u]))
    fixed_tris = np.flatnonzero(gf.fixed[T].all(axis=1))
    if fixed_tris.size:
        rows.append(run("on the clamp (+ a free one)", [t, fixed_tris[0]], [b, [1 / 3] * 3], [u, u]))
    partly = np.flatnonzero(gf.fixed[T].any(axis=1) & ~gf.fixed[T].all(axis=1)
                            & (gf.contactable | gf.fixed)[T].all(axis=1))
    if partly.size:
        tp = int(partly[0])
        bp = gf.fixed[T[tp]].astype(float)
        bp /= bp.sum()
        up = -depth * triangle_normals(gf.vertices, T[[tp]])[0]  # press along this triangle's own normal
        rows.append(run("weight all on clamped vertices", [tp], [bp], [up]))
    for r in rows:
        r["fn_ref"] = f_ref
    return rows


def separation_sweep(gf: Any, separations: Sequence[float] = (1e-1, 1e-2, 1e-3, 1e-4, 1e-6, 1e-8, 1e-10, 0.0), *,
                     mode: Mode = "frictionless", patch_radius: float | None = None) -> list[dict]:
    """Condition number of ``W`` and the force split of two contacts ``d`` apart (barycentric units).

    Returns rows with ``d``, ``cond_W``, ``exact``, ``split`` (share of the
    first contact in the total normal force) and ``total_rel`` (total normal
    force relative to one contact alone).
    """
    T = np.asarray(gf.triangles)
    t = _free_top_triangle(gf)
    b = np.array([0.2, 0.5, 0.3])
    n = triangle_normals(gf.vertices, T[[t]])[0]
    u = -1e-3 * n
    kw: dict[str, Any] = dict(mode=mode, patch_radius=patch_radius)
    one = solve_contacts(gf, [t], [b], [u], rows=None, **kw)
    f1 = float(one.forces[0] @ n)
    out = []
    for d in separations:
        b2 = b + np.array([d, -d, 0.0])
        cap = capacitance(gf, [t, t], [b, b2], **kw)
        sol = solve_contacts(gf, [t, t], [b, b2], [u, u], rows=None, **kw)
        fn = sol.forces @ n
        out.append(dict(d=float(d), cond_W=_cond(cap.W[np.ix_(cap.live_dofs, cap.live_dofs)]), exact=bool(cap.exact),
                        split=float(fn[0] / fn.sum()), total_rel=float(fn.sum() / f1)))
    return out


# --------------------------------------------------------------------------
# locking
# --------------------------------------------------------------------------
def cantilever_tip(order: int, poisson: float, *, length: float = 1.0, height: float = 0.1, size: float = 0.05,
                   young: float = 1e7, load: float = 1.0) -> tuple[float, float]:
    """Tip deflection of a clamped square beam under an end shear, and Timoshenko's value [m].

    The load is a uniform shear traction on the end face (total ``load``);
    the deflection is the mean vertical displacement of the end-face vertices.
    """
    import scipy.sparse.linalg as spla
    from skfem import FacetBasis, LinearForm

    from hailstorm.precompute.fem import clamp_dofs, elasticity_basis, free_dofs, stiffness_matrix, vertex_dofs

    E, P, h, L = young, load, height, length
    mesh = box_mesh((L, h, h), size, clamp="x0")
    basis = elasticity_basis(mesh, order)
    K = stiffness_matrix(basis, E, poisson)
    fixed = clamp_dofs(basis, mesh)
    end = basis.mesh.facets_satisfying(lambda x: np.isclose(x[0], L))
    fb = FacetBasis(basis.mesh, basis.elem, facets=end)

    @LinearForm
    def shear(v, w):
        return -P / h**2 * v[2]

    f = shear.assemble(fb)
    free = free_dofs(K.shape[0], fixed)
    u = np.zeros(K.shape[0])
    u[free] = spla.spsolve(K[free][:, free].tocsc(), f[free])
    tip = np.flatnonzero(np.isclose(mesh.points[:, 0], L))
    w = -u[vertex_dofs(basis, tip)[:, 2]].mean()
    inertia = h**4 / 12
    G = E / (2 * (1 + poisson))
    timoshenko = P * L**3 / (3 * E * inertia) + P * L / (5 / 6 * G * h**2)
    return float(w), float(timoshenko)


def locking_vs_poisson(poissons: Sequence[float] = (0.3, 0.4, 0.45, 0.49, 0.499), *, length: float = 1.0,
                       height: float = 0.1, size: float = 0.05) -> list[dict]:
    """P1 vs P2 tip deflection of a cantilever as ``nu -> 0.5`` (relative to Timoshenko).

    Returns rows ``poisson``, ``w_p1``, ``w_p2``, ``w_beam`` [m] and the ratios
    ``p1_ratio = w_p1 / w_beam``, ``p2_ratio = w_p2 / w_beam``.
    """
    rows = []
    for nu in poissons:
        w1, ref = cantilever_tip(1, nu, length=length, height=height, size=size)
        w2, _ = cantilever_tip(2, nu, length=length, height=height, size=size)
        rows.append(dict(poisson=float(nu), w_p1=w1, w_p2=w2, w_beam=ref, p1_ratio=w1 / ref, p2_ratio=w2 / ref))
    return rows


# --------------------------------------------------------------------------
# stability of the contact integrators
# --------------------------------------------------------------------------
#: Stone radii of the stability study [m] (ice, 2.5-12.5 mm).
STABILITY_RADII = (0.0025, 0.005, 0.0075, 0.01, 0.0125)
#: Energy growth (second half of a run over the first half) above which a run counts as diverged.
GROWTH_LIMIT = 10.0


def predicted_dt_limit(k: Any, m: Any) -> np.ndarray | float:
    """Explicit (symplectic Euler) stability limit ``dt = 2 / omega``, ``omega = sqrt(k / m)`` [s]."""
    dt = 2.0 / np.sqrt(np.asarray(k, dtype=np.float64) / np.asarray(m, dtype=np.float64))
    return float(dt) if np.ndim(dt) == 0 else dt


def seat_contact_stiffness(gf: Any, points: Mapping[str, Sequence[float]] | None = None, *,
                           patch_radius: float | None = None, mode: Mode = "frictionless") -> dict[str, float]:
    """Normal stiffness [N/m] of one stone at named points (x, y) of the seat (default :data:`SEAT_POINTS`)."""
    points = dict(SEAT_POINTS if points is None else points)
    tri, bary = locate_points(gf, list(points.values()))
    k = contact_stiffness(gf, tri, bary, patch_radius=patch_radius, mode=mode)
    return {name: float(kk) for name, kk in zip(points, k)}


def _energy(q, v, k, m, gn):
    """Mechanical energy of a stone on a (bilateral) contact spring, anchor 0, relative to its equilibrium."""
    u_eq = m * gn / k
    return 0.5 * m * v * v + 0.5 * k * (q - u_eq) ** 2


def _growth(k: float, m: float, dt: float, integrator: Integrator, *, steps: int, restitution: float | None,
            gravity: float, impact_speed: float, blowup: float = 1e20) -> float:
    """Energy growth of one stone in contact over ``steps`` steps of :func:`hailstorm.runtime.storm.hail.contact_step`.

    The stone touches the seat (``q = anchor = 0``) moving in at ``impact_speed``
    and stays in contact (bilateral: the contact holds, as for a stone resting
    on the seat); frictionless coordinates (the normal component, as the storm
    uses them).
    Returns ``max E over the second half / max E over the first half`` (``inf``
    once the energy exceeds ``blowup`` times its start or stops being finite).
    """
    from hailstorm.runtime.storm.hail import contact_step, damping_coefficients

    K = np.array([[float(k)]])
    M = np.array([float(m)])
    a = np.zeros(1)
    g = np.array([-float(gravity)])
    q, v = np.zeros(1), np.array([-float(impact_speed)])
    C: np.ndarray | float
    if restitution is None:
        C = 0.0
    elif integrator == "exact":
        C = damping_coefficients(K, M, restitution, integrator="exact")  # one contact: the storm's modal dashpot
    else:
        C = damping_coefficients(K, M, restitution, dt=dt, integrator=integrator)
    e0 = float(_energy(q[0], v[0], k, m, g[0]))
    half = steps // 2
    e1 = e2 = 0.0
    with np.errstate(all="ignore"):
        for n in range(steps):
            res = contact_step(q, v, a, M, g, dt, K=K, damping=C, integrator=integrator, unilateral=False)
            q, v = res.q, res.v
            e = float(_energy(q[0], v[0], k, m, g[0]))
            if not np.isfinite(e) or e > blowup * e0:
                return float("inf")
            if n < half:
                e1 = max(e1, e)
            else:
                e2 = max(e2, e)
    return e2 / e1 if e1 > 0 else (float("inf") if e2 > 0 else 1.0)


@dataclass
class StabilityMap:
    """Result of :func:`stability_map`.

    Attributes
    ----------
    integrator : str
    stiffness : (nk,) ndarray
        Contact stiffness [N/m].
    masses : (nm,) ndarray
        Stone masses [kg].
    dt : (nk, nm, nd) ndarray
        Time steps [s] (the same for every (k, m) unless the grid was relative).
    growth : (nk, nm, nd) ndarray
        Energy growth factor (max energy over the second half of the run over
        the first half; ``inf``: blew up).
    diverged : (nk, nm, nd) bool ndarray
        ``growth > growth_limit``.
    steps, growth_limit, restitution
        The run's settings (``restitution=None``: no dashpot).
    limit : (nk, nm) ndarray or None
        Measured limit by bisection (:func:`measure_dt_limit`; ``inf``: none
        found up to ``span`` times ``2/omega``), if the map was made with
        ``bisect=True``.
    """

    integrator: str
    stiffness: np.ndarray
    masses: np.ndarray
    dt: np.ndarray
    growth: np.ndarray
    diverged: np.ndarray
    steps: int
    growth_limit: float
    restitution: float | None = None
    limit: np.ndarray | None = None

    @property
    def omega(self) -> np.ndarray:
        """``sqrt(k / m)``, (nk, nm) [rad/s]."""
        return np.sqrt(self.stiffness[:, None] / self.masses[None, :])

    @property
    def predicted(self) -> np.ndarray:
        """Predicted explicit limit ``2 / omega``, (nk, nm) [s]."""
        return 2.0 / self.omega

    def measured_bracket(self) -> tuple[np.ndarray, np.ndarray]:
        """Measured limit bracket per (k, m), each (nk, nm) [s].

        ``hi`` is the smallest diverged step (``inf`` if none diverged), ``lo``
        the largest bounded step below it (``0`` if none).
        """
        hi = np.where(self.diverged, self.dt, np.inf).min(axis=2)
        lo = np.where(~self.diverged & (self.dt < hi[..., None]), self.dt, 0.0).max(axis=2)
        return lo, hi

    def table(self) -> str:
        """Plain text: per (k, m) omega, predicted 2/omega, measured bracket, bracket / predicted."""
        lo, hi = self.measured_bracket()
        pred = self.predicted
        damp = "no damping" if self.restitution is None else f"dashpot for e = {self.restitution:g}"
        lines = [f"{self.integrator}: {self.steps} steps, {damp}; diverged if energy growth > {self.growth_limit:g}",
                 f"{'k [N/m]':>10} {'m [g]':>8} {'omega':>9} {'2/omega [s]':>12} {'bounded <= dt':>14} "
                 f"{'diverged >= dt':>15} {'ratio lo..hi':>14}" + (f" {'bisected/pred':>14}" if self.limit is not None
                                                                  else "")]
        for i, k in enumerate(self.stiffness):
            for j, m in enumerate(self.masses):
                p = pred[i, j]
                rng = f"{lo[i, j] / p:.3g}..{hi[i, j] / p:.3g}" if np.isfinite(hi[i, j]) else f">= {lo[i, j] / p:.3g}"
                lines.append(f"{k:10.4g} {m * 1e3:8.3g} {self.omega[i, j]:9.4g} {p:12.4g} {lo[i, j]:14.4g} "
                             f"{hi[i, j]:15.4g} {rng:>14}"
                             + (f" {self.limit[i, j] / p:14.4g}" if self.limit is not None else ""))
        return "\n".join(lines)


def stability_map(
    stiffness: Sequence[float] | np.ndarray,
    masses: Sequence[float] | np.ndarray,
    dts: Sequence[float] | np.ndarray,
    integrator: Integrator,
    *,
    steps: int = 300,
    relative: bool = False,
    restitution: float | None = None,
    gravity: float | None = None,
    impact_speed: float = 1.0,
    growth_limit: float = GROWTH_LIMIT,
    bisect: bool = False,
    rtol: float = 1e-3,
) -> StabilityMap:
    """Bounded or diverged: one stone in contact for every (stiffness, mass, time step).

    Each run advances one stone in a frictionless contact (its normal
    coordinate, as :class:`hailstorm.runtime.storm.driver` does) with
    :func:`hailstorm.runtime.storm.hail.contact_step` for ``steps`` steps, starting as it
    touches the seat moving in at ``impact_speed``, under gravity, and the
    contact holds (bilateral, the stone stays on the seat). The energy
    (kinetic + spring + gravity, relative to the static equilibrium) is
    recorded; the run *diverged* when the maximum over the second half of the
    run exceeds ``growth_limit`` times the maximum over the first half (a
    bounded orbit gives ~1 however eccentric the discrete orbit is near the
    limit, a decaying one < 1, a diverging one ``|lambda|^steps``).

    Parameters
    ----------
    stiffness : (nk,)
        Contact stiffness ``k`` [N/m] (e.g. :func:`seat_contact_stiffness`).
    masses : (nm,)
        Stone masses [kg] (e.g. :func:`hailstorm.runtime.storm.hail.stone_mass`).
    dts : (nd,)
        Time steps [s]; with ``relative=True`` multiples of ``2 / omega`` for
        each (k, m).
    integrator : {"symplectic", "implicit", "exact"}
    steps : int
    restitution : float, optional
        ``None`` (default): no dashpot, the pure stability question. A
        number: the storm's compression-only dashpot for that restitution
        (:func:`hailstorm.runtime.storm.hail.damping_coefficients`, with ``dt`` for the
        stepping integrators, as the storm calls it).
    gravity : float, optional
        Default :data:`hailstorm.runtime.storm.hail.GRAVITY` (along the inward normal).
    bisect : bool
        Also measure the limit of every (k, m) by bisection
        (:func:`measure_dt_limit`, relative tolerance ``rtol``): ``limit``.

    Notes
    -----
    Unilateral contact (the stone may bounce off) is not a stability
    question: a stone that leaves the seat gets at most one or two contact
    steps, and the energy error of an explicit step at impact (where in the
    step the stone arrives) is an accuracy question of its own.
    """
    from hailstorm.runtime.storm.hail import GRAVITY

    k = np.asarray(stiffness, dtype=np.float64).reshape(-1)
    m = np.asarray(masses, dtype=np.float64).reshape(-1)
    d = np.asarray(dts, dtype=np.float64).reshape(-1)
    if np.any(k <= 0) or np.any(m <= 0) or np.any(d <= 0):
        raise ValueError("stiffness, masses and time steps must be positive")
    pred = predicted_dt_limit(k[:, None], m[None, :])
    assert isinstance(pred, np.ndarray)  # (nk, nm) inputs
    dt = np.broadcast_to(d * pred[..., None] if relative else d, (k.size, m.size, d.size)).copy()
    growth = np.empty_like(dt)
    g = GRAVITY if gravity is None else float(gravity)
    for i in range(k.size):
        for j in range(m.size):
            for n in range(d.size):
                growth[i, j, n] = _growth(k[i], m[j], dt[i, j, n], integrator, steps=steps, restitution=restitution,
                                          gravity=g, impact_speed=impact_speed)
    limit = None
    if bisect:
        limit = np.array([[measure_dt_limit(ki, mj, integrator, rtol=rtol, steps=steps, restitution=restitution,
                                            growth_limit=growth_limit, gravity=g, impact_speed=impact_speed)
                           for mj in m] for ki in k])
    return StabilityMap(integrator, k, m, dt, growth, growth > growth_limit, int(steps), float(growth_limit),
                        restitution, limit)


def measure_dt_limit(k: float, m: float, integrator: Integrator = "symplectic", *, rtol: float = 1e-3,
                     span: float = 20.0, steps: int = 300, restitution: float | None = None,
                     growth_limit: float = GROWTH_LIMIT, gravity: float | None = None,
                     impact_speed: float = 1.0) -> float:
    """Measured stability limit [s] of one stone in contact, by bisection in ``dt``.

    Searches ``[2/omega / span, 2/omega * span]``; returns ``inf`` if the run
    is bounded at the top of it (the implicit and exact integrators), ``0``
    if it diverges already at the bottom. Other arguments as
    :func:`stability_map`.
    """
    from hailstorm.runtime.storm.hail import GRAVITY

    g = GRAVITY if gravity is None else float(gravity)

    def bad(dt: float) -> bool:
        return _growth(k, m, dt, integrator, steps=steps, restitution=restitution, gravity=g,
                       impact_speed=impact_speed) > growth_limit

    p = predicted_dt_limit(k, m)
    assert isinstance(p, float)  # scalar k, m
    lo, hi = p / span, p * span
    if not bad(hi):
        return float("inf")
    if bad(lo):
        return 0.0
    while hi / lo - 1.0 > rtol:
        mid = np.sqrt(lo * hi)
        lo, hi = (lo, mid) if bad(mid) else (mid, hi)
    return float(np.sqrt(lo * hi))


def format_degenerate(rows: Sequence[Mapping[str, Any]]) -> str:
    """Plain-text table of :func:`degenerate_contacts` rows."""
    lines = [f"{'case':<32}{'cond(BtDB)':>11}{'path':>8}  {'rigid':<15}{'normal forces [N]':<26}{'total/single':>12}"]
    for r in rows:
        fn = ", ".join(f"{f:.3g}" for f in r["fn"])
        lines.append(f"{r['case']:<32}{r['cond_W']:>11.3g}{'exact' if r['exact'] else 'pinv':>8}  {str(r['rigid']):<15}"
                     f"{fn:<26}{r['fn_total'] / r['fn_ref'] + 0.0:>12.4g}")
    return "\n".join(lines)


def format_locking(rows: Sequence[Mapping[str, Any]]) -> str:
    """Plain-text table of :func:`locking_vs_poisson` rows."""
    lines = [f"{'nu':>6}{'P1/beam':>10}{'P2/beam':>10}{'P2/P1':>8}"]
    for r in rows:
        lines.append(f"{r['poisson']:>6}{r['p1_ratio']:>10.3f}{r['p2_ratio']:>10.3f}{r['w_p2'] / r['w_p1']:>8.2f}")
    return "\n".join(lines)


def plot_stability_map(maps: StabilityMap | Sequence[StabilityMap], path: str | os.PathLike | None = None, *,
                       degenerate: Sequence[Mapping[str, Any]] | None = None,
                       locking: Sequence[Mapping[str, Any]] | None = None, dpi: int = 80):
    """Chart: one panel per integrator, time step against omega, bounded (o) / diverged (x),
    the predicted limit ``dt = 2/omega`` drawn over it; optional second row with
    the degenerate contacts (condition number of ``B^T D B`` per case, exact vs
    pseudo-inverse) and P1/P2 locking. Returns the figure; saves a PNG if ``path``.
    """
    import matplotlib.pyplot as plt  # (headless: matplotlib falls back to Agg by itself)

    maps = [maps] if isinstance(maps, StabilityMap) else list(maps)
    extra = [x for x in (degenerate, locking) if x is not None]
    nrow = 2 if extra else 1
    ncol = max(len(maps), 1)
    fig = plt.figure(figsize=(3.6 * ncol, 3.1 * nrow))
    gs = fig.add_gridspec(nrow, 2 * ncol)
    axes = [fig.add_subplot(gs[0, 2 * c:2 * c + 2]) for c in range(len(maps))]
    for c, (ax, sm) in enumerate(zip(axes, maps)):
        om = np.broadcast_to(sm.omega[..., None], sm.dt.shape).ravel()
        dt = sm.dt.ravel()
        dv = sm.diverged.ravel()
        ax.scatter(om[~dv], dt[~dv], s=9, marker="o", facecolors="none", edgecolors="tab:green", lw=0.7,
                   label="bounded")
        ax.scatter(om[dv], dt[dv], s=12, marker="x", color="tab:red", lw=0.8, label="diverged")
        w = np.geomspace(om.min() / 1.5, om.max() * 1.5, 50)
        ax.plot(w, 2.0 / w, "k-", lw=1.2, label="predicted 2/ω")
        if sm.limit is not None:
            fin = np.isfinite(sm.limit) & (sm.limit > 0)
            meas = sm.limit
        else:
            lo, hi = sm.measured_bracket()
            fin = np.isfinite(hi) & (lo > 0)
            meas = np.sqrt(np.where(fin, lo * hi, 1.0))
        if fin.any():
            ax.plot(sm.omega[fin], meas[fin], "s", ms=3.5, color="tab:blue",
                    label="measured limit" + (" (bisection)" if sm.limit is not None else ""))
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_ylim(dt.min() / 1.5, dt.max() * 1.5)
        n_div = int(dv.sum())
        ax.set_title(f"{sm.integrator}: {n_div}/{dv.size} diverged", fontsize=9)
        ax.set_xlabel("ω = √(k/m) [rad/s]")
        ax.grid(True, alpha=0.3, which="both", lw=0.4)
        if c == 0:
            ax.set_ylabel("time step dt [s]")
            ax.legend(fontsize=7, loc="lower left")
    if extra:
        ncells = 2 * ncol // len(extra)
        k = 0
        if degenerate is not None:
            ax = fig.add_subplot(gs[1, k:k + ncells])
            k += ncells
            names = [r["case"] for r in degenerate]
            cond = np.array([r["cond_W"] for r in degenerate], dtype=float)
            top = 18.0
            bar = np.where(np.isnan(cond), 0.0, np.log10(np.clip(np.nan_to_num(cond, posinf=10**top), 1.0, None)))
            col = ["tab:blue" if r["exact"] else "tab:orange" for r in degenerate]
            y = np.arange(len(names))
            ax.barh(y, bar, color=col)
            for yi, b, c, r in zip(y, bar, cond, degenerate):
                what = ("rigid: no live W" if np.isnan(c) else "singular" if np.isinf(c) else f"{c:.2g}")
                tot = r["fn_total"] / r["fn_ref"] if r["fn_ref"] else float("nan")
                txt = f"{what}; {'Cholesky' if r['exact'] else 'pinv'}; Σf/f₁ = {tot + 0.0:.3g}"
                inside = b > top / 2
                ax.text(b - 0.3 if inside else b + 0.3, float(yi), txt, va="center", ha="right" if inside else "left",
                        fontsize=6.5, color="w" if inside else "k")
            ax.set_xlim(0, top)
            ax.set_yticks(y, names, fontsize=7)
            ax.invert_yaxis()
            ax.axvline(10, color="k", ls=":", lw=0.8)
            ax.set_xlabel("log10 cond(Bᵀ D B)  (dotted: pseudo-inverse above)", fontsize=8)
            ax.set_title("degenerate contacts (blue: Cholesky, orange: pseudo-inverse)", fontsize=9)
        if locking is not None:
            ax = fig.add_subplot(gs[1, k:k + ncells])
            nu = np.array([r["poisson"] for r in locking])
            x = -np.log10(0.5 - nu)
            ax.plot(x, [r["p1_ratio"] for r in locking], "o-", label="P1")
            ax.plot(x, [r["p2_ratio"] for r in locking], "s-", label="P2")
            ax.axhline(1.0, color="k", lw=0.8, ls=":")
            ax.set_xticks(x, [f"{v:g}" for v in nu], fontsize=7)
            ax.set_xlabel("Poisson's ratio ν (→ 0.5)")
            ax.set_ylabel("tip deflection / beam theory")
            ax.set_ylim(0, max(1.1, max(r["p2_ratio"] for r in locking) * 1.1))
            ax.set_title("locking: cantilever, P1 vs P2", fontsize=9)
            ax.legend(fontsize=7)
            ax.grid(True, alpha=0.3)
    fig.tight_layout()
    if path is not None:
        _save_small_png(fig, path, dpi)
    return fig


def _save_small_png(fig: Any, path: str | os.PathLike, dpi: int) -> None:
    """Save a figure as a 256-colour palette PNG (a third of the RGBA size; Pillow ships with matplotlib)."""
    import io

    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    fig.savefig(buf, dpi=dpi, format="png", facecolor="white")
    buf.seek(0)
    with Image.open(buf) as im:
        im.convert("RGB").quantize(256).save(path, format="PNG", optimize=True)


def stability_study(*, small: bool = False, cache_dir: str | os.PathLike | None = None,
                    restitution: float | None = None) -> dict[str, Any]:
    """The stability figure's data: seat stiffness, maps for the three integrators, degenerate contacts, locking.

    Stiffness: the point-contact stiffness of one stone at :data:`SEAT_POINTS`
    on the default saddle (P1, 15 mm mesh; bundle cached under
    :func:`study_cache_dir`) and the bounds 1e3 and 1e5 N/m; masses: ice
    stones of :data:`STABILITY_RADII`. ``small``: fewer masses, steps and
    time steps (seconds).
    """
    from hailstorm.runtime.storm.hail import stone_mass

    h = 0.015
    cache = Path(cache_dir) if cache_dir is not None else study_cache_dir()
    gf = load_bundle(build_bundle(cache / f"seat-P1-h{h * 1e3:g}mm", mesh_size=h, order=1))
    seat_k = seat_contact_stiffness(gf)
    stiffness = np.unique(np.concatenate([[1e3, 1e5], list(seat_k.values())]))
    radii = STABILITY_RADII[::2] if small else STABILITY_RADII
    masses = stone_mass(np.asarray(radii))
    om = np.sqrt(stiffness[:, None] / masses[None, :])
    lo, hi = 2.0 / om.max() / 8, 2.0 / om.min() * 8
    dts = np.geomspace(lo, hi, 14 if small else 36)
    steps = 120 if small else 300
    maps = [stability_map(stiffness, masses, dts, integ, steps=steps, restitution=restitution, bisect=True,
                          rtol=1e-2 if small else 1e-3)
            for integ in ("symplectic", "implicit", "exact")]
    return dict(seat_stiffness=seat_k, stiffness=stiffness, radii=np.asarray(radii), masses=masses, maps=maps,
                degenerate=degenerate_contacts(gf),
                locking=locking_vs_poisson((0.3, 0.4, 0.45, 0.49, 0.499), length=0.5 if small else 1.0))


# --------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------
def main(argv: Sequence[str] | None = None) -> int:
    """``python -m studies.contact_study [--small] [--order 1 2] [--out PNG]``: table and chart."""
    import argparse
    import sys

    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["stability"]:
        return main_stability(argv[1:])
    ap = argparse.ArgumentParser(prog="python -m studies.contact_study", description=main.__doc__,
                                 epilog="python -m studies.contact_study stability --help: the stability study")
    ap.add_argument("--small", action="store_true", help="coarse levels only (seconds)")
    ap.add_argument("--order", type=int, nargs="+", default=[1, 2], help="element orders (default 1 2)")
    ap.add_argument("--out", type=Path, default=None, help="write the chart to this PNG")
    args = ap.parse_args(argv)
    sizes = SMALL_MESH_SIZES if args.small else MESH_SIZES
    studies = [contact_stiffness_vs_mesh(sizes, order=o) for o in args.order]
    for st in studies:
        print(st.table())
        print()
    if args.out is not None:
        plot_stiffness_vs_mesh(studies, args.out)
        print(f"wrote {args.out} ({args.out.stat().st_size / 1024:.0f} KB)")
    return 0


def main_stability(argv: Sequence[str] | None = None) -> int:
    """``python -m studies.contact_study stability [--small] [--restitution E] [--out PNG]``:
    stability tables (three integrators), measured vs predicted limit, degenerate contacts, locking, chart."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m studies.contact_study stability", description=main_stability.__doc__)
    ap.add_argument("--small", action="store_true", help="small grid (seconds)")
    ap.add_argument("--restitution", type=float, default=None,
                    help="use the storm's dashpot for this restitution (default: no damping)")
    ap.add_argument("--out", type=Path, default=None, help="write the chart to this PNG")
    args = ap.parse_args(argv)
    res = stability_study(small=args.small, restitution=args.restitution)
    print("seat point-contact stiffness [N/m]:", {k: round(v) for k, v in res["seat_stiffness"].items()})
    for sm in res["maps"]:
        print(sm.table())
        print()
    sym = res["maps"][0]
    ratio = sym.limit / sym.predicted
    print(f"symplectic: measured (bisection) / predicted 2/omega = {ratio.min():.4f} .. {ratio.max():.4f} "
          f"over {ratio.size} (k, m)")
    print()
    print(format_degenerate(res["degenerate"]))
    print()
    print(format_locking(res["locking"]))
    if args.out is not None:
        plot_stability_map(res["maps"], args.out, degenerate=res["degenerate"], locking=res["locking"])
        print(f"wrote {args.out} ({args.out.stat().st_size / 1024:.0f} KB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
