"""Bad input to the offline stage and to bundles: refused with one line (exit 3), nothing lost.

Table-driven: each CLI row is (arguments, expected part of the one-line error); the
CLI runs in-process (``hailstorm.cli.main``). API rows check the exception type.
Also: writers' locks, temporaries of killed writers, stranded bundles, Ctrl-C while
meshing.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from hailstorm.precompute import build_bundle
from hailstorm.precompute.geometry import MeshError, TetMesh, check_clamped, check_mesh, read_mesh
from hailstorm.runtime.bundle.read import load
from hailstorm.runtime.bundle.format import (
    ARRAY_SPECS,
    FORMAT_VERSION,
    MANIFEST,
    MANIFEST_HASH,
    BundleError,
    array_hash,
    bundle_files,
    manifest_hash,
)
from hailstorm.runtime.bundle.write import bundle_lock, clean_stale_temporaries
from hailstorm.cli import main

ROOT = Path(__file__).resolve().parents[2]


# ----------------------------------------------------------------------------- small meshes

def _tet(origin, s=1.0):
    o = np.asarray(origin, float)
    return [o, o + [s, 0, 0], o + [0, s, 0], o + [0, 0, s]]


def _two_tets(kind: str) -> TetMesh:
    """Tet 0 clamped on its z = 0 face; tet 1 free: apart, hinged on an edge, or sharing a face."""
    pts = _tet([0, 0, 0])
    if kind == "apart":
        pts += _tet([3, 0, 0])
        tets = [[0, 1, 2, 3], [4, 5, 6, 7]]
    elif kind == "edge":  # shares the edge 0-1 only
        pts += [np.array([0.5, -1.0, 0.2]), np.array([0.5, -0.5, 1.0])]
        tets = [[0, 1, 2, 3], [0, 1, 4, 5]]
    elif kind == "face":  # shares the face 1-2-3
        pts += [np.array([1.0, 1.0, 1.0])]
        tets = [[0, 1, 2, 3], [1, 2, 3, 4]]
    else:  # "duplicate"
        tets = [[0, 1, 2, 3], [0, 1, 2, 3]]
    points = np.array(pts, float)
    tets = np.array(tets, np.int64)
    vol = np.einsum("ij,ij->i", np.cross(points[tets[:, 1]] - points[tets[:, 0]], points[tets[:, 2]] - points[tets[:, 0]]),
                    points[tets[:, 3]] - points[tets[:, 0]])
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    from hailstorm.precompute.geometry import boundary_triangles

    bnd = boundary_triangles(tets) if kind != "duplicate" else np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    on_clamp = np.all(np.isin(bnd, [0, 1, 2]), axis=1)
    return TetMesh(points, tets, {"clamp": bnd[on_clamp], "top": bnd[~on_clamp]}, source=f"two-tets-{kind}")


def _write_msh(mesh: TetMesh, path: Path, groups=("clamp", "top")) -> Path:
    import meshio

    tris = [mesh.groups[g] for g in groups]
    tags = [np.full(len(t), k + 1) for k, t in enumerate(tris)]
    cells = [("triangle", np.concatenate(tris)), ("tetra", mesh.tets)]
    phys = [np.concatenate(tags), np.full(len(mesh.tets), 10)]
    field = {g: np.array([k + 1, 2]) for k, g in enumerate(groups)}
    field["body"] = np.array([10, 3])
    meshio.write(path, meshio.Mesh(mesh.points, cells, cell_data={"gmsh:physical": phys, "gmsh:geometrical": phys},
                                   field_data=field), file_format="gmsh22", binary=False)
    return path


def _run(args, capsys) -> tuple[int, str, str]:
    try:
        rc = main([str(a) for a in args])
    except SystemExit as exc:
        rc = exc.code
    out, err = capsys.readouterr()
    return rc, out, err


def _assert_one_line_error(rc, err, message):
    assert rc == 3, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("hailstorm: error: "), err
    assert message in lines[0], lines[0]
    assert "Traceback" not in err


# ----------------------------------------------------------------------------- precompute rows

def _make(kind: str, tmp: Path):
    """Set up the input of one row; returns (extra arguments, files that must survive)."""
    if kind in ("apart", "edge", "duplicate"):
        return ["--geometry", _write_msh(_two_tets(kind), tmp / f"{kind}.msh")], {}
    if kind == "far-node":  # a node sent to z = 1e308: refused as far, not as a degenerate tetrahedron
        mesh = _two_tets("face")
        mesh.points[4, 2] = 1e308
        return ["--geometry", _write_msh(mesh, tmp / "far.msh")], {}
    if kind == "no-top":
        return ["--geometry", _write_msh(_two_tets("face"), tmp / "notop.msh", groups=("clamp",))], {}
    if kind == "text-msh":
        (tmp / "notes.msh").write_text("these are my notes, not a mesh\n")
        return ["--geometry", tmp / "notes.msh"], {}
    if kind == "geometry-dir":
        return ["--geometry", tmp], {}
    if kind == "user-files":
        out = tmp / "out"
        out.mkdir()
        (out / "NOTES.txt").write_text("mine")
        (out / "results").mkdir()
        (out / "results" / "run1.csv").write_text("1,2")
        return [], {out / "NOTES.txt": "mine", out / "results" / "run1.csv": "1,2"}
    if kind == "fake-manifest":
        out = tmp / "out"
        out.mkdir()
        (out / MANIFEST).write_text('{"format": "hailstorm-greens-bundle"}')
        return [], {out / MANIFEST: '{"format": "hailstorm-greens-bundle"}'}
    if kind == "long-out":  # a legal name, too long for the writer's temporaries beside it
        return ["--out", tmp / ("b" * 245)], {}
    if kind == "out-is-file":
        (tmp / "out").write_text("a file")
        return [], {tmp / "out": "a file"}
    if kind == "out-under-file":
        (tmp / "parent").write_text("a file")
        return ["--out", tmp / "parent" / "b"], {tmp / "parent": "a file"}
    return [], {}


PRECOMPUTE_ROWS = [
    # (row, extra args, expected part of the error)
    ("apart", [], "2 parts connected through shared faces, and 1 of them touch no 'clamp' face: part 2"),
    ("edge", [], "2 parts connected through shared faces"),
    ("duplicate", [], "duplicated tetrahedra"),
    ("no-top", [], "notop.msh: the mesh has no surface group 'top'"),
    ("far-node", [], "node 4 lies at [1.0, 1.0, 1e+308], beyond 1e+06 m of the origin"),
    ("text-msh", [], "meshio could not read"),
    ("geometry-dir", [], "is a directory"),
    ("nu-minus-one", ["--poisson", "-1"], "nu <= -1 is not a stable material"),
    ("nu-below", ["--poisson", "-3"], "nu <= -1 is not a stable material"),
    ("nu-half", ["--poisson", "0.5"], "incompressible"),
    ("huge", ["--mesh-size", "1e-5"], "--allow-large"),
    ("user-files", [], "(NOTES.txt, results)"),
    ("fake-manifest", [], "not a complete hailstorm bundle"),
    ("out-is-file", [], "is not a directory"),
    ("long-out", [], "is 245 bytes long; hailstorm writes beside it under the name plus 14"),
    ("out-under-file", [], "is not a directory"),
]


@pytest.mark.parametrize("row, extra, message", PRECOMPUTE_ROWS, ids=[r[0] for r in PRECOMPUTE_ROWS])
def test_precompute_bad_input_is_one_line_exit_3(row, extra, message, tmp_path, capsys, monkeypatch):
    import hailstorm.precompute.pipeline as pipeline

    def no_assembly(*a, **k):  # every refusal comes before the expensive work
        raise AssertionError("assembled although the input is bad")

    monkeypatch.setattr(pipeline, "elasticity_basis", no_assembly)
    args, survivors = _make(row, tmp_path)
    if "--out" not in args:
        args += ["--out", tmp_path / "out"]
    rc, _, err = _run(["precompute", "-q", *args, *extra], capsys)
    _assert_one_line_error(rc, err, message)
    for f, text in survivors.items():
        assert f.read_text() == text  # nothing of the user's is lost
    if row == "fake-manifest":
        assert sorted(os.listdir(tmp_path / "out")) == [MANIFEST]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporaries, no lock


def test_read_only_output_is_refused_before_the_work(tmp_path, capsys, monkeypatch):
    """--out under a read-only directory: one line, exit 3, before meshing (not after the whole computation)."""
    import tempfile

    import hailstorm.precompute.geometry as geometry

    def no_meshing(*a, **k):
        raise AssertionError("meshed although the output is unwritable")

    monkeypatch.setattr(geometry, "mesh_geometry", no_meshing)
    ro = tmp_path / "ro"
    ro.mkdir()
    os.chmod(ro, 0o555)
    if os.geteuid() == 0:  # root writes anywhere: make the directory refuse as it would refuse a user
        real = tempfile.mkstemp

        def mkstemp(*a, dir=None, **k):
            if dir is not None and Path(dir) == ro:
                raise PermissionError(13, "Permission denied", str(ro))
            return real(*a, dir=dir, **k)

        monkeypatch.setattr(tempfile, "mkstemp", mkstemp)
    try:
        rc, _, err = _run(["precompute", "-q", "--out", ro / "sub" / "b"], capsys)
    finally:
        os.chmod(ro, 0o755)
    _assert_one_line_error(rc, err, "cannot write a bundle in")
    assert "Permission denied" in err and os.listdir(ro) == []


def test_cache_that_is_a_file_is_refused(tmp_path, small_box, monkeypatch):
    (tmp_path / "cache").write_text("not a directory")
    monkeypatch.setenv("HAILSTORM_CACHE", str(tmp_path / "cache"))
    with pytest.raises(BundleError, match="is not a directory"):
        build_bundle(None, mesh=small_box)
    assert (tmp_path / "cache").read_text() == "not a directory"


# ----------------------------------------------------------------------------- API rows of the offline stage

@pytest.mark.parametrize("kind, message", [
    ("apart", "1 of them touch no 'clamp' face"),
    ("edge", "a shared edge or vertex is only a hinge"),
    ("duplicate", "duplicated tetrahedra"),
])
def test_unclamped_or_duplicated_meshes_are_refused_by_the_api(kind, message, tmp_path):
    with pytest.raises(MeshError, match=message):
        build_bundle(tmp_path / "b", mesh=_two_tets(kind))
    assert not (tmp_path / "b").exists()


def test_parts_sharing_a_face_are_one_part():
    check_clamped(check_mesh(_two_tets("face")))  # clamped through the shared face: accepted


def test_meshio_exit_is_a_mesh_error(tmp_path):
    (tmp_path / "x.msh").write_text("not a mesh")
    with pytest.raises(MeshError, match="meshio could not read"):
        read_mesh(tmp_path / "x.msh")


def test_memory_estimate_refuses_and_allow_large_overrides(small_box, tmp_path, monkeypatch):
    import hailstorm.precompute.resources as resources

    monkeypatch.setattr(resources, "available_memory", lambda: 10 * 2**20)
    with pytest.raises(resources.TooLargeError, match="allow_large=True"):
        build_bundle(tmp_path / "b", mesh=small_box)
    assert not (tmp_path / "b").exists()
    load(build_bundle(tmp_path / "b", mesh=small_box, allow_large=True))
    # the estimate of a mesh is exact in D
    gf = load(tmp_path / "b")
    est = resources.estimate_mesh(gf.n_vertices, int(gf.contactable.sum()), gf.volume_points.shape[0])
    assert est.d_bytes == gf.D.nbytes


def test_geometry_estimate_bounds_the_default_seat():
    """Before meshing, the estimate of D must not be below what meshing gives (4-15 mm)."""
    from hailstorm.precompute.geometry import _gmsh_session, _measure, default_seat_path, mesh_default_seat
    from hailstorm.precompute.pipeline import extract_surface
    from hailstorm.precompute.resources import estimate_geometry

    gmsh = _gmsh_session()
    try:
        gmsh.open(str(default_seat_path()))
        names = {gmsh.model.getPhysicalName(d, t): (d, t) for d, t in gmsh.model.getPhysicalGroups()}
        area_top, area_all, volume, _ = _measure(gmsh, names)
    finally:
        gmsh.finalize()
    for h in (0.015, 0.008):
        s = extract_surface(mesh_default_seat(h))
        est = estimate_geometry(area_top, area_all, volume, h)
        actual = 72 * s.nodes.size * int(s.contactable.sum())
        assert actual <= est.d_bytes <= 4 * actual


def test_mesh_size_larger_than_the_body_warns(caplog):
    from hailstorm.precompute.geometry import mesh_default_seat

    with caplog.at_level(logging.WARNING):
        mesh_default_seat(0.08)
    assert any("larger than the body's smallest extent" in r.getMessage() for r in caplog.records)


def test_one_default_mesh_size():
    from hailstorm.precompute.pipeline import DEFAULT_MESH_SIZE
    from hailstorm.cli import _parser
    from hailstorm.runtime.storm.scene import SeatSettings

    assert SeatSettings.default().mesh_size == DEFAULT_MESH_SIZE
    assert _parser().parse_args(["precompute", "--out", "x"]).mesh_size == DEFAULT_MESH_SIZE


def test_the_precompute_command_builds_the_default_seats_discretisation():
    """``hailstorm precompute`` without options is the default storm's seat (P2, hat-load columns:
    chosen by measured accuracy, with the near field), not the cheaper P1 of the library's ``build_bundle``."""
    from hailstorm.cli import _parser
    from hailstorm.runtime.storm.scene import SeatSettings

    seat, args = SeatSettings.default(), _parser().parse_args(["precompute", "--out", "x"])
    assert (args.order, args.load, args.volume_size) == (seat.order, seat.load, seat.volume_size) == (2, "hat", None)


