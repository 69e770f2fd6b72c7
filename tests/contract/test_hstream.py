"""The streamed H-matrix (precompute/hstream.py): D compressed from its column blocks as they come."""

import numpy as np
import pytest

from hailstorm.precompute import build_bundle
from hailstorm.precompute.hmatrix import compress
from hailstorm.precompute.htree import admissible_blocks, block_slices, cluster_tree, dofs
from hailstorm.precompute.hstream import StreamedH, streamed_key, tree_order
from hailstorm.runtime.bundle.read import load


@pytest.fixture(scope="module")
def seat_D(seat_bundle):
    """The 15 mm seat's dense D, its trees (leaves of 8) and partition (eta 1: many far blocks)."""
    gf = load(seat_bundle)
    V = np.asarray(gf.vertices, float)
    rows, cols = cluster_tree(V, leaf=8), cluster_tree(V[gf.contact_vertices], leaf=8)
    return np.asarray(gf.D), rows, cols, admissible_blocks(rows, cols, 1.0)


def column_errors(H, D):
    full = H.to_dense()
    return np.linalg.norm(full - D, axis=0) / np.linalg.norm(D, axis=0), full


@pytest.mark.parametrize("width", [7, 64])
def test_streamed_h_is_within_its_tolerance_in_any_block_order(seat_D, width):
    """Blocks of 7 and 64 columns (tree order) fed in a shuffled order: every far block within
    tol of itself (so the whole within tol in Frobenius norm), every column within tol, near blocks
    exact, kept columns exact; about the numbers ``compress`` stores for the same tol (its rule,
    reached by another path: measured 1.0-1.1x here), and not a dense copy."""
    D, rows, cols, part = seat_D
    cd = dofs(cols.perm)
    blocks = [(s, min(s + width, D.shape[1])) for s in range(0, D.shape[1], width)]
    tol = 1e-3
    S = StreamedH(rows, cols, part, tol, blocks, keep=[3, 0, D.shape[1] - 1])
    for i in np.random.default_rng(7).permutation(len(blocks)):
        a, b = blocks[i]
        S.add(a, D[:, cd[a:b]])
    H = S.finish()
    err, full = column_errors(H, D)
    assert err.max() <= tol and np.linalg.norm(full - D) <= tol * np.linalg.norm(D)
    assert np.linalg.norm(full - D) > 0 and H.ranks.size > 0  # compressed, with factored far blocks
    ref = compress(D, rows, cols, part, tol)
    assert H.stored <= 1.3 * ref.stored and len(H.blocks) == len(ref.blocks)
    rd = dofs(rows.perm)
    for i, j, _ in part.near:  # the near blocks hold D's own numbers
        r, c = block_slices(rows, cols, i, j)
        np.testing.assert_array_equal(full[np.ix_(rd[r], cd[c])], D[np.ix_(rd[r], cd[c])])
    for j in (3, 0, D.shape[1] - 1):
        np.testing.assert_array_equal(S.kept[j], D[:, j])
    cols_k, err_k = S.errors(H)
    assert cols_k.tolist() == [0, 3, D.shape[1] - 1] and err_k.max() <= tol


def test_streamed_h_refuses_what_is_not_d(seat_D):
    D, rows, cols, part = seat_D
    blocks = [(0, D.shape[1])]
    S = StreamedH(rows, cols, part, 1e-2, blocks)
    with pytest.raises(ValueError, match="rows"):
        S.add(0, D[:-3])
    S.add(0, D[:, dofs(cols.perm)[:10]])
    with pytest.raises(ValueError, match="10 of D's"):
        S.finish()
    with pytest.raises(ValueError, match="tol"):
        StreamedH(rows, cols, part, -1.0, blocks)


