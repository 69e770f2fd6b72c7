"""A storm's frames in one file: VTK's HDF5 format (VTKHDF), transient, read by ParaView and VTK.

One ``storm.vtkhdf`` holds the whole series, where the ``.vtu`` series writes two files per
frame (a 30 s default storm: 15 002 files): a *partitioned dataset collection* of two
blocks, each a transient ``PolyData`` (VTKHDF 2.2, read by VTK >= 9.4 and ParaView >= 5.13;
``tests/runtime/output/test_vtkhdf.py`` reads it with VTK's own reader where VTK is installed):

* ``seat``: the undeformed surface (points and triangles, written once) with point data
  ``displacement`` and ``peak_displacement`` per frame (float32, [m]; as the storm records
  them);
* ``stones``: per frame the live stones as vertices, with point data ``radius`` [m], ``id``
  and ``force`` (the force each applies to the seat [N]); a frame may have none.

Every per-frame and per-stone field is gzip-compressed (with HDF5's byte shuffle), lossless:
the seat at rest between impacts, the stones' ids, radii and zero forces repeat.

Beside VTK's group the file holds ``/hailstorm`` (the frames' open contacts and largest
shown displacement: what :class:`VTKHDFFrames` and the renderer read without decoding a
frame). Frames are appended as the storm records them (HDF5 datasets that grow: the seat's fields
frame by frame, the small per-frame records every 64 frames); the storm's output directory is put in place only when the file is closed
(:class:`hailstorm.runtime.output.storm_output.StormOutput`).

h5py comes with the ``series`` extra (in ``all``); without it the storm writes the
``.vtu`` series (:class:`hailstorm.runtime.output.files.ParaviewSeries`).
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hailstorm.runtime.output.render import shown_displacement
from hailstorm.runtime.resources import require_extra

__all__ = ["VTKHDF_VERSION", "VTKHDFFrames", "VTKHDFSeries", "read_vtkhdf_frame"]

#: the VTKHDF format version written (transient composite data: 2.2 and later)
VTKHDF_VERSION = (2, 2)
#: the four PolyData topologies, in VTKHDF's order (its per-step offsets have one column each)
_TOPOLOGIES = ("Vertices", "Lines", "Polygons", "Strips")


def _h5py() -> Any:
    return require_extra("h5py", "series", "the storm's one-file time series (storm.vtkhdf)")


def _grow(ds: Any, rows: np.ndarray) -> None:
    """Append ``rows`` along the first axis of the resizable dataset ``ds``."""
    n = ds.shape[0]
    ds.resize(n + rows.shape[0], axis=0)
    if rows.shape[0]:
        ds[n:] = rows


class _Appender:
    """Rows for many growing datasets, gathered in memory and appended in one write per dataset
    every :attr:`FRAMES` frames (a frame's small records, tens of them, would otherwise cost
    an HDF5 call each)."""

    #: frames gathered between two writes
    FRAMES = 64

    def __init__(self) -> None:
        self.rows: dict[Any, list[np.ndarray]] = {}
        self.frames = 0

    def add(self, ds: Any, rows: Any) -> None:
        self.rows.setdefault(ds, []).append(np.asarray(rows, dtype=ds.dtype))

    def end_frame(self) -> None:
        self.frames += 1
        if self.frames >= self.FRAMES:
            self.flush()

    def flush(self) -> None:
        for ds, parts in self.rows.items():
            _grow(ds, np.concatenate(parts))
        self.rows, self.frames = {}, 0


class VTKHDFSeries:
    """A storm's frames written to one VTKHDF file frame by frame (:meth:`add`), then closed
    (:meth:`close`); the same face as :class:`hailstorm.runtime.output.files.ParaviewSeries`.

    Parameters
    ----------
    gf : GreensFunctions
        The bundle (its surface is the seat block's geometry).
    outdir : path
        Directory of the file (created).
    name : str
        The file is ``<name>.vtkhdf``.
    compression : int
        gzip level of the per-frame fields (0: none).

    Raises
    ------
    hailstorm.runtime.resources.MissingExtra
        h5py is not installed (the ``series`` extra).
    """

    def __init__(self, gf: Any, outdir: str | os.PathLike, *, name: str = "storm", compression: int = 4) -> None:
        h5py = _h5py()
        self.outdir = Path(outdir)
        self.outdir.mkdir(parents=True, exist_ok=True)
        self.name = name
        self.path = self.outdir / f"{name}.vtkhdf"
        X = np.asarray(gf.vertices, dtype=np.float64)
        tri = np.asarray(gf.triangles, dtype=np.int64)
        self.n = X.shape[0]
        #: frames written (their times, contacts and largest shown displacements are in ``/hailstorm``)
        self.frames_written = 0
        self._file = h5py.File(self.path, "w", track_order=True)  # VTK reads groups in creation order
        root = self._file.create_group("VTKHDF", track_order=True)
        _type(root, "PartitionedDataSetCollection")
        gz = {"compression": "gzip", "compression_opts": int(compression), "shuffle": True} if compression else {}
        seat = _polydata(root, "seat", 0)
        seat.create_dataset("NumberOfPoints", data=np.array([self.n], dtype=np.int64))
        seat.create_dataset("Points", data=X)
        for topo in _TOPOLOGIES:
            tri_here = topo == "Polygons"
            _topology(seat, topo, cells=tri if tri_here else np.zeros((0, 3), dtype=np.int64))
        pd_seat = seat.create_group("PointData", track_order=True)
        rows = max(1, self.n)
        for field in ("displacement", "peak_displacement"):
            pd_seat.create_dataset(field, shape=(0, 3), maxshape=(None, 3), dtype=np.float32, chunks=(rows, 3), **gz)
        stones = _polydata(root, "stones", 1)
        chunk, rows_chunk = 256, 4096  # per-frame records; per-stone rows (a frame holds ~300 stones)

        def per_stone(group: Any, name: str, dtype: Any, width: int = 0) -> None:
            shape = (0, width) if width else (0,)
            group.create_dataset(name, shape=shape, maxshape=(None, *shape[1:]), dtype=dtype,
                                 chunks=(rows_chunk, *shape[1:]), **gz)

        stones.create_dataset("NumberOfPoints", shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(chunk,))
        per_stone(stones, "Points", np.float64, 3)
        for topo in _TOPOLOGIES:
            g = stones.create_group(topo, track_order=True)
            for ds in ("NumberOfCells", "NumberOfConnectivityIds"):
                g.create_dataset(ds, shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(chunk,))
            for ds in ("Offsets", "Connectivity"):
                per_stone(g, ds, np.int64)
        pd = stones.create_group("PointData", track_order=True)
        per_stone(pd, "radius", np.float64)
        per_stone(pd, "id", np.int64)
        per_stone(pd, "force", np.float64, 3)
        assembly = root.create_group("Assembly", track_order=True)
        assembly["seat"] = h5py.SoftLink("/VTKHDF/seat")
        assembly["stones"] = h5py.SoftLink("/VTKHDF/stones")
        self._seat_fields = (pd_seat["displacement"], pd_seat["peak_displacement"])
        self._steps = {b: _steps(g, fields) for b, g, fields in
                       (("seat", seat, ("displacement", "peak_displacement")), ("stones", stones, ("radius", "id", "force")))}
        self._stone_ds = {name: stones[name] for name in ("NumberOfPoints", "Points", "PointData/radius",
                                                          "PointData/id", "PointData/force")}
        self._stone_topo = {topo: {ds: stones[f"{topo}/{ds}"] for ds in ("NumberOfCells", "NumberOfConnectivityIds",
                                                                        "Offsets", "Connectivity")}
                            for topo in _TOPOLOGIES}
        self._buffer = _Appender()
        self._stone_points = 0
        own = self._file.create_group("hailstorm", track_order=True)
        own.attrs["format"] = "hailstorm-storm-series"
        own.attrs["version"] = 1
        for ds, dt in (("time", np.float64), ("contacts", np.int64), ("peak_norm", np.float64)):
            own.create_dataset(ds, shape=(0,), maxshape=(None,), dtype=dt, chunks=(chunk,))
        self._own = {name: own[name] for name in ("time", "contacts", "peak_norm")}

    def __len__(self) -> int:
        return self.frames_written

    def add(self, frame: Any) -> None:
        """Append one :class:`hailstorm.runtime.storm.recording.Frame`."""
        i = self.frames_written
        u = np.asarray(frame.displacement, dtype=np.float32).reshape(self.n, 3)
        peak = np.asarray(shown_displacement(frame), dtype=np.float32).reshape(self.n, 3)
        for ds, field in zip(self._seat_fields, (u, peak)):  # the large rows: written as they come
            _grow(ds, field)
        t, buf = float(frame.t), self._buffer
        _step(buf, self._steps["seat"], t, part=0, points=0, cells=(0, 0, 0, 0),
              fields={"displacement": i * self.n, "peak_displacement": i * self.n})
        pos = np.asarray(frame.positions, dtype=np.float64).reshape(-1, 3)
        k = pos.shape[0]
        radii = np.asarray(frame.radii, dtype=np.float64).reshape(k)
        ids = np.asarray(frame.ids, dtype=np.int64).reshape(k)
        forces = getattr(frame, "forces", None)
        forces = np.zeros((k, 3)) if forces is None else np.asarray(forces, dtype=np.float64).reshape(k, 3)
        first = self._stone_points
        for name, rows in (("NumberOfPoints", [k]), ("Points", pos), ("PointData/radius", radii),
                           ("PointData/id", ids), ("PointData/force", forces)):
            buf.add(self._stone_ds[name], rows)
        for topo, ds in self._stone_topo.items():
            n_cells = k if topo == "Vertices" else 0
            buf.add(ds["NumberOfCells"], [n_cells])
            buf.add(ds["NumberOfConnectivityIds"], [n_cells])
            buf.add(ds["Offsets"], np.arange(n_cells + 1))
            buf.add(ds["Connectivity"], np.arange(n_cells))
        # per topology, the step's first cell and connectivity id: only the vertices grow
        _step(buf, self._steps["stones"], t, part=i, points=first, cells=(first, 0, 0, 0),
              fields={"radius": first, "id": first, "force": first})
        self._stone_points += k
        umax = float(np.linalg.norm(peak.astype(np.float64), axis=1).max()) if self.n else 0.0
        for name, value in (("time", [t]), ("contacts", [int(frame.contacts)]), ("peak_norm", [umax])):
            buf.add(self._own[name], value)
        buf.end_frame()
        self.frames_written += 1

    def close(self) -> Path:
        """Finish and close the file; returns its path."""
        if self._file.id.valid:
            self._buffer.flush()
            for steps in self._steps.values():
                steps["group"].attrs["NSteps"] = np.int64(self.frames_written)
            self._file.close()
        return self.path

    def files(self) -> list[str]:
        """The series' one file, relative to :attr:`outdir`."""
        return [self.path.name]

    def frames(self) -> VTKHDFFrames:
        """The written frames, read back from the (closed) file on access."""
        self.close()
        return VTKHDFFrames(self.path)


def _type(group: Any, kind: str) -> None:
    group.attrs["Version"] = np.array(VTKHDF_VERSION, dtype=np.int64)
    group.attrs.create("Type", np.bytes_(kind))  # a fixed-length ASCII string, as VTK writes it


def _polydata(root: Any, name: str, index: int) -> Any:
    g = root.create_group(name, track_order=True)
    _type(g, "PolyData")
    g.attrs["Index"] = np.int64(index)
    return g


def _topology(g: Any, name: str, cells: np.ndarray) -> None:
    """A topology group written once (``cells``: (c, nodes) connectivity)."""
    t = g.create_group(name, track_order=True)
    c, w = cells.shape
    t.create_dataset("NumberOfCells", data=np.array([c], dtype=np.int64))
    t.create_dataset("NumberOfConnectivityIds", data=np.array([c * w], dtype=np.int64))
    t.create_dataset("Offsets", data=np.arange(c + 1, dtype=np.int64) * w)
    t.create_dataset("Connectivity", data=cells.astype(np.int64).ravel())


def _steps(g: Any, fields: tuple[str, ...]) -> dict[str, Any]:
    """A block's ``Steps`` group (empty, growing); its datasets by name, and the group as ``"group"``."""
    s = g.create_group("Steps", track_order=True)
    s.attrs["NSteps"] = np.int64(0)
    out: dict[str, Any] = {"group": s}
    out["Values"] = s.create_dataset("Values", shape=(0,), maxshape=(None,), dtype=np.float64, chunks=(256,))
    for ds in ("PartOffsets", "NumberOfParts", "PointOffsets"):
        out[ds] = s.create_dataset(ds, shape=(0,), maxshape=(None,), dtype=np.int64, chunks=(256,))
    for ds in ("CellOffsets", "ConnectivityIdOffsets"):
        out[ds] = s.create_dataset(ds, shape=(0, 4), maxshape=(None, 4), dtype=np.int64, chunks=(256, 4))
    off = s.create_group("PointDataOffsets", track_order=True)
    for f in fields:
        out[f"PointDataOffsets/{f}"] = off.create_dataset(f, shape=(0,), maxshape=(None,), dtype=np.int64,
                                                          chunks=(256,))
    return out


def _step(buf: _Appender, s: dict[str, Any], t: float, *, part: int, points: int,
          cells: tuple[int, int, int, int], fields: dict[str, int]) -> None:
    """Append one step's offsets (``cells``: each topology's first cell, also its first connectivity id)."""
    buf.add(s["Values"], [t])
    buf.add(s["PartOffsets"], [part])
    buf.add(s["NumberOfParts"], [1])
    buf.add(s["PointOffsets"], [points])
    buf.add(s["CellOffsets"], [cells])
    buf.add(s["ConnectivityIdOffsets"], [cells])
    for name, first in fields.items():
        buf.add(s[f"PointDataOffsets/{name}"], [first])


def read_vtkhdf_frame(path: str | os.PathLike, i: int) -> Any:
    """Frame ``i`` of a storm's ``.vtkhdf`` file (:class:`VTKHDFSeries`), as a
    :class:`hailstorm.runtime.storm.recording.Frame`.

    Raises
    ------
    IndexError
        ``i`` is not a frame of the file.
    """
    with _h5py().File(path, "r") as f:
        return _frame(f, i)


def _frame(f: Any, i: int) -> Any:
    from hailstorm.runtime.storm.recording import Frame

    own = f["hailstorm"]
    n_frames = own["time"].shape[0]
    if not -n_frames <= i < n_frames:
        raise IndexError(f"frame {i} of a series of {n_frames}")
    i %= n_frames
    seat, stones = f["VTKHDF"]["seat"], f["VTKHDF"]["stones"]
    n = int(seat["NumberOfPoints"][0])
    u_off = int(seat["Steps"]["PointDataOffsets"]["displacement"][i])
    p_off = int(seat["Steps"]["PointDataOffsets"]["peak_displacement"][i])
    k = int(stones["NumberOfPoints"][i])
    first = int(stones["Steps"]["PointOffsets"][i])
    sd = stones["PointData"]
    return Frame(t=float(own["time"][i]), displacement=np.asarray(seat["PointData"]["displacement"][u_off:u_off + n]),
                 positions=np.asarray(stones["Points"][first:first + k]),
                 radii=np.asarray(sd["radius"][first:first + k]), ids=np.asarray(sd["id"][first:first + k]),
                 contacts=int(own["contacts"][i]),
                 peak_displacement=np.asarray(seat["PointData"]["peak_displacement"][p_off:p_off + n]),
                 forces=np.asarray(sd["force"][first:first + k]))


class VTKHDFFrames(Sequence):
    """The frames of a storm's ``.vtkhdf`` file, read on access (a sequence of
    :class:`hailstorm.runtime.storm.recording.Frame`; nothing is cached; the file is opened
    once and kept open until :meth:`close` or the object is dropped)."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self._file = _h5py().File(self.path, "r")
        self._peaks = np.asarray(self._file["hailstorm"]["peak_norm"][:])

    def __len__(self) -> int:
        return int(self._peaks.size)

    def peak_norm(self, i: int) -> float:
        """Largest ``|peak displacement|`` of frame ``i`` [m], without reading it."""
        return float(self._peaks[i])

    def __getitem__(self, i: int) -> Any:  # type: ignore[override]
        return _frame(self._file, i)

    def close(self) -> None:
        """Close the file."""
        if self._file.id.valid:
            self._file.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # pragma: no cover - interpreter shutdown
            pass
