"""A storm's outputs as a unit, streamed frames, the pre-flight estimate, the summary's
seat, the physical warnings and the compile notices."""

from __future__ import annotations

import json
import logging
import tracemalloc
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from helpers import ctrl_c_at_frame

from hailstorm.cli import main
from hailstorm.runtime.output.storm_output import STORM_MANIFEST, OutputError, StormOutput
from hailstorm.runtime.storm.scene import Scene
from hailstorm.runtime.storm.run import run_storm


def _scene(**kw) -> Scene:
    base = dict(duration=0.06, stones=6, seed=2, spawn_height=0.02, r_min=0.003, r_max=0.008, fps=100.0)
    return Scene.from_flat(**{**base, **kw})


def _run_into(out: Path, gf, scene: Scene, *, video: bool = False, series: str = "vtu") -> dict:
    """Run ``scene`` into ``out`` (the per-frame .vtu series unless ``series``: these tests look at its files)."""
    with StormOutput(out, gf, video=video, series=series) as sink:
        result = run_storm(gf, scene, progress=False, on_frame=sink.add)
        sink.finish(result)
    return json.loads((out / "summary.json").read_text())


def _pvd_files(out: Path) -> list[Path]:
    files = []
    for pvd in sorted(out.glob("*.pvd")):
        files += [out / ds.attrib["file"] for ds in ET.parse(pvd).getroot().iter("DataSet")]
    return files


def _all_files(out: Path) -> set[str]:
    return {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()}


def test_every_file_a_pvd_lists_reads_back_with_meshio(seat_bundle, tmp_path, capsys):
    """The CLI's series on the real seat, including frame 0 before any stone exists."""
    import meshio

    out = tmp_path / "run"
    assert main(["storm", "--series", "vtu", "--gf", str(seat_bundle), "--duration", "0.03", "--stones", "3", "--seed", "1",
                 "--out", str(out), "-q"]) == 0
    summary = json.loads((out / "summary.json").read_text())
    files = _pvd_files(out)
    assert len(files) == 2 * summary["frames"]
    stones0 = meshio.read(out / "frames" / "stones_0000.vtu")  # no stone has spawned at t = 0
    assert np.all(stones0.point_data["id"] < 0) and np.all(stones0.point_data["radius"] == 0)
    for f in files:
        m = meshio.read(f)
        assert m.points.shape[0] >= 1
    # the directory is exactly what the manifest lists
    manifest = json.loads((out / STORM_MANIFEST).read_text())
    assert set(manifest["files"]) | {STORM_MANIFEST} == _all_files(out)
    assert sorted(f.name for f in (out / "frames").iterdir()) == sorted(f.name for f in files)
    assert {"storm.pvd", "storm_stones.pvd", "summary.json", "impacts.csv"} <= set(manifest["files"])
    lines = (out / "impacts.csv").read_text().splitlines()  # a header, then one line per impact
    assert lines[0].startswith("stone,t_onset_s,t_peak_s,x_m,y_m,z_m,radius_m") and len(lines) == 1 + summary["impacts"]
    assert any(f.startswith("storm.") and f.endswith((".mp4", ".gif")) for f in manifest["files"])
    # no temporary directory left beside it
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_interrupted_run_leaves_nothing_and_keeps_the_previous_output(gf, tmp_path):
    out = tmp_path / "run"
    first = _run_into(out, gf, _scene())
    before = {f: (out / f).read_bytes() for f in _all_files(out)}
    interrupt = ctrl_c_at_frame(3)
    with pytest.raises(KeyboardInterrupt):
        with StormOutput(out, gf, video=False, series="vtu") as sink:
            run_storm(gf, _scene(seed=5), progress=False, on_frame=lambda f: (sink.add(f), interrupt(f)))
    assert {f: (out / f).read_bytes() for f in _all_files(out)} == before  # the old run, intact
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]
    assert first["frames"] == len(list((out / "frames").glob("surface_*.vtu")))
    # and a first run that is interrupted leaves no directory at all
    with pytest.raises(KeyboardInterrupt):
        with StormOutput(tmp_path / "new", gf, video=False, series="vtu") as sink:
            interrupt = ctrl_c_at_frame(3)
            run_storm(gf, _scene(), progress=False, on_frame=lambda f: (sink.add(f), interrupt(f)))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]


