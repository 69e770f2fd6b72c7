"""The compressed compliance: the stored H-matrix, compressed bundles (format 3), their errors and refusals."""

import shutil

import numpy as np
import pytest

from hailstorm.precompute import build_bundle
from hailstorm.precompute import hmatrix as construct
from hailstorm.precompute.hmatrix import (
    ERROR_COLUMNS,
    check_tol,
    compress,
    compress_bundle,
)
from hailstorm.precompute.htree import admissible_blocks, cluster_tree, dofs
from hailstorm.runtime.bundle import format as bundle_format
from hailstorm.runtime.bundle.format import BundleError
from hailstorm.runtime.bundle.hmatrix import HMatrix
from hailstorm.runtime.bundle.read import load
from hailstorm.runtime.bundle.write import convert_bundle
from hailstorm.runtime.contact.hertz import press_spheres


@pytest.fixture(scope="module")
def seat_h(seat_bundle, tmp_path_factory):
    """The 15 mm seat's bundle compressed to 1e-3, beside its dense source."""
    return compress_bundle(seat_bundle, tmp_path_factory.mktemp("gfh") / "seat_h", 1e-3)


@pytest.fixture(scope="module")
def box_H(box_bundle):
    gf = load(box_bundle)
    V = np.asarray(gf.vertices, float)
    rows, cols = cluster_tree(V, leaf=8), cluster_tree(V[gf.contact_vertices], leaf=8)
    D = np.asarray(gf.D)
    return D, compress(D, rows, cols, admissible_blocks(rows, cols, 1.0), 1e-2)


def test_columns_and_products_are_the_expanded_matrix(box_H):
    D, H = box_H
    assert (H.ranks >= 0).all() and H.ranks.size > 0, "the box has far blocks stored as factors"
    full = H.to_dense()
    assert full.flags.f_contiguous and full.shape == D.shape
    cols = np.array([5, 0, 5, D.shape[1] - 1, 17])  # unsorted, repeated
    # the same products of factors over other column subsets: equal to rounding (BLAS kernels differ)
    assert np.allclose(H.columns(cols), full[:, cols], rtol=0, atol=1e-14 * np.abs(full).max())
    x = np.random.default_rng(1).standard_normal((D.shape[1], 2))
    scale = np.abs(full).max() * np.abs(x).sum(axis=0).max()
    assert np.allclose(H.matvec(x), full @ x, rtol=0, atol=1e-13 * scale)
    # within the truncation: ||D - H||_F <= tol ||D||_F (each far block to 1e-2 of itself)
    assert np.linalg.norm(D - full) <= 1e-2 * np.linalg.norm(D)
    assert 0 < np.linalg.norm(D - full)  # and truly compressed, not a copy


def test_stored_arrays_round_trip_and_bad_tables_are_refused(box_H):
    _, H = box_H
    arrays = H.to_arrays()
    again = HMatrix.from_arrays(H.shape, arrays)
    assert np.allclose(again.to_dense(), H.to_dense(), rtol=0, atol=1e-14 * np.abs(H.data).max())
    bad = dict(arrays, hmatrix_rows=arrays["hmatrix_rows"][::-1].copy())
    bad["hmatrix_rows"][0] = bad["hmatrix_rows"][1]
    with pytest.raises(ValueError, match="not a permutation"):
        HMatrix.from_arrays(H.shape, bad)
    blocks = arrays["hmatrix_blocks"].copy()
    blocks[0, 3] = blocks[0, 2] + 1 if blocks[0, 3] - blocks[0, 2] > 1 else blocks[0, 3]  # a hole in the tiling
    blocks[1] = blocks[0]
    with pytest.raises(ValueError, match="tile|cover|past the end"):
        HMatrix.from_arrays(H.shape, dict(arrays, hmatrix_blocks=blocks))
    with pytest.raises(ValueError, match="past the end"):
        HMatrix.from_arrays(H.shape, dict(arrays, hmatrix_data=arrays["hmatrix_data"][:-1]))