def test_build_bundle_streams_a_compressed_bundle(small_box, tmp_path):
    """``stream=True``: a format-3 bundle whose columns are within tol of the dense build's D (all of
    them, not only the 200 it measured), under its own key; nothing of D is written beside it; an
    up-to-date bundle is reused; streaming needs a tolerance."""
    dense = load(build_bundle(tmp_path / "dense", mesh=small_box, order=1))
    out = tmp_path / "s"
    p = build_bundle(out, mesh=small_box, order=1, compress_tol=1e-3, stream=True)
    gf = load(p)
    comp = gf.manifest["compliance"]
    assert gf.hmatrix is not None and comp["construction"] == "stream" and comp["tol"] == 1e-3
    assert comp["source_key"] == dense.manifest["key"]
    assert gf.manifest["key"] == streamed_key(dense.manifest["key"], 1e-3)
    D = np.asarray(dense.D)
    err = np.linalg.norm(gf.hmatrix.to_dense() - D, axis=0) / np.linalg.norm(D, axis=0)
    assert err.max() <= 1e-3 and comp["error"]["max"] <= err.max() + 1e-15
    assert not list(tmp_path.glob(".s.work*")) and not (out / "compliance.npy").exists()
    mtime = (out / "hmatrix_data.npy").stat().st_mtime_ns
    assert build_bundle(out, mesh=small_box, order=1, compress_tol=1e-3, stream=True) == p
    assert (out / "hmatrix_data.npy").stat().st_mtime_ns == mtime
    with pytest.raises(ValueError, match="needs --tol"):
        build_bundle(tmp_path / "x", mesh=small_box, order=1, stream=True)


def _feed(S, D, blocks, order):
    """Feed ``S`` the tree-ordered column blocks ``blocks[i]`` of ``D``, ``i`` in ``order``."""
    for i in order:
        a, b = blocks[i]
        S.add(a, D[:, S.cd[a:b]])


def test_streamed_h_checkpoint_resumes_to_the_uninterrupted_numbers(seat_D, tmp_path):
    """Half the blocks fed, saved, read back into a new StreamedH, the rest fed: the same
    H-matrix as feeding all at once (the same operations in the same order: equal to rounding
    of a re-run, asserted at 1e-12 of D), the same kept columns; a checkpoint under another
    tag, of another tolerance, damaged, or missing is not taken (False, state untouched); a
    state mid-update is not saved."""
    D, rows, cols, part = seat_D
    width, tol = 16, 1e-3
    blocks = [(s, min(s + width, D.shape[1])) for s in range(0, D.shape[1], width)]
    order = np.random.default_rng(3).permutation(len(blocks))
    keep = [5, 1, D.shape[1] - 2]
    whole = StreamedH(rows, cols, part, tol, blocks, keep=keep)
    _feed(whole, D, blocks, order)
    Hw = whole.finish()

    half = len(blocks) // 2
    first = StreamedH(rows, cols, part, tol, blocks, keep=keep)
    _feed(first, D, blocks, order[:half])
    path = tmp_path / "stream.npz"
    tag = {"key": "k", "blocks": [list(b) for b in blocks]}
    assert first.save(path, tag)
    second = StreamedH(rows, cols, part, tol, blocks, keep=keep)
    assert second.resume(path, tag) and second.columns_seen == first.columns_seen
    assert sorted(second.starts) == sorted(blocks[i][0] for i in order[:half])
    _feed(second, D, blocks, order[half:])
    H2 = second.finish()
    assert H2.blocks.tolist() == Hw.blocks.tolist()
    np.testing.assert_allclose(H2.to_dense(), Hw.to_dense(), rtol=0, atol=1e-12 * np.abs(D).max())
    assert sorted(second.kept) == sorted(keep)
    for j in keep:
        np.testing.assert_array_equal(second.kept[j], D[:, j])

    fresh = StreamedH(rows, cols, part, tol, blocks, keep=keep)
    assert not fresh.resume(path, {**tag, "key": "other"}) and fresh.starts == [] and fresh.columns_seen == 0
    assert not StreamedH(rows, cols, part, 2 * tol, blocks, keep=keep).resume(path, tag)
    assert not fresh.resume(tmp_path / "missing.npz", tag)
    damaged = tmp_path / "damaged.npz"
    damaged.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    assert not fresh.resume(damaged, tag) and fresh.starts == []
    with pytest.raises(RuntimeError, match="before any add"):
        second.resume(path, tag)
    first._busy = True  # as within add(), interrupted
    assert not first.save(tmp_path / "busy.npz", tag) and not (tmp_path / "busy.npz").exists()


