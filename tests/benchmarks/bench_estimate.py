"""Benchmark: the storm's announced estimate against its measured wall time.

Usage::

    python tests/benchmarks/bench_estimate.py                          # the default scene at 1, 10 and 30 s
    python tests/benchmarks/bench_estimate.py --durations 1,10 --no-inertia
    python tests/benchmarks/bench_estimate.py --out docs/_generated/estimate.txt   # and into the docs

For each duration it runs ``hailstorm storm -q --duration T`` (the default scene;
``--no-inertia``: with ``[validity] inertia = false``) in a fresh process, times it
whole, and prints beside it the estimate the run announces
(:meth:`hailstorm.runtime.storm.scene.Scene.estimate` with the bundle's surface and
its share of the footprint, the video and the start-up: what ``hailstorm`` prints)
and their ratio, and the parts of each (stepping, frames, inertia; measured:
``summary.json``'s ``wall_time_s``, ``output_time_s``, ``inertia_time_s``, and the
rest of the process' wall time). Target (issue 44): the estimate within 2x of the
measured wall time. The default seat's bundle must be cached (``hailstorm`` once).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

# the studies (notebooks/studies) are in the repository, not in the package
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "notebooks"))


def _scene_file(tmp: Path, inertia: bool) -> Path | None:
    if inertia:
        return None
    from importlib import resources

    text = (resources.files("hailstorm.meshes") / "default_scene.toml").read_text()
    path = tmp / "scene.toml"
    path.write_text(text.replace("\ninertia = true", "\ninertia = false"))
    return path


def run(durations: list[float], inertia: bool) -> None:
    """One line per duration: measured and estimated wall time and their parts."""
    import hailstorm.runtime
    from hailstorm.precompute import build_bundle
    from hailstorm.runtime.storm.estimate import hit_fraction
    from hailstorm.runtime.storm.scene import Scene, SeatSettings

    seat = SeatSettings.default()
    gf = hailstorm.runtime.load(build_bundle(None, mesh_size=seat.mesh_size, order=seat.order, load=seat.load,
                                             young=seat.young, poisson=seat.poisson, progress=False))
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        scene_path = _scene_file(tmp, inertia)
        scene = Scene.default() if scene_path is None else Scene.from_toml(scene_path)
        frac = hit_fraction(gf.vertices, gf.triangles, scene.storm.margin)
        print(f"default scene{'' if inertia else ', inertia off'}; seat {gf.n_vertices} surface vertices, "
              f"share of the footprint {frac:.3f}")
        print(f"{'T[s]':>6} {'impacts':>8} {'wall[s]':>9} {'est[s]':>9} {'est/wall':>8}   "
              f"{'step':>7} {'est':>7}   {'frames':>7} {'est':>7}   {'inertia':>7} {'est':>7}   {'rest':>7} {'est':>7}")
        for T in durations:
            est = scene.with_(duration=T).estimate(gf.n_vertices, hit_fraction=frac, video=True, startup=True)
            out = tmp / f"out-{T:g}"
            cmd = [sys.executable, "-m", "hailstorm", "storm", "-q", "--duration", repr(T), "--out", str(out),
                   "--allow-large"] + ([] if scene_path is None else ["--scene", str(scene_path)])
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
            wall = time.perf_counter() - t0
            s = json.loads((out / "summary.json").read_text())
            parts = [s["wall_time_s"], s["output_time_s"], s.get("inertia_time_s", 0.0)]
            rest = wall - sum(parts)  # start-up, the storm's set-up and the video
            print(f"{T:6g} {s['impacts']:8d} {wall:9.1f} {est.seconds:9.1f} {est.seconds / wall:8.2f}   "
                  f"{parts[0]:7.1f} {est.stepping_seconds:7.1f}   {parts[1]:7.1f} {est.frame_seconds:7.1f}   "
                  f"{parts[2]:7.1f} {est.inertia_seconds:7.1f}   {rest:7.1f} "
                  f"{est.seconds - est.stepping_seconds - est.frame_seconds - est.inertia_seconds:7.1f}", flush=True)
    print("wall: the whole process; est: the announced estimate; step: the time stepping (wall_time_s); frames: "
          "writing the series (output_time_s; its estimate also holds the video's); inertia: inertia_time_s; rest: the "
          "start-up, the storm's set-up and the video")


def main(argv: list[str] | None = None) -> None:
    from studies import record

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--durations", default="1,10,30", help="simulated durations [s], comma-separated")
    ap.add_argument("--no-inertia", action="store_true", help="run with [validity] inertia = false")
    record.add_out_option(ap)
    argv = sys.argv[1:] if argv is None else argv
    args = ap.parse_args(argv)
    durations = [float(x) for x in args.durations.split(",")]
    record.run_or_record(args.out, "python tests/benchmarks/bench_estimate.py", argv,
                         lambda: run(durations, not args.no_inertia))


if __name__ == "__main__":
    main()
