"""`hailstorm storm` on bad input: one line on stderr, exit code 3, no traceback, and
nothing written or lost (table-driven; in-process through ``hailstorm.cli.main``)."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hailstorm.cli import EXIT_INPUT, main

TINY = ["--duration", "0.01", "--stones", "1", "--no-video", "-q"]  # a storm of seconds


def _file(tmp: Path) -> Path:
    (tmp / "taken").write_text("a file the user owns")
    return tmp / "taken"


def _foreign_dir(tmp: Path) -> Path:
    (tmp / "mine").mkdir()
    (tmp / "mine" / "thesis.tex").write_text("years of work")
    return tmp / "mine"


def _user_summary(tmp: Path) -> Path:
    (tmp / "old").mkdir()
    (tmp / "old" / "summary.json").write_text('{"mine": true}')
    return tmp / "old"


def _read_only_dir(tmp: Path) -> Path:
    (tmp / "ro").mkdir()
    (tmp / "ro").chmod(0o555)
    return tmp / "ro"


def _scene(text: str):
    def make(tmp: Path) -> Path:
        (tmp / "scene.toml").write_text(text)
        return tmp / "scene.toml"
    return make


# (id, extra arguments: a list whose callables get tmp_path, expected fragment of the one-line error)
ROWS = [
    ("out-is-a-file", ["--out", _file], "exists and is not a directory"),
    ("out-under-a-file", ["--out", lambda t: _file(t) / "sub"], "is not a directory"),
    ("out-holds-user-files", ["--out", _foreign_dir], "thesis.tex"),
    ("out-holds-a-user-summary", ["--out", _user_summary], "summary.json"),
    ("out-on-an-unwritable-file-system", ["--out", lambda t: Path("/proc/hailstorm-out")], "cannot write --out"),
    pytest.param("out-read-only", ["--out", _read_only_dir], "not writable",
                 marks=pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only directories")),
    ("toml-storm-not-a-table", ["--scene", _scene("storm = 5\n")], "[storm] must be a table"),
    ("toml-value-of-wrong-type", ["--scene", _scene("[hail]\nr_min = [1]\n")], "r_min must be a number"),
    ("toml-string-for-number", ["--scene", _scene('[storm]\nduration = "long"\n')], "duration must be a number"),
    ("dt-1e-12", ["--dt", "1e-12"], "--allow-large"),
    ("dt-1e-8", ["--dt", "1e-8"], "20,000,000 steps"),
    ("rate-1e9", ["--scene", _scene("[storm]\nrate = 1e9\n")], "of memory"),
    ("scene-missing", ["--scene", lambda t: t / "nope.toml"], "cannot read scene file"),
    ("gf-missing", ["--gf", lambda t: t / "no-bundle"], "no-bundle"),
    # the second bad-input round
    ("stones-5-million-in-0.1-s", ["--stones", "5000000", "--duration", "0.1"], "impacts expected of 5,000,000 stones"),
    ("duration-1e308", ["--duration", "1e308"], "not a finite number of steps"),
    ("duration-1e300-count-in-scientific-notation", ["--duration", "1e300"], "5e+303 steps"),
    ("out-name-too-long-for-its-temporary", ["--out", lambda t: t / ("o" * 240)], "is 240 bytes long"),
    ("scene-not-utf8", ["--scene", lambda t: (t / "s.toml").write_bytes(b"[storm]\nduration = 0.1 # \xff\xfe\n")
                        and t / "s.toml"], "s.toml is not a UTF-8 text file"),
]


@pytest.mark.parametrize("name, extra, message", ROWS)
def test_bad_storm_input_is_one_line_exit_3(seat_bundle, tmp_path, capsys, name, extra, message):
    args = [str(a(tmp_path)) if callable(a) else a for a in extra]
    if "--out" not in args:
        args += ["--out", str(tmp_path / "out")]
    if "--gf" not in args:
        args += ["--gf", str(seat_bundle)]
    args += ["--no-video", "-q"]
    if not name.startswith(("dt", "rate")):  # those rows need the default duration and the rate
        if "--duration" not in args:
            args += ["--duration", "0.01"]
        if "--stones" not in args:
            args += ["--stones", "1"]
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    rc = main(["storm", *args])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert rc == EXIT_INPUT, err
    assert len(lines) == 1 and lines[0].startswith("hailstorm: error: "), err
    assert message in lines[0]
    assert len(lines[0]) < 400, lines[0]  # no 300-digit numbers
    # nothing the user owns was touched, and no run was left behind
    assert {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()} == before
    assert not (tmp_path / "out").exists() and not list(tmp_path.glob(".*"))


@pytest.mark.parametrize("reader", ["head -1", "true"])
def test_broken_pipe_exits_quietly(box_bundle, reader):
    """`hailstorm info X | head -1`: the reader leaves early (``true``: before the first
    line); no traceback, nothing on stderr."""
    run = subprocess.run(f"{sys.executable} -m hailstorm.cli info {box_bundle} | {reader}", shell=True,
                         capture_output=True, text=True, timeout=300)
    assert run.stdout == ("" if reader == "true" else f"bundle   {box_bundle}\n")
    assert run.stderr == ""


def test_a_large_storm_runs_with_allow_large(seat_bundle, tmp_path, monkeypatch):
    """The override: the estimate is checked, and --allow-large passes it."""
    import hailstorm.runtime.storm.estimate as estimate_mod

    monkeypatch.setattr(estimate_mod, "MAX_STEPS", 10)  # 50 steps: "too many" here
    out = tmp_path / "out"
    assert main(["storm", "--gf", str(seat_bundle), "--out", str(out), *TINY]) == EXIT_INPUT
    assert main(["storm", "--gf", str(seat_bundle), "--out", str(out), "--allow-large", *TINY]) == 0
    assert (out / "summary.json").is_file()


# ---- the bounded --out scan ------------------------------------------------------------


class _CountingScandir:
    """``os.scandir`` that counts the entries it yields (os.walk uses it too)."""

    def __init__(self, real):
        self.real, self.seen = real, 0

    def __call__(self, path="."):
        counter, it = self, self.real(path)

        class _It:
            def __enter__(self):
                return self

            def __exit__(self, *exc):
                it.close()

            def __iter__(self):
                return self

            def __next__(self):
                e = next(it)
                counter.seen += 1
                return e

            def close(self):
                it.close()

        return _It()


def _big_tree(root: Path, folders: int = 4000, files: int = 2) -> Path:
    root.mkdir()
    for i in range(folders):
        (root / f"d{i:04d}").mkdir()
        for j in range(files):
            (root / f"d{i:04d}" / f"f{j}").write_bytes(b"")
    return root


@pytest.mark.parametrize("with_manifest", [False, True])
def test_out_holding_a_big_foreign_tree_is_refused_after_a_bounded_scan(tmp_path, monkeypatch, with_manifest):
    """``--out $HOME``: 4000 folders of user files (with or without a storm manifest on
    top) are refused after visiting a handful of entries, not the whole tree (the old
    check walked all 12 000 and then compared every folder with every file)."""
    import json

    from hailstorm.runtime.output.storm_output import STORM_MANIFEST, OutputError, check_storm_out

    root = _big_tree(tmp_path / "home")
    if with_manifest:
        (root / STORM_MANIFEST).write_text(json.dumps({"format": "hailstorm-storm-output", "version": 1,
                                                       "files": ["summary.json", "frames/surface_0000.vtu"]}))
    counting = _CountingScandir(os.scandir)
    monkeypatch.setattr(os, "scandir", counting)
    with pytest.raises(OutputError, match="not a hailstorm storm output") as err:
        check_storm_out(root)
    monkeypatch.undo()
    assert counting.seen <= 20, counting.seen
    assert "d" in str(err.value) and "more" in str(err.value)
    assert len(str(err.value).splitlines()) == 1


def test_bounded_scan_still_accepts_a_previous_storm_output_and_spots_one_stray_file(tmp_path):
    """The bounded scan keeps the old answers: an exact previous output passes, one
    extra file deep in its frames folder, or an extra empty folder, is named."""
    import json

    from hailstorm.runtime.output.storm_output import STORM_MANIFEST, OutputError, check_storm_out

    out = tmp_path / "run"
    (out / "frames").mkdir(parents=True)
    listed = ["summary.json", "storm.pvd", "frames/surface_0000.vtu", "frames/stones_0000.vtu"]
    for f in listed:
        (out / f).write_text("x")
    (out / STORM_MANIFEST).write_text(json.dumps({"format": "hailstorm-storm-output", "version": 1,
                                                  "files": listed}))
    check_storm_out(out)
    (out / "frames" / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="frames/notes.txt"):
        check_storm_out(out)
    (out / "frames" / "notes.txt").unlink()
    (out / "extra").mkdir()
    with pytest.raises(OutputError, match="extra/"):
        check_storm_out(out)


# ---- the scene's estimate and values through the API ---------------------------


def test_a_burst_of_stones_is_refused_by_its_time_estimate():
    """10 million stones in 0.05 s passed the memory and step checks and ran for hours, and so
    did 2 million: the time estimate (impacts at the measured cost, each dearer as more land at
    once) refuses them, names the rule, and --allow-large passes it; a long sparse storm is
    not refused (its inertia is read from a table); the default storm is far below the limit."""
    from hailstorm.runtime.storm.estimate import MAX_SECONDS
    from hailstorm.runtime.storm.scene import Scene, StormTooLarge

    for stones in (10_000_000, 2_000_000):
        est = Scene.from_flat(stones=stones, duration=0.05).estimate()
        assert est.seconds > 1e3 * MAX_SECONDS and est.near_at_once > 1e4
        with pytest.raises(StormTooLarge, match=rf"estimated [0-9.e+]+ (days|h) \(stepping .*\({stones:,} impacts "
                                                rf"expected of {stones:,} stones, [0-9.e+]+ stones near the seat at "
                                                r"once\), more than 1 h"):
            est.check()
        est.check(allow_large=True)
    sparse = Scene.from_flat(stones=100_000, duration=100.0).estimate()  # 0.2 stones per step
    assert sparse.inertia_seconds < 0.01 * sparse.stepping_seconds  # (read from the table: no longer refused for it)
    sparse.check()
    Scene.from_flat(stones=100_000, duration=100.0, inertia=False).estimate().check()
    assert Scene.default().estimate().seconds < MAX_SECONDS / 100
    assert Scene.from_flat(stones=200, duration=0.05, inertia=False).estimate().seconds < 2.0  # a small burst runs


def test_duration_overflowing_the_step_count_is_a_scene_error():
    from hailstorm.runtime.storm.scene import Scene, SceneError

    with pytest.raises(SceneError, match="not a finite number of steps"):
        Scene.from_flat(duration=1e308)
    assert "e+303" in Scene.from_flat(duration=1e300).estimate().describe()


def test_numpy_integers_are_integers_in_a_scene():
    import numpy as np

    from hailstorm.runtime.storm.scene import Scene

    scene = Scene.from_flat(stones=np.int64(5), seed=np.int32(3))
    assert scene.storm.stones == 5 and type(scene.storm.stones) is int and scene.storm.seed == 3


def test_non_utf8_scene_names_the_file(tmp_path):
    from hailstorm.runtime.storm.scene import Scene, SceneError

    (tmp_path / "latin1.toml").write_bytes("[storm]\n# Grüße\nduration = 0.1\n".encode("latin-1"))
    with pytest.raises(SceneError, match="latin1.toml is not a UTF-8 text file"):
        Scene.from_toml(tmp_path / "latin1.toml")


# ---- a killed storm's temporaries ------------------------------------------------------


def _storm_cmd(seat_bundle, out, duration="3"):
    return [sys.executable, "-m", "hailstorm.cli", "storm", "--gf", str(seat_bundle), "--out", str(out),
            "--duration", duration, "--no-video", "-q"]


def _wait_for_partial(tmp_path, proc, timeout=240.0):
    import time

    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        found = list(tmp_path.glob(".out.partial-*"))
        if found and ((found[0] / "storm.vtkhdf").is_file() or any((found[0] / "frames").glob("*.vtu"))):
            return found[0]
        assert proc.poll() is None, proc.communicate()
        time.sleep(0.2)
    raise AssertionError("the storm wrote no frames")


@pytest.mark.parametrize("sig", ["SIGKILL", "SIGTERM", "SIGHUP"])
def test_a_killed_storm_leaves_nothing_behind(seat_bundle, tmp_path, sig):
    """SIGTERM (and SIGHUP, a closed terminal): the storm removes its temporary directory
    and says so in one line (exit 128 + the signal); SIGKILL: the next storm into the same
    --out removes the dead one's directory (its lock is free) -- but never a running storm's."""
    import signal as _signal

    from hailstorm.runtime.output.storm_output import clean_stale_partials

    out = tmp_path / "out"
    proc = subprocess.Popen(_storm_cmd(seat_bundle, out), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    partial = _wait_for_partial(tmp_path, proc)
    assert clean_stale_partials(out) == []  # a running storm's directory is left alone
    assert partial.is_dir()
    proc.send_signal(getattr(_signal, sig))
    _, err = proc.communicate(timeout=120)
    if sig != "SIGKILL":
        assert proc.returncode == 128 + getattr(_signal, sig), err
        assert err.strip().splitlines() == [f"hailstorm: terminated ({sig})"], err
        assert not partial.exists(), sorted(str(p.relative_to(partial)) for p in partial.rglob("*"))
    else:
        assert partial.is_dir()  # nobody could clean up
        assert main(["storm", "--gf", str(seat_bundle), "--out", str(out), *TINY]) == 0
        assert not partial.exists()
        assert (out / "summary.json").is_file()
    assert not list(tmp_path.glob(".out.*"))


def test_a_killed_storms_partial_is_cleaned_by_a_storm_into_another_out(tmp_path):
    """A killed storm's temporary directory (its lock file present, not held) beside another
    --out is removed too, as bundle writers clean their folder."""
    from hailstorm.runtime.output.storm_output import clean_stale_partials

    dead = tmp_path / ".first.partial-abc"
    dead.mkdir()
    (dead / ".hailstorm-writing").write_text("")
    (dead / "summary.json").write_text("{}")
    assert clean_stale_partials(tmp_path / "second") == [dead]
    assert not dead.exists()


def test_a_partial_without_our_lock_file_is_left_alone(tmp_path):
    from hailstorm.runtime.output.storm_output import clean_stale_partials

    stranger = tmp_path / ".out.partial-abc"
    stranger.mkdir()
    (stranger / "data").write_text("not ours for certain")
    assert clean_stale_partials(tmp_path / "out") == []
    assert (stranger / "data").is_file()


# ---- Storm.add_stones: one validation point --------------------------------------------

_C = [0.06, 0.0, 0.01]  # 1 cm above the middle of the plate (the plate is z = 0, normal +z)
# (id, pos, vel, radius, fragment of the error)
STONE_ROWS = [
    ("nan-position", [np.nan, 0.0, 0.01], [0, 0, -1.0], 0.005, "non-finite position"),
    ("inf-velocity", _C, [0, 0, -np.inf], 0.005, "non-finite velocity"),
    ("negative-radius", _C, [0, 0, -1.0], -0.005, "radius -0.005"),
    ("zero-radius", _C, [0, 0, -1.0], 0.0, "radius 0.0"),
    ("nan-radius", _C, [0, 0, -1.0], np.nan, "radius nan"),
    ("position-of-two", [0.06, 0.0], [0, 0, -1.0], 0.005, "shape (3,) or (k, 3), got (2,)"),
    ("velocities-of-the-wrong-count", [_C, _C], np.zeros((3, 3)), 0.005, "shape (3,) or (2, 3)"),
    ("radii-of-the-wrong-count", [_C, _C], [0, 0, -1.0], [0.005, 0.005, 0.005], "one number or 2 numbers"),
    ("complex-position", np.array(_C) + 1j, [0, 0, -1.0], 0.005, "stone positions must be real numbers"),
    ("string-radius", _C, [0, 0, -1.0], "big", "stone radii must be real numbers"),
    ("inside-the-seat", [0.06, 0.0, -0.002], [0, 0, -1.0], 0.001, "starts inside the seat"),
    ("overlapping-the-seat", _C, [0, 0, -1.0], 0.02, "overlaps the seat by 0.01 m"),
    ("a-kilometre-stone", _C, [0, 0, -1.0], 1e3, "overlaps the seat by 1e+03 m"),
]


@pytest.fixture(scope="module")
def plate_storm():
    from helpers import plate_gf

    from hailstorm.runtime.storm.scene import Scene
    from hailstorm.runtime.storm.driver import Storm

    return Storm(plate_gf(), Scene.from_flat(duration=0.01), spawn=False, warm=False)


@pytest.mark.parametrize("name, pos, vel, radius, message", STONE_ROWS, ids=[r[0] for r in STONE_ROWS])
def test_bad_stones_are_refused_clearly(plate_storm, name, pos, vel, radius, message):
    from hailstorm.runtime.storm.stones import StoneError

    before = len(plate_storm.stones)
    with pytest.raises(StoneError, match=re.escape(message)) as err:
        plate_storm.add_stones(np.asarray(pos), np.asarray(vel), np.asarray(radius))
    assert len(str(err.value).splitlines()) == 1
    assert len(plate_storm.stones) == before and plate_storm.stats.hailstones == 0


def test_good_stones_still_go_in(plate_storm):
    """Above the seat, touching it (within the contact's opening gap, 1 % of the radius), and
    outside its box: accepted (one row, or many)."""
    ids = plate_storm.add_stones(np.array([[0.06, 0.0, 0.005], [0.06, 0.01, 0.02], [1.0, 1.0, 1.0],
                                           [0.06, 0.02, 0.00499]]), np.array([0.0, 0.0, -1.0]), 0.005)
    assert ids.tolist() == [0, 1, 2, 3]
    plate_storm.stones.retire(ids)


# ---- silent empty storms ---------------------------------------------------------------

EMPTY_ROWS = [
    ("dt-1-s", dict(duration=2.0, dt=1.0, stones=50), "lower dt ([time] dt = 1 s)"),
    ("cd-1e-9-tunnels", dict(duration=0.2, stones=50, cd=1e-9), "[hail] cd = 1e-09"),
]


@pytest.mark.parametrize("name, settings, message", EMPTY_ROWS, ids=[r[0] for r in EMPTY_ROWS])
def test_stones_through_the_footprint_without_a_hit_warn(caplog, name, settings, message):
    """0 impacts although the stones crossed the seat's footprint (they passed through
    it in one step): a warning, as for the wind that carries every stone past."""
    import logging

    from helpers import plate_gf

    from hailstorm.runtime.storm.scene import Scene
    from hailstorm.runtime.storm.run import run_storm

    with caplog.at_level(logging.WARNING):
        result = run_storm(plate_gf(), Scene.from_flat(**settings), progress=False)
    assert result.stats.impacts == 0
    warned = [r.getMessage() for r in caplog.records if "passed through the seat's footprint" in r.getMessage()]
    assert len(warned) == 1 and message in warned[0], caplog.text


def test_a_storm_with_impacts_does_not_warn_of_passing_through(caplog):
    import logging

    from helpers import plate_gf

    from hailstorm.runtime.storm.scene import Scene
    from hailstorm.runtime.storm.run import run_storm

    with caplog.at_level(logging.WARNING):
        result = run_storm(plate_gf(), Scene.from_flat(duration=0.2, stones=50), progress=False)
    assert result.stats.impacts > 0
    assert "passed through" not in caplog.text


def test_disk_full_refusal_states_sizes_in_adaptive_units(tmp_path, monkeypatch):
    """'need about 0.00 GiB but ... has 0.00 GiB free' -> sizes a person can read."""
    import collections

    from helpers import plate_gf

    import hailstorm.runtime.output.storm_output as files
    from hailstorm.runtime.output.storm_output import OutputError, StormOutput

    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(files.shutil, "disk_usage", lambda p: usage(10**6, 10**6, 300))
    with pytest.raises(OutputError, match=r"need about 12\.1 KiB but .* has 300 B free"):
        StormOutput(tmp_path / "out", plate_gf(), disk_bytes=12_345).open()
    assert list(tmp_path.iterdir()) == []


# ---- two writers, one --out ------------------------------------------------------------


def test_a_second_storm_into_a_running_storms_out_is_refused(tmp_path):
    from helpers import plate_gf

    from hailstorm.runtime.output.storm_output import OutputError, StormOutput

    gf = plate_gf()
    first = StormOutput(tmp_path / "out", gf, video=False)
    first.open()
    try:
        with pytest.raises(OutputError, match="another storm is writing --out"):
            StormOutput(tmp_path / "out", gf, video=False).open()
    finally:
        first.abort()
    assert list(tmp_path.iterdir()) == []


def test_a_storm_whose_out_was_written_meanwhile_keeps_both(seat_bundle, tmp_path):
    """--out written by another run during this storm (a storm that started before this
    one's check, another tool): this commit is refused, the other result stays, this
    storm's is kept and named (was: the last writer silently replaced the other)."""
    import json

    from hailstorm.runtime.bundle.read import load
    from hailstorm.runtime.output.storm_output import STORM_MANIFEST, OutputError, StormOutput
    from hailstorm.runtime.storm.scene import Scene
    from hailstorm.runtime.storm.run import run_storm

    gf = load(seat_bundle)
    out = tmp_path / "out"
    mine = StormOutput(out, gf, video=False)
    mine.open()
    result = run_storm(gf, Scene.from_flat(duration=0.01, stones=1, seed=2), progress=False, on_frame=mine.add)
    out.mkdir()  # the other run's complete output lands first
    (out / "summary.json").write_text('{"seed": 1}')
    (out / STORM_MANIFEST).write_text(json.dumps({"format": "hailstorm-storm-output", "version": 1,
                                                  "files": ["summary.json"]}))
    with pytest.raises(OutputError, match="written by another run while this storm ran") as err:
        mine.finish(result)
    kept = Path(str(err.value).rsplit(" ", 1)[-1])
    assert json.loads((kept / "summary.json").read_text())["seed"] == 2
    assert json.loads((out / "summary.json").read_text()) == {"seed": 1}


# ---- messages -------------------------------------------------------------------------


def test_file_too_large_names_the_output(seat_bundle, tmp_path, capsys, monkeypatch):
    """A write's EFBIG carries no file name: the one line names --out (and the limit)."""
    import errno

    import hailstorm.runtime.output.storm_output as files

    def too_large(self, frame):
        raise OSError(errno.EFBIG, os.strerror(errno.EFBIG))

    from hailstorm.runtime.output.vtkhdf import VTKHDFSeries

    monkeypatch.setattr(files.ParaviewSeries, "add", too_large)
    monkeypatch.setattr(VTKHDFSeries, "add", too_large)
    out = tmp_path / "out"
    rc = main(["storm", "--gf", str(seat_bundle), "--out", str(out), *TINY])
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert rc == EXIT_INPUT and len(lines) == 1, lines
    assert f"writing {out}: File too large" in lines[0] and "size limit" in lines[0]
    assert list(tmp_path.iterdir()) == []


def _pair_peak(gf, d, integrator="exact", r=0.005, v0=5.0):
    """Peak contact force of two stones ``d`` apart dropped together on the seat's top."""
    from hailstorm.runtime.storm.scene import Scene
    from hailstorm.runtime.storm.driver import Storm

    c = np.asarray(gf.vertices)[int(np.argmax(np.asarray(gf.vertices)[:, 2]))]
    sc = Scene.from_flat(duration=0.05, stones=0, integrator=integrator)
    st = Storm(gf, sc, spawn=False)
    st.add_stones(np.array([c + [-d / 2, 0, r + 2e-3], c + [d / 2, 0, r + 2e-3]]), np.tile([0.0, 0.0, -v0], (2, 1)),
                  np.full(2, r))
    for _ in range(int(0.02 / sc.time.dt)):
        st.step()
    return st.stats.max_contact_force


def test_two_stones_nearly_coincident_peak_force_is_bounded(seat_bundle):
    """A report gave 952 N for two stones 1e-7 m apart under the exact integrator
    (4.6 N at 0 and 1e-9 m). Not reproduced here (the configuration was not recorded):
    this documents and bounds it -- on the seat's top, at 0 to 1e-5 m apart, the peak is
    that of the coincident pair within 5 % (measured: 10.27 N at every distance on the
    15 mm seat: the two contacts share their point and its normal, the smooth surface's
    there; with a normal from each centre's direction to that point, 1e-7 m apart gave 21.2 N)."""
    from hailstorm.runtime.bundle.read import load

    gf = load(seat_bundle)
    peaks = {d: _pair_peak(gf, d) for d in (0.0, 1e-9, 1e-7, 1e-5)}
    ref = peaks[0.0]
    assert np.isfinite(ref) and ref > 0
    assert all(abs(p - ref) <= 0.05 * ref for p in peaks.values()), peaks


def test_sigterm_wrapped_by_a_compiled_kernel_still_ends_as_sigterm(monkeypatch, capsys):
    """A SIGTERM whose exception is raised while a numba dispatcher returns surfaces as a
    SystemError ("returned a result with an exception set"): still exit 143, one line.
    The signal is sent to this process for real; the wrapper is what the dispatcher does."""
    import os
    import signal as _signal

    import hailstorm.cli as cli

    def storm_killed_in_a_kernel(args):
        try:
            os.kill(os.getpid(), _signal.SIGTERM)
            for _ in range(10_000):  # the handler runs at the next bytecode boundary
                pass
        except BaseException as exc:
            raise SystemError("CPUDispatcher(<function step>) returned a result with an exception set") from exc
        raise AssertionError("SIGTERM was not delivered")

    monkeypatch.setattr(cli, "_run_storm", storm_killed_in_a_kernel)
    previous = _signal.getsignal(_signal.SIGTERM), _signal.getsignal(_signal.SIGHUP)
    assert cli.main(["storm", "-q"]) == 143
    assert capsys.readouterr().err.strip().splitlines() == ["hailstorm: terminated (SIGTERM)"]
    assert (_signal.getsignal(_signal.SIGTERM), _signal.getsignal(_signal.SIGHUP)) == previous  # put back


def test_a_scene_file_and_the_command_line_are_checked_together(tmp_path, seat_bundle):
    """A scene with dt = 1 s run with --duration 2 was refused ("dt (1.0 s) must not exceed
    duration (0.2 s)": the file was checked against its default duration before the option
    applied); the two are now checked together, and a file alone is still refused."""
    from hailstorm.runtime.storm.scene import Scene, SceneError

    path = tmp_path / "dt1.toml"
    path.write_text("[time]\ndt = 1.0\n")
    scene = Scene.from_toml(path, overrides={"storm": {"duration": 2.0}})
    assert scene.time.dt == 1.0 and scene.storm.duration == 2.0
    with pytest.raises(SceneError, match=r"dt1.toml: dt \(1.0 s\) must not exceed duration \(0.2 s\)"):
        Scene.from_toml(path)
    with pytest.raises(SceneError, match="dt1.toml with the command line's options: dt"):
        Scene.from_toml(path, overrides={"storm": {"duration": 0.5}})
    out = tmp_path / "out"
    assert main(["storm", "--gf", str(seat_bundle), "--scene", str(path), "--duration", "2", "--stones", "3",
                 "--no-video", "-q", "--out", str(out)]) == 0
    assert json.loads((out / "summary.json").read_text())["sim_time_s"] == pytest.approx(2.0)


def test_a_swallowed_signal_still_ends_the_storm(seat_bundle, tmp_path, monkeypatch, capsys):
    """A termination signal whose exception Python swallowed (raised inside a callback from C,
    numba's compiler's: only the handler's record of it survives) still ends the storm as that
    signal at its next frame: one line, exit 128 + its number, nothing put in place, and the
    unraisable hook as it was."""
    import signal as _signal

    import hailstorm.cli as cli
    from hailstorm.runtime.output.storm_output import StormOutput

    real_add = StormOutput.add
    seen = []

    def add(self, frame):
        seen.append(frame.t)
        if len(seen) == 2:  # the handler ran, its exception was lost on the way
            cli._RECEIVED.append(int(_signal.SIGTERM))
        return real_add(self, frame)

    monkeypatch.setattr(StormOutput, "add", add)
    hook = sys.unraisablehook
    out = tmp_path / "out"
    rc = main(["storm", "--gf", str(seat_bundle), "--out", str(out), "--duration", "0.05", "--stones", "2",
               "--no-video", "-q"])
    assert rc == 128 + int(_signal.SIGTERM)
    assert capsys.readouterr().err.strip().splitlines() == ["hailstorm: terminated (SIGTERM)"]
    assert len(seen) == 2  # ended at the frame after
    assert not out.exists() and list(tmp_path.iterdir()) == []
    assert sys.unraisablehook is hook
