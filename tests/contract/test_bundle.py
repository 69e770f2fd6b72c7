"""Bundle round trip, refusal of damaged bundles, atomic writes, the cache key."""

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

import hailstorm.runtime
from hailstorm.precompute import build_bundle
from hailstorm.runtime.bundle.read import load
from hailstorm.runtime.bundle.format import ARRAY_SPECS, MANIFEST, MANIFEST_HASH, BundleError, manifest_hash
from hailstorm.runtime.bundle.write import write_bundle


def _copy(src, dst):
    shutil.copytree(src, dst)
    return dst


def test_round_trip_preserves_every_array(box_bundle, small_box):
    gf = load(box_bundle)
    assert gf.vertices.shape == (gf.n_vertices, 3)
    assert np.array_equal(gf.volume_points, small_box.points)
    assert np.array_equal(gf.volume_tets, small_box.tets)
    assert np.array_equal(gf.vertices, small_box.points[gf.surface_nodes])
    assert gf.young == 1e6 and gf.poisson == 0.3 and gf.order == 1
    # rewrite what we read and read it again: identical arrays and hashes
    arrays = {name: np.asarray(getattr(gf, name if name != "compliance" else "D")) for name in ARRAY_SPECS}
    again = load(write_bundle(box_bundle.parent / "again", arrays, {"key": "x", "options": gf.manifest["options"],
                                                                    "material": gf.manifest["material"]}))
    for name in ARRAY_SPECS:
        a = getattr(gf, name if name != "compliance" else "D")
        b = getattr(again, name if name != "compliance" else "D")
        assert np.array_equal(a, b), name
    assert again.manifest["arrays"] == gf.manifest["arrays"]


def test_bundle_directory_permissions_follow_the_umask(box_bundle):
    """The bundle directory gets the mode a plain mkdir would give (not mkdtemp's 0o700,
    nor a fixed 0o755), like the files in it."""
    import os
    import stat

    gf = load(box_bundle)
    arrays = {name: np.asarray(getattr(gf, name if name != "compliance" else "D")) for name in ARRAY_SPECS}
    meta = {"key": "x", "options": gf.manifest["options"], "material": gf.manifest["material"]}
    umask = os.umask(0o027)
    try:
        out = write_bundle(box_bundle.parent / "perm", arrays, meta)
        assert stat.S_IMODE(out.stat().st_mode) == 0o750
        assert stat.S_IMODE((out / MANIFEST).stat().st_mode) == 0o640
    finally:
        os.umask(umask)


def test_compliance_is_memory_mapped(box_bundle):
    assert isinstance(load(box_bundle).D, np.memmap)


def test_corrupted_array_is_refused(box_bundle, tmp_path):
    b = _copy(box_bundle, tmp_path / "b")
    raw = bytearray((b / "compliance.npy").read_bytes())
    raw[-8] ^= 0xFF
    (b / "compliance.npy").write_bytes(bytes(raw))
    with pytest.raises(BundleError, match="hash"):
        load(b)


