"""Read a storm's ParaView series back without hailstorm: the seat's dents and the stones, frame by frame.

Usage::

    python examples/read_paraview.py RUN_DIR            # the output of `hailstorm storm --out RUN_DIR`
    python examples/read_paraview.py --small            # runs a 0.03 s storm on a small block first (seconds)
    python examples/read_paraview.py --small --series vtu

A storm writes its series as one ``storm.vtkhdf`` (VTK's HDF5 format, read here with h5py:
``/VTKHDF/seat`` holds the undeformed surface once and ``PointData/displacement`` and
``peak_displacement`` [m] for every frame, one after the other; ``/VTKHDF/stones`` the stones
of every frame, with ``radius`` [m], ``id`` and ``force`` [N]; ``Steps`` says where each frame
starts), or with ``--series vtu`` as ``storm.pvd`` and ``storm_stones.pvd`` listing one
``.vtu`` per frame (read here with meshio). Prints one line per frame that shows a dent or a
stone in contact, and the deepest dent of the run.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent


def collection(pvd: Path) -> list[tuple[float, Path]]:
    """The (time, file) entries of a ParaView ``.pvd`` collection, in order."""
    root = ET.parse(pvd).getroot()
    return [(float(d.get("timestep")), pvd.parent / d.get("file")) for d in root.iter("DataSet")]


def vtu_frames(run: Path):
    """Per frame: (t, seat's peak |u| since the previous frame, stones' ids, forces), from the .vtu series."""
    import meshio

    for (t, seat_file), (_, stone_file) in zip(collection(run / "storm.pvd"), collection(run / "storm_stones.pvd")):
        surface, ball = meshio.read(seat_file), meshio.read(stone_file)
        live = ball.point_data["id"] >= 0          # a frame without stones holds one placeholder (id -1)
        yield t, float(np.max(surface.point_data["|u| peak"])), ball.point_data["id"][live], \
            ball.point_data["force"][live], surface.points.shape[0]


def vtkhdf_frames(run: Path):
    """The same, from ``storm.vtkhdf`` (h5py: the datasets and the per-step offsets of VTKHDF)."""
    import h5py

    with h5py.File(run / "storm.vtkhdf", "r") as f:
        seat, stones = f["VTKHDF/seat"], f["VTKHDF/stones"]
        n = int(seat["NumberOfPoints"][0])
        for i, t in enumerate(seat["Steps/Values"][:]):
            first = int(seat["Steps/PointDataOffsets/peak_displacement"][i])
            peak = np.linalg.norm(seat["PointData/peak_displacement"][first:first + n], axis=1)
            k, s0 = int(stones["NumberOfPoints"][i]), int(stones["Steps/PointOffsets"][i])
            yield float(t), float(peak.max()), stones["PointData/id"][s0:s0 + k], \
                stones["PointData/force"][s0:s0 + k], n


def small_run(out: Path, series: str) -> Path:
    from hailstorm import precompute

    gf = precompute.build_bundle(geometry=HERE / "geometries" / "block.geo", mesh_size=0.012, order=1,
                                 young=5e5, poisson=0.4)
    cmd = ["storm", "--gf", str(gf), "--duration", "0.03", "--stones", "5", "--no-video", "-q", "--out", str(out),
           "--series", series]
    print("$ hailstorm " + " ".join(cmd), flush=True)
    subprocess.run([sys.executable, "-m", "hailstorm", *cmd], check=True)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, nargs="?", help="a storm's output directory")
    ap.add_argument("--small", action="store_true", help="run a short storm on a small block first")
    ap.add_argument("--series", choices=("vtkhdf", "vtu"), default="vtkhdf", help="the series --small writes")
    args = ap.parse_args(argv)
    if args.run is None and not args.small:
        ap.error("give a storm's output directory, or --small")
    run = small_run(args.run or Path("read-paraview-out"), args.series) if args.small else args.run

    frames = vtkhdf_frames(run) if (run / "storm.vtkhdf").is_file() else vtu_frames(run)
    deepest, count, n = (0.0, 0.0), 0, 0
    for t, peak, ids, forces, n in frames:
        force = np.linalg.norm(forces, axis=1)
        if peak > 0 or (force > 0).any():
            print(f"t = {t * 1e3:6.1f} ms: deepest dent since the previous frame {peak * 1e3:.3f} mm, "
                  f"{len(ids)} stones, {int((force > 0).sum())} in contact, total force {force.sum():.2f} N")
        deepest, count = max(deepest, (peak, t)), count + 1
    print(f"{count} frames of {n} seat vertices; the deepest dent {deepest[0] * 1e3:.3f} mm at "
          f"t = {deepest[1] * 1e3:.1f} ms")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
