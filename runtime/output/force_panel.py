"""The video's force panel: the force on the seat against time, up to the frame's instant.

:class:`ForcePanel` draws a strip (matplotlib, off-screen) with

* the **total contact force on the seat** (the sum over the stones of the magnitude of
  the force each applies), one value per time step of the storm (its history; without
  one, the frames' totals), drawn up to the frame's instant over the whole run in grey;
* **each impact's peak force** as a marker, the numbers of ``impacts.csv``
  (``peak_force_N``), at the impact's time (:func:`hailstorm.runtime.output.impacts.impact_times`),
  shown once the frame's instant has passed it; a peak may stand above the line, which
  samples the force once per time step (and sums the stones in contact together);
* the frame's instant as a vertical line (its total force is in the video's caption:
  text drawn by matplotlib each frame would cost more than the rest of the panel).

The parts that do not change (axes, labels, the whole run in grey) are drawn once and
restored for each frame (blitting).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["ForcePanel"]

_LINE = "#1f4e79"
_PEAK = "#e8590c"


class ForcePanel:
    """The force strip of the 3-D video (see the module notes).

    Parameters
    ----------
    size : (int, int)
        Width and height [pixels].
    duration : float
        The time axis's end [s].
    history : (m, 3) ndarray, optional
        The storm's per-step (time, total contact force [N], open contacts).
    impact_t, impact_force : (k,) ndarray, optional
        Each impact's time [s] and peak force [N] (``impacts.csv``).
    dpi : float
        Text scale.
    """

    def __init__(self, size: tuple[int, int], *, duration: float, history: np.ndarray | None = None,
                 impact_t: np.ndarray | None = None, impact_force: np.ndarray | None = None,
                 dpi: float = 100.0) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.lines import Line2D

        w, h = int(size[0]), int(size[1])
        self.size = (w, h)
        self.history = None if history is None or len(history) == 0 else \
            np.asarray(history, dtype=np.float64).reshape(-1, 3)
        self.impact_t = np.zeros(0) if impact_t is None else np.asarray(impact_t, dtype=np.float64).reshape(-1)
        self.impact_force = np.zeros(0) if impact_force is None else \
            np.asarray(impact_force, dtype=np.float64).reshape(-1)
        if self.impact_t.shape != self.impact_force.shape:
            raise ValueError("impact_t and impact_force differ in length")
        self._totals: list[tuple[float, float]] = []
        fig = Figure(figsize=(w / dpi, h / dpi), dpi=dpi, facecolor="white")
        self.fig, self.canvas = fig, FigureCanvasAgg(fig)
        ax = fig.add_axes((0.065, 0.25, 0.90, 0.58))
        ax.set_xlim(0.0, max(float(duration), 1e-9) * 1e3)
        top = max(float(self.history[:, 1].max()) if self.history is not None else 0.0,
                  float(self.impact_force.max(initial=0.0)))
        self._top = top
        ax.set_ylim(0.0, 1.1 * top if top > 0 else 1.0)
        ax.set_xlabel("t [ms]", labelpad=1)
        ax.set_ylabel("force [N]")
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize="small")
        if self.history is not None:  # the whole run, faint
            ax.plot(self.history[:, 0] * 1e3, self.history[:, 1], color="0.78", lw=0.8, zorder=1)
        (self.line,) = ax.plot([], [], color=_LINE, lw=1.1, zorder=2, animated=True)
        (self.markers,) = ax.plot([], [], "v", color=_PEAK, ms=5, mec="k", mew=0.4, zorder=3, animated=True)
        self.now = ax.axvline(0.0, color="k", lw=0.8, alpha=0.6, animated=True)
        ax.legend(handles=[Line2D([], [], color=_LINE, lw=1.1, label="total contact force on the seat (all stones)"),
                           Line2D([], [], ls="", marker="v", color=_PEAK, mec="k", mew=0.4,
                                  label="each impact's peak force (impacts.csv peak_force_N)")],
                  loc="lower right", bbox_to_anchor=(1.0, 1.0), fontsize="small", frameon=False, ncol=2,
                  borderaxespad=0.1)
        ax.set_title("force on the seat", loc="left", fontsize="medium")
        self.ax = ax
        self._dynamic = [self.line, self.markers, self.now]
        self._background: Any = None
        #: the total force drawn at the last instant [N] (None: not recorded) and the impacts marked by then
        self.total: float | None = None
        self.impacts_shown = 0

    def _series(self, t: float, now: float | None) -> tuple[np.ndarray, np.ndarray, float | None]:
        if self.history is not None:
            hist = self.history
            before = hist[:, 0] < t - 1e-12
            ts, fs = hist[before, 0], hist[before, 1]
            if now is None:
                now = float(np.interp(t, hist[:, 0], hist[:, 1])) if t >= hist[0, 0] else 0.0
            return np.append(ts, t), np.append(fs, now), now
        if now is None:
            return np.zeros(0), np.zeros(0), None
        past = [(ti, fi) for ti, fi in self._totals if ti < t - 1e-12] + [(t, now)]
        self._totals = past
        top = max(f for _, f in past)
        if top > self._top:  # the axis grows with the frames' totals: redraw the static parts
            self._top = top
            self.ax.set_ylim(0.0, 1.1 * top)
            self._background = None
        return np.array([p[0] for p in past]), np.array([p[1] for p in past]), now

    def draw(self, t: float, total: float | None) -> np.ndarray:
        """The panel at instant ``t`` [s] whose total contact force is ``total`` [N] (None: not
        recorded; read from the history). Sets :attr:`total` (the value drawn at ``t``) and
        :attr:`impacts_shown` (the impacts marked).

        Returns
        -------
        (height, width, 4) uint8 ndarray
            RGBA, a view of the canvas (valid until the next call).
        """
        ts, fs, now = self._series(float(t), total)
        self.line.set_data(ts * 1e3, fs)
        seen = self.impact_t <= t + 1e-12
        self.markers.set_data(self.impact_t[seen] * 1e3, self.impact_force[seen])
        self.now.set_xdata([t * 1e3, t * 1e3])
        self.total, self.impacts_shown = now, int(seen.sum())
        if self._background is None:
            self.canvas.draw()
            self._background = self.canvas.copy_from_bbox(self.fig.bbox)
        else:
            self.canvas.restore_region(self._background)
        for a in self._dynamic:
            self.fig.draw_artist(a)
        return np.asarray(self.canvas.buffer_rgba())
