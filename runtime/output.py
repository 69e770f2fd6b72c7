"""Writers for a storm's results: summary.json, a ParaView time series, an animation.

A CLI storm writes its outputs as a unit with :class:`StormOutput`: frames are
streamed to disk as the storm records them (memory stays flat in the
duration), everything goes into a hidden temporary sibling of the output
directory, and one rename puts the complete set in place. An interrupted or
failed run leaves nothing; a rerun replaces only a directory that holds
exactly a previous storm output (recognised by :data:`STORM_MANIFEST`, the list
of files the project wrote), and refuses any other non-empty directory.

Use::

    from hailstorm.runtime.output import StormOutput
    with StormOutput("run1", gf) as out:           # checks "run1" can be written, first
        result = hailstorm.runtime.run_storm(gf, scene, on_frame=out.add)
        out.finish(result)                         # pvd, summary.json, storm.mp4: then in place

matplotlib, imageio and meshio are imported inside the writers, so importing
this module costs nothing.
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hailstorm.runtime.atomic import probe_writable, write_text_atomic

__all__ = [
    "STORM_MANIFEST",
    "FrameSeries",
    "OutputError",
    "ParaviewSeries",
    "StormOutput",
    "check_storm_out",
    "summary",
    "write_animation",
    "write_paraview",
    "write_summary",
]

_log = logging.getLogger(__name__)

#: the file, in a storm's output directory, that lists every file the storm wrote
STORM_MANIFEST = "hailstorm-storm.json"
_MANIFEST_FORMAT = "hailstorm-storm-output"

#: bytes per surface vertex of one frame's surface VTU on disk (measured: ~60-65 B on the
#: default seat, zlib-compressed float64 fields), an upper bound for the disk estimate
FRAME_BYTES_PER_VERTEX = 80


class OutputError(ValueError):
    """An output directory cannot be written, or writing it would overwrite files
    hailstorm did not write."""


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


def _seat_of(gf: Any) -> dict[str, Any] | None:
    """The seat a bundle was actually computed for (from its manifest), in the scene's
    ``[seat]`` layout, or None when ``gf`` carries no manifest."""
    m = getattr(gf, "manifest", None)
    if not isinstance(m, dict):
        return None
    opts, mat = m.get("options", {}), m.get("material", {})
    seat = {"mesh_size": opts.get("mesh_size"), "order": opts.get("order"),
            "young": mat.get("young", opts.get("young")), "poisson": mat.get("poisson", opts.get("poisson"))}
    if opts.get("geometry") is not None:
        seat["geometry"] = str(opts["geometry"])
    return seat


def summary(result: Any, gf: Any = None) -> dict[str, Any]:
    """The summary as a dict (what :func:`write_summary` writes).

    Keys (every key and its unit is listed in the README, "Storm outputs"):
    ``hailstones`` (spawned), ``impacts`` (contact onsets faster than
    the scene's ``rest_speed``), ``stones_hit`` (stones that touched the seat
    at least once, slow touches included), ``max_contact_force`` [N],
    ``max_indentation_m`` (largest normal contact displacement),
    ``max_simultaneous_contacts``, ``max_penetration_m`` (deepest overlap of a
    stone with the deformed surface), ``steps``, ``substeps``,
    ``capacitance_rebuilds``, ``frames`` (recorded, = files in each series),
    ``sim_time_s``, ``wall_time_s`` (the stepping, recording the frames
    included, writing them not), ``output_time_s`` (writing the frames as they
    were recorded),
    ``real_time_factor`` (simulated / wall-clock time; > 1 is faster than real
    time), ``setup_time_s`` (building the storm: spatial index, spawn plan,
    loading the compiled kernels), ``backend``, ``seed``, ``dt``,
    ``integrator``, ``mode``, and the scene.

    Parameters
    ----------
    result : StormResult
    gf : GreensFunctions, optional
        The bundle the storm ran on. Given, the scene's ``[seat]`` section
        records the seat the bundle was computed for (its manifest: mesh size,
        order, material), not the scene's ``[seat]`` request, and ``bundle``
        records its path and key.
    """
    d = dict(result.stats)
    d["scene"] = result.scene.to_dict()
    seat = _seat_of(gf) if gf is not None else None
    if seat is not None:
        d["scene"]["seat"] = seat
        d["bundle"] = {"path": str(getattr(gf, "path", "")), "key": gf.manifest.get("key")}
    return _jsonable(d)


def write_summary(result: Any, path: str | os.PathLike, gf: Any = None) -> Path:
    """Write ``summary.json`` for a :class:`hailstorm.runtime.recording.StormResult`; returns the path.
    ``gf``: see :func:`summary`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(path, json.dumps(summary(result, gf), indent=2, sort_keys=True) + "\n")


