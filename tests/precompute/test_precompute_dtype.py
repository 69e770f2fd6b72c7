"""``precompute --dtype float32``: D solved in float64 and rounded block by block as it is written."""

import logging

import numpy as np
import pytest

import hailstorm.runtime
from hailstorm.precompute import build_bundle
from hailstorm.precompute.blocks import BlockStore, work_dir
from hailstorm.precompute.greens import ColumnProblem
from hailstorm.precompute.resources import estimate_geometry, estimate_mesh
from hailstorm.runtime.bundle.format import read_manifest
from helpers import count_solves, interrupt_after  # the block-store test helpers

#: small blocks, so that the 216-node box has several (as in test_blocks)
BLOCK = 40_000
#: unit roundoff of float32 (round to nearest)
U32 = 2.0**-24
BOX = dict(young=1e6, poisson=0.3, block_bytes=BLOCK)


@pytest.fixture(scope="module")
def box64(tmp_path_factory, small_box):
    return build_bundle(tmp_path_factory.mktemp("d64") / "b", mesh=small_box, **BOX)


def _rel_rounding(d32, d64):
    """Largest |fl32(x) - x| / |x| over the nonzero entries, in float64."""
    d32, d64 = np.asarray(d32, dtype=np.float64), np.asarray(d64)
    nz = d64 != 0
    assert np.array_equal(d32 != 0, nz)
    return float((np.abs(d32 - d64)[nz] / np.abs(d64[nz])).max())


def test_float32_build_is_the_float64_build_rounded_entry_by_entry(tmp_path, small_box, box64, box_bundle):
    out = build_bundle(tmp_path / "b32", mesh=small_box, dtype="float32", **BOX)
    g32, g64 = hailstorm.runtime.load(out, rehash=True), hailstorm.runtime.load(box64)
    assert g32.manifest["solve_stats"]["blocks"] > 3  # the cast happened block by block
    assert g32.dtype == np.float32 and g32.D.flags.f_contiguous and g32.D.shape == g64.D.shape
    D64 = np.asarray(g64.D)
    # each entry is its float64 value rounded to nearest: within 2^-24 of itself ...
    assert 0 < _rel_rounding(g32.D, D64) <= U32
    # ... and exactly numpy's rounding of the float64 build
    assert np.array_equal(np.asarray(g32.D), D64.astype(np.float32))
    assert (out / "compliance.npy").stat().st_size < 0.51 * (box64 / "compliance.npy").stat().st_size
    m = g32.manifest
    assert m["options"]["dtype"] == "float32" and m["arrays"]["compliance"]["dtype"] == "<f4"
    cast = m["dtype_cast"]
    assert cast["source_dtype"] == "float64" and cast["source_key"] == g64.manifest["key"]
    assert cast["max_abs_error"] == np.abs(np.asarray(g32.D, dtype=np.float64) - D64).max()
    assert 0 < cast["max_rel_error"] <= U32
    # the keys: float32 has its own; float64 (asked for or not) keeps the key bundles had before the option
    assert m["key"] != g64.manifest["key"]
    assert "dtype" not in g64.manifest["options"] and "dtype_cast" not in g64.manifest
    assert g64.manifest["key"] == read_manifest(box_bundle)["key"]  # box_bundle: built without dtype=
    again = build_bundle(tmp_path / "b64", mesh=small_box, dtype="float64", **BOX)
    assert read_manifest(again)["key"] == g64.manifest["key"]


def test_float32_and_float64_bundles_at_one_out_are_not_confused(tmp_path, small_box, monkeypatch):
    out = tmp_path / "b"
    build_bundle(out, mesh=small_box, **BOX)
    calls = count_solves(monkeypatch)
    g = hailstorm.runtime.load(build_bundle(out, mesh=small_box, dtype="float32", **BOX))
    assert g.dtype == np.float32 and len(calls) == g.manifest["solve_stats"]["blocks"]  # not reused


