"""Contact studies: mesh dependence of point vs patch contacts, degenerate contacts, locking.

Three importable studies (tested in ``tests/test_contact_study.py``, charted
in ``notebooks/mesh_dependence.ipynb``):

:func:`contact_stiffness_vs_mesh`
    Effective normal stiffness ``k`` of one stone at fixed points of the seat
    against the mesh size, for a point contact (force on one triangle's
    vertices) and a patch contact (force spread over a Hertz pressure disc of
    fixed physical radius, :func:`runtime.weights.patch_weights`). A point
    load on an elastic body is singular (Boussinesq: ``u ~ 1/r``), so the
    point stiffness keeps falling as the mesh is refined (like ``h`` on a
    half-space); the patch stiffness converges.
:func:`degenerate_contacts`
    Coincident, nearly coincident, clamped and conflicting contacts: the
    condition number of ``W = B^T D B`` and what the solver does with it
    (:attr:`runtime.contact.Capacitance.exact`, rigid flags, the force split).
:func:`locking_vs_poisson`
    Tip deflection of a cantilever with P1 and P2 tetrahedra as
    ``nu -> 0.5``: P1 locks (volumetric and in bending), P2 much less.

The committed figure is regenerated with::

    python -m precompute.contact_study --out notebooks/figures/mesh_dependence.png

(``--small`` for the coarse levels only). Bundles are cached under
``<hailstorm cache>/contact_study`` (see :func:`precompute.default_cache_dir`),
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

from precompute.geometry import TetMesh, box_mesh
from precompute.pipeline import build_bundle, default_cache_dir
from runtime.bundle import load as load_bundle
from runtime.contact import capacitance, hertz_radius, solve_contacts, triangle_normals

__all__ = [
    "SEAT_POINTS",
    "StiffnessStudy",
    "contact_stiffness",
    "contact_stiffness_vs_mesh",
    "degenerate_contacts",
    "locate_points",
    "locking_vs_poisson",
    "plot_stiffness_vs_mesh",
    "separation_sweep",
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


def contact_stiffness(gf: Any, tri: Any, bary: Any, *, patch_radius: Any = None, mode: str = "frictionless",
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
        return np.abs(np.diff(k, axis=0)) / np.abs(k[1:])

    def table(self) -> str:
        """A plain-text table (one row per level, point | patch per probe)."""
        ctl = self.k_control is not None
        cols = ["point", "patch"] + (["wide"] if ctl else [])
        ks = [self.k_point, self.k_patch] + ([self.k_control] if ctl else [])
        head = f"{'h [mm]':>7} {'verts':>6} | " + " | ".join(
            " ".join(f"{c:>8}" for c in cols) for _ in self.points)
        title = " | ".join(f"{p:^{9 * len(cols) - 1}}" for p in self.points)
        lines = [f"P{self.order}: k [kN/m]; point contact, patch a = {self.patch_radius * 1e3:.2f} mm"
                 + (f", wide patch a = {self.control_radius * 1e3:.0f} mm (control)" if ctl else ""),
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
    mode: str = "frictionless",
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
        (:func:`runtime.weights.hertz_radius`).
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
    from precompute.fem import DEFAULT_POISSON, DEFAULT_YOUNG

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
        kw = dict(order=order, young=young, poisson=poisson)
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
    import matplotlib

    if path is not None:
        matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

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


def degenerate_contacts(gf: Any, *, depth: float = 1e-3, mode: str = "frictionless",
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
    kw = dict(mode=mode, patch_radius=patch_radius)

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
                     mode: str = "frictionless", patch_radius: float | None = None) -> list[dict]:
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
    kw = dict(mode=mode, patch_radius=patch_radius)
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

    from precompute.fem import clamp_dofs, elasticity_basis, free_dofs, stiffness_matrix, vertex_dofs

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
# command line
# --------------------------------------------------------------------------
def main(argv: Sequence[str] | None = None) -> int:
    """``python -m precompute.contact_study [--small] [--order 1 2] [--out PNG]``: table and chart."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m precompute.contact_study", description=main.__doc__)
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


if __name__ == "__main__":
    raise SystemExit(main())