def test_build_bundle_stream_resumes_after_a_failure(small_box, tmp_path, monkeypatch, caplog):
    """A streamed build that stops on an error after 3 blocks keeps its checkpoint (written after
    every block here, CHECKPOINT_SECONDS = 0) and the same call resumes from it: it solves only
    the missing blocks (``blocks_resumed``), ends with the uninterrupted build's H-matrix and
    removes its checkpoint. A failure inside a block's update (a kill mid-update) leaves the
    previous block's checkpoint, which is resumed the same way."""
    import logging

    from hailstorm.precompute import hstream, solve_loops

    opts = dict(mesh=small_box, order=1, compress_tol=1e-3, stream=True, block_bytes=8 * 1000 * 6)
    ref = load(build_bundle(tmp_path / "ref", **opts))
    n_blocks = ref.manifest["solve_stats"]["blocks"]
    assert n_blocks >= 6
    monkeypatch.setattr(solve_loops, "CHECKPOINT_SECONDS", 0.0)
    for where, kept in (("after", 3), ("inside", 2)):
        name = "add" if where == "after" else "_add"  # add(): between blocks; _add(): within one
        real = getattr(hstream.StreamedH, name)
        calls = {"n": 0}

        def failing(self, start, values, real=real, where=where):
            calls["n"] += 1
            if where == "inside" and calls["n"] == 3:
                raise RuntimeError("disk gone")
            real(self, start, values)
            if where == "after" and calls["n"] == 3:
                raise RuntimeError("disk gone")

        out = tmp_path / where
        monkeypatch.setattr(hstream.StreamedH, name, failing)
        with pytest.raises(RuntimeError, match="disk gone"):
            build_bundle(out, **opts)
        checkpoint = tmp_path / f".{where}.work" / "stream.npz"
        assert checkpoint.is_file() and not (out / "hmatrix_data.npy").exists()
        monkeypatch.setattr(hstream.StreamedH, name, real)
        with caplog.at_level(logging.INFO, logger="hailstorm"):
            gf = load(build_bundle(out, **opts))
        assert f"resuming: {kept} of {n_blocks} blocks done" in caplog.text
        caplog.clear()
        stats = gf.manifest["solve_stats"]
        assert stats["blocks_resumed"] == kept and stats["blocks_solved"] == n_blocks - kept
        assert gf.hmatrix.blocks.tolist() == ref.hmatrix.blocks.tolist()
        D = ref.hmatrix.to_dense()
        np.testing.assert_allclose(gf.hmatrix.to_dense(), D, rtol=0, atol=1e-12 * np.abs(D).max())
        assert gf.manifest["compliance"]["error"]["max"] == pytest.approx(ref.manifest["compliance"]["error"]["max"],
                                                                         rel=1e-9)
        assert not checkpoint.exists() and not checkpoint.parent.exists()


