"""The seat in 3-D (VTK, off-screen): the picture of one instant of the storm.

:class:`SeatView` draws the seat's surface deformed by a displacement field (scaled
by a factor it prints), shaded and coloured by the displacement's magnitude with a
colour bar in mm, the stones as shaded spheres where they are, from a three-quarter
camera that frames the saddle (:func:`three_quarter_camera`), with an inset whose camera
follows a point (the storm's largest impact in view, chosen by the caller).

The colours: the seat's own grey where it does not move, then the dent colours of
:func:`dent_colours` up the scale, the colour bar's labels in mm on a square-root scale
(:data:`COLOUR_GAMMA`): a dent of a tenth of the run's largest is a third of the way up,
clearly coloured, where a linear scale draws it nearly grey.

VTK is imported when a view is made (the ``video`` extra).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hailstorm.runtime.output.offscreen import offscreen_window

__all__ = ["COLOUR_GAMMA", "SeatView", "dent_colours", "displacement_scale", "three_quarter_camera"]

#: the colour scale's exponent: colour position = (|u| / top) ** COLOUR_GAMMA
COLOUR_GAMMA = 0.5
#: where the inset is in the picture (xmin, ymin, xmax, ymax as fractions; y up): the upper left, empty in
#: the three-quarter view (the seat runs from the lower left to the upper right)
INSET_VIEWPORT = (0.008, 0.36, 0.30, 0.86)
#: the scaled displacement the factor aims at: this fraction of the seat's size (bounding-box diagonal)
SCALE_TARGET = 0.02

_SKY_TOP = (0.60, 0.68, 0.77)  # the background's gradient, top to bottom: a stormy sky
_SKY_BOTTOM = (0.89, 0.91, 0.93)
_ICE = (0.90, 0.94, 1.0)  # a hailstone
_ICE_PRESSING = (1.0, 0.72, 0.45)  # a hailstone pressing on the seat
_SEAT = (0.42, 0.44, 0.48)  # the seat where it does not move


def dent_colours(n: int = 256) -> np.ndarray:
    """The colour table of the displacement, bottom (no displacement: the seat's grey) to top.

    Parameters
    ----------
    n : int
        Entries.

    Returns
    -------
    (n, 3) float ndarray
        RGB in [0, 1], evenly spaced in colour position (the square root of ``|u|`` over the top).
    """
    from matplotlib import colormaps

    x = np.linspace(0.0, 1.0, n)
    hot = colormaps["inferno"](0.30 + 0.66 * x)[:, :3]  # purple, red, orange, yellow
    w = np.clip(x / 0.12, 0.0, 1.0)[:, None]  # from the seat's grey into the dent colours over the first 12 %
    return (1.0 - w) * np.asarray(_SEAT) + w * hot


def displacement_scale(peak: float, vertices: np.ndarray, *, target: float = SCALE_TARGET) -> float:
    """The factor the displacement is drawn with: the smallest of 1, 2, 5, 10, 20, ... that
    draws ``peak`` [m] at least ``target`` of the seat's size (its bounding-box diagonal).

    Parameters
    ----------
    peak : float
        The largest displacement to draw [m].
    vertices : (n, 3) ndarray
    target : float

    Returns
    -------
    float
        1 when ``peak`` is 0 or already large enough.
    """
    X = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    size = float(np.linalg.norm(X.max(axis=0) - X.min(axis=0))) if len(X) else 0.0
    if not peak > 0 or size == 0.0:
        return 1.0
    need = target * size / float(peak)
    k = 1.0
    while k < need and k < 1e6:  # 1, 2, 5, 10, 20, 50, ...
        k *= 2.5 if str(k).startswith("2") else 2.0
    return k


def three_quarter_camera(vertices: np.ndarray, aspect: float, *, azimuth: float = -125.0, elevation: float = 32.0,
                         view_angle: float = 30.0, fill: float = 0.9) -> tuple[np.ndarray, np.ndarray]:
    """A camera that sees the seat from the front, one side and above, framing it.

    Parameters
    ----------
    vertices : (n, 3) ndarray
        The seat (z up).
    aspect : float
        The view's width over its height.
    azimuth, elevation : float
        Direction from the seat to the camera [degrees]: azimuth from +x towards +y,
        elevation above the x-y plane.
    view_angle : float
        The vertical view angle [degrees].
    fill : float
        The fraction of the view's width or height the seat spans (whichever is tighter).

    Returns
    -------
    position, focal_point : (3,) ndarray
        View-up is +z.
    """
    X = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    a, e = np.radians(azimuth), np.radians(elevation)
    back = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])  # from the seat to the camera
    right = np.cross(-back, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, -back)
    centre = 0.5 * (X.min(axis=0) + X.max(axis=0))
    # centre the seat's projected extent, then back off until every vertex is within `fill` of the view
    d = X - centre
    r, u = d @ right, d @ up
    centre = centre + right * 0.5 * (r.max() + r.min()) + up * 0.5 * (u.max() + u.min())
    d = X - centre
    r, u, f = d @ right, d @ up, d @ back
    tv = np.tan(np.radians(view_angle) / 2.0) * fill
    th = tv * aspect
    dist = float(np.max(np.maximum(np.abs(r) / th, np.abs(u) / tv) + f))
    return centre + back * dist, centre


class SeatView:
    """The 3-D picture of the seat and the stones at one instant (see the module notes).

    Parameters
    ----------
    vertices : (n, 3) ndarray
        The seat's surface vertices [m].
    triangles : (m, 3) int ndarray
        Its triangles (outward).
    size : (int, int)
        The picture's width and height [pixels].
    top : float
        The top of the colour scale [m] (the largest ``|u|`` of the run).
    scale : float
        The factor the displacement is drawn with.
    label : str
        What the colour bar shows (its title, before the unit).
    inset : bool
        Draw the inset (a close-up following :meth:`draw`'s ``focus``).
    samples : int
        Multisample anti-aliasing (0: FXAA, a cheaper smoothing of the edges; -1: none).
    """

    def __init__(self, vertices: np.ndarray, triangles: np.ndarray, *, size: tuple[int, int], top: float,
                 scale: float = 1.0, label: str = "|u|", inset: bool = True, samples: int = -1) -> None:
        from vtkmodules.util.numpy_support import numpy_to_vtk
        from vtkmodules.vtkRenderingCore import vtkCoordinate

        self.width, self.height = int(size[0]), int(size[1])
        self.X = np.ascontiguousarray(vertices, dtype=np.float64).reshape(-1, 3)
        self.T = np.ascontiguousarray(triangles, dtype=np.int64).reshape(-1, 3)
        self.top_mm = float(top) * 1e3 if top > 0 else 1.0
        self.scale = float(scale)
        self.rw = offscreen_window((self.width, self.height), samples=max(int(samples), 0))
        self._np = numpy_to_vtk
        seat = self._seat_actor()
        stones = self._stones_actor()
        lights = self._main_renderer(seat, stones, inset=inset, samples=samples)
        fs = max(10, int(round(self.height * 0.030)))  # the text's size follows the picture's
        self._add_caption(fs)
        self._add_colour_bar(label, fs)
        self.inset: Any = None
        if inset:
            self._add_inset(seat, stones, lights, samples=samples, font_size=fs)
        self._coord = vtkCoordinate()
        self._coord.SetCoordinateSystemToWorld()
        self._px = None
        self.focus: np.ndarray | None = None

    def _seat_actor(self) -> Any:
        """The seat's actor: its mesh over arrays the view owns (points, normals and ``|u|`` [mm],
        refilled in place each frame), coloured through the lookup table ``self.lut`` (the dent
        colours on the square-root scale), Phong-shaded.

        Returns
        -------
        vtkActor
        """
        from vtkmodules.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray
        from vtkmodules.vtkCommonCore import vtkLookupTable, vtkPoints
        from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
        from vtkmodules.vtkRenderingCore import vtkActor, vtkPolyDataMapper

        n = self.X.shape[0]
        # the seat: points, normals and |u| [mm] are arrays the view owns, refilled in place each frame
        self._pts = self.X.copy()
        self._nrm = np.zeros_like(self._pts)
        self._mag = np.zeros(n)
        points = vtkPoints()
        points.SetData(numpy_to_vtk(self._pts, deep=False))
        cells = vtkCellArray()
        cells.SetData(numpy_to_vtkIdTypeArray(np.arange(0, 3 * len(self.T) + 1, 3, dtype=np.int64), deep=True),
                      numpy_to_vtkIdTypeArray(self.T.ravel().copy(), deep=True))
        poly = vtkPolyData()
        poly.SetPoints(points)
        poly.SetPolys(cells)
        nrm = numpy_to_vtk(self._nrm, deep=False)
        nrm.SetName("Normals")
        poly.GetPointData().SetNormals(nrm)
        mag = numpy_to_vtk(self._mag, deep=False)
        mag.SetName("|u|")
        poly.GetPointData().SetScalars(mag)
        self._poly, self._points = poly, points
        table = dent_colours(256)
        lut = vtkLookupTable()
        lut.SetNumberOfTableValues(256)
        lut.SetRange(0.0, self.top_mm)
        # the table is even in |u| (what VTK indexes by); its colour at |u| is the dent colour at (|u|/top)^gamma
        pos = np.linspace(0.0, 1.0, 256) ** COLOUR_GAMMA
        for i in range(256):
            rgb = [float(np.interp(pos[i], np.linspace(0, 1, 256), table[:, c])) for c in range(3)]
            lut.SetTableValue(i, *rgb, 1.0)
        lut.SetBelowRangeColor(*_SEAT, 1.0)
        lut.SetAboveRangeColor(*table[-1], 1.0)
        lut.UseAboveRangeColorOn()
        self.lut = lut
        mapper = vtkPolyDataMapper()
        mapper.SetInputData(poly)
        mapper.SetLookupTable(lut)
        mapper.SetScalarRange(0.0, self.top_mm)
        mapper.InterpolateScalarsBeforeMappingOn()  # per-pixel colour of the value, not blended vertex colours
        seat = vtkActor()
        seat.SetMapper(mapper)
        prop = seat.GetProperty()
        prop.SetInterpolationToPhong()
        prop.SetAmbient(0.12)
        prop.SetDiffuse(0.85)
        prop.SetSpecular(0.25)
        prop.SetSpecularPower(30.0)
        return seat

    def _stones_actor(self) -> Any:
        """The stones' actor: one sphere glyph per point of ``self._spd`` (filled by
        :meth:`set_stones`), scaled by its ``diameter`` array and coloured by its ``colour`` array.

        Returns
        -------
        vtkActor
        """
        from vtkmodules.vtkCommonDataModel import vtkPolyData
        from vtkmodules.vtkFiltersSources import vtkSphereSource
        from vtkmodules.vtkRenderingCore import vtkActor, vtkGlyph3DMapper

        # the stones: one sphere glyph per stone, scaled by its diameter, coloured per stone
        self._spd = vtkPolyData()
        sphere = vtkSphereSource()
        sphere.SetThetaResolution(20)
        sphere.SetPhiResolution(12)
        sphere.SetRadius(0.5)
        glyphs = vtkGlyph3DMapper()
        glyphs.SetInputData(self._spd)
        glyphs.SetSourceConnection(sphere.GetOutputPort())
        glyphs.SetScaleModeToScaleByMagnitude()
        glyphs.SetScaleArray("diameter")
        glyphs.SetScalarModeToUsePointFieldData()
        glyphs.SelectColorArray("colour")
        glyphs.SetColorModeToDirectScalars()
        glyphs.ScalarVisibilityOn()
        stones = vtkActor()
        stones.SetMapper(glyphs)
        sp = stones.GetProperty()
        sp.SetSpecular(0.6)
        sp.SetSpecularPower(50.0)
        sp.SetAmbient(0.15)
        self._glyphs = glyphs
        self.n_stones_drawn = 0
        return stones

    def _main_renderer(self, seat: Any, stones: Any, *, inset: bool, samples: int) -> list[Any]:
        """The main view (``self.renderer``): the sky, the seat and the stones, two lights, and the
        three-quarter camera framing the seat between the inset (when drawn) and the colour bar.

        Parameters
        ----------
        seat, stones : vtkActor
        inset : bool
            Leave room for the inset on the left.
        samples : int
            As the class parameter (0: FXAA).

        Returns
        -------
        list of vtkLight
            The lights, for the inset to share.
        """
        from vtkmodules.vtkRenderingCore import vtkLight, vtkRenderer

        ren = vtkRenderer()
        ren.GradientBackgroundOn()
        ren.SetBackground(*_SKY_BOTTOM)
        ren.SetBackground2(*_SKY_TOP)
        ren.AddActor(seat)
        ren.AddActor(stones)
        if samples == 0:
            ren.UseFXAAOn()
        self.rw.AddRenderer(ren)
        # two lights (each costs a pass of the software rasterizer's shading): a key light above and to
        # the left of the camera, and a dimmer one at the camera that fills the shadows
        lights = []
        for where, power in (((-1.0, 1.5, 0.8), 0.85), ((0.0, 0.0, 1.0), 0.35)):
            light = vtkLight()
            light.SetLightTypeToCameraLight()
            light.SetPosition(*where)
            light.SetFocalPoint(0.0, 0.0, 0.0)
            light.SetIntensity(power)
            lights.append(light)
            ren.AddLight(light)
        cam = ren.GetActiveCamera()
        # the seat is framed in the part of the picture right of the inset and left of the colour bar
        x0, x1 = (INSET_VIEWPORT[2] if inset else 0.0), 0.90
        pos, focal = three_quarter_camera(self.X, (x1 - x0) * self.width / max(self.height, 1))
        cam.SetPosition(*pos)
        cam.SetFocalPoint(*focal)
        cam.SetViewUp(0.0, 0.0, 1.0)
        cam.SetViewAngle(30.0)
        cam.SetWindowCenter(1.0 - x0 - x1, 0.0)  # the focal point at the middle of [x0, x1]
        ren.ResetCameraClippingRange(*self._bounds(0.2))
        self.renderer = ren
        return lights

    def _add_caption(self, font_size: int) -> None:
        """The caption (``self.caption``): text at the main view's top left, set by :meth:`draw`."""
        from vtkmodules.vtkRenderingCore import vtkTextActor

        self.caption = vtkTextActor()
        self.caption.GetTextProperty().SetFontSize(font_size)
        self.caption.GetTextProperty().SetColor(0.05, 0.05, 0.08)
        self.caption.GetTextProperty().SetFontFamilyToCourier()
        self.caption.GetTextProperty().SetVerticalJustificationToTop()
        self.caption.SetDisplayPosition(int(0.012 * self.width), int(self.height - 0.015 * self.height))
        self.renderer.AddViewProp(self.caption)

    def _add_colour_bar(self, label: str, font_size: int) -> None:
        """The colour bar (``self.colour_bar``) of ``self.lut`` at the main view's right, titled
        ``label`` [mm]."""
        from vtkmodules.vtkRenderingAnnotation import vtkScalarBarActor

        bar = vtkScalarBarActor()
        bar.SetLookupTable(self.lut)
        bar.SetTitle(f"{label} [mm]")
        bar.SetNumberOfLabels(6)
        bar.SetLabelFormat("%.2g")
        bar.SetBarRatio(0.28)
        bar.UnconstrainedFontSizeOn()
        for tp in (bar.GetTitleTextProperty(), bar.GetLabelTextProperty()):
            tp.SetColor(0.05, 0.05, 0.08)
            tp.SetFontSize(font_size)
            tp.ItalicOff()
            tp.ShadowOff()
            tp.BoldOff()
        coord = bar.GetPositionCoordinate()
        coord.SetCoordinateSystemToNormalizedViewport()
        bar.SetPosition(0.905, 0.05)
        bar.SetWidth(0.09)
        bar.SetHeight(0.42)
        self.renderer.AddViewProp(bar)
        self.colour_bar = bar

    def _add_inset(self, seat: Any, stones: Any, lights: list[Any], *, samples: int, font_size: int) -> None:
        """The inset (``self.inset``, at :data:`INSET_VIEWPORT`): the same actors and lights as the
        main view, its camera aimed by :meth:`set_focus`, with a label (``self.inset_label``)."""
        from vtkmodules.vtkRenderingCore import vtkRenderer, vtkTextActor

        ins = vtkRenderer()
        ins.SetViewport(*INSET_VIEWPORT)
        ins.SetBackground(*_SKY_BOTTOM)
        ins.SetBackground2(*_SKY_TOP)
        ins.GradientBackgroundOn()
        ins.AddActor(seat)
        ins.AddActor(stones)
        if samples == 0:
            ins.UseFXAAOn()
        for light in lights:
            ins.AddLight(light)
        ins.GetActiveCamera().SetViewAngle(30.0)
        self.inset_label = vtkTextActor()
        self.inset_label.GetTextProperty().SetFontSize(max(9, int(font_size * 0.85)))
        self.inset_label.GetTextProperty().SetColor(0.05, 0.05, 0.08)
        self.inset_label.GetTextProperty().SetVerticalJustificationToTop()
        where = self.inset_label.GetPositionCoordinate()
        where.SetCoordinateSystemToNormalizedViewport()
        where.SetValue(0.02, 0.97)
        ins.AddViewProp(self.inset_label)
        self.rw.AddRenderer(ins)
        self.inset = ins

    def _bounds(self, grow: float) -> list[float]:
        lo, hi = self.X.min(axis=0), self.X.max(axis=0)
        pad = grow * (hi - lo).max()
        return [lo[0] - pad, hi[0] + pad, lo[1] - pad, hi[1] + pad, lo[2] - pad, hi[2] + 3 * pad]

    def _update_normals(self) -> None:
        p = self._pts[self.T]
        fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # area-weighted face normals
        n = self._nrm.shape[0]
        for d in range(3):  # summed over each vertex's triangles (bincount: faster than np.add.at)
            self._nrm[:, d] = np.bincount(self.T.ravel(), weights=np.repeat(fn[:, d], 3), minlength=n)
        self._nrm /= np.maximum(np.linalg.norm(self._nrm, axis=1, keepdims=True), 1e-30)

    def set_stones(self, positions: np.ndarray, radii: np.ndarray, pressing: np.ndarray | None = None) -> None:
        """The stones to draw: centres (k, 3) [m], radii (k,) [m], and which press on the seat (k,) bool."""
        from vtkmodules.vtkCommonCore import vtkPoints

        pos = np.ascontiguousarray(positions, dtype=np.float64).reshape(-1, 3)
        k = pos.shape[0]
        r = np.asarray(radii, dtype=np.float64).reshape(k)
        press = np.zeros(k, bool) if pressing is None else np.asarray(pressing, bool).reshape(k)
        pts = vtkPoints()
        pts.SetData(self._np(pos.copy(), deep=True))
        self._spd.SetPoints(pts)
        pd = self._spd.GetPointData()
        d = self._np(2.0 * r, deep=True)
        d.SetName("diameter")
        rgb = np.where(press[:, None], np.asarray(_ICE_PRESSING), np.asarray(_ICE))
        c = self._np(np.ascontiguousarray((rgb * 255).round().astype(np.uint8)), deep=True)
        c.SetName("colour")
        for name in ("diameter", "colour"):
            pd.RemoveArray(name)
        pd.AddArray(d)
        pd.AddArray(c)
        self._spd.Modified()
        self.n_stones_drawn = k

    def set_focus(self, point: np.ndarray | None, radius: float, label: str = "") -> None:
        """Aim the inset at ``point`` [m] (a close-up some ``radius`` [m] across); None: keep the last aim."""
        if self.inset is None:
            return
        self.inset_label.SetInput(label)
        if point is None:
            return
        p = np.asarray(point, dtype=np.float64).reshape(3)
        self.focus = p
        main = self.renderer.GetActiveCamera()
        back = np.asarray(main.GetPosition()) - np.asarray(main.GetFocalPoint())
        back /= np.linalg.norm(back)
        back = back + np.array([0.0, 0.0, 0.6])  # a little steeper than the main view: into the dent
        back /= np.linalg.norm(back)
        dist = max(radius, 1e-4) / np.tan(np.radians(15.0))
        cam = self.inset.GetActiveCamera()
        cam.SetFocalPoint(*p)
        cam.SetPosition(*(p + back * dist))
        cam.SetViewUp(0.0, 0.0, 1.0)
        self.inset.ResetCameraClippingRange(*self._bounds(0.2))

    def draw(self, displacement: np.ndarray | None, caption: str = "", *, out: np.ndarray | None = None) -> np.ndarray:
        """The picture of the seat displaced by ``displacement`` (n, 3) [m] (None: at rest), with
        the stones of :meth:`set_stones` and the inset of :meth:`set_focus`.

        Parameters
        ----------
        displacement : (n, 3) ndarray or None
        caption : str
            The text at the top left.
        out : (height, width, 3 or 4) uint8 ndarray, optional
            Written in place (its first three channels) and returned.

        Returns
        -------
        (height, width, 3) uint8 ndarray
            Row 0 at the top.
        """
        from vtkmodules.util.numpy_support import vtk_to_numpy
        from vtkmodules.vtkCommonCore import vtkUnsignedCharArray

        if displacement is None:
            self._pts[:] = self.X
            self._mag[:] = 0.0
        else:
            u = np.asarray(displacement, dtype=np.float64).reshape(-1, 3)
            np.multiply(u, self.scale, out=self._pts)
            self._pts += self.X
            self._mag[:] = np.linalg.norm(u, axis=1) * 1e3
        self._update_normals()
        self._points.GetData().Modified()
        self._poly.GetPointData().GetNormals().Modified()
        self._poly.GetPointData().GetScalars().Modified()
        self._poly.Modified()
        self.caption.SetInput(caption)
        self.rw.Render()
        if self._px is None:
            self._px = vtkUnsignedCharArray()
        self.rw.GetPixelData(0, 0, self.width - 1, self.height - 1, 0, self._px, 0)
        if out is None:
            out = np.empty((self.height, self.width, 3), np.uint8)
        out[..., :3] = vtk_to_numpy(self._px).reshape(self.height, self.width, 3)[::-1]
        if self.inset is not None:  # the inset's frame
            x0, y0, x1, y1 = INSET_VIEWPORT
            c0, c1 = int(round(x0 * self.width)), int(round(x1 * self.width)) - 1
            r0, r1 = self.height - int(round(y1 * self.height)), self.height - int(round(y0 * self.height)) - 1
            for sl in (np.s_[r0:r0 + 2, c0:c1 + 1, :3], np.s_[r1 - 1:r1 + 1, c0:c1 + 1, :3],
                       np.s_[r0:r1 + 1, c0:c0 + 2, :3], np.s_[r0:r1 + 1, c1 - 1:c1 + 1, :3]):
                out[sl] = 40
        return out

    def project(self, points: np.ndarray) -> np.ndarray:
        """Where world points [m] appear in the main view's picture: (k, 2) pixel (column, row),
        row 0 at the top (as in :meth:`draw`'s array)."""
        P = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        out = np.empty((P.shape[0], 2))
        for i, p in enumerate(P):
            self._coord.SetValue(*p)
            x, y = self._coord.GetComputedDoubleDisplayValue(self.renderer)
            out[i] = (x, self.height - 1 - y)
        return out

    def close(self) -> None:
        """Release the OpenGL context."""
        self.rw.Finalize()