def test_compressed_bundle_is_within_tol_of_every_column(seat_bundle, seat_h):
    dense, h = load(seat_bundle), load(seat_h)
    assert h.manifest["format_version"] == 3 and h.hmatrix is not None and dense.hmatrix is None
    comp = h.manifest["compliance"]
    assert comp["storage"] == "hmatrix" and comp["tol"] == 1e-3
    # the error the bundle records: 200 exact columns drawn at random, and it holds for every column
    assert comp["error"]["columns"] == min(ERROR_COLUMNS, dense.D.shape[1]) == 200
    err = np.linalg.norm(h.D - dense.D, axis=0) / np.linalg.norm(dense.D, axis=0)
    assert err.max() <= 1e-3
    assert comp["error"]["max"] <= err.max() + 1e-15 and comp["error"]["median"] > 0
    assert comp["stored_bytes"] == h.hmatrix.data.nbytes < comp["dense_bytes"] == dense.D.size * 8
    assert comp["source_key"] == dense.manifest["key"] != h.manifest["key"]
    # everything else is the source's
    for name in ("vertices", "triangles", "areas", "fixed", "contactable", "volume_tets", "surface_nodes"):
        assert np.array_equal(getattr(h, name), getattr(dense, name))


def test_contacts_on_the_compressed_bundle_are_the_dense_ones(seat_bundle, seat_h):
    """press_spheres (Hertz patches, near field) reads the compressed D like the dense one: forces within 0.1 %."""
    dense, h = load(seat_bundle), load(seat_h)
    rng = np.random.default_rng(4)
    tri = np.flatnonzero(dense.contactable[dense.triangles].all(axis=1))
    tri = rng.choice(tri, size=6, replace=False)
    bary = rng.dirichlet(np.ones(3), size=6)
    args = (tri, bary, np.full(6, 1.5e-3), 5e-3)
    a, b = press_spheres(dense, *args), press_spheres(h, *args)
    assert np.allclose(b.normal_force, a.normal_force, rtol=1e-3, atol=0)
    assert np.allclose(b.patch_radius, a.patch_radius, rtol=1e-3, atol=0)
    ua, ub = a.solution.surface_displacement, b.solution.surface_displacement
    assert np.abs(ub - ua).max() <= 1e-3 * np.abs(ua).max()


def test_a_reader_of_format_2_only_refuses_a_compressed_bundle(seat_h, monkeypatch):
    """What a hailstorm from before compressed bundles says: a version error, never a wrong D."""
    monkeypatch.setattr(bundle_format, "READ_VERSIONS", (2,))
    with pytest.raises(BundleError, match="format version 3.*upgrade hailstorm"):
        load(seat_h)


def test_tampered_factors_are_refused(seat_h, tmp_path):
    b = shutil.copytree(seat_h, tmp_path / "b")
    data = np.load(b / "hmatrix_data.npy")
    data[np.argmax(np.abs(data))] *= 1.01
    np.save(b / "hmatrix_data.npy", data)
    with pytest.raises(BundleError, match="hash"):
        load(b)


@pytest.mark.parametrize("tol", [0.0, -1e-3, 0.5, 1e-13, float("nan"), float("inf"), True])
def test_tol_out_of_range_is_refused(tol):
    with pytest.raises(ValueError, match=r"compression tolerance .*\[1e-12, 0\.1\]"):
        check_tol(tol)


def test_unreachable_tol_names_the_error_reached(seat_bundle, tmp_path, monkeypatch):
    monkeypatch.setattr(construct, "column_errors", lambda H, D, cols: np.full(len(cols), 0.05))
    with pytest.raises(ValueError, match=r"1e-05 is unreachable.*off by up to 0\.05"):
        compress_bundle(seat_bundle, tmp_path / "h", 1e-5)
    assert not (tmp_path / "h").exists()


def test_compressing_needs_a_dense_float64_source(seat_bundle, seat_h, tmp_path):
    with pytest.raises(BundleError, match="already compressed"):
        compress_bundle(seat_h, tmp_path / "x", 1e-2)
    f32 = convert_bundle(seat_bundle, tmp_path / "f32", "float32")
    with pytest.raises(BundleError, match="float32; compress a float64"):
        compress_bundle(f32, tmp_path / "y", 1e-2)
    with pytest.raises(BundleError, match="stores D compressed"):
        convert_bundle(seat_h, tmp_path / "z", "float32")


