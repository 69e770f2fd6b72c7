"""A storm's frames in one VTKHDF file (hailstorm.runtime.output.vtkhdf): read back by h5py and by
VTK's own reader, equal to the storm's state, the topology once, smaller than the .vtu series."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from helpers import ctrl_c_at_frame

from hailstorm.runtime.output.storm_output import STORM_MANIFEST, StormOutput
from hailstorm.runtime.output.vtkhdf import VTKHDFFrames, read_vtkhdf_frame
from hailstorm.runtime.storm.run import run_storm
from hailstorm.runtime.storm.scene import Scene

h5py = pytest.importorskip("h5py")


def _scene(**kw) -> Scene:
    base = dict(duration=0.06, stones=6, seed=2, spawn_height=0.02, r_min=0.003, r_max=0.008, fps=100.0,
                inertia=False)
    return Scene.from_flat(**{**base, **kw})


@pytest.fixture(scope="module")
def written(seat_bundle, tmp_path_factory):
    """The same storm kept in memory and streamed into storm.vtkhdf."""
    import hailstorm.runtime

    gf = hailstorm.runtime.load(seat_bundle)
    kept = run_storm(gf, _scene(), progress=False, keep_frames=True)
    out = tmp_path_factory.mktemp("vtkhdf") / "run"
    with StormOutput(out, gf, video=False) as sink:
        streamed = run_storm(gf, _scene(), progress=False, on_frame=sink.add)
        paths = sink.finish(streamed)
    return gf, kept, out, paths


def test_every_frame_reads_back_as_the_storms_state(written):
    """Frame by frame: the time, the open contacts, the displacement and the peak (float32, as the
    storm records them), every stone's centre, radius, id and force, exactly."""
    gf, kept, out, paths = written
    assert paths["paraview"] == out / "storm.vtkhdf" and "stones" not in paths
    frames = VTKHDFFrames(out / "storm.vtkhdf")
    try:
        assert len(frames) == len(kept.frames) == json.loads((out / "summary.json").read_text())["frames"]
        assert sum(len(f.ids) for f in kept.frames) > 0 and any(len(f.ids) == 0 for f in kept.frames)
        for i, want in enumerate(kept.frames):
            got = frames[i]
            assert got.t == want.t and got.contacts == want.contacts
            np.testing.assert_array_equal(got.displacement, want.displacement)
            assert got.displacement.dtype == np.float32
            np.testing.assert_array_equal(got.peak_displacement, want.peak_displacement)
            for name in ("positions", "radii", "ids", "forces"):
                np.testing.assert_array_equal(getattr(got, name), getattr(want, name), err_msg=f"{name} of {i}")
            peak = float(np.linalg.norm(want.peak_displacement.astype(np.float64), axis=1).max())
            assert frames.peak_norm(i) == peak
        last = read_vtkhdf_frame(out / "storm.vtkhdf", -1)
        np.testing.assert_array_equal(last.positions, kept.frames[-1].positions)
        with pytest.raises(IndexError, match="frame 99 of a series of"):
            frames[99]
    finally:
        frames.close()
    manifest = json.loads((out / STORM_MANIFEST).read_text())
    assert "storm.vtkhdf" in manifest["files"] and not (out / "frames").exists()


def test_the_topology_is_written_once_and_the_fields_compressed(written):
    gf, kept, out, _ = written
    with h5py.File(out / "storm.vtkhdf", "r") as f:
        seat = f["VTKHDF/seat"]
        assert seat["Points"].shape == (gf.n_vertices, 3)
        np.testing.assert_array_equal(seat["Polygons/Connectivity"][:].reshape(-1, 3), gf.triangles)
        u = seat["PointData/displacement"]
        assert u.shape == (len(kept.frames) * gf.n_vertices, 3) and u.dtype == np.float32
        assert u.compression == "gzip"
        assert f["VTKHDF"].attrs["Type"] == b"PartitionedDataSetCollection"
        assert seat["Steps"].attrs["NSteps"] == len(kept.frames)
        assert not np.any(seat["Steps/PointOffsets"][:])  # every step reuses the one surface


def test_vtks_own_reader_reads_every_step(written):
    """VTK's vtkHDFReader (what ParaView uses): the steps' times, the seat's triangles and
    displacement, and the stones (none in the first frames) of each step."""
    vtk = pytest.importorskip("vtk")
    from vtk.util.numpy_support import vtk_to_numpy

    gf, kept, out, _ = written
    reader = vtk.vtkHDFReader()
    reader.SetFileName(str(out / "storm.vtkhdf"))
    reader.UpdateInformation()
    assert reader.GetNumberOfSteps() == len(kept.frames)
    for i, want in enumerate(kept.frames):
        reader.SetStep(i)
        reader.Update()
        data = reader.GetOutputDataObject(0)
        assert data.GetNumberOfPartitionedDataSets() == 2
        seat = data.GetPartitionedDataSet(0).GetPartition(0)
        assert seat.GetNumberOfCells() == len(gf.triangles) and seat.GetNumberOfPoints() == gf.n_vertices
        np.testing.assert_array_equal(vtk_to_numpy(seat.GetPointData().GetArray("displacement")), want.displacement)
        stones = data.GetPartitionedDataSet(1).GetPartition(0)
        k = 0 if stones is None else stones.GetNumberOfPoints()
        assert k == len(want.ids), i
        if k:
            np.testing.assert_array_equal(vtk_to_numpy(stones.GetPoints().GetData()), want.positions)
            np.testing.assert_array_equal(vtk_to_numpy(stones.GetPointData().GetArray("radius")), want.radii)
            assert stones.GetNumberOfCells() == k


def test_a_frame_costs_less_than_its_vtu_pair(written, tmp_path):
    """Per frame (the growth from half the frames to all: a file's fixed part aside), the one
    file takes less than half what a frame's two .vtu files do."""
    gf, kept, out, _ = written
    from hailstorm.runtime.output.files import write_paraview
    from hailstorm.runtime.output.vtkhdf import VTKHDFSeries

    frames = kept.frames[1:] * 4  # (repeated: enough frames to see the growth)
    half = len(frames) // 2

    def sizes(kind: str, part: list) -> int:
        where = tmp_path / f"{kind}-{len(part)}"
        if kind == "vtu":
            write_paraview(part, gf, where)
        else:
            series = VTKHDFSeries(gf, where)
            for f in part:
                series.add(f)
            series.close()
        return sum(p.stat().st_size for p in where.rglob("*") if p.is_file())

    grow = {kind: (sizes(kind, frames) - sizes(kind, frames[:half])) / (len(frames) - half) for kind in ("vtu", "h5")}
    assert grow["h5"] < 0.5 * grow["vtu"], grow


def test_an_interrupted_storm_leaves_no_file(seat_bundle, tmp_path):
    """Ctrl-C while the file is open: the temporary directory goes, the file with it; no --out."""
    import hailstorm.runtime

    gf = hailstorm.runtime.load(seat_bundle)
    interrupt = ctrl_c_at_frame(3)
    with pytest.raises(KeyboardInterrupt):
        with StormOutput(tmp_path / "out", gf, video=False, series="vtkhdf") as sink:
            run_storm(gf, _scene(), progress=False, on_frame=lambda f: (sink.add(f), interrupt(f)))
    assert list(tmp_path.iterdir()) == []


def test_an_unknown_series_is_refused(seat_bundle, tmp_path):
    with pytest.raises(ValueError, match="unknown series format 'pvd'; choose from vtkhdf, vtu"):
        StormOutput(tmp_path / "out", None, series="pvd")
    assert not Path(tmp_path / "out").exists()
