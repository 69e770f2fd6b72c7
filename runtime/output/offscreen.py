"""An off-screen OpenGL window for the 3-D video (VTK), on a machine with or without a display.

VTK's wheels (``pip install vtk``, the ``video`` extra) choose their OpenGL window at run
time. Without a display the default one (X11) fails with a warning before VTK falls back;
this module asks for the head-less ones first: EGL (Mesa's software ``llvmpipe`` or a GPU
driver: ``libEGL.so.1``, present on most Linux desktops and in the ``libegl1`` package),
then OSMesa (``libOSMesa.so``), then the platform's default window (X11 with a display,
Windows, macOS). A class is tried only where its system library is found (VTK 9.7's OSMesa
window reports an OpenGL context without ``libOSMesa`` and then crashes the process in its
first render), and kept only if it draws a test picture: the first that does is used
(:func:`offscreen_window`); :func:`three_d_available` says whether any does (probed once
per process), so that the storm's video falls back to the 2-D renderer
(:mod:`hailstorm.runtime.output.render`) where none does.

VTK is imported inside the functions: importing this module costs nothing and needs no VTK.
"""

from __future__ import annotations

import contextlib
import ctypes.util
import functools
import importlib.util
import os
import sys
from collections.abc import Iterator
from typing import Any

__all__ = ["ThreeDUnavailable", "offscreen_window", "three_d_available", "vtk_installed"]

#: the window classes tried, in order (head-less first)
WINDOW_CLASSES = ("vtkEGLRenderWindow", "vtkOSOpenGLRenderWindow", "vtkRenderWindow")


class ThreeDUnavailable(RuntimeError):
    """No off-screen OpenGL window could be created (or VTK is not installed).

    The message is one line saying why and what to install.
    """


def vtk_installed() -> bool:
    """Is VTK installed (found without importing it)?"""
    try:
        return importlib.util.find_spec("vtkmodules") is not None
    except (ImportError, ValueError):
        return False


@contextlib.contextmanager
def _quiet_vtk() -> Iterator[None]:
    """Silence VTK's warnings and log on stderr (a failed window class reports its failure there)."""
    from vtkmodules.vtkCommonCore import vtkLogger, vtkObject

    warn = vtkObject.GetGlobalWarningDisplay()
    level = vtkLogger.GetCurrentVerbosityCutoff()
    vtkObject.GlobalWarningDisplayOff()
    vtkLogger.SetStderrVerbosity(vtkLogger.VERBOSITY_OFF)
    try:
        yield
    finally:
        vtkObject.SetGlobalWarningDisplay(warn)
        vtkLogger.SetStderrVerbosity(level)


def _usable(name: str) -> bool:
    """Can window class ``name`` start on this machine (its system library found)?"""
    if name == "vtkEGLRenderWindow":
        return sys.platform.startswith("linux") and ctypes.util.find_library("EGL") is not None
    if name == "vtkOSOpenGLRenderWindow":
        return ctypes.util.find_library("OSMesa") is not None
    # the platform's own window: on Linux only with a display
    return not sys.platform.startswith("linux") or bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def _draws(rw: Any) -> bool:
    """Does the window draw (a 4 x 4 clear to a known colour, read back)?"""
    from vtkmodules.vtkCommonCore import vtkUnsignedCharArray
    from vtkmodules.vtkRenderingCore import vtkRenderer

    ren = vtkRenderer()
    ren.SetBackground(1.0, 0.0, 1.0)
    rw.AddRenderer(ren)
    rw.Render()
    px = vtkUnsignedCharArray()
    rw.GetPixelData(0, 0, 3, 3, 0, px, 0)
    rw.RemoveRenderer(ren)
    return px.GetNumberOfTuples() == 16 and px.GetTuple3(5) == (255.0, 0.0, 255.0)


def _window(name: str) -> Any:
    import vtkmodules.vtkRenderingOpenGL2 as gl2  # registers the OpenGL factories

    if name == "vtkRenderWindow":
        from vtkmodules.vtkRenderingCore import vtkRenderWindow

        return vtkRenderWindow()
    cls = getattr(gl2, name, None)
    return None if cls is None else cls()


def offscreen_window(size: tuple[int, int], *, samples: int = 0) -> Any:
    """A VTK render window drawing off-screen, of ``size`` (width, height) pixels.

    Parameters
    ----------
    size : (int, int)
        Width and height [pixels].
    samples : int
        Multisample anti-aliasing samples per pixel (0: none).

    Returns
    -------
    vtkRenderWindow
        Its class is the first of :data:`WINDOW_CLASSES` that creates an OpenGL context.

    Raises
    ------
    ThreeDUnavailable
        VTK is not installed, or no window class creates a context.
    """
    if not vtk_installed():
        raise ThreeDUnavailable("the 3-D video needs VTK: pip install 'hailstorm[video]'")
    tried = []
    with _quiet_vtk():
        for name in WINDOW_CLASSES:
            if not _usable(name):
                continue
            try:
                rw = _window(name)
                if rw is None:
                    continue
                rw.SetOffScreenRendering(1)
                rw.SetMultiSamples(int(samples))
                rw.SetSize(4, 4)
                if rw.SupportsOpenGL() and _draws(rw):
                    rw.SetSize(int(size[0]), int(size[1]))
                    return rw
                rw.Finalize()
            except Exception:  # noqa: BLE001 - a window class that cannot start: try the next
                pass
            tried.append(name)
    raise ThreeDUnavailable("no off-screen OpenGL for the 3-D video (" + (f"{', '.join(tried)} failed; " if tried else "")
                            + "install libegl1 or libosmesa6)")


@functools.cache
def three_d_available() -> str | None:
    """The off-screen window class the 3-D video would use, or None (no VTK, or no OpenGL).

    Probed once per process (a window of 8 x 8 pixels; about 0.3 s).
    """
    try:
        rw = offscreen_window((8, 8))
    except ThreeDUnavailable:
        return None
    name = rw.GetClassName()
    rw.Finalize()
    return name
