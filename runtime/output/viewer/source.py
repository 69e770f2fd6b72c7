"""A storm's output folder read back for the viewer: the seat, the frames, the impacts.

:func:`open_storm_out` checks the folder (what :mod:`hailstorm.runtime.output.files` writes:
the manifest ``hailstorm-storm.json``, ``summary.json``, ``impacts.csv`` and the ParaView
series, one ``storm.vtkhdf`` or ``storm.pvd`` with ``.vtu`` files per frame) and returns a
:class:`StormOut` whose :meth:`StormOut.frames` streams the frames one by one (memory stays
flat in the storm's length). Anything missing, unreadable or cut short raises
:class:`ViewerInputError` with one line naming it (``hailstorm view`` exits 3).
"""

from __future__ import annotations

import json
import math
import os
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["FrameData", "StormOut", "ViewerInputError", "open_storm_out"]

#: the storm's manifest (:data:`hailstorm.runtime.output.storm_output.STORM_MANIFEST`; kept literal so
#: that reading an output folder imports no writer)
MANIFEST = "hailstorm-storm.json"
_MANIFEST_FORMAT = "hailstorm-storm-output"


class ViewerInputError(ValueError):
    """The folder given to ``hailstorm view`` is not a (complete) storm output; the message is one line."""


@dataclass
class FrameData:
    """One recorded frame as the viewer needs it.

    ``displacement`` and ``peak`` are (n, 3) float32 [m] (``peak``: the largest displacement
    since the previous frame, per vertex); the stones are the live ones: ``positions`` (k, 3),
    ``radii`` (k,), ``ids`` (k,), ``force`` (k,) the magnitude of the force each applies to the
    seat [N]; ``contacts`` the open contacts (None when the series does not record them).
    """

    t: float
    displacement: np.ndarray
    peak: np.ndarray
    positions: np.ndarray
    radii: np.ndarray
    ids: np.ndarray
    force: np.ndarray
    contacts: int | None = None


@dataclass
class StormOut:
    """A storm's output folder, checked (:func:`open_storm_out`)."""

    path: Path
    #: "vtkhdf" or "vtu"
    series: str
    vertices: np.ndarray
    triangles: np.ndarray
    times: np.ndarray
    summary: dict[str, Any]
    #: impacts.csv: its header (column names) and its data lines, verbatim
    impact_columns: list[str]
    impact_lines: list[str]
    #: live stones per frame where the series says so without reading the frames (VTKHDF), else None
    stone_counts: np.ndarray | None = None
    _vtu: list[tuple[str, str]] = field(default_factory=list, repr=False)

    @property
    def n_frames(self) -> int:
        return int(self.times.size)

    def impact_table(self) -> dict[str, np.ndarray]:
        """impacts.csv's numeric columns as float arrays (an empty field is NaN; ``beyond`` stays text)."""
        rows = [line.split(",") for line in self.impact_lines]
        out: dict[str, np.ndarray] = {}
        for j, name in enumerate(self.impact_columns):
            col = [r[j] for r in rows]
            if name == "beyond":
                out[name] = np.array(col, dtype=object)
            else:
                out[name] = np.array([float(v) if v else math.nan for v in col], dtype=np.float64)
        return out

    def frames(self) -> Iterator[FrameData]:
        """The frames in order, read one by one."""
        if self.series == "vtkhdf":
            yield from self._vtkhdf_frames()
        else:
            yield from self._vtu_frames()

    def _vtkhdf_frames(self) -> Iterator[FrameData]:
        from hailstorm.runtime.output.vtkhdf import VTKHDFFrames

        path = self.path / "storm.vtkhdf"
        try:
            frames = VTKHDFFrames(path)
        except (OSError, KeyError) as exc:
            raise ViewerInputError(f"{path}: cannot be read ({_one_line(exc)}); cut short or damaged?") from None
        try:
            for i in range(len(frames)):
                try:
                    f = frames[i]
                except (OSError, KeyError, ValueError) as exc:
                    raise ViewerInputError(f"{path}: frame {i} cannot be read ({_one_line(exc)}); "
                                           "cut short or damaged?") from None
                yield _frame_data(f)
        finally:
            frames.close()

    def _vtu_frames(self) -> Iterator[FrameData]:
        from hailstorm.runtime.output.vtu import read_vtu

        for (t, (sname, stname)) in zip(self.times, self._vtu):
            try:
                _, s = read_vtu(self.path / sname)
                pts, st = read_vtu(self.path / stname)
            except (OSError, ValueError, KeyError, ET.ParseError) as exc:
                raise ViewerInputError(f"{self.path / sname}: cannot be read ({_one_line(exc)}); "
                                       "cut short or damaged?") from None
            ids = np.asarray(st["id"], dtype=np.int64)
            keep = ids >= 0  # a frame without stones holds one placeholder of id -1
            force = st.get("force")
            force = np.zeros(int(keep.sum())) if force is None else np.linalg.norm(
                np.asarray(force, dtype=np.float64).reshape(-1, 3)[keep], axis=1)
            yield FrameData(t=float(t), displacement=np.asarray(s["displacement"], dtype=np.float32),
                            peak=np.asarray(s.get("peak_displacement", s["displacement"]), dtype=np.float32),
                            positions=np.asarray(pts, dtype=np.float64)[keep],
                            radii=np.asarray(st["radius"], dtype=np.float64)[keep], ids=ids[keep], force=force)


