"""The default seat, measured: does it dent like a seat, and does its shell matter?

Two figures of the padded saddle (``meshes/saddle.geo``: a foam pad whose
underside is clamped on a rigid shell):

Locality
    A 1 N load spread uniformly over a 5 mm disc (radius 2.5 mm in plan, along
    the inward normal) at the rear, the middle and the nose of the crown. The
    ratio is the largest displacement magnitude of any surface node farther
    than 40 mm from the load centre over the displacement magnitude under the
    load centre (interpolated on its surface triangle). Target: <= 0.2.
Shell effect
    The same pad on an *elastic* shell: a 3 mm nylon plate (the region the
    geometry reserves under the pad, the pad's underside lowered by 3 mm,
    meshed as two layers of prisms split into tetrahedra, conforming to the
    pad) held only where the rails hold a real saddle (a socket under the nose,
    two at the rear). The contact stiffness of a stone is F over the mean
    displacement of its contact disc (uniform over the 5 mm disc, and Hertz
    weights over a 1.5 mm disc); the figure is 1 - k_elastic / k_rigid. Below
    2 % the rigid base is the right model (issue #14).

Run::

    python -m studies.seat_study                 # locality, P1 at 6 mm (the default seat)
    python -m studies.seat_study --order 2 --shell
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from hailstorm.precompute.fem import (
    DEFAULT_POISSON,
    DEFAULT_YOUNG,
    clamp_dofs,
    elasticity_basis,
    free_dofs,
    stiffness_matrix,
)
from hailstorm.precompute.geometry import DEFAULT_MESH_SIZE, TetMesh, boundary_triangles, check_mesh, mesh_default_seat, tet_volumes
from hailstorm.precompute.greens import factorize
from studies.study import LoadCase, locate_probes, nodal_loads, trace_nodes, trace_shape

#: Load sites on the crown (plan x, y) [m]: rear, middle, nose.
SITES = {"rear": (0.235, 0.0), "middle": (0.150, 0.0), "nose": (0.035, 0.0)}
#: Shell: thickness [m] and nylon 6 (E [Pa], nu): the softest common shell material.
SHELL_THICKNESS = 0.003
SHELL_MATERIAL = (3.0e9, 0.40)
#: Rail sockets on the shell's underside, plan boxes (x0, x1, |y|0, |y|1) [m].
RAIL_SOCKETS = ((0.020, 0.050, 0.0, 0.008), (0.215, 0.245, 0.025, 0.045))


@dataclass
class Site:
    """One load case's figures."""

    name: str
    under: float  # |u| under the load centre [m]
    far: float  # max |u| beyond the far distance [m]
    mean_disc: float  # mean normal displacement over the disc (per newton) [m]
    mean_hertz: float  # Hertz-weighted mean over a 1.5 mm disc (per newton) [m]

    @property
    def ratio(self) -> float:
        return self.far / self.under


def with_shell(mesh: TetMesh, thickness: float = SHELL_THICKNESS, layers: int = 2,
               sockets=RAIL_SOCKETS) -> TetMesh:
    """``mesh`` (a pad clamped on its underside) on an elastic shell: the underside
    extruded down by ``thickness`` in ``layers`` layers of prisms (3 tetrahedra each,
    diagonals chosen by global node number so neighbours conform). Volume groups
    ``pad`` and ``shell``; ``clamp`` is the shell's underside inside the rail sockets."""
    base = mesh.groups["clamp"]
    nodes, local = np.unique(base, return_inverse=True)
    local = local.reshape(-1, 3)
    n0 = mesh.points.shape[0]
    pts = [mesh.points]
    ids = [nodes]
    for k in range(1, layers + 1):
        p = mesh.points[nodes].copy()
        p[:, 2] -= thickness * k / layers
        pts.append(p)
        ids.append(n0 + (k - 1) * nodes.size + np.arange(nodes.size))
    points = np.concatenate(pts)
    tets = []
    for k in range(layers):
        top, bot = ids[k][local], ids[k + 1][local]
        order = np.argsort(top, axis=1)  # sort each triangle by its top node numbers (bottom numbers follow)
        t, b = np.take_along_axis(top, order, 1), np.take_along_axis(bot, order, 1)
        i, j, m = t.T
        i2, j2, m2 = b.T
        tets += [np.column_stack(c) for c in ((i, j, m, i2), (j, m, i2, j2), (m, i2, j2, m2))]
    shell = np.concatenate(tets)
    vol = tet_volumes(points, shell)
    shell[vol < 0] = shell[vol < 0][:, [0, 2, 1, 3]]
    all_tets = np.concatenate([mesh.tets, shell])
    bottom = ids[layers][local]
    cen = points[bottom].mean(axis=1)
    held = np.zeros(len(bottom), dtype=bool)
    for x0, x1, y0, y1 in sockets:
        held |= (cen[:, 0] >= x0) & (cen[:, 0] <= x1) & (np.abs(cen[:, 1]) >= y0) & (np.abs(cen[:, 1]) <= y1)
    nt = mesh.tets.shape[0]
    volumes = {"pad": np.arange(nt), "shell": nt + np.arange(shell.shape[0])}
    groups = {"top": mesh.groups["top"], "clamp": bottom[held]}
    return check_mesh(TetMesh(points, all_tets, groups, mesh.source + "+shell", volumes))


