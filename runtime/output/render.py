"""The storm's animation: what happened, frame by frame.

Each frame (:class:`StormRenderer`, 1280 x 720 pixels by default) shows

* the seat **seen from above**, coloured by the peak displacement ``|u|``
  since the previous frame on a logarithmic scale fixed for the whole video
  (from the run's largest value down :data:`COLOUR_DECADES` decades; less is
  grey), with the colour bar naming the quantity and its unit;
* the seat **seen from the side** (its silhouette, looking along +y);
* the stones in both views as circles of their true radius in data units
  (both views have equal axis scales, and the same metres per pixel), filled
  and edged in orange while they press on the seat;
* the time, the number of stones in view: those whose sphere intersects
  the view box (:func:`view_box`, the region both views show; :func:`in_view`),
  which are exactly the stones drawn, and the time scale of the playback (how
  many times slower than real time, :func:`playback_slowdown`: an impact lasts
  about a millisecond, so the video is a slow motion);
* the total contact force on the seat against time, up to the frame's
  instant (from :attr:`hailstorm.runtime.storm.driver.StormResult.history`, one value
  per time step, so that impacts shorter than a frame interval show; its last
  point is the frame's own total, ``|forces|`` summed over the stones).

Why a logarithmic colour scale: the dents of one storm span more than a
decade (stone masses span 125x between the smallest and the largest radius,
and impact speeds vary; in the default storm at ``--duration 0.3`` the 34
frames with a dent peak at 0.31 to 18.1 mm, median 1.3 mm, 65 % of them below
a tenth of the largest). A linear scale up to the peak draws most dents at
less than a tenth of the scale, nearly the background colour; a linear scale
up to a typical dent saturates the large ones and hides their shape. Two
decades below the run's peak show every dent and its fall-off, each colour
meaning the same depth in every frame.

matplotlib and imageio (the ``video`` extra) are imported inside the functions
(:func:`hailstorm.runtime.resources.require_extra`), so importing this module costs
nothing and needs neither.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np

from hailstorm.runtime.resources import require_extra

__all__ = [
    "COLOUR_DECADES",
    "FRAME_SIZE",
    "StormRenderer",
    "display_unit",
    "in_view",
    "playback_slowdown",
    "seen_from_above",
    "shown_displacement",
    "slowdown_text",
    "total_force",
    "view_box",
]

_log = logging.getLogger(__name__)

#: pixel size (width, height) of a rendered frame
FRAME_SIZE = (1280, 720)
#: decades of the logarithmic colour scale below the run's peak displacement
COLOUR_DECADES = 2.0
#: the view box around the seat: this much beyond its bounding box on every side [m] ...
VIEW_MARGIN = 0.01
#: ... and this much above its top, where the stones fall in [m]
VIEW_ABOVE = 0.06

_SKY = "#c9d3dd"  # background: a stormy grey-blue, so that the white stones show
_ICE = "#f4f8fc"  # hailstones
_PRESS = "#ff7f0e"  # the edge of a stone in contact
_PRESS_FACE = (1.0, 0.50, 0.05, 0.55)  # and its fill
_BELOW = "#8d949c"  # the seat where |u| is below the colour scale
_SEAT = "#5b636b"  # the seat's silhouette in the side view


def shown_displacement(frame: Any) -> np.ndarray:
    """What a picture of a frame shows: the peak displacement since the previous
    frame when the storm recorded it (impacts last ~1 ms, shorter than a frame
    interval, so the instantaneous field would almost never show a dent), else
    the displacement at the frame's instant.

    Parameters
    ----------
    frame : hailstorm.runtime.storm.driver.Frame

    Returns
    -------
    (n, 3) ndarray
        Per surface vertex [m].
    """
    peak = getattr(frame, "peak_displacement", None)
    return frame.displacement if peak is None else peak


def total_force(frame: Any) -> float | None:
    """The total contact force on the seat at a frame's instant [N]: the sum of the
    magnitudes of the forces its stones apply (``None`` when the frame has no
    ``forces``)."""
    f = getattr(frame, "forces", None)
    if f is None:
        return None
    f = np.asarray(f, dtype=np.float64).reshape(-1, 3)
    return float(np.linalg.norm(f, axis=1).sum())


def display_unit(peak: float) -> tuple[str, float]:
    """The unit the colour bar shows a displacement of largest value ``peak`` [m] in:
    ``("mm", 1e3)`` from 1 mm up, else ``("µm", 1e6)`` (name, factor from metres)."""
    return ("mm", 1e3) if peak >= 1e-3 else ("µm", 1e6)


def view_box(vertices: np.ndarray, *, margin: float = VIEW_MARGIN,
             above: float = VIEW_ABOVE) -> tuple[np.ndarray, np.ndarray]:
    """The box the animation shows: the seat's bounding box grown by ``margin`` on
    every side and by ``above`` more on top (the plan view shows its x-y extent, the
    side view its x-z extent).

    Returns
    -------
    lo, hi : (3,) ndarray
        Opposite corners [m].
    """
    X = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    lo, hi = X.min(axis=0) - margin, X.max(axis=0) + margin
    hi[2] += above
    return lo, hi


def in_view(positions: np.ndarray, radii: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Which stones are in view: their sphere intersects the box ``[lo, hi]`` (the
    distance from the centre to the box is at most the radius).

    Returns
    -------
    (k,) bool ndarray
    """
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(radii, dtype=np.float64).reshape(-1)
    d = p - np.clip(p, lo, hi)
    return np.einsum("ij,ij->i", d, d) <= r * r