def _frame_data(f: Any) -> FrameData:
    k = np.asarray(f.positions).reshape(-1, 3).shape[0]
    forces = f.forces
    force = np.zeros(k) if forces is None else np.linalg.norm(np.asarray(forces, dtype=np.float64).reshape(k, 3), axis=1)
    peak = f.peak_displacement if f.peak_displacement is not None else f.displacement
    return FrameData(t=float(f.t), displacement=np.asarray(f.displacement, dtype=np.float32),
                     peak=np.asarray(peak, dtype=np.float32), positions=np.asarray(f.positions, dtype=np.float64).reshape(k, 3),
                     radii=np.asarray(f.radii, dtype=np.float64).reshape(k), ids=np.asarray(f.ids, dtype=np.int64).reshape(k),
                     force=force, contacts=int(f.contacts))


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__


def open_storm_out(path: str | os.PathLike) -> StormOut:
    """Check a storm's output folder and read its seat, frame times, summary and impacts.

    Raises
    ------
    ViewerInputError
        The folder does not exist, is not a storm's output (no ``hailstorm-storm.json``),
        or a file it lists is missing, unreadable or cut short; the message names it.
    """
    out = Path(path)
    if not out.exists():
        raise ViewerInputError(f"{out}: no such folder (give the --out folder of `hailstorm storm`)")
    if not out.is_dir():
        raise ViewerInputError(f"{out} is not a folder (give the --out folder of `hailstorm storm`)")
    man_path = out / MANIFEST
    if not man_path.is_file():
        raise ViewerInputError(f"{out} is not a storm's output: {MANIFEST} is missing "
                               "(written by `hailstorm storm --out DIR`)")
    try:
        manifest = json.loads(man_path.read_text())
    except (OSError, ValueError) as exc:
        raise ViewerInputError(f"{man_path} cannot be read ({_one_line(exc)}); cut short or damaged?") from None
    if not isinstance(manifest, dict) or manifest.get("format") != _MANIFEST_FORMAT \
            or not isinstance(manifest.get("files"), list):
        raise ViewerInputError(f"{man_path} is not a storm output's manifest")
    listed = [str(f) for f in manifest["files"]]
    for name in ("summary.json", "impacts.csv"):
        if name not in listed:
            raise ViewerInputError(f"{out}: {name} is missing (not listed in {MANIFEST}; "
                                   "rerun the storm with this version of hailstorm)")
    missing = [f for f in listed if not (out / f).is_file()]
    if missing:
        more = f" and {len(missing) - 1} more" if len(missing) > 1 else ""
        raise ViewerInputError(f"{out}: {missing[0]}{more} missing (listed in {MANIFEST}); cut short?")
    try:
        summary = json.loads((out / "summary.json").read_text())
        if not isinstance(summary, dict):
            raise ValueError("not a JSON object")
    except (OSError, ValueError) as exc:
        raise ViewerInputError(f"{out / 'summary.json'} cannot be read ({_one_line(exc)}); cut short?") from None
    columns, lines = _read_impacts(out / "impacts.csv")
    counts = None
    if "storm.vtkhdf" in listed:
        series, X, tri, times, counts, vtu = "vtkhdf", *_vtkhdf_head(out / "storm.vtkhdf"), []
    elif "storm.pvd" in listed:
        series, (X, tri, times, vtu) = "vtu", _vtu_head(out)
    else:
        raise ViewerInputError(f"{out}: the ParaView series is missing (neither storm.vtkhdf nor storm.pvd is "
                               f"listed in {MANIFEST})")
    frames = summary.get("frames")
    if isinstance(frames, int) and frames != times.size:
        raise ViewerInputError(f"{out}: the series holds {times.size} frames where summary.json counts {frames}; "
                               "cut short?")
    if times.size == 0:
        raise ViewerInputError(f"{out}: the series holds no frame")
    n_imp = summary.get("impacts")
    if isinstance(n_imp, int) and n_imp != len(lines):
        raise ViewerInputError(f"{out / 'impacts.csv'} holds {len(lines)} impacts where summary.json counts "
                               f"{n_imp}; cut short?")
    return StormOut(path=out, series=series, vertices=X, triangles=tri, times=times, summary=summary,
                    impact_columns=columns, impact_lines=lines, stone_counts=counts, _vtu=vtu)