# ----------------------------------------------------------------------------- bundle rows (info / load)

def _rehash(m: dict) -> dict:
    m[MANIFEST_HASH] = manifest_hash(m)
    return m


def _edit(b: Path, fn, rehash: bool = False) -> None:
    m = json.loads((b / MANIFEST).read_text())
    m = fn(m)
    if rehash and isinstance(m, dict):
        _rehash(m)
    (b / MANIFEST).write_text(json.dumps(m))


def _nan_in_d(b: Path) -> None:
    D = np.load(b / "compliance.npy")
    D = np.asfortranarray(D)
    D[0, 0] = np.nan
    np.save(b / "compliance.npy", D)
    m = json.loads((b / MANIFEST).read_text())
    m["arrays"]["compliance"].update(sha256=array_hash(D), bytes=(b / "compliance.npy").stat().st_size)
    (b / MANIFEST).write_text(json.dumps(_rehash(m)))


def _setitem(m, path, value):
    d = m
    for k in path[:-1]:
        d = d[k]
    d[path[-1]] = value
    return m


def _delitem(m, path):
    d = m
    for k in path[:-1]:
        d = d[k]
    del d[path[-1]]
    return m


BUNDLE_ROWS = [
    # (row, damage, expected part of the error)
    ("edited-young", lambda b: _edit(b, lambda m: _setitem(m, ["material", "young"], 5e6)), "does not match its hash"),
    ("manifest-list", lambda b: _edit(b, lambda m: [m]), "is a JSON list"),
    ("arrays-null", lambda b: _edit(b, lambda m: _setitem(m, ["arrays"], None), rehash=True), "'arrays'"),
    ("no-material", lambda b: _edit(b, lambda m: _delitem(m, ["material"]), rehash=True), "'material'"),
    ("young-text", lambda b: _edit(b, lambda m: _setitem(m, ["material", "young"], "soft"), rehash=True),
     "'material.young'"),
    ("no-key", lambda b: _edit(b, lambda m: _delitem(m, ["key"]), rehash=True), "'key'"),
    ("entry-no-file", lambda b: _edit(b, lambda m: _delitem(m, ["arrays", "areas", "file"]), rehash=True),
     "'arrays.areas.file'"),
    ("file-outside", lambda b: _edit(b, lambda m: _setitem(m, ["arrays", "areas", "file"], "../areas.npy"),
                                     rehash=True), "a file name inside the bundle"),
    ("timings-text", lambda b: _edit(b, lambda m: _setitem(m, ["timings_s", "solve"], "fast"), rehash=True),
     "'timings_s.solve'"),
    ("appended-bytes", lambda b: (b / "compliance.npy").open("ab").write(b"\0" * 16), "bytes, manifest says"),
    ("nan-in-D", _nan_in_d, "non-finite"),
]