def test_rerun_replaces_a_previous_output_without_stale_frames(gf, tmp_path):
    out = tmp_path / "run"
    long = _run_into(out, gf, _scene(duration=0.1))
    short = _run_into(out, gf, _scene(duration=0.03))
    assert long["frames"] > short["frames"]
    assert len(list((out / "frames").glob("*.vtu"))) == 2 * short["frames"]
    assert json.loads((out / "summary.json").read_text())["sim_time_s"] == pytest.approx(0.03)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"]  # the old one was removed


def test_rerun_refuses_a_previous_output_the_user_added_to(gf, tmp_path):
    out = tmp_path / "run"
    _run_into(out, gf, _scene())
    (out / "notes.txt").write_text("mine")
    (out / "frames" / "extra.vtu").write_text("mine too")
    with pytest.raises(OutputError, match="notes.txt.*frames/extra.vtu|frames/extra.vtu.*notes.txt"):
        _run_into(out, gf, _scene(seed=9))
    assert (out / "notes.txt").read_text() == "mine" and (out / "frames" / "extra.vtu").read_text() == "mine too"


def test_streamed_storm_keeps_no_frames_and_memory_stays_flat(gf):
    """With an ``on_frame`` sink the frames are not kept: the traced peak memory of a
    storm 10x as long stays within 1.3x (frames kept, it grows with the duration). (The
    inertia factors, after the storm, are off: their local pads' peak would hide the frames'.)"""
    seen = []

    # every kernel and cache the longer storm reaches loaded first (a kernel loaded, or compiled, inside
    # one measurement only would be traced as that storm's memory)
    run_storm(gf, _scene(duration=0.5, stones=4, fps=2500.0, inertia=False), progress=False, on_frame=lambda f: None)

    def peak(duration: float, keep: bool | None) -> float:
        seen.clear()
        # (2 500 frames a second: kept, the long storm's 1 250 frames of the plate, ~6 MB, dwarf the rest)
        sc = _scene(duration=duration, stones=4, fps=2500.0, inertia=False)
        run_storm(gf, sc, progress=False, on_frame=lambda f: None, keep_frames=keep)  # warm caches
        tracemalloc.start()
        res = run_storm(gf, sc, progress=False, on_frame=lambda f: seen.append(f.t), keep_frames=keep)
        _, top = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        assert res.stats["frames"] == len(seen)
        assert len(res.frames) == (len(seen) if keep else 0)
        return top

    short, long = peak(0.05, None), peak(0.5, None)
    assert long <= 1.3 * short, (short, long)
    kept_short, kept_long = peak(0.05, True), peak(0.5, True)
    assert kept_long > 1.5 * kept_short  # the measure sees the frames when they are kept


def test_estimate_matches_the_run(gf):
    for sc in (_scene(), _scene(duration=0.05, fps=30.0, dt=5e-4), _scene(duration=0.01, fps=1e6, dt=1e-3)):
        est = sc.estimate(gf.n_vertices)
        res = run_storm(gf, sc, progress=False, keep_frames=False, on_frame=lambda f: None)
        assert est.steps == res.stats["steps"]
        assert est.frames == res.stats["frames"]
        assert est.stones == res.stats["hailstones"]


@pytest.mark.parametrize("series", ["vtkhdf", "vtu"])
def test_disk_estimate_bounds_the_written_output(seat_bundle, tmp_path, series):
    from hailstorm.runtime.bundle.read import load

    g = load(seat_bundle)
    sc = Scene.from_flat(duration=0.04, stones=4, seed=3, spawn_height=0.01)
    _run_into(tmp_path / "run", g, sc, series=series)
    written = sum(p.stat().st_size for p in (tmp_path / "run").rglob("*") if p.is_file())
    est = sc.estimate(g.n_vertices, series=series).disk_bytes
    assert written <= est <= 3 * written