def test_build_bundle_compresses_reuses_and_keys_by_tol(small_box, tmp_path):
    out = tmp_path / "b"
    dense = build_bundle(tmp_path / "dense", mesh=small_box, order=1)
    p = build_bundle(out, mesh=small_box, order=1, compress_tol=1e-2)
    first = load(p)
    assert first.hmatrix is not None
    assert first.manifest["compliance"]["source_key"] == load(dense).manifest["key"]
    mtime = (out / "hmatrix_data.npy").stat().st_mtime_ns
    assert build_bundle(out, mesh=small_box, order=1, compress_tol=1e-2) == p  # up to date: reused
    assert (out / "hmatrix_data.npy").stat().st_mtime_ns == mtime
    again = load(build_bundle(out, mesh=small_box, order=1, compress_tol=1e-4))
    assert again.manifest["key"] != first.manifest["key"] and again.manifest["compliance"]["tol"] == 1e-4
    assert load(build_bundle(out, mesh=small_box, order=1)).hmatrix is None  # dense again on request
    with pytest.raises(ValueError, match="float64"):
        build_bundle(tmp_path / "c", mesh=small_box, order=1, compress_tol=1e-2, dtype="float32")


def test_dofs_are_vertex_major():
    assert dofs(np.array([2, 0])).tolist() == [6, 7, 8, 0, 1, 2]


@pytest.mark.parametrize("tol", [1e-1, 1e-3, 1e-5, 1e-8])
def test_low_rank_meets_its_bound_and_the_svd_rank(tol):
    """The randomized range finder (blocks of 192 and more) keeps ||B - X V^T||_F <= tol ||B||_F exactly,
    at a rank within a few of the truncated SVD's (the optimum)."""
    rng = np.random.default_rng(3)
    m, n = 400, 300
    U, _ = np.linalg.qr(rng.standard_normal((m, n)))
    V, _ = np.linalg.qr(rng.standard_normal((n, n)))
    B = (U * np.exp(-0.35 * np.arange(n))) @ V.T  # a far block's decaying spectrum
    X, W = construct.low_rank(B, tol, np.random.default_rng(0))
    assert np.linalg.norm(B - X @ W.T) <= tol * np.linalg.norm(B) * (1 + 1e-12)
    best = construct.truncation_rank(np.linalg.svd(B, compute_uv=False), tol)
    assert best <= X.shape[1] <= best + 3


def test_a_compressed_d_is_expanded_once_into_the_cache_and_memory_mapped(seat_bundle, seat_h, tmp_path,
                                                                         monkeypatch):
    monkeypatch.setenv("HAILSTORM_CACHE", str(tmp_path / "cache"))
    first = load(seat_h)
    assert isinstance(first.D, np.memmap) and first.D.flags.f_contiguous and not first.D.flags.writeable
    assert first.D.dtype == np.float32 == first.dtype  # tol 1e-3: float32's rounding is 1e-4 of it
    (cached,) = (tmp_path / "cache" / "expanded").glob("*.npy")
    before = cached.stat().st_mtime_ns
    D = np.array(first.D)
    exact = first.hmatrix.to_dense()
    assert np.array_equal(D, exact.astype(np.float32))  # rounded to nearest, nothing else
    assert np.abs(D - exact).max() <= 2.0**-24 * np.abs(exact).max()
    again = load(seat_h)
    assert cached.stat().st_mtime_ns == before and np.array_equal(again.D, D)  # reused
    # an expansion changed behind the project's back fails its stamp and is rebuilt
    spoiled = np.load(cached, mmap_mode="r+")
    spoiled[0, 0] += 1.0
    spoiled.flush()
    del spoiled
    rebuilt = load(seat_h)
    # the same products of factors, in other column batches: BLAS may round them apart by an ulp of float64,
    # which can move a float32 rounding by one float32 ulp
    rounding = 2.0**-23 * np.abs(D).max()
    assert np.allclose(rebuilt.D, D, rtol=0, atol=rounding) and cached.stat().st_mtime_ns != before
    in_memory = load(seat_h, mmap=False)
    assert not isinstance(in_memory.D, np.memmap) and np.allclose(in_memory.D, D, rtol=0, atol=rounding)
    assert in_memory.D.dtype == np.float32