_SKY = "#c9d3dd"  # background: a stormy grey-blue, so that the white stones show
_ICE = "#f4f8fc"  # hailstones


def _shown(frame: Any) -> np.ndarray:
    """What a picture of a frame shows: the peak displacement since the previous
    frame when the storm recorded it (impacts last ~1 ms, shorter than a frame
    interval, so the instantaneous field would almost never show a dent), else
    the displacement at the frame's instant."""
    peak = getattr(frame, "peak_displacement", None)
    return frame.displacement if peak is None else peak


def _pvd(entries: list[tuple[float, str]]) -> str:
    rows = "\n".join(f'    <DataSet timestep="{t:.9g}" group="" part="0" file="{fn}"/>' for t, fn in entries)
    return ('<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
            f"  <Collection>\n{rows}\n  </Collection>\n</VTKFile>\n")


class ParaviewSeries:
    """A ParaView time series written frame by frame (:meth:`add`), then closed (:meth:`close`).

    The seat (``frames/surface_NNNN.vtu``) carries point data ``displacement``
    (vector, [m]), ``|u|``, ``peak_displacement`` and ``|u| peak`` (the largest
    displacement since the previous frame); its points are the *undeformed*
    vertices (use ParaView's "Warp By Vector" to see the deformation). The
    stones (``frames/stones_NNNN.vtu``) are vertex cells with point data
    ``radius`` [m] and ``id`` (use a "Glyph" filter, sphere, scale by
    ``radius``, factor 2). A frame without stones holds one placeholder point
    of radius 0 and id -1 (a VTU without cells cannot be read back by meshio).
    Only the running list of file names and times is kept, not the frames.

    Parameters
    ----------
    gf : GreensFunctions
    outdir : path
        Directory of the series (created).
    name : str
        The collections are ``<name>.pvd`` (seat) and ``<name>_stones.pvd``.
    """

    def __init__(self, gf: Any, outdir: str | os.PathLike, *, name: str = "storm") -> None:
        self.outdir = Path(outdir)
        self.name = name
        (self.outdir / "frames").mkdir(parents=True, exist_ok=True)
        self._X = np.asarray(gf.vertices, dtype=np.float64)
        self._tri = np.asarray(gf.triangles, dtype=np.int64)
        self._dummy = self._X.mean(axis=0)[None, :] if len(self._X) else np.zeros((1, 3))
        #: per frame: (t, surface file, stones file, open contacts, max |shown displacement|)
        self.entries: list[tuple[float, str, str, int, float]] = []

    def __len__(self) -> int:
        return len(self.entries)

    def add(self, frame: Any) -> None:
        """Write one :class:`hailstorm.runtime.recording.Frame` (both files)."""
        import meshio

        i = len(self.entries)
        u = np.asarray(frame.displacement, dtype=np.float64)
        peak = np.asarray(_shown(frame), dtype=np.float64)
        sname = f"frames/surface_{i:04d}.vtu"
        meshio.write(self.outdir / sname, meshio.Mesh(
            self._X, [("triangle", self._tri)],
            point_data={"displacement": u, "|u|": np.linalg.norm(u, axis=1), "peak_displacement": peak,
                        "|u| peak": np.linalg.norm(peak, axis=1)}))
        pos = np.asarray(frame.positions, dtype=np.float64).reshape(-1, 3)
        radii = np.asarray(frame.radii, dtype=np.float64)
        ids = np.asarray(frame.ids, dtype=np.int64)
        if pos.shape[0] == 0:  # placeholder: meshio cannot read a VTU without cells
            pos, radii, ids = self._dummy, np.zeros(1), np.full(1, -1, dtype=np.int64)
        k = pos.shape[0]
        stname = f"frames/stones_{i:04d}.vtu"
        meshio.write(self.outdir / stname, meshio.Mesh(pos, [("vertex", np.arange(k, dtype=np.int64)[:, None])],
                                                       point_data={"radius": radii, "id": ids}))
        umax = float(np.linalg.norm(peak, axis=1).max()) if len(peak) else 0.0
        self.entries.append((float(frame.t), sname, stname, int(frame.contacts), umax))

    def close(self) -> Path:
        """Write the two ``.pvd`` collections; returns ``<name>.pvd``."""
        main = self.outdir / f"{self.name}.pvd"
        main.write_text(_pvd([(t, s) for t, s, _, _, _ in self.entries]))
        (self.outdir / f"{self.name}_stones.pvd").write_text(_pvd([(t, s) for t, _, s, _, _ in self.entries]))
        return main

    def files(self) -> list[str]:
        """Every file of the series, relative to :attr:`outdir`."""
        names = [f"{self.name}.pvd", f"{self.name}_stones.pvd"]
        for _, s, st, _, _ in self.entries:
            names += [s, st]
        return names

    def frames(self) -> "FrameSeries":
        """The written frames, read back on access."""
        return FrameSeries(self)