@pytest.mark.parametrize("row, damage, message", BUNDLE_ROWS, ids=[r[0] for r in BUNDLE_ROWS])
def test_info_on_a_damaged_bundle_is_one_line_exit_3(row, damage, message, box_bundle, tmp_path, capsys):
    b = Path(shutil.copytree(box_bundle, tmp_path / "b"))
    damage(b)
    rc, _, err = _run(["info", b], capsys)
    _assert_one_line_error(rc, err, message)
    with pytest.raises(BundleError, match=message.replace("(", r"\(").replace(")", r"\)")):
        load(b)


def test_info_says_what_it_verified(box_bundle, capsys):
    rc, out, _ = _run(["info", box_bundle], capsys)
    assert rc == 0 and "verified manifest hash" in out and "SHA-256" in out and "D finite" in out


def test_info_into_a_closed_pipe_is_quiet(box_bundle):
    """`hailstorm info B | head -1`: the reader leaves early; no traceback."""
    p = subprocess.Popen([sys.executable, "-m", "hailstorm.cli", "info", str(box_bundle)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, env={**os.environ, "PYTHONPATH": str(ROOT)})
    p.stdout.close()  # before the child has printed anything
    err = p.stderr.read().decode()
    p.wait(timeout=120)
    assert "Traceback" not in err and "BrokenPipe" not in err, err
    assert p.returncode == 0


def test_writing_a_nan_compliance_is_refused(box_bundle, tmp_path):
    from hailstorm.runtime.bundle.write import write_bundle

    gf = load(box_bundle)
    arrays = {name: np.array(getattr(gf, name if name != "compliance" else "D")) for name in ARRAY_SPECS}
    arrays["compliance"][3, 1] = np.inf
    with pytest.raises(BundleError, match="compliance holds 1 non-finite"):
        write_bundle(tmp_path / "nan", arrays, {"key": "x", "options": {"order": 1}, "material": gf.manifest["material"]})
    assert not (tmp_path / "nan").exists()


def test_writing_a_manifest_load_would_refuse_is_refused(box_bundle, tmp_path):
    from hailstorm.runtime.bundle.write import write_bundle

    gf = load(box_bundle)
    arrays = {name: np.asarray(getattr(gf, name if name != "compliance" else "D")) for name in ARRAY_SPECS}
    with pytest.raises(BundleError, match="'material'"):
        write_bundle(tmp_path / "b", arrays, {"key": "x", "options": {"order": 1}})
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- replacing, debris, locks

def test_rebuilding_replaces_a_bundle_but_never_user_files(small_box, tmp_path):
    out = build_bundle(tmp_path / "b", mesh=small_box, young=1e6)
    build_bundle(out, mesh=small_box, young=2e6)  # a bundle of bundle files: replaced
    assert load(out).young == 2e6 and set(os.listdir(out)) == bundle_files(FORMAT_VERSION)
    (out / "NOTES.txt").write_text("mine")
    with pytest.raises(BundleError, match=r"\(NOTES.txt\)"):
        build_bundle(out, mesh=small_box, young=3e6)
    assert (out / "NOTES.txt").read_text() == "mine" and load(out).young == 2e6


def _stale_copy(src: Path, parent: Path, name: str) -> Path:
    d = parent / name
    shutil.copytree(src, d)
    return d


def test_stale_temporaries_are_removed_and_user_lookalikes_kept(box_bundle, small_box, tmp_path):
    _stale_copy(box_bundle, tmp_path, ".b.tmp-abc123")  # a killed writer of b
    part = tmp_path / ".other.tmp-xyz"  # a writer of another bundle, killed early
    part.mkdir()
    shutil.copy(box_bundle / "areas.npy", part)
    (tmp_path / ".other.lock").write_text("12345\n")  # its lock file, not held
    mine = tmp_path / ".x.tmp-mine"
    mine.mkdir()
    (mine / "thesis.tex").write_text("mine")  # the user's, with a look-alike name
    build_bundle(tmp_path / "b", mesh=small_box)
    assert sorted(p.name for p in tmp_path.iterdir()) == [".x.tmp-mine", "b"]
    assert (mine / "thesis.tex").read_text() == "mine"


@pytest.mark.parametrize("left", [("tmp", "old"), ("old",), ("tmp",)])
def test_bundle_stranded_between_the_renames_is_recovered(box_bundle, tmp_path, left):
    """A writer killed after `out -> .out.old-*` and before `.out.tmp-* -> out`."""
    new = _stale_copy(box_bundle, tmp_path, ".b.tmp-new") if "tmp" in left else None
    if "old" in left:
        old = _stale_copy(box_bundle, tmp_path, ".b.old-prev")
        _edit(old, lambda m: _setitem(m, ["key"], "previous"), rehash=True)
    before = sorted(p.name for p in tmp_path.iterdir())
    with pytest.raises(BundleError, match=r"interrupted .* left it at .*\.b\.(tmp|old)-.*hailstorm precompute"):
        load(tmp_path / "b")  # reading changes nothing: the copy is named, not moved
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    clean_stale_temporaries(tmp_path)  # what the next writer does first
    gf = load(tmp_path / "b")
    assert gf.manifest["key"] == ("previous" if new is None else load(box_bundle).manifest["key"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b"]


_KILLABLE_WRITER = """
import sys, time, pathlib, numpy as np
from hailstorm.precompute import box_mesh, build_bundle
real, n = np.save, [0]
def slow_save(fh, a, **k):
    real(fh, a, **k)
    n[0] += 1
    if n[0] == 3:
        pathlib.Path(sys.argv[2]).write_text("writing")
        time.sleep(600)
np.save = slow_save
build_bundle(sys.argv[1], mesh=box_mesh((0.1, 0.1, 0.05), 0.02))
"""


def _start_writer(out: Path, flag: Path) -> subprocess.Popen:
    p = subprocess.Popen([sys.executable, "-c", _KILLABLE_WRITER, str(out), str(flag)],
                         env={**os.environ, "PYTHONPATH": str(ROOT)}, stderr=subprocess.PIPE)
    for _ in range(1200):
        if flag.exists() or p.poll() is not None:
            break
        time.sleep(0.05)
    assert flag.exists(), p.stderr.read().decode() if p.poll() is not None else "writer did not start writing"
    return p


def test_sigkill_mid_write_leaves_debris_the_next_writer_removes(small_box, tmp_path):
    out = tmp_path / "b"
    p = _start_writer(out, tmp_path / "flag")
    clean_stale_temporaries(tmp_path)  # a live writer: its temporary stays
    assert [q.name for q in tmp_path.iterdir() if q.name.startswith(".b.tmp-")]
    p.kill()
    p.wait(timeout=60)
    assert [q.name for q in tmp_path.iterdir() if q.name.startswith(".b.tmp-")]  # kill -9 leaves it
    build_bundle(out, mesh=small_box)
    assert sorted(q.name for q in tmp_path.iterdir()) == ["b", "flag"]
    load(out)


def test_a_second_writer_waits_for_the_first(small_box, tmp_path, caplog):
    out = tmp_path / "b"
    done = {}
    with bundle_lock(out):
        refused = []

        def try_at_once():
            try:
                with bundle_lock(out, wait=False):
                    pass
            except BundleError as exc:
                refused.append(str(exc))

        other = threading.Thread(target=try_at_once)
        other.start()
        other.join(timeout=60)
        assert refused and "being written by another process (pid" in refused[0]
        t = threading.Thread(target=lambda: done.setdefault("path", build_bundle(out, mesh=small_box)))
        with caplog.at_level(logging.INFO):
            t.start()
            for _ in range(2400):
                if any("waiting for another hailstorm" in r.getMessage() for r in caplog.records):
                    break
                time.sleep(0.05)
            assert any("waiting for another hailstorm" in r.getMessage() for r in caplog.records)
            assert "path" not in done and not out.exists()
    t.join(timeout=300)
    assert done["path"] == out and load(out).n_vertices > 0
    assert sorted(q.name for q in tmp_path.iterdir()) == ["b"]  # the lock file went with the lock


def _build_in_process(out, young):
    from hailstorm.precompute import box_mesh

    try:
        build_bundle(out, mesh=box_mesh((0.1, 0.1, 0.05), 0.02), young=young)
    except BundleError as exc:  # waited for a writer with other inputs: refused, not handed its bundle
        assert "was just written by another run with other inputs" in str(exc)
        sys.exit(3)


def test_two_processes_writing_one_bundle(tmp_path):
    import multiprocessing as mp

    out = tmp_path / "b"
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=_build_in_process, args=(out, e)) for e in (1e6, 2e6, 1e6)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(timeout=300)
    # each writer either wrote (or reused) its own bundle or was refused with the one-line
    # reason (never silently handed the other's bundle); at least one wrote
    codes = [p.exitcode for p in procs]
    assert set(codes) <= {0, 3} and 0 in codes, codes
    assert load(out).young in (1e6, 2e6)
    assert sorted(q.name for q in tmp_path.iterdir()) == ["b"]


@pytest.mark.skipif(not hasattr(signal, "SIGINT"), reason="POSIX signals")
def test_ctrl_c_while_meshing_ends_the_process(tmp_path):
    """SIGINT during gmsh's meshing ends the run promptly, with nothing left behind."""
    code = ("import logging, sys; logging.basicConfig(level=logging.INFO)\n"
            "from hailstorm.precompute import build_bundle\n"
            "build_bundle(sys.argv[1], mesh_size=0.0006, allow_large=True)\n")
    # (a job started in the background by a non-interactive shell, as CI may be, inherits
    # SIGINT ignored, and an ignored SIGINT is rightly left ignored: give the child the default)
    p = subprocess.Popen([sys.executable, "-c", code, str(tmp_path / "b")], stderr=subprocess.PIPE, text=True,
                         env={**os.environ, "PYTHONPATH": str(ROOT)},
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    seen = []

    def read():
        for line in p.stderr:
            seen.append(line)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    for _ in range(12000):  # a loaded machine can take minutes to import gmsh and read the geometry
        if any("meshing" in s for s in seen) or p.poll() is not None:
            break
        time.sleep(0.05)
    assert any("meshing" in s for s in seen), f"meshing never started: {seen}"
    time.sleep(0.5)  # inside gmsh's generate
    p.send_signal(signal.SIGINT)
    try:
        p.wait(timeout=60)
    except subprocess.TimeoutExpired:
        p.kill()
        p.wait()
        pytest.fail("Ctrl-C did not stop the meshing")
    assert any("meshing" in s for s in seen), seen
    assert p.returncode != 0
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- the supernodal solver's fallback

def _contrast_box(contrast: float):
    """The small box in two materials, the lower half ``contrast`` times stiffer."""
    from hailstorm.precompute import box_mesh

    mesh = box_mesh((0.1, 0.1, 0.05), 0.02)
    c = mesh.points[mesh.tets].mean(axis=1)[:, 2]
    mesh = TetMesh(mesh.points, mesh.tets, mesh.groups, mesh.source,
                   {"hard": np.flatnonzero(c < 0.025), "soft": np.flatnonzero(c >= 0.025)})
    return mesh, {"soft": (1e6, 0.3), "hard": (1e6 * contrast, 0.3)}


def test_supernodal_falls_back_to_cholmod_when_the_pattern_cannot_be_recovered(tmp_path, monkeypatch, caplog):
    """A 1e18 stiffness contrast can cancel factor entries to exact zeros whose pattern the
    supernodal solver cannot recover ("the ordering changed"; forced here, the failure
    depends on the rounding): the bundle is built with CHOLMOD instead, with a one-line
    note, and its D is splu's (to the conditioning's rounding: relative 1e-6 of max |D|
    at this contrast)."""
    import hailstorm.precompute.supernodal as supernodal
    from hailstorm.precompute.supernodal import PatternError

    def refuse(A):
        raise PatternError("cannot recover the factor's pattern: the ordering changed")

    mesh, mats = _contrast_box(1e18)
    ref = load(build_bundle(tmp_path / "splu", mesh=mesh, materials=mats, solver="splu"))
    monkeypatch.setattr(supernodal, "supernodal_factor", refuse)
    with caplog.at_level(logging.INFO, logger="hailstorm.precompute.greens"):
        gf = load(build_bundle(tmp_path / "sn", mesh=mesh, materials=mats, solver="supernodal"))
    notes = [r.getMessage() for r in caplog.records if "using CHOLMOD" in r.getMessage()]
    assert len(notes) == 1 and "cannot recover the factor's pattern" in notes[0], caplog.text
    D, R = np.asarray(gf.D), np.asarray(ref.D)
    assert np.abs(D - R).max() <= 1e-6 * np.abs(R).max()



@pytest.mark.parametrize("where", ["supernodal", "cholmod"])
def test_a_non_positive_pivot_falls_back_to_lu(tmp_path, monkeypatch, caplog, where):
    """At a 1e18 stiffness contrast a Cholesky factor can meet a non-positive pivot on an SPD
    matrix (rounding; reported for the layered example with the pad at 1e24 Pa, forced here):
    the bundle is built with SuperLU's LU instead, with a one-line note, its D splu's (to the
    conditioning's rounding, as above), and no work directory left behind."""
    import hailstorm.precompute.supernodal as supernodal

    def not_pd(*args, **kwargs):
        raise np.linalg.LinAlgError("the matrix is not positive definite (a non-positive pivot)")

    mesh, mats = _contrast_box(1e18)
    ref = load(build_bundle(tmp_path / "splu", mesh=mesh, materials=mats, solver="splu"))
    monkeypatch.setattr(supernodal, "supernodal_factor", not_pd)
    if where == "cholmod":
        import cholespy

        def cholmod_not_pd(*args):
            raise ValueError("Matrix is not positive definite!")  # cholespy's words

        monkeypatch.setattr(cholespy, "CholeskySolverD", cholmod_not_pd)
    with caplog.at_level(logging.INFO, logger="hailstorm.precompute.greens"):
        gf = load(build_bundle(tmp_path / "b", mesh=mesh, materials=mats, solver=where))
    notes = [r.getMessage() for r in caplog.records if "using SuperLU's LU" in r.getMessage()]
    assert len(notes) == 1 and "not positive definite" in notes[0], caplog.text
    D, R = np.asarray(gf.D), np.asarray(ref.D)
    assert np.abs(D - R).max() <= 1e-6 * np.abs(R).max()
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == []



def test_a_solve_that_fails_before_any_block_leaves_no_work_directory(small_box, tmp_path, monkeypatch):
    """An error in the solve before the first block (here every factorization refused) is
    reported and leaves no ``.NAME.work`` behind: there is nothing to resume."""
    import hailstorm.precompute.greens as greens

    def broken(A, solver="supernodal", **kw):
        raise RuntimeError("no factor today")

    monkeypatch.setattr(greens, "factorize", broken)
    with pytest.raises(RuntimeError, match="no factor today"):
        build_bundle(tmp_path / "b", mesh=small_box)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- bundles

def test_replacing_a_read_only_bundle_removes_its_old_copy(small_box, tmp_path):
    """The replaced bundle was read-only: its old copy (``.b.tmp-*`` after the exchange) is
    made writable and removed, not left hidden (as a non-root user the old code left it)."""
    out = build_bundle(tmp_path / "b", mesh=small_box, young=1e6)
    for p in [*out.iterdir(), out]:
        p.chmod(0o555 if p.is_dir() else 0o444)
    build_bundle(tmp_path / "b", mesh=small_box, young=2e6)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b"]
    assert load(tmp_path / "b").manifest["material"]["young"] == 2e6


def test_an_old_copy_that_cannot_be_removed_is_reported(small_box, tmp_path, monkeypatch, caplog):
    """The removal's failure is reported (one warning naming the copy), not ignored."""
    import hailstorm.runtime.bundle.write as write

    build_bundle(tmp_path / "b", mesh=small_box, young=1e6)
    real = shutil.rmtree

    def failing(path, *a, **k):
        if ".b.tmp-" in str(path) or ".b.old-" in str(path):
            return None  # nothing removed, no exception: as a read-only copy for a non-root user
        return real(path, *a, **k)

    monkeypatch.setattr(write.shutil, "rmtree", failing)
    with caplog.at_level(logging.WARNING):
        build_bundle(tmp_path / "b", mesh=small_box, young=2e6)
    monkeypatch.undo()
    left = [p.name for p in tmp_path.iterdir() if p.name.startswith(".b.")]
    warned = [r.getMessage() for r in caplog.records if "could not be removed" in r.getMessage()]
    assert len(left) == 1 and len(warned) == 1 and left[0] in warned[0], (left, caplog.text)


def _fake_work_dir(out: Path) -> Path:
    """What a replacement of ``out`` killed mid-way leaves: the work directory's own files."""
    from hailstorm.precompute.blocks import work_dir

    w = work_dir(out)
    (w / "blocks").mkdir(parents=True)
    (w / "blocks" / "0.json").write_text("{}")
    (w / "compliance.npy").write_bytes(b"\0" * 4096)
    (w / "work.json").write_text('{"key": "other inputs"}')
    return w


def test_an_up_to_date_reuse_removes_a_killed_replacements_work_directory(small_box, tmp_path):
    out = build_bundle(tmp_path / "b", mesh=small_box)
    w = _fake_work_dir(out)
    assert build_bundle(tmp_path / "b", mesh=small_box) == out  # reused
    assert not w.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b"]


def test_a_disk_full_refusal_leaves_no_work_directory(small_box, tmp_path, monkeypatch):
    import collections

    import hailstorm.precompute.resources as resources
    from hailstorm.precompute.resources import TooLargeError

    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(resources.shutil, "disk_usage", lambda p: usage(10**9, 10**9, 0))
    with pytest.raises(TooLargeError, match="of disk for D"):
        build_bundle(tmp_path / "b", mesh=small_box)
    monkeypatch.undo()
    assert sorted(p.name for p in tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- bundles

def test_a_writer_that_waited_for_another_with_other_inputs_is_refused(small_box, tmp_path, monkeypatch):
    """Two precomputes of one --out with different materials: the one that waited for the
    lock finds the other's fresh bundle and refuses (one line), instead of replacing it
    while the other reports success; the other's bundle stays. (The other writer's run is
    played inside the lock's wait.)"""
    import contextlib

    import hailstorm.precompute.pipeline as pipeline
    from hailstorm.runtime.bundle.write import bundle_lock as real_lock

    out = tmp_path / "b"

    @contextlib.contextmanager
    def lock_after_the_other_writer(path, **kw):
        monkeypatch.setattr(pipeline, "bundle_lock", real_lock)
        build_bundle(out, mesh=small_box, young=1e6)  # the other writer, done while we waited
        with real_lock(path, **kw) as held:
            yield held

    monkeypatch.setattr(pipeline, "bundle_lock", lock_after_the_other_writer)
    with pytest.raises(BundleError, match="was just written by another run with other inputs"):
        build_bundle(out, mesh=small_box, young=3e6)
    assert load(out).manifest["material"]["young"] == 1e6
    # run again (nobody writing now): it replaces the bundle, as a rerun should
    assert load(build_bundle(out, mesh=small_box, young=3e6)).manifest["material"]["young"] == 3e6


def test_a_writer_that_waited_for_another_with_the_same_inputs_reuses_its_bundle(small_box, tmp_path, monkeypatch):
    import contextlib

    import hailstorm.precompute.pipeline as pipeline
    from hailstorm.runtime.bundle.write import bundle_lock as real_lock

    out = tmp_path / "b"

    @contextlib.contextmanager
    def lock_after_the_other_writer(path, **kw):
        monkeypatch.setattr(pipeline, "bundle_lock", real_lock)
        build_bundle(out, mesh=small_box, young=1e6)
        with real_lock(path, **kw) as held:
            yield held

    monkeypatch.setattr(pipeline, "bundle_lock", lock_after_the_other_writer)
    key = load(build_bundle(out, mesh=small_box, young=1e6)).manifest["key"]
    assert load(out).manifest["key"] == key


def test_the_block_example_at_12_mm_p2_builds_with_the_default_solver(tmp_path):
    """A real case whose supernodal pattern check failed ("cannot recover the factor's pattern"):
    the default solver now falls back to CHOLMOD, and D equals CHOLMOD's own to the solves'
    rounding (both direct, the same SPD system)."""
    import hailstorm.runtime

    geo = ROOT / "examples" / "geometries" / "block.geo"
    kw = dict(geometry=geo, mesh_size=0.012, order=2, young=5e5, poisson=0.4)
    a = hailstorm.runtime.load(build_bundle(tmp_path / "default", **kw))
    b = hailstorm.runtime.load(build_bundle(tmp_path / "cholmod", solver="cholmod", **kw))
    Da, Db = np.asarray(a.D), np.asarray(b.D)
    assert Da.shape == Db.shape
    assert np.abs(Da - Db).max() <= 1e-8 * np.abs(Db).max()


def test_a_compression_that_waited_for_another_tolerance_is_refused(small_box, tmp_path, monkeypatch):
    """Two precomputes of one --out at two tolerances (--tol 1e-2 and 1e-3) compress the same dense
    source in place: the one that takes the lock second finds the other's compressed bundle and
    refuses (one line), as two dense writers with other inputs do; the other's bundle stays. (The
    other writer's compression is played inside the lock's wait.)"""
    import contextlib

    import hailstorm.runtime.bundle.write as write
    from hailstorm.precompute.hmatrix import compress_bundle

    out = build_bundle(tmp_path / "b", mesh=small_box)
    real_lock = write.bundle_lock

    @contextlib.contextmanager
    def lock_after_the_other_writer(path, **kw):
        monkeypatch.setattr(write, "bundle_lock", real_lock)
        compress_bundle(out, out, 1e-2)  # the other writer, done while we waited
        with real_lock(path, **kw) as held:
            yield held

    monkeypatch.setattr(write, "bundle_lock", lock_after_the_other_writer)
    with pytest.raises(BundleError, match="was just written by another run with other inputs"):
        compress_bundle(out, out, 1e-3)
    assert load(out).manifest["compliance"]["tol"] == 1e-2
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
