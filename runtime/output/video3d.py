"""The storm's 3-D video frame: the seat in 3-D over the force panel.

Each frame (:class:`Storm3DRenderer`, 1280 x 720 pixels by default) shows

* above, the seat in 3-D (:class:`hailstorm.runtime.output.seat_view.SeatView`): its surface
  deformed by the displacement *at the frame's instant* (a dent shows as long as the seat
  is dented; ``dents="peak"``: the largest displacement since the previous frame, as the
  2-D video shows), drawn scaled by a factor printed on the frame
  (:func:`~hailstorm.runtime.output.seat_view.displacement_scale`), coloured by the true
  ``|u|`` on one scale for the whole video (a colour bar in mm), the stones in view as
  spheres (orange while they press on the seat), from a three-quarter camera, and an
  inset whose camera follows the largest impact in view (the stone pressing hardest on
  the seat; without one, the deepest dent; without one, where it last looked);
* the caption: time, stones in view (whose sphere meets
  :func:`hailstorm.runtime.output.render.view_box`), stones in contact, playback speed,
  and the displacement's drawing scale;
* below, the force panel (:class:`hailstorm.runtime.output.force_panel.ForcePanel`): the
  total contact force on the seat and each impact's peak (``impacts.csv``).

It needs VTK with an off-screen OpenGL (:func:`hailstorm.runtime.output.offscreen.three_d_available`);
:func:`hailstorm.runtime.output.animation.write_animation` falls back to the 2-D renderer without.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from hailstorm.runtime.output.force_panel import ForcePanel
from hailstorm.runtime.output.impacts import impact_times
from hailstorm.runtime.output.render import in_view, shown_displacement, slowdown_text, total_force, view_box
from hailstorm.runtime.output.seat_view import SeatView, displacement_scale

__all__ = ["DENTS", "PANEL_FRACTION", "Storm3DRenderer", "dents_of"]

#: what the seat's shape shows: the displacement at the frame's instant, or the peak since the previous frame
DENTS = ("now", "peak")
#: the force panel's share of the frame's height
PANEL_FRACTION = 0.25
#: a dent the inset aims at when no stone presses: at least this fraction of the colour scale's top
_DENT_FOCUS = 0.05


def dents_of(frame: Any, dents: str = "now") -> np.ndarray:
    """The displacement a frame's picture shows (n, 3) [m]: ``"now"`` the frame's own,
    ``"peak"`` the largest since the previous frame (where recorded)."""
    if dents not in DENTS:
        raise ValueError(f"dents must be one of {DENTS}, not {dents!r}")
    return np.asarray(frame.displacement if dents == "now" else shown_displacement(frame))


class Storm3DRenderer:
    """Renders the frames of one storm to images (:meth:`render`; see the module notes).

    Parameters
    ----------
    gf : GreensFunctions
        The seat (``vertices``, ``triangles``).
    top : float
        The top of the colour scale [m] (the largest ``|u|`` the video shows).
    duration : float
        The force panel's time axis [s].
    history : (m, 3) ndarray, optional
        The storm's per-step (time, total contact force, contacts).
    impact_t, impact_force : (k,) ndarray, optional
        The impacts' times [s] and peak forces [N] (``impacts.csv``; :meth:`for_frames`
        estimates the times).
    size : (int, int)
        Width and height [pixels].
    dents : {"now", "peak"}
        See :func:`dents_of`.
    scale : float, optional
        The displacement's drawing scale (default: :func:`displacement_scale` of ``top``).
    samples : int
        Anti-aliasing of the 3-D view (see :class:`SeatView`).
    """

    def __init__(self, gf: Any, *, top: float, duration: float, history: np.ndarray | None = None,
                 impact_t: np.ndarray | None = None, impact_force: np.ndarray | None = None,
                 size: tuple[int, int] = (1280, 720), dents: str = "now", scale: float | None = None,
                 samples: int = -1) -> None:
        w, h = int(size[0]), int(size[1])
        if w < 320 or h < 240:
            raise ValueError(f"frame size {w} x {h} is too small (at least 320 x 240 pixels)")
        if dents not in DENTS:
            raise ValueError(f"dents must be one of {DENTS}, not {dents!r}")
        self.dents = dents
        self.size = (w, h)
        X = np.asarray(gf.vertices, dtype=np.float64)
        self.lo, self.hi = view_box(X)
        self.top = max(float(top), 0.0)
        self.scale = displacement_scale(self.top, X) if scale is None else float(scale)
        self.panel_height = int(round(PANEL_FRACTION * h))
        what = "|u|" if dents == "now" else "peak |u|"
        self.view = SeatView(X, gf.triangles, size=(w, h - self.panel_height), top=self.top, scale=self.scale,
                             label=what, samples=samples)
        self.panel = ForcePanel((w, self.panel_height), duration=duration, history=history, impact_t=impact_t,
                                impact_force=impact_force)
        #: the last frame's caption, the stones in view and those pressing, and the inset's label
        self.caption = ""
        self.n_in_view = 0
        self.n_pressing = 0
        self.inset_label = ""
        self._last_impact = ""

    @classmethod
    def for_frames(cls, frames: Sequence[Any], gf: Any, *, history: np.ndarray | None = None,
                   which: Sequence[int] | None = None, impacts: dict[str, np.ndarray] | None = None,
                   size: tuple[int, int] = (1280, 720), dents: str = "now", samples: int = -1) -> "Storm3DRenderer":
        """A renderer for the frames ``which`` of ``frames``: the colour scale's top is their largest
        shown ``|u|``, the time axis ends at the last of them (or the history's end), and the impacts'
        times are estimated from their stones' tracks (:func:`impact_times`).

        Parameters
        ----------
        frames : sequence of Frame
        gf : GreensFunctions
        history : (m, 3) ndarray, optional
        which : sequence of int, optional
            The frames that will be rendered (default: all).
        impacts : dict, optional
            The columns of ``impacts.csv`` (:func:`hailstorm.runtime.output.impacts.read_impacts`).
        size, dents, samples
            See the class parameters.
        """
        which = list(range(len(frames))) if which is None else [int(i) for i in which]
        if not which:
            raise ValueError("no frames to render")
        top, seen = 0.0, []
        for i in which:  # one pass: the colour scale's top and the stones' tracks
            f = frames[i]
            u = np.asarray(dents_of(f, dents), dtype=np.float64)
            top = max(top, float(np.linalg.norm(u, axis=1).max(initial=0.0)))
            seen.append(_Track(float(f.t), np.asarray(f.ids), np.asarray(f.positions)))
        end = seen[-1].t
        if history is not None and len(history):
            end = max(end, float(np.asarray(history)[-1, 0]))
        it = ifo = None
        if impacts is not None and len(impacts.get("stone", ())):
            it, ifo = impact_times(impacts, seen, history), np.asarray(impacts["peak_force_N"], dtype=np.float64)
        return cls(gf, top=top, duration=end, history=history, impact_t=it, impact_force=ifo, size=size,
                   dents=dents, samples=samples)

    def _aim(self, frame: Any, show: np.ndarray, u: np.ndarray) -> None:
        """Aim the inset: the largest impact in view, else the deepest dent, else where it was."""
        pos = np.asarray(frame.positions, dtype=np.float64).reshape(-1, 3)
        r = np.asarray(frame.radii, dtype=np.float64).reshape(-1)
        f = getattr(frame, "forces", None)
        F = np.linalg.norm(np.asarray(f, dtype=np.float64).reshape(-1, 3), axis=1) if f is not None \
            else np.zeros(len(r))
        F = np.where(show, F, 0.0)
        if F.size and F.max() > 0:
            k = int(np.argmax(F))
            sid = int(np.asarray(frame.ids).reshape(-1)[k])
            self._last_impact = f"stone {sid}"
            self.inset_label = f"largest impact in view: stone {sid}, {F[k]:.1f} N now"
            self.view.set_focus(pos[k], 7.0 * r[k], self.inset_label)
            return
        mag = np.linalg.norm(u, axis=1)
        j = int(np.argmax(mag)) if mag.size else 0
        if mag.size and mag[j] > _DENT_FOCUS * self.top > 0:
            self.inset_label = f"deepest dent now: |u| {mag[j] * 1e3:.2f} mm"
            X = self.view.X
            size = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0)))
            self.view.set_focus(X[j] + self.scale * u[j], 0.08 * size, self.inset_label)
            return
        self.inset_label = "no impact now" + (f" (last: {self._last_impact})" if self._last_impact else "")
        self.view.set_focus(None, 0.0, self.inset_label)

    def render(self, frame: Any, *, alpha: bool = False, slowdown: float | None = None) -> np.ndarray:
        """Draw one frame.

        Parameters
        ----------
        frame : hailstorm.runtime.storm.recording.Frame
        alpha : bool
            Return RGBA (opaque) instead of RGB.
        slowdown : float, optional
            How many times slower than real time the video plays here (in the caption).

        Returns
        -------
        (height, width, 3 or 4) uint8 ndarray
        """
        u = np.asarray(dents_of(frame, self.dents), dtype=np.float64).reshape(-1, 3)
        show = in_view(frame.positions, frame.radii, self.lo, self.hi)
        f = getattr(frame, "forces", None)
        pressing = (np.linalg.norm(np.asarray(f, dtype=np.float64).reshape(-1, 3), axis=1) > 0) if f is not None \
            else np.zeros(show.size, bool)
        self.n_in_view, self.n_pressing = int(show.sum()), int((pressing & show).sum())
        pos = np.asarray(frame.positions, dtype=np.float64).reshape(-1, 3)[show]
        if self.scale != 1.0 and pressing[show].any():
            # a stone pressing on the seat moves with the drawn (scaled) dent: it sits in it, as it does in the
            # storm, rather than hovering over a dent drawn deeper than it is
            X = self.view.X
            for i in np.flatnonzero(pressing[show]):
                j = int(np.argmin(np.einsum("ij,ij->i", X - pos[i], X - pos[i])))
                pos[i] = pos[i] + (self.scale - 1.0) * u[j]
        self.view.set_stones(pos, np.asarray(frame.radii)[show], pressing[show])
        if self.view.inset is not None:
            self._aim(frame, show, u)
        total = total_force(frame)
        if total is None and self.panel.history is not None:
            total = float(np.interp(float(frame.t), self.panel.history[:, 0], self.panel.history[:, 1]))
        n_imp = int((self.panel.impact_t <= float(frame.t) + 1e-12).sum())
        self.caption = (f"t = {frame.t * 1e3:7.1f} ms   stones in view {self.n_in_view:3d}   in contact "
                        f"{int(frame.contacts):2d}{slowdown_text(slowdown, 3)}\n"
                        "force on the seat now " + ("(not recorded)" if total is None else f"{total:7.2f} N")
                        + f"   impacts so far {n_imp:3d}\n"
                        f"shape: displacement drawn x{self.scale:g}; colour: true |u|"
                        + (" now" if self.dents == "now" else " peak since the previous frame"))
        w, h = self.size
        img = np.empty((h, w, 4 if alpha else 3), np.uint8)
        if alpha:
            img[..., 3] = 255
        self.view.draw(u, self.caption, out=img[:h - self.panel_height])
        img[h - self.panel_height:, :, :3] = self.panel.draw(float(frame.t), total)[..., :3]
        return img

    def close(self) -> None:
        """Release the 3-D view's OpenGL context."""
        self.view.close()


class _Track:
    """A frame's time and stones, without its surface (what :func:`impact_times` reads)."""

    def __init__(self, t: float, ids: np.ndarray, positions: np.ndarray) -> None:
        self.t, self.ids, self.positions = t, ids, positions