class FrameSeries(Sequence):
    """The frames of a :class:`ParaviewSeries`, read back from its files on access
    (a sequence of :class:`hailstorm.runtime.recording.Frame`; nothing is cached)."""

    def __init__(self, series: ParaviewSeries) -> None:
        self._series = series

    def __len__(self) -> int:
        return len(self._series.entries)

    def peak_norm(self, i: int) -> float:
        """Largest ``|peak displacement|`` of frame ``i`` [m], without reading it."""
        return self._series.entries[i][4]

    def __getitem__(self, i: int) -> Any:  # type: ignore[override]
        import meshio

        from hailstorm.runtime.recording import Frame

        t, sname, stname, contacts, _ = self._series.entries[i]
        s = meshio.read(self._series.outdir / sname)
        st = meshio.read(self._series.outdir / stname)
        ids = np.asarray(st.point_data["id"], dtype=np.int64)
        keep = ids >= 0
        return Frame(t=t, displacement=s.point_data["displacement"], positions=st.points[keep],
                     radii=np.asarray(st.point_data["radius"])[keep], ids=ids[keep], contacts=contacts,
                     peak_displacement=s.point_data["peak_displacement"])


def write_paraview(result: Any, gf: Any, outdir: str | os.PathLike, *, name: str = "storm") -> Path:
    """Write a ParaView time series of a storm's frames (see :class:`ParaviewSeries`).

    Parameters
    ----------
    result : StormResult or sequence of Frame
    gf : GreensFunctions
    outdir : path
    name : str

    Returns
    -------
    pathlib.Path
        ``outdir/<name>.pvd`` (the collection to open in ParaView); the stones'
        series is ``outdir/<name>_stones.pvd``.
    """
    series = ParaviewSeries(gf, outdir, name=name)
    for f in getattr(result, "frames", result):
        series.add(f)
    return series.close()


