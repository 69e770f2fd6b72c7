"""Render the front page's picture: one frame of the default storm's video.

Usage::

    python docs/storm_frame.py                      # writes docs/images/storm-frame.png
    python docs/storm_frame.py --out frame.png --duration 0.1 --size 960 540
    python docs/storm_frame.py --gf DIR --out frame.png      # on another bundle

Runs the packaged default scene (``Scene.default()``, optionally shortened with
``--duration``) on the default seat (the bundle ``hailstorm`` builds and caches),
keeps its frames, and renders with the video's own 3-D renderer
(:class:`hailstorm.runtime.output.video3d.Storm3DRenderer`: the seat's state at the
frame's instant, colour scale set over all frames and the impacts' markers at their
``t_peak_s``, as in ``storm.mp4``, with 4x multisampling for the still; saved in 256 colours) the frame
with the deepest dent at its instant, ties broken by the most stones in contact.
Prints the frame's time and what it shows. Without an off-screen OpenGL (VTK's EGL or
OSMesa) it falls back to the 2-D renderer.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from hailstorm.precompute import build_bundle
from hailstorm.runtime import Scene, SeatSettings, load, run_storm


def default_seat():
    """The default seat's bundle, built once and cached (as ``hailstorm`` does)."""
    seat = SeatSettings.default()
    return load(build_bundle(None, mesh_size=seat.mesh_size, order=seat.order, load=seat.load,
                             volume_size=seat.volume_size, young=seat.young, poisson=seat.poisson))


def pick_frame(frames) -> int:
    """Index of the frame with the deepest dent at its instant, then the most contacts."""
    def score(i: int) -> tuple[float, int]:
        dent = float(np.linalg.norm(np.asarray(frames[i].displacement), axis=1).max(initial=0.0))
        return dent, int(frames[i].contacts)
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
    from hailstorm.runtime.output.offscreen import three_d_available

    if three_d_available() is not None:
        from hailstorm.runtime.output.video3d import Storm3DRenderer
        from hailstorm.runtime.storm.limits import IMPACT_COLUMNS

        rec = result.stats.validity
        impacts = rec.table() if rec is not None else {k: np.zeros(0) for k in IMPACT_COLUMNS}
        renderer = Storm3DRenderer.for_frames(frames, gf, history=result.history, impacts=impacts,
                                              size=tuple(args.size), samples=4)
        what = "3-D"
    else:
        from hailstorm.runtime.output.render import StormRenderer

        renderer = StormRenderer.for_frames(frames, gf, history=result.history, size=tuple(args.size))
        what = "2-D (no off-screen OpenGL here)"
    image = renderer.render(frames[i])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    from PIL import Image  # (matplotlib's own dependency)

    # 256 colours (octree, dithered): a tenth of the full-colour file, the gradients kept
    Image.fromarray(np.ascontiguousarray(image[..., :3])).quantize(
        colors=256, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.FLOYDSTEINBERG).save(args.out, optimize=True)
    dent = float(np.linalg.norm(np.asarray(frames[i].displacement), axis=1).max(initial=0.0))
    print(f"{args.out}: {what} frame {i} of {len(frames)} at t = {frames[i].t * 1e3:.1f} ms, "
          f"{int(frames[i].contacts)} stone(s) in contact, deepest dent {dent * 1e3:.2f} mm")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
