"""Time the storm's video, 3-D (VTK off-screen) against 2-D (matplotlib), side by side on the default storm.

Usage::

    python docs/video_timing.py                 # writes docs/_generated/video_timing.txt
    python docs/video_timing.py --rounds 5 --size 1280 720

Runs the default storm once (frames kept; the storm's own wall time is reported too), then
alternates the two renderers ``--rounds`` times: per frame, the render alone (median over
the frames), and the whole :func:`~hailstorm.runtime.output.animation.write_animation` (render
and encode). The minimum over the rounds is the figure (the machine's other load only adds).
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time
from pathlib import Path

# the studies' run records (notebooks/studies: in the repository, not in the package)
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "notebooks"))

import numpy as np

from hailstorm.precompute import build_bundle
from hailstorm.runtime import Scene, SeatSettings, load, run_storm
from hailstorm.runtime.output.files import impacts_csv
from hailstorm.runtime.output.impacts import read_impacts
from hailstorm.runtime.output.offscreen import three_d_available
from hailstorm.runtime.output.animation import write_animation
from studies.record import stamp
from hailstorm.runtime.output.render import StormRenderer
from hailstorm.runtime.output.video3d import Storm3DRenderer


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--size", type=int, nargs=2, default=(1280, 720), metavar=("W", "H"))
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "_generated" / "video_timing.txt")
    args = ap.parse_args(argv)
    size = tuple(args.size)

    seat = SeatSettings.default()
    gf = load(build_bundle(None, mesh_size=seat.mesh_size, order=seat.order, load=seat.load,
                           volume_size=seat.volume_size, young=seat.young, poisson=seat.poisson))
    result = run_storm(gf, Scene.default(), progress=False, keep_frames=True)
    frames, history = result.frames, result.history
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "impacts.csv"
        path.write_text(impacts_csv(result.stats))
        impacts = read_impacts(path)
        times: dict[str, list[float]] = {"2d render": [], "3d render": [], "2d write_animation": [],
                                         "3d write_animation": []}
        for _ in range(args.rounds):
            for style in ("2d", "3d"):
                r = StormRenderer.for_frames(frames, gf, history=history, size=size) if style == "2d" else \
                    Storm3DRenderer.for_frames(frames, gf, history=history, impacts=impacts, size=size)
                per = []
                for f in frames:
                    t0 = time.perf_counter()
                    r.render(f, alpha=True)
                    per.append(time.perf_counter() - t0)
                getattr(r, "close", lambda: None)()
                times[f"{style} render"].append(float(np.median(per)))
                t0 = time.perf_counter()
                write_animation(result, gf, Path(tmp) / f"{style}.mp4", history=history, style=style,
                                impacts=impacts, size=size)
                times[f"{style} write_animation"].append(time.perf_counter() - t0)
    lines = [f"# python docs/video_timing.py --rounds {args.rounds} --size {size[0]} {size[1]}",
             stamp(),
             f"# {platform.platform()}, {os.cpu_count()} cores, 3-D window: {three_d_available()}",
             f"# the default storm: {len(frames)} frames, {result.stats['sim_time_s']:g} s simulated, "
             f"storm wall time {result.stats['wall_time_s']:.2f} s",
             "# per round; the figure is the minimum (render: median s/frame; write_animation: s for all frames)"]
    for k, v in times.items():
        lines.append(f"{k:22s} min {min(v):8.4f}   rounds " + " ".join(f"{x:.4f}" for x in v))
    text = "\n".join(lines) + "\n"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print(text, end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
