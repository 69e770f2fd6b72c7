"""Render the front page's picture: one frame of the default storm's video.

Usage::

    python docs/storm_frame.py                      # writes docs/images/storm-frame.png
    python docs/storm_frame.py --out frame.png --duration 0.1 --size 960 540
    python docs/storm_frame.py --gf DIR --out frame.png      # on another bundle

Runs the packaged default scene (``Scene.default()``, optionally shortened with
``--duration``) on the default seat (the bundle ``hailstorm`` builds and caches),
keeps its frames, and renders with the video's own renderer
(:class:`hailstorm.runtime.output.render.StormRenderer`, colour scale set over
all frames as in ``storm.mp4``) the frame with the most stones in contact, ties
broken by the deepest dent shown. Prints the frame's time and what it shows.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from hailstorm.precompute import build_bundle
from hailstorm.runtime import Scene, SeatSettings, load, run_storm
from hailstorm.runtime.output.render import StormRenderer, shown_displacement


def default_seat():
    """The default seat's bundle, built once and cached (as ``hailstorm`` does)."""
    seat = SeatSettings.default()
    return load(build_bundle(None, mesh_size=seat.mesh_size, order=seat.order, load=seat.load,
                             volume_size=seat.volume_size, young=seat.young, poisson=seat.poisson))


def pick_frame(frames) -> int:
    """Index of the frame with the most contacts, then the deepest shown dent."""
    def score(i: int) -> tuple[int, float]:
        dent = float(np.linalg.norm(shown_displacement(frames[i]), axis=1).max(initial=0.0))
        return int(frames[i].contacts), dent
    return max(range(len(frames)), key=score)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "images" / "storm-frame.png")
    ap.add_argument("--duration", type=float, default=None, help="simulated time [s] (default: the scene's)")
    ap.add_argument("--size", type=int, nargs=2, default=(1280, 720), metavar=("W", "H"))
    ap.add_argument("--gf", type=Path, default=None, help="a bundle directory (default: the default seat)")
    args = ap.parse_args(argv)

    scene = Scene.default()
    if args.duration is not None:
        scene = scene.with_(duration=args.duration)
    gf = default_seat() if args.gf is None else load(args.gf)
    result = run_storm(gf, scene, progress=False, keep_frames=True)
    frames = result.frames
    i = pick_frame(frames)
    renderer = StormRenderer.for_frames(frames, gf, history=result.history, size=tuple(args.size))
    image = renderer.render(frames[i])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    import matplotlib.image

    matplotlib.image.imsave(args.out, image)
    dent = float(np.linalg.norm(shown_displacement(frames[i]), axis=1).max(initial=0.0))
    print(f"{args.out}: frame {i} of {len(frames)} at t = {frames[i].t * 1e3:.1f} ms, "
          f"{int(frames[i].contacts)} stone(s) in contact, deepest dent shown {dent * 1e3:.2f} mm")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