def test_summary_records_the_seat_the_bundle_was_computed_for(seat_bundle, tmp_path, caplog):
    """With --gf the scene's [seat] is not used: the summary says what was, and a warning says so."""
    scene = tmp_path / "scene.toml"
    scene.write_text("[seat]\nmesh_size = 0.004\norder = 2\ncoarsening = 5.0\n")
    out = tmp_path / "run"
    assert main(["storm", "--gf", str(seat_bundle), "--scene", str(scene), "--duration", "0.01", "--stones", "1",
                 "--out", str(out), "--no-video"]) == 0
    err = " ".join(r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)
    assert "[seat] settings are ignored with --gf" in err and "mesh_size = 0.004" in err
    assert "coarsening = 5.0 (bundle: 2.5)" in err
    s = json.loads((out / "summary.json").read_text())
    manifest = json.loads((Path(seat_bundle) / "manifest.json").read_text())
    assert s["scene"]["seat"] == {"mesh_size": 0.015, "order": 1, "young": manifest["material"]["young"],
                                  "poisson": manifest["material"]["poisson"]}
    assert s["bundle"]["key"] == manifest["key"]


def test_physical_warnings(gf, caplog):
    assert _scene().physical_warnings(gf.vertices) == []
    big = _scene(r_min=0.05, r_max=0.07, distribution="uniform", spawn_height=0.1)
    assert any("larger than the seat" in w for w in big.physical_warnings(gf.vertices))
    wide = _scene(patch_min_radius=0.07)
    assert any("point contact" in w for w in wide.physical_warnings(gf.vertices))
    # wind without drag: every stone is spawned upwind for a drag-limited fall and misses
    windy = _scene(wind=(30.0, 0.0, 0.0), drag=False, stones=20, duration=0.3, spawn_height=2.0)
    assert any("no stone reaches the seat" in w for w in windy.physical_warnings(gf.vertices))
    updraft = _scene(wind=(0.0, 0.0, 40.0), stones=20, duration=0.3, spawn_height=2.0)
    assert any("no stone reaches the seat" in w for w in updraft.physical_warnings(gf.vertices))
    for sc in (windy, updraft):
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="hailstorm.runtime.storm.driver"):
            res = run_storm(gf, sc, progress=False)
        assert any("no stone reaches the seat" in r.getMessage() for r in caplog.records)
        assert res.stats["stones_hit"] == 0  # the storm itself agrees
    # and the calm storm of the same stones does hit
    calm = _scene(wind=(0.0, 0.0, 0.0), stones=20, duration=0.3, spawn_height=2.0)
    assert calm.physical_warnings(gf.vertices) == []
    assert run_storm(gf, calm, progress=False).stats["stones_hit"] > 0


@pytest.mark.parametrize("integrator", ["implicit", "exact", "symplectic"])
def test_the_warm_up_covers_the_scenes_kernels_in_announced_tasks(gf, integrator):
    """The storm warms up its kernels in tasks (each announced when it compiles, with
    its measured seconds: hailstorm.runtime.storm.warmup; tests/test_warmup.py): those of the
    scene's integrator and contact model only, and all of them run."""
    import hailstorm.runtime.storm.driver as storm_mod

    st = storm_mod.Storm(gf, _scene(integrator=integrator))
    names = [t.name for t in st.warm_tasks()]
    assert any("free-flight" in m for m in names) and any("narrow-phase" in m for m in names)
    assert any("contact-set" in m for m in names) and any("the patch kernels" == m for m in names)
    assert [m for m in names if "integrator" in m] == [f"the {integrator} integrator's kernels"]
    # measured seconds (the packaged ones cover the default scene's tasks; another integrator's
    # are None, "not measured yet", until its first compile on this machine records them)
    assert all(t.seconds is None or t.seconds > 0 for t in st.warm_tasks())
    if integrator == "implicit":
        assert all(t.seconds > 0 for t in st.warm_tasks())
    assert list(st.warm_report.times) and set(st.warm_report.times) == set(names)
    point = storm_mod.Storm(gf, _scene(integrator=integrator, patch="none"), warm=False)
    assert point.warm_report is None
    assert "the patch-compliance kernel" in [t.name for t in point.warm_tasks()]