def test_truncated_array_is_refused(box_bundle, tmp_path):
    b = _copy(box_bundle, tmp_path / "b")
    raw = (b / "compliance.npy").read_bytes()
    (b / "compliance.npy").write_bytes(raw[: len(raw) // 2])
    with pytest.raises(BundleError, match="truncated|corrupted"):
        load(b)


def test_missing_array_and_manifest_are_refused(box_bundle, tmp_path):
    b = _copy(box_bundle, tmp_path / "b")
    (b / "areas.npy").unlink()
    with pytest.raises(BundleError, match="areas.npy is missing"):
        load(b)
    (b / MANIFEST).unlink()
    with pytest.raises(BundleError, match="manifest.json is missing"):
        load(b)
    with pytest.raises(BundleError, match="does not exist"):
        load(tmp_path / "nowhere")


def test_mismatched_bundle_is_refused(box_bundle, seat_bundle, tmp_path):
    b = _copy(box_bundle, tmp_path / "b")
    # an array from another bundle, with its manifest entry: hashes pass, consistency does not
    shutil.copy(seat_bundle / "compliance.npy", b / "compliance.npy")
    m = json.loads((b / MANIFEST).read_text())
    m["arrays"]["compliance"] = json.loads((seat_bundle / MANIFEST).read_text())["arrays"]["compliance"]
    m[MANIFEST_HASH] = manifest_hash(m)  # a consistent manifest: only the cross-array checks catch it
    (b / MANIFEST).write_text(json.dumps(m))
    with pytest.raises(BundleError, match="inconsistent"):
        load(b)


@pytest.mark.parametrize("version, advice", [(99, "A newer hailstorm wrote it: upgrade hailstorm"),
                                             (1, "Re-run `hailstorm precompute`")])
def test_other_format_version_is_refused(box_bundle, tmp_path, version, advice):
    b = _copy(box_bundle, tmp_path / "b")
    m = json.loads((b / MANIFEST).read_text())
    m["format_version"] = version
    (b / MANIFEST).write_text(json.dumps(m))
    with pytest.raises(BundleError, match=f"version {version}; this hailstorm reads versions 2 and 3") as err:
        load(b)
    assert advice in str(err.value)


def test_non_bundle_directory_is_never_overwritten(small_box, tmp_path):
    target = tmp_path / "precious"
    target.mkdir()
    (target / "thesis.tex").write_text("years of work")
    with pytest.raises(BundleError, match="not part of a hailstorm bundle"):
        build_bundle(target, mesh=small_box)
    assert (target / "thesis.tex").read_text() == "years of work"


def test_failed_write_leaves_old_bundle_intact(box_bundle, tmp_path, monkeypatch):
    b = _copy(box_bundle, tmp_path / "b")
    before = {p.name: p.read_bytes() for p in b.iterdir()}
    gf = load(b)
    arrays = {name: np.asarray(getattr(gf, name if name != "compliance" else "D")) for name in ARRAY_SPECS}
    calls = {"n": 0}
    real_save = np.save

    def failing_save(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 5:
            raise OSError("disk full")
        return real_save(*args, **kwargs)

    monkeypatch.setattr(np, "save", failing_save)
    with pytest.raises(OSError, match="disk full"):
        write_bundle(b, arrays, {"key": "new"})
    assert {p.name: p.read_bytes() for p in b.iterdir()} == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temp litter
    load(b)


def test_cache_key_reuses_same_and_recomputes_different(small_box, tmp_path):
    out = tmp_path / "b"
    build_bundle(out, mesh=small_box, young=1e6)
    stamp = (out / MANIFEST).stat().st_mtime_ns
    key = load(out).manifest["key"]
    build_bundle(out, mesh=small_box, young=1e6)
    assert (out / MANIFEST).stat().st_mtime_ns == stamp  # reused, not rewritten
    build_bundle(out, mesh=small_box, young=2e6)  # different material: never the old D
    gf = load(out)
    assert gf.manifest["key"] != key and gf.young == 2e6
    moved = small_box.points.copy()
    moved[:, 0] *= 1.01
    from hailstorm.precompute.geometry import TetMesh

    build_bundle(out, mesh=TetMesh(moved, small_box.tets, small_box.groups, "moved"), young=2e6)
    assert not np.array_equal(load(out).vertices, gf.vertices)  # a different mesh is recomputed


def test_runtime_imports_no_meshing_or_fem(box_bundle):
    code = (
        "import sys, hailstorm.runtime; gf = hailstorm.runtime.load(sys.argv[1]); gf.compliance([0], gf.contact_vertices[:2]);"
        "bad = [m for m in ('gmsh', 'skfem', 'meshio', 'hailstorm.precompute') if m in sys.modules];"
        "assert not bad, bad"
    )
    subprocess.run([sys.executable, "-c", code, str(box_bundle)], check=True)


def test_the_runtime_stage_runs_a_storm_without_the_offline_stage(box_bundle):
    """The stages stay apart: the default scene and a storm load nothing of the offline
    stage (hailstorm.precompute, gmsh, scikit-fem), in a fresh interpreter."""
    code = (
        "import sys\n"
        "from hailstorm.runtime import Scene, load, run_storm\n"
        "sc = Scene.default().with_(duration=0.02)\n"
        "res = run_storm(load(sys.argv[1]), sc, progress=False)\n"
        "assert res.stats['hailstones'] >= 0\n"
        "bad = [m for m in sys.modules if m.split('.')[0] in ('gmsh', 'skfem')"
        " or m.startswith('hailstorm.precompute')]\n"
        "assert not bad, bad\n"
    )
    subprocess.run([sys.executable, "-c", code, str(box_bundle)], check=True)


def test_one_top_level_package_named_hailstorm():
    """Outside the checkout the old top-level names are gone; the CLI runs as a module."""
    import tempfile

    with tempfile.TemporaryDirectory() as cwd:
        env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
        for old in ("runtime", "precompute"):
            r = subprocess.run([sys.executable, "-c", f"import {old}"], cwd=cwd, env=env, capture_output=True)
            assert r.returncode != 0
        r = subprocess.run([sys.executable, "-m", "hailstorm", "--help"], cwd=cwd, env=env, capture_output=True,
                           text=True)
        assert r.returncode == 0 and "precompute" in r.stdout


def test_compliance_argument_errors(box_bundle):
    gf = hailstorm.runtime.load(box_bundle)
    with pytest.raises(IndexError):
        gf.compliance([gf.n_vertices], [int(gf.contact_vertices[0])])
    with pytest.raises(ValueError, match="vertex indices"):
        gf.compliance([0.5], [0])


def test_compliance_is_stored_column_major(box_bundle):
    """Gathering the columns of a contact set must be a contiguous read."""
    D = load(box_bundle).D
    assert D.flags.f_contiguous and not D.flags.c_contiguous


def test_displacement_is_compliance_times_forces(seat_bundle, rng):
    gf = load(seat_bundle)
    verts = np.concatenate([rng.choice(gf.contact_vertices, 4, replace=False), np.flatnonzero(gf.fixed)[:1]])
    f = rng.normal(size=(verts.size, 3))
    expected = (gf.compliance(np.arange(gf.n_vertices), verts) @ f.ravel()).reshape(-1, 3)
    tol = 1e-13 * np.abs(expected).max()  # rounding: the kernel sums in another order than the matmul
    assert np.allclose(gf.displacement(verts, f), expected, rtol=1e-13, atol=tol)
    rows = np.array([3, 1, 4])
    assert np.allclose(gf.displacement(verts, f, rows=rows), expected[rows], rtol=1e-13, atol=tol)


def test_displacement_refuses_a_vertex_without_a_column(small_box, tmp_path):
    """A free surface vertex outside the contact group has no column of D: no force there."""
    from hailstorm.precompute.geometry import TetMesh

    top = small_box.groups["top"]
    upper = top[np.all(np.isclose(small_box.points[top][:, :, 2], 0.05), axis=1)]  # only the z = max face
    mesh = TetMesh(small_box.points, small_box.tets, {"clamp": small_box.groups["clamp"], "top": upper}, "box-top")
    gf = load(build_bundle(tmp_path / "b", mesh=mesh, young=1e6, poisson=0.3))
    with pytest.raises(ValueError, match="neither contactable nor fixed"):
        gf.displacement([int(np.flatnonzero(~gf.contactable & ~gf.fixed)[0])], [[0, 0, 1.0]])


# ---------------------------------------------------------------------------
# verification stamps: every file hashed once per change, not on every load
# ---------------------------------------------------------------------------
def _counting_scan(monkeypatch):
    import hailstorm.runtime.bundle.format as bundle_mod

    calls = []
    real = bundle_mod.scan_array

    def scan(a):
        calls.append(a.shape)
        return real(a)

    monkeypatch.setattr(bundle_mod, "scan_array", scan)
    return calls


def test_load_hashes_each_file_once_per_change(box_bundle, tmp_path, monkeypatch):
    monkeypatch.setenv("HAILSTORM_CACHE", str(tmp_path / "cache"))
    b = tmp_path / "b"
    shutil.copytree(box_bundle, b)
    calls = _counting_scan(monkeypatch)
    load(b)
    assert len(calls) == len(ARRAY_SPECS)  # first load: every array hashed
    calls.clear()
    gf = load(b)
    assert calls == []  # unchanged since: nothing re-read
    assert np.isfinite(gf.compliance([0], gf.contact_vertices[:2])).all()
    load(b, rehash=True)
    assert len(calls) == len(ARRAY_SPECS)  # what `hailstorm info` does


@pytest.mark.parametrize("restore_mtime", [False, True])
def test_a_file_changed_after_its_stamp_is_hashed_and_refused(box_bundle, tmp_path, monkeypatch, restore_mtime):
    monkeypatch.setenv("HAILSTORM_CACHE", str(tmp_path / "cache"))
    b = tmp_path / "b"
    shutil.copytree(box_bundle, b)
    load(b)  # stamps every file
    f = b / "compliance.npy"
    st = f.stat()
    with open(f, "r+b") as fh:  # flip one byte of D, same size
        fh.seek(st.st_size - 3)
        byte = fh.read(1)
        fh.seek(st.st_size - 3)
        fh.write(bytes([byte[0] ^ 0xFF]))
    if restore_mtime:  # the modification time put back: the status-change time still moved
        os.utime(f, ns=(st.st_atime_ns, st.st_mtime_ns))
    with pytest.raises(BundleError, match="content hash"):
        load(b)


def test_an_unwritable_cache_only_costs_the_speed_up(box_bundle, tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    monkeypatch.setenv("HAILSTORM_CACHE", str(blocker))
    calls = _counting_scan(monkeypatch)
    load(box_bundle)
    load(box_bundle)
    assert len(calls) == 2 * len(ARRAY_SPECS)


def test_a_version_that_does_not_match_the_arrays_is_said_so(box_bundle, tmp_path):
    """A dense bundle whose manifest says 3 (the compressed format; the other way round in
    tests/contract/test_hmatrix.py): a version mismatch, not a missing array entry."""
    b = _copy(box_bundle, tmp_path / "b")
    m = json.loads((b / MANIFEST).read_text())
    m["format_version"] = 3
    m[MANIFEST_HASH] = manifest_hash(m)
    (b / MANIFEST).write_text(json.dumps(m))
    with pytest.raises(BundleError, match=r"format_version 3 does not match its arrays, which are version 2's"):
        load(b)
