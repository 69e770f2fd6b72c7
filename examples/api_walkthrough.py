"""The Python API, step by step: a bundle, contacts, spheres, a storm and its files.

Usage::

    python examples/api_walkthrough.py                 # on the default seat (built once, cached)
    python examples/api_walkthrough.py --small         # on the small block of examples/geometries (seconds)
    python examples/api_walkthrough.py --out walk      # where the storm's files go (default: ./walkthrough-out)

Every step prints one line. The bundle is cached (``$HAILSTORM_CACHE``, default
``~/.cache/hailstorm``): a second run reuses it.
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
from threadpoolctl import threadpool_limits

from hailstorm import precompute, runtime
from hailstorm.runtime.bundle.write import convert_bundle
from hailstorm.runtime.output.storm_output import StormOutput
from hailstorm.runtime.output.animation import write_animation

BLOCK = Path(__file__).resolve().parent / "geometries" / "block.geo"


def build(small: bool) -> Path:
    """Offline stage: mesh, assemble, compute D and write the bundle (or reuse the cached one)."""
    if small:
        return precompute.build_bundle(geometry=BLOCK, mesh_size=0.012, order=1, young=5e5, poisson=0.4)
    seat = runtime.SeatSettings.default()
    return precompute.build_bundle(mesh_size=seat.mesh_size, order=seat.order, load=seat.load,
                                   young=seat.young, poisson=seat.poisson, progress=True)


def top_triangles(gf: runtime.GreensFunctions, k: int) -> np.ndarray:
    """``k`` contactable triangles facing up (outward normal z > 0.9), highest first."""
    X = gf.vertices[gf.triangles]
    n = np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    ok = gf.contactable[gf.triangles].all(axis=1) & (n[:, 2] > 0.9)
    idx = np.flatnonzero(ok)
    return idx[np.argsort(-X[idx, :, 2].mean(axis=1))][:k]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="a small block instead of the default seat")
    ap.add_argument("--out", type=Path, default=Path("walkthrough-out"), help="the storm's output directory")
    args = ap.parse_args(argv)

    # 1. the bundle: D memory-mapped, verified on first load
    gf = runtime.load(build(args.small))
    print(f"bundle: {gf.n_vertices} surface vertices, {int(gf.contactable.sum())} contactable, "
          f"D {gf.D.shape[0]} x {gf.D.shape[1]} {gf.dtype}, E = {gf.young:g} Pa, nu = {gf.poisson:g}")

    # 2. a block of D: rows and columns are surface vertex indices (3 dofs each)
    tri = top_triangles(gf, 3)
    verts = np.unique(gf.triangles[tri])
    block = gf.compliance(verts, verts)
    print(f"D block of {verts.size} vertices: {block.shape}, largest entry {np.abs(block).max():.3g} m/N")

    # 3. contacts: three points pressed 0.5 mm into the surface, frictionless and unilateral
    bary = np.full((tri.size, 3), 1.0 / 3.0)            # the triangles' centroids
    push = np.tile([0.0, 0.0, -5e-4], (tri.size, 1))    # prescribed displacement of each contact point [m]
    with threadpool_limits(1):                          # tiny dense solves: one BLAS thread is fastest
        sol = runtime.solve_contacts(gf, tri, bary, push, mode="frictionless", unilateral=True)
    print(f"solve_contacts: normal forces {np.round(sol.forces[:, 2], 3)} N on the solid, "
          f"deepest surface point {sol.surface_displacement[:, 2].min() * 1e3:.3f} mm")

    # 4. the capacitance, reused: new displacements, low-rank add/remove
    cap = runtime.capacitance(gf, tri, bary)            # sticky point contacts: W = B^T D B, K = W^-1
    f = cap.forces(push)
    cap.add(int(top_triangles(gf, 4)[-1]), [0.2, 0.3, 0.5])
    cap.remove(0)
    print(f"capacitance: {tri.size} contacts, force sum {f[:, 2].sum():.3f} N; after add/remove {cap.s} contacts")

    # 5. rigid spheres pressed in, with patches consistent with the sphere (Hertz for a << R)
    spheres = runtime.press_spheres(gf, tri[:1], bary[:1], [2e-4], 0.005)
    a_sphere = runtime.sphere_radius(spheres.normal_force, 0.005, gf.young, gf.poisson)
    a_hertz = runtime.hertz_radius(spheres.normal_force, 0.005, gf.young, gf.poisson)
    print(f"press_spheres: 0.2 mm with R = 5 mm -> {spheres.normal_force[0]:.3f} N, patch radius "
          f"{spheres.patch_radius[0] * 1e3:.2f} mm (the sphere's contact radius of that force "
          f"{a_sphere[0] * 1e3:.2f} mm, Hertz's {a_hertz[0] * 1e3:.2f} mm)")

    # 6. a short storm, its frames kept in memory, and its video
    scene = runtime.Scene.from_flat(duration=0.04 if args.small else 0.2, stones=6 if args.small else 40)
    result = runtime.run_storm(gf, scene, progress=False)
    st = result.stats
    print(f"run_storm (frames in memory): {st['hailstones']} stones, {st['impacts']} impacts, "
          f"{len(result.frames)} frames, largest contact force {st['max_contact_force']:.3g} N")
    with tempfile.TemporaryDirectory() as tmp:
        video = write_animation(result, gf, Path(tmp) / "storm.mp4", max_frames=4 if args.small else 100,
                                size=(640, 360) if args.small else (1280, 720))
        print(f"write_animation: {video.name}, {video.stat().st_size / 1024:.0f} KiB")

    # 7. the same storm streamed to disk as it runs (memory flat in the duration), as `hailstorm storm` does
    with StormOutput(args.out, gf, video=not args.small) as out:
        streamed = runtime.run_storm(gf, scene, progress=False, on_frame=out.add)
        files = out.finish(streamed)
    print(f"StormOutput: {sorted(files)} in {args.out}/ (frames kept in memory: {len(streamed.frames)})")

    # 8. the same bundle with D in float32: half the size, each entry within 2^-24 of itself
    with tempfile.TemporaryDirectory() as tmp:
        gf32 = runtime.load(convert_bundle(gf.path, Path(tmp) / "gf32", "float32"))
        with threadpool_limits(1):
            f32 = runtime.solve_contacts(gf32, tri, bary, push, mode="frictionless", unilateral=True).forces
        err = np.abs(f32 - sol.forces).max() / np.abs(sol.forces).max()
        print(f"convert_bundle: D {gf32.dtype}, {gf32.D.nbytes / 2**20:.2f} MiB; forces within {err:.1e} (relative)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