def test_tree_order_permutes_the_columns(box_system):
    """Column j of the reordered problem is column dofs(cols.perm)[j] of D (point loads and hat loads)."""
    import dataclasses
    import scipy.sparse as sp

    from hailstorm.precompute.greens import column_problem

    s = box_system
    problem = column_problem(s.K, s.fixed, s.load, s.read)
    cols = cluster_tree(np.asarray(s.basis.doflocs.T[s.load[::3]], float), leaf=4)  # the loaded vertices
    cd = dofs(cols.perm)
    f = problem.factor()
    np.testing.assert_allclose(tree_order(problem, cols).solve(f, 0, 12),
                               problem.solve(f, 0, problem.shape[1])[:, cd[:12]], rtol=1e-12, atol=1e-18)
    loads = sp.random(problem.Kff.shape[0], problem.shape[1], density=0.01, random_state=0, format="csc")
    hat = dataclasses.replace(problem, loads=loads, load_pos=None)
    np.testing.assert_allclose(tree_order(hat, cols).solve(f, 0, 12), hat.solve(f, 0, hat.shape[1])[:, cd[:12]],
                               rtol=1e-12, atol=1e-18)


def test_bench_stream_prints_both_routes_with_a_header(tmp_path, capsys):
    """tests/benchmarks/bench_stream.py on the 15 mm seat (P1): one table row per route, both within
    the tolerance; ``--resume``'s row (a streamed run stopped and rerun) matches the uninterrupted
    bundle; ``--out`` writes the command and the stamp above what it printed."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_stream.py"
    spec = importlib.util.spec_from_file_location("bench_stream_script", path)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    out = tmp_path / "stream.txt"
    argv = ["--mesh-size", "0.015", "--order", "1", "--load", "point", "--tol", "1e-3", "--resume", "--out", str(out)]
    assert script.main(argv) == 0
    printed = capsys.readouterr().out
    resume = [line for line in printed.splitlines() if line.startswith("| ") and " of " in line]
    assert len(resume) == 1  # the stopped-and-rerun row: the rerun ends with the uninterrupted numbers
    assert float(resume[0].split("|")[-2]) <= 1e-12
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
            for line in printed.splitlines() if line.startswith("| dense") or line.startswith("| stream")}
    assert set(rows) == {"dense", "stream"}
    # peak disk is sampled every 0.2 s: a 2 s run's dense D can fall between samples, so only its form here
    assert all(float(v[5]) >= 0 for v in rows.values())
    assert all(float(v[9]) <= 1e-3 for v in rows.values())
    text = out.read_text().splitlines()
    assert text[0] == "$ python tests/benchmarks/bench_stream.py " + " ".join(argv) and text[1].startswith("# ")
    assert printed.splitlines()[0] in text


def test_streamed_h_is_held_once_when_saved_and_finished(seat_D, tmp_path):
    """The checkpoint and the finished H copy block by block: neither allocates a second H at once
    (Python's allocator traces numpy's buffers). The first 50 000-vertex build held H (2.3 GiB)
    twice in both places and peaked at 10.4 GiB."""
    import tracemalloc

    D, rows, cols, part = seat_D
    blocks = [(s, min(s + 16, D.shape[1])) for s in range(0, D.shape[1], 16)]
    S = StreamedH(rows, cols, part, 1e-3, blocks)
    _feed(S, D, blocks, range(len(blocks)))
    stored = sum(a.nbytes for a in S._near.values()) + sum(f.U.nbytes + f.s.nbytes + f.V.nbytes
                                                            for f in S._far.values())
    largest = max([a.nbytes for a in S._near.values()] + [f.U.nbytes + f.V.nbytes for f in S._far.values()])
    assert largest < 0.1 * stored  # else the test could not tell one H from one block
    tracemalloc.start()
    try:
        assert S.save(tmp_path / "c.npz", {"k": 1})
        save_peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.reset_peak()
        base = tracemalloc.get_traced_memory()[0]
        H = S.finish()
        finish_peak = tracemalloc.get_traced_memory()[1] - base
    finally:
        tracemalloc.stop()
    assert save_peak < 0.3 * stored, (save_peak, stored)
    # H, a block or two in flight, and the block table's Python objects (measured ~520 bytes a block)
    assert finish_peak < H.data.nbytes + 3 * largest + 1024 * H.blocks.shape[0], (finish_peak, H.data.nbytes)
