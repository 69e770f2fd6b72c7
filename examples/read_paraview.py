"""Read a storm's ParaView series back with meshio: the seat's dents and the stones, frame by frame.

Usage::

    python examples/read_paraview.py RUN_DIR            # the output of `hailstorm storm --out RUN_DIR`
    python examples/read_paraview.py --small            # runs a 0.03 s storm on a small block first (seconds)

``storm.pvd`` lists the seat's frames (``frames/surface_NNNN.vtu``: the undeformed
vertices, point data ``displacement``, ``|u|``, ``peak_displacement``, ``|u| peak``
[m]) and ``storm_stones.pvd`` the stones' (vertex cells, point data ``radius`` [m],
``id``, ``force`` [N]). A ``.pvd`` is a small XML list of (time, file); meshio
reads each file. Prints one line per frame that shows a dent or a stone in
contact, and the deepest dent of the run.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import meshio
import numpy as np

HERE = Path(__file__).resolve().parent


def collection(pvd: Path) -> list[tuple[float, Path]]:
    """The (time, file) entries of a ParaView ``.pvd`` collection, in order."""
    root = ET.parse(pvd).getroot()
    return [(float(d.get("timestep")), pvd.parent / d.get("file")) for d in root.iter("DataSet")]


def small_run(out: Path) -> Path:
    from hailstorm import precompute

    gf = precompute.build_bundle(geometry=HERE / "geometries" / "block.geo", mesh_size=0.012, order=1,
                                 young=5e5, poisson=0.4)
    cmd = ["storm", "--gf", str(gf), "--duration", "0.03", "--stones", "5", "--no-video", "-q", "--out", str(out)]
    print("$ hailstorm " + " ".join(cmd), flush=True)
    subprocess.run([sys.executable, "-m", "hailstorm", *cmd], check=True)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, nargs="?", help="a storm's output directory")
    ap.add_argument("--small", action="store_true", help="run a short storm on a small block first")
    args = ap.parse_args(argv)
    if args.run is None and not args.small:
        ap.error("give a storm's output directory, or --small")
    run = small_run(args.run or Path("read-paraview-out")) if args.small else args.run

    seat, stones = collection(run / "storm.pvd"), collection(run / "storm_stones.pvd")
    deepest = (0.0, 0.0)
    for (t, seat_file), (_, stone_file) in zip(seat, stones):
        surface = meshio.read(seat_file)
        peak = float(np.max(surface.point_data["|u| peak"]))
        ball = meshio.read(stone_file)
        force = np.linalg.norm(ball.point_data["force"], axis=1)
        live = ball.point_data["id"] >= 0          # a frame without stones holds one placeholder (id -1)
        if peak > 0 or (force > 0).any():
            print(f"t = {t * 1e3:6.1f} ms: deepest dent since the previous frame {peak * 1e3:.3f} mm, "
                  f"{int(live.sum())} stones, {int((force > 0).sum())} in contact, total force {force.sum():.2f} N")
        deepest = max(deepest, (peak, t))
    print(f"{len(seat)} frames of {surface.points.shape[0]} seat vertices; the deepest dent "
          f"{deepest[0] * 1e3:.3f} mm at t = {deepest[1] * 1e3:.1f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