def test_an_old_output_that_cannot_be_removed_is_swept_by_the_next_storm(gf, tmp_path, monkeypatch, caplog):
    """The previous output could not be removed once the new one was in place (read-only files): the
    storm is complete (no error), warns once naming the leftover, and the next storm beside it
    removes it (the files its manifest lists)."""
    import hailstorm.runtime.output.storm_output as files

    out = tmp_path / "run"
    _run_into(out, gf, _scene())
    real = files._remove_storm_output

    def denied(path):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(files, "_remove_storm_output", denied)
    with caplog.at_level(logging.WARNING, logger="hailstorm.runtime.output.storm_output"):
        second = _run_into(out, gf, _scene(seed=7))
    assert json.loads((out / "summary.json").read_text()) == second
    left = [p for p in tmp_path.iterdir() if p.name.startswith(".run.old-")]
    assert len(left) == 1 and (left[0] / STORM_MANIFEST).is_file()
    assert [r.getMessage() for r in caplog.records if "could not be removed" in r.getMessage()][0].count(str(left[0])) == 1
    monkeypatch.setattr(files, "_remove_storm_output", real)
    _run_into(tmp_path / "other", gf, _scene(duration=0.02))  # a storm beside it sweeps it
    assert not left[0].exists() and sorted(p.name for p in tmp_path.iterdir()) == ["other", "run"]


@pytest.mark.parametrize("which", ["parent", "out"])
def test_an_output_made_read_only_during_the_run_is_left_as_it_was(gf, tmp_path, monkeypatch, which):
    """--out (or its folder) made read-only while the storm ran: nothing is replaced, the error says
    where the results are (exit 3 on the command line: the output is not in place), and the
    results are complete there."""
    import hailstorm.runtime.output.storm_output as files

    out = tmp_path / "run"
    first = _run_into(out, gf, _scene())
    target = out if which == "out" else tmp_path
    monkeypatch.setattr(files, "_writable", lambda p: Path(p) != target)
    with pytest.raises(OutputError, match=r"became read-only during the run; --out is as it was, and this storm's "
                                          r"results are in .*\.run\.partial-") as err:
        _run_into(out, gf, _scene(seed=7))
    assert json.loads((out / "summary.json").read_text()) == first  # the old output, untouched
    kept = Path(str(err.value).rsplit(" ", 1)[-1])
    assert json.loads((kept / "summary.json").read_text())["hailstones"] == 6


def test_results_kept_after_a_refused_commit_survive_the_next_storm(gf, tmp_path, monkeypatch):
    """The results an error names (``this storm's results are in .run.partial-*``: --out became
    read-only) are the user's now, not a killed storm's temporary: the next storm beside them,
    once the folder is writable again, leaves them where the message said."""
    import hailstorm.runtime.output.storm_output as files

    out = tmp_path / "run"
    _run_into(out, gf, _scene())
    real = files._writable
    monkeypatch.setattr(files, "_writable", lambda p: Path(p) != out)
    with pytest.raises(OutputError, match="became read-only during the run") as err:
        _run_into(out, gf, _scene(seed=7))
    kept = Path(str(err.value).rsplit(" ", 1)[-1])
    monkeypatch.setattr(files, "_writable", real)
    _run_into(out, gf, _scene(seed=8))  # writable again: a storm into the same --out
    assert json.loads((kept / "summary.json").read_text())["hailstones"] == 6
