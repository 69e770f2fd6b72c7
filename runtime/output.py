"""Writers for a storm's results: summary.json, a ParaView time series, an animation.

matplotlib, imageio and meshio are imported inside the writers, so importing
this module costs nothing.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from runtime.atomic import write_text_atomic

__all__ = ["summary", "write_animation", "write_paraview", "write_summary"]


def _jsonable(v: Any) -> Any:
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return f if math.isfinite(f) else None
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    return v


def summary(result: Any) -> dict[str, Any]:
    """The summary as a dict (what :func:`write_summary` writes).

    Keys: ``hailstones`` (spawned), ``impacts`` (contact onsets faster than
    the scene's ``rest_speed``), ``stones_hit``, ``max_contact_force`` [N],
    ``max_indentation_m`` (largest normal contact displacement), 
    ``max_simultaneous_contacts``, ``max_penetration_m`` (deepest overlap of a
    stone with the deformed surface), ``steps``, ``substeps``,
    ``capacitance_rebuilds``, ``sim_time_s``, ``wall_time_s`` (the stepping,
    frames included), ``real_time_factor`` (simulated / wall-clock time; > 1
    is faster than real time), ``setup_time_s`` (building the storm: spatial
    index, spawn plan, loading the compiled kernels), ``backend``, ``seed``,
    ``dt``, ``integrator``, ``mode``, and the scene.
    """
    d = dict(result.stats)
    d["scene"] = result.scene.to_dict()
    return _jsonable(d)


def write_summary(result: Any, path: str | os.PathLike) -> Path:
    """Write ``summary.json`` for a :class:`runtime.storm.StormResult`; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(path, json.dumps(summary(result), indent=2, sort_keys=True) + "\n")


_SKY = "#c9d3dd"  # background: a stormy grey-blue, so that the white stones show
_ICE = "#f4f8fc"  # hailstones


def _shown(frame: Any) -> np.ndarray:
    """What a picture of a frame shows: the peak displacement since the previous
    frame when the storm recorded it (impacts last ~1 ms, shorter than a frame
    interval, so the instantaneous field would almost never show a dent), else
    the displacement at the frame's instant."""
    peak = getattr(frame, "peak_displacement", None)
    return frame.displacement if peak is None else peak


def write_paraview(result: Any, gf: Any, outdir: str | os.PathLike, *, name: str = "storm") -> Path:
    """Write a ParaView time series: one VTU per frame for the seat surface and the stones.

    Frames go to ``outdir/frames/``. The seat (``surface_NNNN.vtu``) carries point data ``displacement`` (vector,
    [m]) and ``|u|``; its points are the *undeformed* vertices (use ParaView's
    "Warp By Vector" to see the deformation). The stones (``stones_NNNN.vtu``)
    are vertex cells with point data ``radius`` [m] and ``id`` (use a "Glyph"
    filter, sphere, scale by ``radius``, factor 2).

    Returns
    -------
    pathlib.Path
        ``outdir/<name>.pvd`` (the collection to open in ParaView); the stones'
        series is ``outdir/<name>_stones.pvd``.
    """
    import meshio

    outdir = Path(outdir)
    frames_dir = outdir / "frames"
    frames_dir.mkdir(parents=True, exist_ok=True)
    X = np.asarray(gf.vertices, dtype=np.float64)
    tri = np.asarray(gf.triangles, dtype=np.int64)
    surf_entries, stone_entries = [], []
    for i, f in enumerate(result.frames):
        u = np.asarray(f.displacement, dtype=np.float64)
        peak = np.asarray(_shown(f), dtype=np.float64)
        sname = f"frames/surface_{i:04d}.vtu"
        meshio.write(outdir / sname, meshio.Mesh(X, [("triangle", tri)],
                                                 point_data={"displacement": u, "|u|": np.linalg.norm(u, axis=1),
                                                             "peak_displacement": peak,
                                                             "|u| peak": np.linalg.norm(peak, axis=1)}))
        k = f.positions.shape[0]
        pts = f.positions if k else np.zeros((0, 3))
        stname = f"frames/stones_{i:04d}.vtu"
        meshio.write(outdir / stname, meshio.Mesh(pts, [("vertex", np.arange(k, dtype=np.int64)[:, None])],
                                                  point_data={"radius": np.asarray(f.radii, dtype=np.float64),
                                                              "id": np.asarray(f.ids, dtype=np.int64)}))
        surf_entries.append((f.t, sname))
        stone_entries.append((f.t, stname))

    def pvd(entries: list[tuple[float, str]]) -> str:
        rows = "\n".join(f'    <DataSet timestep="{t:.9g}" group="" part="0" file="{fn}"/>' for t, fn in entries)
        return ('<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
                f"  <Collection>\n{rows}\n  </Collection>\n</VTKFile>\n")

    main = outdir / f"{name}.pvd"
    main.write_text(pvd(surf_entries))
    (outdir / f"{name}_stones.pvd").write_text(pvd(stone_entries))
    return main


def write_animation(
    result: Any,
    gf: Any,
    path: str | os.PathLike,
    *,
    max_frames: int = 100,
    fps: float = 20.0,
    dpi: int = 80,
    exaggeration: float | None = None,
    progress: bool = False,
) -> Path:
    """Render the storm: the seat coloured by ``|u|`` (mm) with the stones as spheres.

    Parameters
    ----------
    result : StormResult
    gf : GreensFunctions
    path : path
        ``.mp4`` (imageio-ffmpeg) or ``.gif``. If MP4 writing fails (no
        ffmpeg), a GIF is written next to it instead.
    max_frames : int
        At most this many frames (evenly subsampled).
    fps : float
        Playback frame rate.
    dpi : int
    exaggeration : float, optional
        Scale of the drawn displacement (default: so the largest displacement
        over the storm shows as ~5 mm; ``1`` is true scale).
    progress : bool
        tqdm bar over frames.

    Returns
    -------
    pathlib.Path
        The file written (may be the ``.gif`` fallback).
    """
    import imageio.v2 as imageio
    from matplotlib import cm, colors
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames = result.frames
    idx = np.unique(np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).round().astype(int))
    X = np.asarray(gf.vertices, dtype=np.float64)
    tri = np.asarray(gf.triangles)
    # the underside is never seen from the elevated camera: skip it (cheaper render)
    p = X[tri]
    fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    show = fn[:, 2] > -0.5 if len(fn) else np.zeros(0, bool)
    tri_s = tri[show]
    peaks = np.array([float(np.linalg.norm(_shown(frames[i]), axis=1).max()) for i in idx] or [0.0])
    umax = float(peaks.max())
    if exaggeration is None:
        exaggeration = 1.0 if umax <= 0 else max(1.0, 0.005 / umax)
    # colour scale: the median of the frames' maxima (where something is pressed), so that an
    # ordinary impact shows; the few larger ones saturate (the colour bar says so)
    vmax = float(np.median(peaks[peaks > 0])) if np.any(peaks > 0) else 0.0
    norm = colors.Normalize(vmin=0.0, vmax=max(vmax * 1e3, 1e-6))
    cmap = cm.viridis
    lo, hi = X.min(axis=0), X.max(axis=0)
    span = hi - lo
    ztop = hi[2] + 0.06  # room for the falling stones above the seat
    light = np.array([-0.3, -0.5, 1.0])
    light /= np.linalg.norm(light)
    # sphere template
    uu, vv = np.meshgrid(np.linspace(0, 2 * np.pi, 10), np.linspace(0, np.pi, 6))
    sph = np.stack([np.cos(uu) * np.sin(vv), np.sin(uu) * np.sin(vv), np.cos(vv)], axis=-1)

    # an off-screen Agg figure of its own: the caller's pyplot state and backend are not touched
    fig = Figure(figsize=(6.4, 4.8), dpi=dpi, facecolor=_SKY)
    canvas = FigureCanvasAgg(fig)
    ax = fig.add_subplot(111, projection="3d", facecolor=_SKY)
    fig.subplots_adjust(left=0.0, right=0.95, bottom=0.0, top=1.0)
    # the caption is a figure text: an axes title would sit above the (full-height) axes, off the image
    caption = fig.text(0.02, 0.97, "", fontsize=8, va="top", family="monospace")
    sm = cm.ScalarMappable(norm=norm, cmap=cmap)
    peak_shown = any(getattr(frames[i], "peak_displacement", None) is not None for i in idx)
    fig.colorbar(sm, ax=ax, shrink=0.6, pad=0.02, extend="max" if umax > vmax else "neither",
                 label="peak |u| since the previous frame [mm]" if peak_shown else "|u| [mm]")
    images: list[npt.ArrayLike] = []
    it = idx
    if progress:
        from tqdm.auto import tqdm

        it = tqdm(idx, desc="render", unit="frame", leave=False)
    for i in it:
        f = frames[i]
        u = np.asarray(_shown(f), dtype=np.float64)
        mag = np.linalg.norm(u, axis=1) * 1e3
        ax.cla()
        x = X + exaggeration * u
        q = x[tri_s]
        n = np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        shade = 0.45 + 0.55 * np.clip(n @ light, 0.0, 1.0)  # Lambert: gives the curved top its depth
        rgba = cmap(norm(mag[tri_s].mean(axis=1)))
        rgba[:, :3] *= shade[:, None]
        poly = Poly3DCollection(q, linewidths=0.0, antialiased=False)
        poly.set_facecolor(rgba)
        poly.set_edgecolor(rgba)
        ax.add_collection3d(poly)
        for c, r in zip(f.positions, f.radii):
            if np.all(c >= lo - 0.01) and np.all(c[:2] <= hi[:2] + 0.01) and c[2] <= ztop:
                s = c + r * sph
                ax.plot_surface(s[..., 0], s[..., 1], s[..., 2], color=_ICE, linewidth=0, shade=True)
        ax.set_xlim(lo[0] - 0.01, hi[0] + 0.01)
        ax.set_ylim(lo[1] - 0.01, hi[1] + 0.01)
        ax.set_zlim(lo[2], ztop)
        ax.set_box_aspect((span[0] + 0.02, span[1] + 0.02, ztop - lo[2]), zoom=1.15)
        ax.view_init(elev=28, azim=-55)
        ax.set_axis_off()
        caption.set_text(f"t = {f.t * 1e3:6.1f} ms   stones {len(f.radii)}   contacts {f.contacts}"
                         + (f"   (u x{exaggeration:.0f})" if exaggeration != 1 else ""))
        canvas.draw()
        images.append(np.asarray(canvas.buffer_rgba())[..., :3].copy())
    if path.suffix.lower() == ".gif":
        imageio.mimsave(path, images, duration=1.0 / fps, loop=0)
        return path
    try:
        imageio.mimsave(path, images, fps=fps, macro_block_size=1, codec="libx264", quality=7)
        return path
    except Exception:  # no ffmpeg: fall back to a GIF
        gif = path.with_suffix(".gif")
        imageio.mimsave(gif, images, duration=1.0 / fps, loop=0)
        return gif