def test_a_tight_tolerance_expands_into_float64():
    from hailstorm.runtime.bundle.hmatrix import FLOAT32_TOL, expansion_dtype

    assert expansion_dtype(1e-2) == expansion_dtype(FLOAT32_TOL) == np.float32
    assert expansion_dtype(FLOAT32_TOL / 2) == expansion_dtype(1e-8) == np.float64


def test_loading_and_info_leave_a_compressed_d_unexpanded(seat_h, tmp_path, monkeypatch, capsys):
    """The expansion waits for the first read of D: ``hailstorm info`` (which re-hashes every file) and a
    load write nothing into the cache; the first ``gf.D`` does, once."""
    from hailstorm.cli import main
    from hailstorm.runtime.bundle.read import CompressedGreensFunctions

    monkeypatch.setenv("HAILSTORM_CACHE", str(tmp_path / "cache"))
    expansions = lambda: sorted((tmp_path / "cache").glob("expanded/*.npy"))  # noqa: E731
    assert main(["info", str(seat_h)]) == 0
    assert "as an H-matrix" in capsys.readouterr().out and expansions() == []
    gf = load(seat_h)
    assert isinstance(gf, CompressedGreensFunctions) and not gf.expanded and gf.dtype == np.float32
    assert expansions() == []
    D = gf.D
    assert gf.expanded and gf.D is D and len(expansions()) == 1
    assert D.shape == gf.hmatrix.shape and D.dtype == gf.dtype


def test_an_unwritable_cache_expands_in_memory(seat_h, tmp_path, monkeypatch):
    blocker = tmp_path / "not-a-dir"
    blocker.write_text("a file where the cache would be")
    monkeypatch.setenv("HAILSTORM_CACHE", str(blocker))
    gf = load(seat_h, verify=False)
    assert not isinstance(gf.D, np.memmap) and gf.D.shape == tuple(gf.manifest["compliance"]["shape"])
    assert blocker.read_text() == "a file where the cache would be"