class StormRenderer:
    """Renders frames of one storm to images (:meth:`render`), all with one colour
    scale and one force axis (see the module notes for what a frame shows).

    The figure is off-screen (Agg) and its own: the caller's pyplot state and
    backend are not touched. Its parts are attributes (``fig``, ``ax_plan``,
    ``ax_side``, ``ax_force``, ``colorbar``, ``force_line``), for tests and for
    callers who want to save a single frame (``renderer.fig.savefig(...)``).

    Parameters
    ----------
    gf : GreensFunctions
        The seat (``vertices``, ``triangles``).
    peak : float
        The largest ``|u|`` to show [m] (the top of the colour scale; the
        run's largest shown displacement).
    duration : float
        Time axis of the force panel [s].
    history : (m, 3) ndarray, optional
        The storm's per-step (time, total contact force, contacts)
        (:attr:`StormResult.history`). Without it the force panel plots the
        totals of the frames rendered so far.
    peak_shown : bool
        The frames carry ``peak_displacement`` (labels the colour bar).
    size : (int, int)
        Image width and height [pixels].
    dpi : float
        Dots per inch of the figure: scales the text and lines, not the image.
    """

    def __init__(self, gf: Any, *, peak: float, duration: float, history: np.ndarray | None = None,
                 peak_shown: bool = True, size: tuple[int, int] = FRAME_SIZE, dpi: float = 100.0) -> None:
        require_extra("matplotlib", "video", "the animation (matplotlib)")
        from matplotlib import colormaps, colors
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.ticker import FuncFormatter

        w, h = int(size[0]), int(size[1])
        if w < 320 or h < 240:
            raise ValueError(f"frame size {w} x {h} is too small (at least 320 x 240 pixels)")
        X = np.asarray(gf.vertices, dtype=np.float64)
        tri = np.asarray(gf.triangles, dtype=np.int64)
        self.lo, self.hi = view_box(X)
        span = self.hi - self.lo
        self.peak = max(float(peak), 0.0)
        self.unit, self.factor = display_unit(self.peak)
        vmax = self.peak * self.factor if self.peak > 0 else 1.0
        self.norm = colors.LogNorm(vmin=vmax * 10.0 ** -COLOUR_DECADES, vmax=vmax, clip=False)
        self.cmap = colormaps["viridis"].with_extremes(under=_BELOW, bad=(0.0, 0.0, 0.0, 0.0))
        self.history = None if history is None or len(history) == 0 else \
            np.asarray(history, dtype=np.float64).reshape(-1, 3)
        self.duration = float(duration)
        self._totals: list[tuple[float, float]] = []  # (t, F) of the frames rendered, without a history

        fig = Figure(figsize=(w / dpi, h / dpi), dpi=dpi, facecolor=_SKY)
        self.fig = fig
        self.canvas = FigureCanvasAgg(fig)
        # layout in pixels: the plan view over the side view on the left at one scale
        # (metres per pixel), the colour bar beside them, the force panel on the right
        top_pad, bottom_pad, gap = 0.075 * h, 0.075 * h, 0.07 * h
        s = min(0.5 * w / span[0], (h - top_pad - bottom_pad - gap) / (span[1] + span[2]))
        x0 = 0.06 * w
        pw, ph, sh = span[0] * s, span[1] * s, span[2] * s
        side_y = bottom_pad
        plan_y = side_y + sh + gap

        def frac(x: float, y: float, ww: float, hh: float) -> list[float]:
            return [x / w, y / h, ww / w, hh / h]

        mm = FuncFormatter(lambda v, _: f"{v * 1e3:.0f}")
        p = X[tri]
        overlays = self._add_plan_view(X, tri, frac(x0, plan_y, pw, ph), (pw, ph), mm)
        self._add_side_view(p, frac(x0, side_y, pw, sh), mm)
        cx = x0 + pw + 0.012 * w
        self._add_colour_bar(frac(cx, plan_y, 0.012 * w, ph), peak_shown)
        fx = cx + 0.012 * w + 0.13 * w
        self._add_force_panel(frac(fx, bottom_pad, w - fx - 0.03 * w, h - top_pad - bottom_pad))

        self.caption = fig.text(x0 / w, 1.0 - 0.02, "", fontsize="large", va="top", family="monospace")
        #: the stones' circle collections of the last rendered frame (plan view, side view)
        self.stones_drawn: list[Any] = []
        # what changes from frame to frame, in drawing order (over the seat's image: its contours);
        # the rest is drawn once and restored for each frame (blitting: the axes, ticks and
        # labels cost more to draw than everything else)
        self._dynamic = [self.surface, *overlays, self.force_line, self.force_now, self.force_title, self.caption]
        for a in self._dynamic:
            a.set_animated(True)
        self._background: Any = None
        #: stones in view in the last rendered frame (the number on screen)
        self.n_in_view = 0

    def _add_plan_view(self, X: np.ndarray, tri: np.ndarray, rect: list[float], pixels: tuple[float, float],
                       mm: Any) -> list[Any]:
        """The seat seen from above (``self.ax_plan``): its image (``self.surface``, one sample per
        pixel, coloured by :meth:`render`), its height contours every 5 mm and its outline.

        Parameters
        ----------
        X : (n, 3) ndarray
            The seat's vertices [m].
        tri : (m, 3) int ndarray
            Its triangles.
        rect : list of float
            The axes' place in the figure (left, bottom, width, height as fractions).
        pixels : (float, float)
            The axes' width and height [pixels].
        mm : matplotlib.ticker.Formatter
            The tick labels in mm.

        Returns
        -------
        list
            The contour sets drawn over the image (redrawn over it each frame).
        """
        span = self.hi - self.lo
        ax = self.fig.add_axes(rect, facecolor=_SKY)
        ax.set_xlim(self.lo[0], self.hi[0])
        ax.set_ylim(self.lo[1], self.hi[1])
        ax.set_aspect("equal", adjustable="box")
        ax.xaxis.set_major_formatter(mm)
        ax.yaxis.set_major_formatter(mm)
        ax.set_ylabel("y [mm]")
        ax.set_title("seen from above", fontsize="medium", loc="left")
        self.ax_plan = ax
        # the seat seen from above, one sample per pixel: each pixel shows the highest point of the
        # surface over it, its value linearly interpolated in that triangle (so an edge of the
        # colour scale is a clean contour, not the jagged run of triangles Gouraud blending draws)
        p = X[tri]
        fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        nx, ny = max(int(round(pixels[0])), 2), max(int(round(pixels[1])), 2)
        self._interp = seen_from_above(X, tri[fn[:, 2] > 0], self.lo[:2], self.hi[:2], nx, ny)
        M, inside, shape = self._interp
        # the image is coloured here (an RGBA array, one sample per screen pixel): cheaper than
        # matplotlib's colour mapping and resampling of a masked float image
        self._rgba = np.zeros(shape + (4,), dtype=np.uint8)
        self.surface = ax.imshow(self._rgba, origin="lower", interpolation="nearest",
                                 extent=(self.lo[0], self.hi[0], self.lo[1], self.hi[1]), aspect="equal", zorder=1)
        #: the last rendered frame's value at each pixel of the plan view [unit], NaN off the seat
        self.shown = np.full(shape, np.nan)
        # the seat's shape: height contours every 5 mm and its outline from above
        height = np.full(shape[0] * shape[1], np.nan)
        height[inside] = M @ X[:, 2]
        height = height.reshape(shape)
        xs = self.lo[0] + (np.arange(shape[1]) + 0.5) * span[0] / shape[1]
        ys = self.lo[1] + (np.arange(shape[0]) + 0.5) * span[1] / shape[0]
        overlays: list[Any] = []
        if inside.size:
            levels = np.arange(np.ceil(np.nanmin(height) / 0.005) * 0.005, np.nanmax(height), 0.005)
            if levels.size:
                overlays.append(ax.contour(xs, ys, np.ma.masked_invalid(height), levels=levels, colors="k",
                                           linewidths=0.4, alpha=0.35, zorder=2))
            overlays.append(ax.contour(xs, ys, np.isfinite(height).astype(float), levels=[0.5], colors="k",
                                       linewidths=0.7, alpha=0.7, zorder=2))
        return overlays

    def _add_side_view(self, p: np.ndarray, rect: list[float], mm: Any) -> None:
        """The seat seen from the side (``self.ax_side``): its triangles ``p`` (m, 3, 3) [m]
        projected on x-z, at ``rect`` in the figure, ticks labelled by ``mm``."""
        from matplotlib.collections import PolyCollection

        ax2 = self.fig.add_axes(rect, facecolor=_SKY)
        ax2.set_xlim(self.lo[0], self.hi[0])
        ax2.set_ylim(self.lo[2], self.hi[2])
        ax2.set_aspect("equal", adjustable="box")
        ax2.xaxis.set_major_formatter(mm)
        ax2.yaxis.set_major_formatter(mm)
        ax2.set_xlabel("x [mm]")
        ax2.set_ylabel("z [mm]")
        ax2.set_title("seen from the side", fontsize="medium", loc="left")
        ax2.add_collection(PolyCollection(p[:, :, [0, 2]], facecolors=_SEAT, edgecolors=_SEAT, linewidths=0.3))
        self.ax_side = ax2

    def _add_colour_bar(self, rect: list[float], peak_shown: bool) -> None:
        """The colour bar (``self.colorbar``) of ``self.norm`` and ``self.cmap`` at ``rect``, its
        label naming the quantity (the peak since the previous frame when ``peak_shown``) and unit."""
        from matplotlib.cm import ScalarMappable
        from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

        cax = self.fig.add_axes(rect)
        what = "peak |u| since the previous frame" if peak_shown else "|u|"
        self.colorbar = self.fig.colorbar(ScalarMappable(norm=self.norm, cmap=self.cmap), cax=cax, extend="min")
        self.colorbar.ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        self.colorbar.ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
        self.colorbar.ax.yaxis.set_minor_formatter(NullFormatter())
        self.colorbar.set_label(f"{what} [{self.unit}], log scale\n(grey: below {self.norm.vmin:.3g} {self.unit})"
                                if self.peak > 0 else f"{what}: the seat did not move")

    def _add_force_panel(self, rect: list[float]) -> None:
        """The force panel (``self.ax_force``) at ``rect``: time axis to ``self.duration``, force
        axis to the history's largest total, with the force line, the frame's point and a title."""
        axf = self.fig.add_axes(rect, facecolor="white")
        axf.set_xlim(0.0, max(self.duration, 1e-9) * 1e3)
        fmax = float(self.history[:, 1].max()) if self.history is not None and len(self.history) else 0.0
        self._fmax = fmax
        axf.set_ylim(0.0, 1.05 * fmax if fmax > 0 else 1.0)
        axf.set_xlabel("t [ms]")
        axf.set_ylabel("total contact force on the seat [N]")
        axf.grid(alpha=0.3)
        (self.force_line,) = axf.plot([], [], color="#1f4e79", lw=1.0)
        (self.force_now,) = axf.plot([], [], "o", color=_PRESS, ms=5)
        self.ax_force = axf
        self.force_title = axf.set_title("", fontsize="medium", loc="left")

    @classmethod
    def for_frames(cls, frames: Any, gf: Any, *, history: np.ndarray | None = None, which: Any = None,
                   size: tuple[int, int] = FRAME_SIZE, dpi: float = 100.0) -> "StormRenderer":
        """A renderer scaled for a sequence of frames: the colour scale tops at the
        largest shown ``|u|`` of the frames ``which`` (default: all), the time axis
        runs to the last time of ``history`` or of those frames.

        Parameters
        ----------
        frames : sequence of Frame
            e.g. :attr:`StormResult.frames` or
            :meth:`hailstorm.runtime.output.files.ParaviewSeries.frames` (whose
            ``peak_norm`` gives each frame's peak without reading it).
        gf : GreensFunctions
        history : (m, 3) ndarray, optional
            See the class parameters.
        which : sequence of int, optional
            The frames that will be rendered.
        size, dpi
            See the class parameters.
        """
        which = range(len(frames)) if which is None else which
        which = [int(i) for i in which]
        if not which:
            raise ValueError("no frames to render")
        peak_norm = getattr(frames, "peak_norm", None)
        if peak_norm is None:
            def peak_norm(i: int) -> float:
                # (in float64, as :meth:`render` takes the norms: a float32 norm rounds below them)
                return float(np.linalg.norm(np.asarray(shown_displacement(frames[i]), dtype=np.float64),
                                            axis=1).max(initial=0.0))
        peak = max(peak_norm(i) for i in which)
        last = frames[which[-1]]
        end = float(last.t)
        if history is not None and len(history):
            end = max(end, float(np.asarray(history)[-1, 0]))
        return cls(gf, peak=peak, duration=end, history=history, size=size, dpi=dpi,
                   peak_shown=getattr(last, "peak_displacement", None) is not None)

    def in_view(self, frame: Any) -> np.ndarray:
        """Which of ``frame``'s stones are in view (:func:`in_view` with this renderer's box)."""
        return in_view(frame.positions, frame.radii, self.lo, self.hi)

    def _draw_stones(self, frame: Any) -> None:
        from matplotlib.collections import PatchCollection
        from matplotlib.patches import Circle

        for c in self.stones_drawn:
            c.remove()
        self.stones_drawn = []
        show = self.in_view(frame)
        self.n_in_view = int(show.sum())
        self.n_pressing = 0
        if not self.n_in_view:
            return
        pos = np.asarray(frame.positions, dtype=np.float64).reshape(-1, 3)[show]
        r = np.asarray(frame.radii, dtype=np.float64)[show]
        f = getattr(frame, "forces", None)
        pressing = (np.linalg.norm(np.asarray(f).reshape(-1, 3)[show], axis=1) > 0 if f is not None
                    else np.zeros(r.size, bool))
        edges = np.where(pressing, _PRESS, "#ffffff")
        widths = np.where(pressing, 2.4, 0.8)
        self.n_pressing = int(pressing.sum())
        for ax, k, face in ((self.ax_plan, 1, (0.96, 0.97, 0.99, 0.45)), (self.ax_side, 2, _ICE)):
            # side view: the nearest stones on top (viewed along +y: small y is near)
            order = np.argsort(-pos[:, 1]) if k == 2 else np.argsort(pos[:, 2])
            # a stone pressing on the seat is filled with the contact colour: visible at a glance
            faces = [_PRESS_FACE if pressing[i] else face for i in order]
            pc = PatchCollection([Circle((pos[i, 0], pos[i, k]), r[i]) for i in order], facecolors=faces,
                                 edgecolors=edges[order], linewidths=widths[order], zorder=3, animated=True)
            ax.add_collection(pc)
            self.stones_drawn.append(pc)

    def _force_series(self, frame: Any) -> tuple[np.ndarray, np.ndarray, float | None]:
        t = float(frame.t)
        now = total_force(frame)
        if self.history is not None:
            hist = self.history
            before = hist[:, 0] < t - 1e-12
            ts, fs = hist[before, 0], hist[before, 1]
            if now is None:  # a frame without forces: the history's value at its instant
                now = float(np.interp(t, hist[:, 0], hist[:, 1])) if len(hist) and t >= hist[0, 0] else 0.0
        else:
            if now is None:
                return np.zeros(0), np.zeros(0), None
            past = [(ti, fi) for ti, fi in self._totals if ti < t - 1e-12]
            ts, fs = np.array([p[0] for p in past]), np.array([p[1] for p in past])
            self._totals = past + [(t, now)]
            top = max(fs.max(initial=0.0), now)
            if top > self._fmax:
                self._fmax = top
                self.ax_force.set_ylim(0.0, 1.05 * top)
                self._background = None  # the axis changed: redraw the static parts
        return np.append(ts, t), np.append(fs, now), now

    def render(self, frame: Any, *, alpha: bool = False, slowdown: float | None = None) -> np.ndarray:
        """Draw one frame.

        Parameters
        ----------
        frame : hailstorm.runtime.storm.driver.Frame
        alpha : bool
            Return RGBA (a plain copy of the canvas: cheaper than dropping the
            alpha channel, which is what the video writer takes).
        slowdown : float, optional
            How many times slower than real time the video plays at this frame
            (:func:`playback_slowdown`), shown in the caption.

        Returns
        -------
        (height, width, 3 or 4) uint8 ndarray
        """
        mag = np.linalg.norm(np.asarray(shown_displacement(frame), dtype=np.float64), axis=1)
        M, inside, shape = self._interp
        vals = M @ (mag * self.factor)
        self.shown.flat[inside] = vals
        rgba = self._rgba.reshape(-1, 4)
        # below the scale (zero included) maps to the "under" colour
        rgba[inside] = self.cmap(self.norm(np.maximum(vals, 0.5 * self.norm.vmin)), bytes=True)
        self.surface.set_data(self._rgba)
        self._draw_stones(frame)
        ts, fs, now = self._force_series(frame)
        self.force_line.set_data(ts * 1e3, fs)
        self.force_now.set_data(ts[-1:] * 1e3, fs[-1:])
        self.force_title.set_text("total contact force: not recorded" if now is None
                                  else f"total contact force  {now:7.2f} N")
        self.caption.set_text(f"t = {frame.t * 1e3:7.1f} ms    stones in view {self.n_in_view:3d}    "
                              f"in contact {int(frame.contacts):3d}" + slowdown_text(slowdown))
        if self._background is None:
            self.canvas.draw()  # the static parts (animated artists are skipped)
            self._background = self.canvas.copy_from_bbox(self.fig.bbox)
        else:
            self.canvas.restore_region(self._background)
        for a in self._dynamic + self.stones_drawn:
            self.fig.draw_artist(a)
        buf = np.asarray(self.canvas.buffer_rgba())
        return buf.copy() if alpha else buf[..., :3].copy()