def test_a_float32_run_does_not_resume_float64_blocks(tmp_path, small_box, box64, monkeypatch, caplog):
    """The decision: a work directory of float64 blocks is another run's (another key): started afresh."""
    out = tmp_path / "b"
    with monkeypatch.context() as m:
        written = interrupt_after(m, 3)
        with pytest.raises(KeyboardInterrupt):
            build_bundle(out, mesh=small_box, **BOX)  # float64, interrupted
    assert written == [0, 1, 2] and len(list((work_dir(out) / "blocks").iterdir())) == 3
    calls = count_solves(monkeypatch)
    with caplog.at_level(logging.INFO):
        g = hailstorm.runtime.load(build_bundle(out, mesh=small_box, dtype="float32", **BOX))
    assert "starting afresh" in caplog.text and "D as float64" in caplog.text and "resuming" not in caplog.text
    assert len(calls) == g.manifest["solve_stats"]["blocks"]
    assert g.dtype == np.float32
    assert np.array_equal(np.asarray(g.D), np.asarray(hailstorm.runtime.load(box64).D).astype(np.float32))


def test_an_interrupted_float32_run_resumes_its_own_blocks(tmp_path, small_box, box64, monkeypatch, caplog):
    out = tmp_path / "b"
    with monkeypatch.context() as m:
        interrupt_after(m, 3)
        with pytest.raises(KeyboardInterrupt):
            build_bundle(out, mesh=small_box, dtype="float32", **BOX)
    calls = count_solves(monkeypatch)
    with caplog.at_level(logging.INFO):
        g = hailstorm.runtime.load(build_bundle(out, mesh=small_box, dtype="float32", **BOX), rehash=True)
    n = g.manifest["solve_stats"]["blocks"]
    assert f"resuming: 3 of {n} blocks done" in caplog.text and len(calls) == n - 3
    D64 = np.asarray(hailstorm.runtime.load(box64).D)
    assert np.array_equal(np.asarray(g.D), D64.astype(np.float32))
    # the rounding recorded covers the resumed blocks too (kept in their records)
    assert g.manifest["dtype_cast"]["max_abs_error"] == np.abs(np.asarray(g.D, dtype=np.float64) - D64).max()


def test_a_block_overflowing_float32_is_refused_and_not_recorded(tmp_path):
    store = BlockStore(tmp_path / "w", "k" * 64, (4, 4), [(0, 2), (2, 4)], "float32")
    with pytest.raises(ValueError, match="overflow"):
        store.write(0, np.full((4, 2), 1e39))
    assert store.missing == [0, 1] and not list((tmp_path / "w" / "blocks").iterdir())
    store.write(1, np.full((4, 2), 1.0 / 3.0))
    scale, err = store.rounding
    assert scale == 1.0 / 3.0 and err == abs(float(np.float32(1.0 / 3.0)) - 1.0 / 3.0)
    with pytest.raises(ValueError, match="float16"):
        BlockStore(tmp_path / "w2", "k" * 64, (4, 4), [(0, 4)], "float16")


def test_a_block_rounded_elsewhere_is_written_as_it_came(tmp_path):
    """A RoundedBlock (cast where it was solved: a Dask worker) is stored exactly (one code path: the cast, then its storage) with its
    recorded error; one in the wrong storage type or shape is refused before any write."""
    from hailstorm.runtime.bundle.format import round_block

    store = BlockStore(tmp_path / "w", "k" * 64, (4, 4), [(0, 2), (2, 4)], "float32")
    vals = np.arange(8.0).reshape(4, 2) / 3.0
    blk = round_block(vals, "float32")
    assert blk.values.dtype == np.float32 and blk.max_abs == vals.max()
    assert blk.max_abs_error == np.abs(vals.astype(np.float32).astype(np.float64) - vals).max() > 0
    with pytest.raises(ValueError, match="float64"):
        store.write(0, round_block(vals, "float64"))
    with pytest.raises(ValueError, match="shape"):
        store.write(0, round_block(vals[:, :1], "float32"))
    with pytest.raises(ValueError, match="overflow"):
        round_block(np.full((4, 2), 1e39), "float32")
    assert store.missing == [0, 1]
    store.write(0, blk)
    store.write(1, vals)  # float64 values: cast here, the same way
    assert store.rounding == (vals.max(), blk.max_abs_error)
    D = np.load(tmp_path / "w" / "compliance.npy")
    assert np.array_equal(D[:, :2], blk.values) and np.array_equal(D[:, 2:], vals.astype(np.float32))