def measure(mesh: TetMesh, order: int, young, poisson, *, sites=SITES, radius: float = 0.0025,
            far: float = 0.04, hertz_radius: float = 0.0015) -> list[Site]:
    """Solve the disc loads at ``sites`` directly on ``mesh`` (per-tet ``young``/``poisson`` allowed)."""
    basis = elasticity_basis(mesh, order)
    K = stiffness_matrix(basis, young, poisson)
    fixed = clamp_dofs(basis, mesh)
    free = free_dofs(K.shape[0], fixed)
    fact = factorize(K.tocsr()[free][:, free], "cholmod")
    tris = boundary_triangles(mesh.tets)
    top = mesh.groups["top"]
    topkey = set(map(tuple, np.sort(top, axis=1).tolist()))
    tris = tris[[tuple(t) in topkey for t in np.sort(tris, axis=1).tolist()]]  # outward top triangles
    nodes, table = trace_nodes(basis, tris, order)
    surf = np.unique(boundary_triangles(mesh.tets))
    out = []
    for name, c in sites.items():
        loc = locate_probes(mesh.points, tris, np.array([c]))
        N = trace_shape(loc.lam, order)[0]
        dofs = table[nodes[loc.triangle[0]]]  # (a, 3)
        centre = np.einsum("a,ad->d", loc.lam[0], mesh.points[tris[loc.triangle[0]]])
        res = []
        for a, profile in ((radius, "uniform"), (hertz_radius, "hertz")):
            f = _disc_load(mesh, tris, nodes, table, c, a, order, profile)
            F = np.zeros(K.shape[0])
            F[table.ravel()] = f.ravel()
            F /= np.linalg.norm(f.sum(axis=0))  # 1 N
            u = np.zeros(K.shape[0])
            u[free] = fact.solve(F[free])
            res.append((u, F))
        u, F = res[0]
        under = float(np.linalg.norm(N @ u[dofs]))
        U = u[table[surf]]  # (n, 3)
        d = np.linalg.norm(mesh.points[surf] - centre, axis=1)
        far_u = float(np.linalg.norm(U[d > far], axis=1).max())
        out.append(Site(name, under, far_u, float(F @ u), float(res[1][1] @ res[1][0])))
    return out


def _disc_load(mesh, tris, nodes, table, c, a, order, profile) -> np.ndarray:
    if profile == "uniform":
        return nodal_loads(mesh.points, tris, nodes, table.shape[0], LoadCase(c, a, 1.0), order=order)
    # Hertz pressure sqrt(1 - r^2/a^2) as a sum of thin uniform discs (Abel layering, 24 rings)
    f = np.zeros((table.shape[0], 3))
    rs = a * np.sqrt(1 - ((np.arange(24) + 0.5) / 24) ** 2)
    for r in rs:
        f += nodal_loads(mesh.points, tris, nodes, table.shape[0], LoadCase(c, float(r), 1.0), order=order)
    return f


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mesh-size", type=float, default=DEFAULT_MESH_SIZE)
    ap.add_argument("--order", type=int, choices=(1, 2), default=1)
    ap.add_argument("--shell", action="store_true", help="also measure the elastic shell's effect")
    ap.add_argument("--shell-young", type=float, default=SHELL_MATERIAL[0],
                    help=f"shell Young's modulus [Pa] (default {SHELL_MATERIAL[0]:g}, nylon 6; carbon-fibre laminate ~5e10)")
    ap.add_argument("--out", default=None, metavar="FILE", help="also write the output there (with its header)")
    args = ap.parse_args(argv)
    if args.out is None:
        _run(args)
    else:
        from studies import record

        record.whole_output(args.out, "python -m studies.seat_study", sys.argv[1:] if argv is None
                            else list(argv), lambda: _run(args))
    return 0


def _run(args: argparse.Namespace) -> None:
    t0 = time.perf_counter()
    pad = mesh_default_seat(args.mesh_size)
    rigid = measure(pad, args.order, DEFAULT_YOUNG, DEFAULT_POISSON)
    print(f"padded saddle, rigid base, P{args.order} at {args.mesh_size * 1e3:g} mm "
          f"({pad.tets.shape[0]} tets), E = {DEFAULT_YOUNG:g} Pa, nu = {DEFAULT_POISSON}")
    print("site     |u| under [um/N]  max |u| > 40 mm [um/N]  ratio (target <= 0.2)")
    for s in rigid:
        print(f"{s.name:<8} {s.under * 1e6:>16.2f}  {s.far * 1e6:>22.3f}  {s.ratio:>6.3f}")
    if args.shell:
        mesh = with_shell(pad)
        mats = np.where(np.arange(mesh.tets.shape[0]) < pad.tets.shape[0], 0, 1)
        young = np.array([DEFAULT_YOUNG, args.shell_young])[mats]
        poisson = np.array([DEFAULT_POISSON, SHELL_MATERIAL[1]])[mats]
        elastic = measure(mesh, args.order, young, poisson)
        print(f"\nelastic shell: {SHELL_THICKNESS * 1e3:g} mm (E = {args.shell_young:g} Pa, "
              f"nu = {SHELL_MATERIAL[1]}) held at the rail sockets ({mesh.groups['clamp'].shape[0]} triangles)")
        print("site     1 - k_elastic/k_rigid: 5 mm uniform disc, 1.5 mm Hertz disc   locality ratio")
        for r, e in zip(rigid, elastic):
            print(f"{r.name:<8} {1 - r.mean_disc / e.mean_disc:>28.2%} {1 - r.mean_hertz / e.mean_hertz:>18.2%}"
                  f"   {e.ratio:>10.3f}")
    print(f"({time.perf_counter() - t0:.1f} s)")


if __name__ == "__main__":
    sys.exit(main())