def playback_slowdown(times: np.ndarray, fps: float) -> np.ndarray:
    """How many times slower than real time a video plays frames recorded at ``times`` [s] at
    ``fps`` frames per second: ``1 / (fps * interval)``, with the interval since the previous
    frame (the span a frame's peak displacement covers); NaN for the first frame and for a
    zero interval."""
    t = np.asarray(times, dtype=np.float64).reshape(-1)
    gap = np.diff(t, prepend=np.nan)
    ok = gap > 0
    return np.where(ok, 1.0 / (float(fps) * np.where(ok, gap, 1.0)), np.nan)


def slowdown_text(slowdown: float | None, indent: int = 4) -> str:
    """The caption's time scale after ``indent`` spaces: ``"    playback 12.5x slower than real
    time"`` (empty when unknown)."""
    if slowdown is None or not np.isfinite(slowdown):
        return ""
    pad = " " * indent
    if slowdown >= 1.0:
        return f"{pad}playback {slowdown:.3g}x slower than real time"
    return f"{pad}playback {1.0 / slowdown:.3g}x faster than real time"


def seen_from_above(vertices: np.ndarray, triangles: np.ndarray, lo: np.ndarray, hi: np.ndarray, nx: int,
                    ny: int) -> tuple[Any, np.ndarray, tuple[int, int]]:
    """The surface seen from above on an ``ny`` x ``nx`` pixel grid over the x-y box
    ``[lo, hi]``: at each pixel centre, the highest of the triangles over it (a
    z-buffer), and the linear interpolation from the vertices to that point.

    Parameters
    ----------
    vertices : (n, 3) ndarray
    triangles : (t, 3) int ndarray
    lo, hi : (2,) ndarray
        Opposite corners of the grid [m].
    nx, ny : int
        Pixels along x and y.

    Returns
    -------
    M : scipy.sparse.csr_matrix, (p, n)
        Barycentric weights: ``M @ f`` are the values of the vertex field ``f``
        at the ``p`` pixels the surface covers.
    inside : (p,) int ndarray
        Those pixels' flat indices in the grid (row-major, row 0 at ``lo[1]``).
    shape : (int, int)
        ``(ny, nx)``.
    """
    from scipy.sparse import csr_matrix

    X = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    T = np.asarray(triangles, dtype=np.int64).reshape(-1, 3)
    # continuous pixel coordinates: pixel (i, j) has its centre at (i, j)
    u = (X[:, 0] - lo[0]) * (nx / (hi[0] - lo[0])) - 0.5
    v = (X[:, 1] - lo[1]) * (ny / (hi[1] - lo[1])) - 0.5
    tu, tv = u[T], v[T]
    i0 = np.clip(np.ceil(tu.min(axis=1)), 0, nx).astype(np.int64)
    i1 = np.clip(np.floor(tu.max(axis=1)), -1, nx - 1).astype(np.int64)
    j0 = np.clip(np.ceil(tv.min(axis=1)), 0, ny).astype(np.int64)
    j1 = np.clip(np.floor(tv.max(axis=1)), -1, ny - 1).astype(np.int64)
    ni, nj = np.maximum(i1 - i0 + 1, 0), np.maximum(j1 - j0 + 1, 0)
    count = ni * nj
    k = np.repeat(np.arange(T.shape[0]), count)  # candidate (triangle, pixel) pairs over each bounding box
    off = np.arange(k.size) - np.repeat(np.cumsum(count) - count, count)
    ii, jj = i0[k] + off % ni[k], j0[k] + off // ni[k]
    x, y = tu[k], tv[k]
    det = (y[:, 1] - y[:, 2]) * (x[:, 0] - x[:, 2]) + (x[:, 2] - x[:, 1]) * (y[:, 0] - y[:, 2])
    ok = np.abs(det) > 1e-12  # a triangle seen edge-on covers nothing
    det = np.where(ok, det, 1.0)
    l0 = ((y[:, 1] - y[:, 2]) * (ii - x[:, 2]) + (x[:, 2] - x[:, 1]) * (jj - y[:, 2])) / det
    l1 = ((y[:, 2] - y[:, 0]) * (ii - x[:, 2]) + (x[:, 0] - x[:, 2]) * (jj - y[:, 2])) / det
    w = np.stack([l0, l1, 1.0 - l0 - l1], axis=1)
    ok &= np.all(w >= -1e-9, axis=1)
    k, w, pix = k[ok], w[ok], (jj * nx + ii)[ok]
    z = np.einsum("ij,ij->i", w, X[T[k], 2])
    order = np.lexsort((-z, pix))  # per pixel, the highest first
    first = order[np.r_[True, pix[order][1:] != pix[order][:-1]]] if order.size else order
    inside = pix[first]
    M = csr_matrix((w[first].ravel(), (np.repeat(np.arange(first.size), 3), T[k[first]].ravel())),
                   shape=(first.size, X.shape[0]))
    return M, inside, (ny, nx)