def test_bad_dtype_is_refused_before_any_work(tmp_path, small_box, monkeypatch):
    calls = count_solves(monkeypatch)
    for bad in ("float16", "f4", np.float32, None):
        with pytest.raises(ValueError, match="storage type"):
            build_bundle(tmp_path / "b", mesh=small_box, dtype=bad, **BOX)
    assert not calls and not (tmp_path / "b").exists() and not work_dir(tmp_path / "b").exists()


def test_estimates_of_d_halve_and_the_solver_memory_does_not():
    for e64, e32 in [(estimate_mesh(12078, 10401, 21000, 1), estimate_mesh(12078, 10401, 21000, 1, "float32")),
                     (estimate_geometry(0.02, 0.05, 1e-4, 0.002), estimate_geometry(0.02, 0.05, 1e-4, 0.002,
                                                                                    dtype="float32"))]:
        assert abs(e32.d_bytes - e64.d_bytes / 2) <= 1
        assert e32.total_bytes == e64.total_bytes  # blocks are solved in float64 either way
    assert estimate_mesh(12078, 10401, 21000, 1).d_bytes == 9 * 8 * 12078 * 10401


def test_cli_dtype_float32_and_info(tmp_path, capsys):
    from hailstorm.cli import main

    out = tmp_path / "b"
    assert main(["precompute", "--mesh-size", "0.03", "--order", "1", "--dtype", "float32", "--out", str(out), "-q"]) == 0
    g = hailstorm.runtime.load(out)
    assert g.dtype == np.float32 and g.manifest["options"]["dtype"] == "float32"
    capsys.readouterr()
    assert main(["info", str(out)]) == 0
    line = [s for s in capsys.readouterr().out.splitlines() if s.startswith("D ")][0]
    assert "float32" in line and "float64" not in line
    with pytest.raises(SystemExit) as exc:
        main(["precompute", "--dtype", "float16", "--out", str(tmp_path / "c")])
    assert exc.value.code == 2


@pytest.mark.parametrize("order", [1, 2])
def test_the_estimate_counts_the_assembly_it_measures(small_box, order):
    """The FE basis and the assembly's triplets (tracemalloc sees numpy's allocations) fit in the
    per-dof allowance, which the estimate includes (it was missing: the peak was the solve's only)."""
    import tracemalloc

    from hailstorm.precompute.fem import elasticity_basis, stiffness_matrix
    from hailstorm.precompute.resources import ASSEMBLY_BYTES_PER_DOF, BASE_BYTES

    tracemalloc.start()
    try:
        K = stiffness_matrix(elasticity_basis(small_box, order), 1e6, 0.3)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak <= ASSEMBLY_BYTES_PER_DOF * K.shape[0]
    est = estimate_mesh(100, 50, small_box.points.shape[0], order)
    assert est.n_dofs >= K.shape[0] and est.total_bytes >= BASE_BYTES + ASSEMBLY_BYTES_PER_DOF * est.n_dofs


def test_the_fe_basis_is_freed_before_the_solve(tmp_path, small_box, monkeypatch):
    import weakref

    import hailstorm.precompute.pipeline as pipeline

    refs, alive = [], []
    real_basis, real_solve = pipeline.elasticity_basis, ColumnProblem.solve

    def basis(*a, **k):
        b = real_basis(*a, **k)
        refs.append(weakref.ref(b))
        return b

    def solve(self, factor, start, stop):
        alive.append(refs[0]() is not None)
        return real_solve(self, factor, start, stop)

    monkeypatch.setattr(pipeline, "elasticity_basis", basis)
    monkeypatch.setattr(ColumnProblem, "solve", solve)
    build_bundle(tmp_path / "b", mesh=small_box, **BOX)
    assert alive and not any(alive)