class _VideoWriter:
    """Frames appended one by one to an MP4 (imageio-ffmpeg), or to a GIF beside it
    when MP4 writing fails (no ffmpeg); nothing is held in memory."""

    def __init__(self, path: Path, fps: float) -> None:
        self.path, self.fps = path, fps
        self._w: Any = None

    def _open_gif(self) -> None:
        import imageio.v2 as imageio

        if self.path.suffix.lower() != ".gif":
            self.path = self.path.with_suffix(".gif")
        self._w = imageio.get_writer(self.path, mode="I", duration=1.0 / self.fps, loop=0)

    def append(self, image: np.ndarray) -> None:
        import imageio.v2 as imageio

        if self._w is None:
            if self.path.suffix.lower() == ".gif":
                self._open_gif()
            else:
                try:
                    self._w = imageio.get_writer(self.path, fps=self.fps, macro_block_size=1, codec="libx264",
                                                 quality=7)
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
    dpi: int = 80,
    exaggeration: float | None = None,
    progress: bool = False,
) -> Path:
    """Render the storm: the seat coloured by ``|u|`` (mm) with the stones as spheres.

    Frames are rendered and appended to the file one at a time (at most
    ``max_frames`` are read, each once or twice when they are read back from
    disk), so memory does not grow with the storm.

    Parameters
    ----------
    result : StormResult or sequence of Frame
        A result whose frames were kept in memory, or any sequence of frames
        such as :meth:`ParaviewSeries.frames` (read back from the files).
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
    from matplotlib import cm, colors
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames = getattr(result, "frames", result)
    if len(frames) == 0:
        raise ValueError("no frames to render (run the storm with keep_frames=True, or render a ParaviewSeries)")
    idx = np.unique(np.linspace(0, len(frames) - 1, min(max_frames, len(frames))).round().astype(int))
    X = np.asarray(gf.vertices, dtype=np.float64)
    tri = np.asarray(gf.triangles)
    # the underside is never seen from the elevated camera: skip it (cheaper render)
    p = X[tri]
    fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
    show = fn[:, 2] > -0.5 if len(fn) else np.zeros(0, bool)
    tri_s = tri[show]
    peak_norm = getattr(frames, "peak_norm", lambda i: float(np.linalg.norm(_shown(frames[i]), axis=1).max()))
    peaks = np.array([peak_norm(int(i)) for i in idx] or [0.0])
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
    peak_shown = getattr(frames[int(idx[0])], "peak_displacement", None) is not None
    fig.colorbar(sm, ax=ax, shrink=0.6, pad=0.02, extend="max" if umax > vmax else "neither",
                 label="peak |u| since the previous frame [mm]" if peak_shown else "|u| [mm]")
    video = _VideoWriter(path, fps)
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
        video.append(np.asarray(canvas.buffer_rgba())[..., :3].copy())
    return video.close()


def _listing(out: Path) -> tuple[list[str], list[str]]:
    """Files and directories under ``out`` (relative POSIX paths), depth first."""
    files, dirs = [], []
    for root, dnames, fnames in os.walk(out):
        rel = Path(root).relative_to(out)
        files += [(rel / f).as_posix() for f in fnames]
        dirs += [(rel / d).as_posix() for d in dnames]
    return sorted(files), sorted(dirs)


def _our_files(out: Path) -> set[str] | None:
    """The files a previous storm output in ``out`` lists (its manifest included), or
    None if ``out`` holds no readable storm manifest."""
    try:
        m = json.loads((out / STORM_MANIFEST).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(m, dict) or m.get("format") != _MANIFEST_FORMAT or not isinstance(m.get("files"), list):
        return None
    return {str(f) for f in m["files"]} | {STORM_MANIFEST}


def _foreign(out: Path) -> list[str]:
    """What in the existing directory ``out`` hailstorm did not write (empty: ``out`` is
    empty or holds exactly a previous storm output)."""
    files, dirs = _listing(out)
    ours = _our_files(out)
    if ours is None:
        return files + [d + "/" for d in dirs if not any(f.startswith(d + "/") for f in files)]
    parents = {Path(f).parent.as_posix() for f in ours}
    return [f for f in files if f not in ours] + [d + "/" for d in dirs if d not in parents]


def check_storm_out(out: str | os.PathLike) -> None:
    """Check that a storm may write its outputs to ``out`` (nothing is written).

    ``out`` may be new, an empty directory, or a directory holding exactly a
    previous storm output (the files listed by its :data:`STORM_MANIFEST`),
    which a new run replaces as a whole.

    Raises
    ------
    OutputError
        ``out`` is a file, is not writable, or holds files hailstorm did not
        write (named in the message, which is one line).
    """
    out = Path(out)
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise OutputError(f"--out {out} exists and is not a directory; refusing to overwrite it")
        foreign = _foreign(out)
        if foreign:
            shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
            raise OutputError(f"--out {out} holds files that are not a hailstorm storm output ({shown}); "
                              "refusing to overwrite it (choose an empty or new directory)")
        if not os.access(out, os.W_OK | os.X_OK):
            raise OutputError(f"--out {out} is not writable")
    try:
        probe_writable(out.absolute().parent)
    except NotADirectoryError as exc:
        raise OutputError(f"cannot create --out {out}: {exc.filename} is not a directory") from None
    except OSError as exc:
        where = Path(exc.filename).parent if exc.filename else out.absolute().parent
        raise OutputError(f"cannot write --out {out}: {where}: {exc.strerror or exc}") from None


class StormOutput:
    """A storm's output directory, written as a unit.

    :meth:`open` (or ``with``) checks ``out`` (:func:`check_storm_out`) and
    the free disk space, then creates a hidden temporary sibling of ``out``;
    :meth:`add` writes each frame there as the storm records it; :meth:`finish`
    writes the ``.pvd`` collections, ``summary.json``, the animation and the
    manifest :data:`STORM_MANIFEST`, and renames the directory into place
    (replacing a previous storm output). Leaving the ``with`` block without
    :meth:`finish` (an error, Ctrl-C) removes the temporary directory and
    leaves ``out`` as it was.

    Parameters
    ----------
    out : path
        The output directory.
    gf : GreensFunctions
        The bundle the storm runs on.
    video : bool
        Render ``storm.mp4`` (GIF fallback) from the written frames.
    disk_bytes : int, optional
        Expected size of the outputs (:meth:`hailstorm.runtime.scene.Scene.estimate`):
        refused up front if the file system has less free space.
    progress : bool
        A tqdm bar while rendering.
    """

    def __init__(self, out: str | os.PathLike, gf: Any, *, video: bool = True, disk_bytes: int | None = None,
                 progress: bool = False) -> None:
        self.out = Path(out)
        self.gf = gf
        self.video = video
        self.disk_bytes = disk_bytes
        self.progress = progress
        self.staging: Path | None = None
        self.series: ParaviewSeries | None = None
        self.files: list[str] = []
        self.committed = False

    def __enter__(self) -> "StormOutput":
        self.open()
        return self

    def __exit__(self, *exc: Any) -> None:
        if not self.committed:
            self.abort()

    def open(self) -> None:
        """Check ``out`` and create the temporary directory (see the class notes).

        Raises
        ------
        OutputError
            See :func:`check_storm_out`; or not enough free disk space.
        """
        check_storm_out(self.out)
        parent = self.out.absolute().parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
            if self.disk_bytes is not None:
                free = shutil.disk_usage(parent).free
                if self.disk_bytes > free:
                    raise OutputError(f"the outputs need about {self.disk_bytes / 2**30:.2f} GiB but {parent} has "
                                      f"{free / 2**30:.2f} GiB free (lower [output] fps or the duration)")
            self.staging = Path(tempfile.mkdtemp(prefix=f".{self.out.name}.partial-", dir=parent))
        except OSError as exc:
            raise OutputError(f"cannot write --out {self.out}: {exc.strerror or exc}") from None
        self.series = ParaviewSeries(self.gf, self.staging)

    def add(self, frame: Any) -> None:
        """Write one recorded frame (the storm's ``on_frame`` callback)."""
        assert self.series is not None, "StormOutput.open() first"
        self.series.add(frame)

    def __call__(self, frame: Any) -> None:
        self.add(frame)

    def finish(self, result: Any) -> dict[str, Path]:
        """Write the collections, the summary and the animation; put the directory in place.

        Returns
        -------
        dict
            ``{"summary", "paraview", "stones", "video"}`` -> final paths (``video``
            only when rendered; it may be the GIF fallback).
        """
        assert self.series is not None and self.staging is not None, "StormOutput.open() first"
        series, staging = self.series, self.staging
        if len(series) == 0:  # the result's frames were kept in memory instead of streamed
            for f in result.frames:
                series.add(f)
        series.close()
        result.stats.frames = len(series)  # the summary counts the files it describes
        write_summary(result, staging / "summary.json", self.gf)
        files = [*series.files(), "summary.json"]
        video = None
        if self.video:
            video = write_animation(series.frames(), self.gf, staging / "storm.mp4", progress=self.progress)
            files.append(video.name)
        manifest = {"format": _MANIFEST_FORMAT, "version": 1, "files": sorted(files)}
        (staging / STORM_MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
        self._commit()
        paths = {"summary": self.out / "summary.json", "paraview": self.out / f"{series.name}.pvd",
                 "stones": self.out / f"{series.name}_stones.pvd"}
        if video is not None:
            paths["video"] = self.out / video.name
        return paths

    def _commit(self) -> None:
        staging, out = self.staging, self.out
        assert staging is not None
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(staging, 0o777 & ~umask)  # mkdtemp's directory is private; a plain mkdir's is not
        if out.is_dir() and any(out.iterdir()):
            if _foreign(out):  # someone wrote into it during the run: keep both
                raise OutputError(f"--out {out} changed during the run and now holds other files; "
                                  f"the results are in {staging}")
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=staging.parent))
            old.rmdir()
            os.replace(out, old)
            os.replace(staging, out)
            self.committed = True
            _remove_storm_output(old)
        else:
            os.replace(staging, out)  # a new name, or over an empty directory
            self.committed = True
        self.staging = None

    def abort(self) -> None:
        """Remove the temporary directory (everything in it was written here)."""
        if self.staging is not None:
            shutil.rmtree(self.staging, ignore_errors=True)
            self.staging = None


def _remove_storm_output(path: Path) -> None:
    """Delete a replaced storm output: the files its manifest lists, then the emptied
    directories; anything else is left in place (and reported)."""
    ours = _our_files(path) or set()
    for f in ours:
        (path / f).unlink(missing_ok=True)
    _, dirs = _listing(path)
    for d in sorted(dirs, key=lambda d: -d.count("/")) + ["."]:
        try:
            (path / d).rmdir()
        except OSError:
            pass
    if path.exists():
        _log.warning("the replaced storm output kept files it did not list: %s", path)