#: the columns the viewer reads from impacts.csv (a file without them is not a storm's)
_NEEDED_COLUMNS = ("stone", "x_m", "y_m", "z_m", "radius_m", "speed_m_s", "peak_force_N", "peak_force_dynamic_N")


def _read_impacts(path: Path) -> tuple[list[str], list[str]]:
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise ViewerInputError(f"{path} cannot be read ({_one_line(exc)})") from None
    lines = text.splitlines()
    if not lines or not text.endswith("\n"):
        raise ViewerInputError(f"{path} is cut short (no header line)" if not lines else
                               f"{path} is cut short (its last line has no end)")
    columns = lines[0].split(",")
    absent = [c for c in _NEEDED_COLUMNS if c not in columns]
    if absent:
        raise ViewerInputError(f"{path} is not a storm's impact table (no column {absent[0]})")
    rows = lines[1:]
    for k, line in enumerate(rows, start=2):
        if line.count(",") != len(columns) - 1:
            raise ViewerInputError(f"{path}: line {k} has {line.count(',') + 1} fields for {len(columns)} columns; "
                                   "cut short?")
    return columns, rows


def _vtkhdf_head(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    from hailstorm.runtime.resources import require_extra

    h5py = require_extra("h5py", "series", "reading the storm's one-file time series (storm.vtkhdf)")
    try:
        with h5py.File(path, "r") as f:
            seat = f["VTKHDF"]["seat"]
            X = np.asarray(seat["Points"][:], dtype=np.float64).reshape(-1, 3)
            tri = np.asarray(seat["Polygons"]["Connectivity"][:], dtype=np.int64).reshape(-1, 3)
            times = np.asarray(f["hailstorm"]["time"][:], dtype=np.float64)
            n_disp = seat["PointData"]["displacement"].shape[0]
            counts = np.asarray(f["VTKHDF"]["stones"]["NumberOfPoints"][:], dtype=np.int64)
    except (OSError, KeyError, ValueError) as exc:
        raise ViewerInputError(f"{path} cannot be read ({_one_line(exc)}); cut short or damaged?") from None
    if n_disp < times.size * X.shape[0]:
        raise ViewerInputError(f"{path} holds the displacement of {n_disp // max(X.shape[0], 1)} frames for "
                               f"{times.size} times; cut short?")
    if counts.size < times.size:
        raise ViewerInputError(f"{path} holds the stones of {counts.size} frames for {times.size} times; cut short?")
    return X, tri, times, counts


def _vtu_head(out: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[tuple[str, str]]]:
    """The ``.vtu`` series: the seat from its first surface file, the times and file pairs from the two ``.pvd``."""
    def collection(name: str) -> list[tuple[float, str]]:
        p = out / name
        try:
            root = ET.parse(p).getroot()
            return [(float(d.get("timestep", "nan")), str(d.get("file"))) for d in root.iter("DataSet")]
        except (OSError, ET.ParseError, ValueError) as exc:
            raise ViewerInputError(f"{p} cannot be read ({_one_line(exc)}); cut short?") from None

    seat, stones = collection("storm.pvd"), collection("storm_stones.pvd")
    if len(seat) != len(stones):
        raise ViewerInputError(f"{out}: storm.pvd lists {len(seat)} frames, storm_stones.pvd {len(stones)}; cut short?")
    for _, f in seat + stones:
        if not (out / f).is_file():
            raise ViewerInputError(f"{out}: {f} is missing (listed in storm.pvd); cut short?")
    if not seat:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64), np.zeros(0), []
    first = out / seat[0][1]
    try:
        X, tri = _vtu_triangles(first)
    except (OSError, ValueError, KeyError, ET.ParseError) as exc:
        raise ViewerInputError(f"{first} cannot be read ({_one_line(exc)}); cut short?") from None
    return X, tri, np.array([t for t, _ in seat]), [(s, st) for (_, s), (_, st) in zip(seat, stones)]


def _vtu_triangles(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The points and triangles of a surface ``.vtu`` the series wrote."""
    from hailstorm.runtime.output.vtu import read_vtu, read_vtu_cells

    points, _ = read_vtu(path)
    return np.asarray(points, dtype=np.float64).reshape(-1, 3), read_vtu_cells(path, 3)
