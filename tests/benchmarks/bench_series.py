"""A storm's ParaView series as one VTKHDF file against the .vtu pairs: files, bytes, write time.

Usage::

    python tests/benchmarks/bench_series.py                    # the default storm over 30 s
    python tests/benchmarks/bench_series.py --duration 1
    python tests/benchmarks/bench_series.py --out docs/_generated/series.txt

Runs the default scene once (inertia off: it does not touch the frames) and hands every
frame to both writers (:class:`hailstorm.runtime.output.vtkhdf.VTKHDFSeries` and
:class:`hailstorm.runtime.output.files.ParaviewSeries`), timing each; prints the files,
the bytes on disk and the write time of each, and checks the one file against the state:
the last frame read back equals the storm's last frame (target: a 30 s default storm in at
most 300 MB).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "notebooks"))


def run(duration: float) -> None:
    import hailstorm.runtime
    from studies.resolution_study import seat_bundle
    from hailstorm.runtime.output.files import ParaviewSeries
    from hailstorm.runtime.output.vtkhdf import VTKHDFSeries, read_vtkhdf_frame
    from hailstorm.runtime.storm.scene import Scene, SeatSettings

    gf = seat_bundle(SeatSettings.default().mesh_size)
    scene = Scene.default().with_(duration=duration, inertia=False)
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        one, pairs = VTKHDFSeries(gf, tmp / "one"), ParaviewSeries(gf, tmp / "vtu")
        spent = {"vtkhdf": 0.0, "vtu": 0.0}
        last = []

        def both(frame) -> None:
            for name, series in (("vtkhdf", one), ("vtu", pairs)):
                t0 = time.perf_counter()
                series.add(frame)
                spent[name] += time.perf_counter() - t0
            last[:] = [frame]

        res = hailstorm.runtime.run_storm(gf, scene, progress=False, on_frame=both, allow_large=True)
        for name, series in (("vtkhdf", one), ("vtu", pairs)):
            t0 = time.perf_counter()
            series.close()
            spent[name] += time.perf_counter() - t0
        frames = len(one)
        print(f"the default storm over {duration:g} s: {frames} frames of {gf.n_vertices} seat vertices, "
              f"{res.stats['hailstones']} stones; stepping {res.stats['wall_time_s']:.1f} s")
        print(f"  {'series':<8} {'files':>7} {'MB':>9} {'kB/frame':>9} {'write[s]':>9}")
        for name, folder in (("vtkhdf", tmp / "one"), ("vtu", tmp / "vtu")):
            files = [p for p in folder.rglob("*") if p.is_file()]
            size = sum(p.stat().st_size for p in files)
            print(f"  {name:<8} {len(files):>7} {size / 1e6:>9.1f} {size / 1e3 / frames:>9.1f} {spent[name]:>9.2f}")
        back = read_vtkhdf_frame(one.path, -1)
        same = (np.array_equal(back.displacement, last[0].displacement)
                and np.array_equal(back.positions, last[0].positions) and np.array_equal(back.ids, last[0].ids))
        print(f"  the last frame read back from storm.vtkhdf equals the storm's: {same}")


def main(argv: list[str] | None = None) -> None:
    from studies import record

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=30.0, help="simulated time [s] (default 30)")
    record.add_out_option(ap)
    argv = sys.argv[1:] if argv is None else argv
    args = ap.parse_args(argv)
    record.run_or_record(args.out, "python tests/benchmarks/bench_series.py", argv, lambda: run(args.duration))


if __name__ == "__main__":
    main()