def test_old_expansions_beyond_the_budget_are_removed_and_nothing_else(box_H, tmp_path, monkeypatch):
    """Writing an expansion past the budget removes the oldest of this project's expansions (and their
    stamps); the one just written, a file the project did not write and an expansion changed since its
    stamp stay; a removed one is rebuilt, equal, on its next use."""
    import os

    from hailstorm.runtime.bundle import hmatrix as runtime_h
    from hailstorm.runtime.bundle.stamps import stamp, stamped_hash

    monkeypatch.setenv("HAILSTORM_CACHE", str(tmp_path / "cache"))
    folder = tmp_path / "cache" / "expanded"
    _, H = box_H
    size = H.shape[0] * H.shape[1] * 8
    paths = []
    for i, tag in enumerate(["first", "second"]):
        runtime_h.expanded(H, tag, cache=folder)
        (p,) = set(folder.glob(f"{tag}*.npy"))
        os.utime(p, ns=(10**18 + i, 10**18 + i))  # oldest first (utime changes ctime: stamp again)
        stamp(p, f"{tag}-float64")
        paths.append(p)
    foreign = folder / "mine-float64.npy"  # a user's file with an expansion's name: no stamp
    np.save(foreign, np.zeros(3))
    os.utime(foreign, ns=(1, 1))
    runtime_h.expanded(H, "changed", cache=folder)
    (changed,) = set(folder.glob("changed*.npy"))
    os.utime(changed, ns=(2, 2))  # changed behind the project's back: its stamp no longer matches
    monkeypatch.setattr(runtime_h, "EXPANDED_BUDGET", 2 * size + size // 2)
    third = runtime_h.expanded(H, "third", cache=folder)  # three expansions > 2.5 of them: the oldest goes
    assert not paths[0].exists() and stamped_hash(paths[0]) is None
    assert paths[1].exists() and foreign.exists() and len(list(folder.glob("third*.npy"))) == 1
    assert runtime_h.prune_expansions(folder, budget=0, keep=next(folder.glob("third*.npy"))) == [paths[1]]
    assert foreign.exists() and np.array_equal(np.asarray(third), H.to_dense())
    assert changed.exists() and stamped_hash(changed) is None
    again = runtime_h.expanded(H, "first", cache=folder)  # rebuilt on its next use
    assert np.array_equal(np.asarray(again), H.to_dense())


def test_a_storm_on_the_compressed_bundle_is_the_dense_storm(seat_bundle, seat_h, tmp_path):
    """The same storm on both bundles (the frames read the expanded D, float32 at this tolerance; the dense
    D rounded to float32 too): the same impacts, and the contact forces and dents within the compression's
    1e-3 per column."""
    from hailstorm.runtime import run_storm
    from hailstorm.runtime.storm.scene import Scene

    scene = Scene.from_flat(duration=0.04, stones=30, seed=5)
    a = run_storm(load(convert_bundle(seat_bundle, tmp_path / "f32", "float32")), scene, progress=False,
                  keep_frames=True)
    b = run_storm(load(seat_h), scene, progress=False, keep_frames=True)
    assert a.stats.impacts == b.stats.impacts > 0
    assert b.stats.max_contact_force == pytest.approx(a.stats.max_contact_force, rel=1e-3)
    assert np.allclose(b.history[:, 1], a.history[:, 1], rtol=0, atol=1e-3 * a.history[:, 1].max())
    ua = np.stack([f.displacement for f in a.frames])
    ub = np.stack([f.displacement for f in b.frames])
    assert np.abs(ub - ua).max() <= 2e-3 * np.abs(ua).max()


def test_a_compressed_bundle_of_the_wrong_shape_is_refused_before_it_is_expanded(seat_h, tmp_path, monkeypatch):
    """An H-matrix that does not fit the surface (one contactable vertex fewer, hashes redone) is refused as
    inconsistent, and nothing is expanded."""
    import json

    from hailstorm.runtime.bundle import read
    from hailstorm.runtime.bundle.format import MANIFEST, array_hash, manifest_hash

    b = shutil.copytree(seat_h, tmp_path / "b")
    contactable = np.load(b / "contactable.npy")
    contactable[np.flatnonzero(contactable)[0]] = False
    np.save(b / "contactable.npy", contactable)
    m = json.loads((b / MANIFEST).read_text())
    m["arrays"]["contactable"].update(sha256=array_hash(contactable), bytes=(b / "contactable.npy").stat().st_size)
    del m["manifest_sha256"]
    m["manifest_sha256"] = manifest_hash(m)
    (b / MANIFEST).write_text(json.dumps(m))
    calls = []
    monkeypatch.setattr(read, "expanded", lambda *args, **kw: calls.append(args))
    with pytest.raises(BundleError, match=r"inconsistent: compliance has shape"):
        load(b)
    assert not calls


def test_a_compressed_bundle_labelled_version_2_is_a_version_mismatch(seat_h, tmp_path):
    """A compressed bundle whose manifest says format version 2 (hash redone): a version mismatch
    naming both versions, not a missing ``arrays.compliance`` entry."""
    import json

    from hailstorm.runtime.bundle.format import MANIFEST, manifest_hash

    b = shutil.copytree(seat_h, tmp_path / "b")
    m = json.loads((b / MANIFEST).read_text())
    m["format_version"] = 2
    del m["manifest_sha256"]
    m["manifest_sha256"] = manifest_hash(m)
    (b / MANIFEST).write_text(json.dumps(m))
    with pytest.raises(BundleError, match=r"format_version 2 does not match its arrays, which are version 3's "
                                          r"\(a compressed D"):
        load(b)


def test_inconsistent_recorded_errors_are_refused_on_load(seat_h, tmp_path, capsys):
    """A compressed bundle whose manifest says its largest column error is below its median (hash
    redone, as an edit would): refused on load, and by ``hailstorm info`` in one line, exit 3."""
    import json

    from hailstorm.cli import main
    from hailstorm.runtime.bundle.format import MANIFEST, manifest_hash

    b = shutil.copytree(seat_h, tmp_path / "b")
    m = json.loads((b / MANIFEST).read_text())
    err = m["compliance"]["error"]
    err["max"], err["median"] = err["median"] / 10, err["median"]
    del m["manifest_sha256"]
    m["manifest_sha256"] = manifest_hash(m)
    (b / MANIFEST).write_text(json.dumps(m))
    with pytest.raises(BundleError, match="recorded column errors are inconsistent"):
        load(b)
    assert main(["info", str(b)]) == 3
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "recorded column errors are inconsistent" in lines[0]
