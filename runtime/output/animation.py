"""The storm's video file: frames rendered one at a time and appended to an MP4 (or a GIF).

:func:`write_animation` chooses the renderer once: the 3-D view
(:class:`hailstorm.runtime.output.video3d.Storm3DRenderer`) where VTK draws off-screen,
else the 2-D map (:class:`hailstorm.runtime.output.render.StormRenderer`), and writes
the frames as they are rendered (:class:`VideoWriter`), so that memory does not grow
with the storm.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from hailstorm.runtime.output.render import FRAME_SIZE, StormRenderer, playback_slowdown
from hailstorm.runtime.resources import require_extra

__all__ = ["VideoWriter", "write_animation"]

_log = logging.getLogger(__name__)


class VideoWriter:
    """Frames appended one by one to an MP4 (imageio-ffmpeg), or to a GIF beside it
    when MP4 writing fails (no ffmpeg); nothing is held in memory."""

    def __init__(self, path: Path, fps: float) -> None:
        self.path, self.fps = path, fps
        self._w: Any = None

    def _open_gif(self) -> None:
        imageio = require_extra("imageio.v2", "video", "the animation (imageio)")

        if self.path.suffix.lower() != ".gif":
            self.path = self.path.with_suffix(".gif")
        self._w = imageio.get_writer(self.path, mode="I", duration=1.0 / self.fps, loop=0)

    def append(self, image: np.ndarray) -> None:
        imageio = require_extra("imageio.v2", "video", "the animation (imageio)")

        if self._w is None:
            if self.path.suffix.lower() == ".gif":
                self._open_gif()
            else:
                try:
                    # x264's "veryfast" preset: half the encoding time of its default at 1280 x 720
                    # (measured 0.05 against 0.10 s per frame), files ~1.4x larger
                    self._w = imageio.get_writer(self.path, fps=self.fps, macro_block_size=1, codec="libx264",
                                                 quality=7, ffmpeg_params=["-preset", "veryfast"])
                    self._w.append_data(image)
                    return
                except Exception:  # no ffmpeg: fall back to a GIF
                    _log.warning("could not write %s (ffmpeg): writing a GIF instead", self.path.name)
                    try:
                        if self._w is not None:
                            self._w.close()
                    except Exception:  # noqa: S110 - the broken MP4 writer
                        pass
                    self.path.unlink(missing_ok=True)
                    self._open_gif()
        self._w.append_data(image)

    def close(self) -> Path:
        if self._w is not None:
            self._w.close()
        return self.path


def write_animation(
    result: Any,
    gf: Any,
    path: str | os.PathLike,
    *,
    max_frames: int = 100,
    fps: float = 20.0,
    size: tuple[int, int] = FRAME_SIZE,
    dpi: float = 100.0,
    history: np.ndarray | None = None,
    progress: bool = False,
    style: str = "auto",
    dents: str = "now",
    impacts: dict[str, np.ndarray] | None = None,
) -> Path:
    """Render the storm to a video: in 3-D (:class:`hailstorm.runtime.output.video3d.Storm3DRenderer`)
    where VTK draws off-screen, else the 2-D map of :class:`StormRenderer` (with a warning
    saying why).

    Frames are rendered and appended to the file one at a time (at most
    ``max_frames`` are read, each once, plus once more for the colour scale
    unless the sequence knows its peaks, as :class:`FrameSeries` does), so
    memory does not grow with the storm.

    Parameters
    ----------
    result : StormResult or sequence of Frame
        A result whose frames were kept in memory, or any sequence of frames
        such as :meth:`hailstorm.runtime.output.files.ParaviewSeries.frames` (read
        back from the files).
    gf : GreensFunctions
    path : path
        ``.mp4`` (imageio-ffmpeg) or ``.gif``. If MP4 writing fails (no
        ffmpeg), a GIF is written next to it instead.
    max_frames : int
        At most this many frames (evenly subsampled).
    fps : float
        Playback frame rate.
    size : (int, int)
        Frame width and height [pixels].
    dpi : float
        Text and line scale (dots per inch of the figure), not the image size.
    history : (m, 3) ndarray, optional
        Per-step (time, total contact force, contacts) for the force panel;
        default ``result.history`` when ``result`` has one.
    progress : bool
        tqdm bar over frames.
    style : {"auto", "3d", "2d"}
        ``"3d"``: the 3-D video (raises
        :class:`~hailstorm.runtime.output.offscreen.ThreeDUnavailable` without VTK or an
        off-screen OpenGL); ``"2d"``: the map from above and the side view; ``"auto"``: 3-D
        where it can be drawn, else 2-D.
    dents : {"now", "peak"}
        The 3-D video's seat: the displacement at each frame's instant, or the largest since
        the previous frame (the 2-D video always shows the latter).
    impacts : dict, optional
        The columns of ``impacts.csv`` (:func:`hailstorm.runtime.output.impacts.read_impacts`):
        the 3-D video's force panel marks each impact's peak force.

    Returns
    -------
    pathlib.Path
        The file written (may be the ``.gif`` fallback).
    """
    path = Path(path)
    frames = getattr(result, "frames", result)
    if len(frames) == 0:
        raise ValueError("no frames to render (run the storm with keep_frames=True, or render a ParaviewSeries)")
    if history is None:
        history = getattr(result, "history", None)
        if history is not None and len(history) == 0:
            history = None
    path.parent.mkdir(parents=True, exist_ok=True)
    idx = np.unique(np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).round().astype(int))
    if style not in ("auto", "3d", "2d"):
        raise ValueError(f"style must be 'auto', '3d' or '2d', not {style!r}")
    renderer: Any = None
    if style != "2d":
        from hailstorm.runtime.output.offscreen import ThreeDUnavailable, three_d_available

        if style == "3d" or three_d_available() is not None:
            from hailstorm.runtime.output.video3d import Storm3DRenderer

            try:
                renderer = Storm3DRenderer.for_frames(frames, gf, history=history, which=idx, impacts=impacts,
                                                      size=size, dents=dents)
            except ThreeDUnavailable as exc:
                if style == "3d":
                    raise
                _log.warning("the 2-D video instead of the 3-D one: %s", exc)
        else:
            _log.warning("the 2-D video instead of the 3-D one: no VTK with an off-screen OpenGL "
                         "(pip install 'hailstorm[video]'; on Linux also libegl1 or libosmesa6)")
    if renderer is None:
        renderer = StormRenderer.for_frames(frames, gf, history=history, which=idx, size=size, dpi=dpi)
    video = VideoWriter(path, fps)
    it: Any = idx
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(idx, desc="render", unit="frame", leave=False)
    t_prev = np.nan
    for i in it:
        frame = frames[int(i)]
        slow = playback_slowdown(np.array([t_prev, float(frame.t)]), fps)[1]  # the time scale on screen
        video.append(renderer.render(frame, alpha=True, slowdown=float(slow)))
        t_prev = float(frame.t)
    getattr(renderer, "close", lambda: None)()
    return video.close()
