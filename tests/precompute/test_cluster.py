"""Column blocks on a real Dask cluster (distributed.LocalCluster, 2 worker processes)."""

import logging
import os
import signal
import sys

import numpy as np
import pytest

import hailstorm.runtime
from hailstorm.precompute import build_bundle
from hailstorm.precompute.blocks import BlockStore
from hailstorm.precompute.cluster import ClusterError
from hailstorm.runtime.resources import MissingExtra

distributed = pytest.importorskip("distributed")

BLOCK = 40_000  # ten blocks of the box's D


class KillFirstBlock(distributed.WorkerPlugin):
    """Kills (SIGKILL) the worker process that starts the first block of D, once per flag file."""

    def __init__(self, flag: str):
        self.flag = flag

    def transition(self, key, start, finish, **kwargs):
        if finish == "executing" and str(key).startswith("hailstorm-block"):
            try:
                os.close(os.open(self.flag, os.O_CREAT | os.O_EXCL | os.O_WRONLY))
            except FileExistsError:
                return
            os.kill(os.getpid(), signal.SIGKILL)


@pytest.fixture(scope="module")
def cluster():
    import cloudpickle

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers need not import the tests
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                  silence_logs=logging.ERROR) as c:
        yield c


def _counting_writes(monkeypatch, blocks: list | None = None):
    """The indices of the blocks the store writes (and, into ``blocks``, what it was handed)."""
    written = []
    real = BlockStore.write

    def write(self, i, values):
        written.append(i)
        if blocks is not None:
            blocks.append(values)
        real(self, i, values)

    monkeypatch.setattr(BlockStore, "write", write)
    return written


def _rel(a, b):
    a, b = np.asarray(a), np.asarray(b)
    return np.abs(a - b).max() / np.abs(b).max()


@pytest.fixture(scope="module")
def serial(tmp_path_factory, small_box):
    out = build_bundle(tmp_path_factory.mktemp("serial") / "b", mesh=small_box, young=1e6, poisson=0.3,
                       block_bytes=BLOCK)
    return hailstorm.runtime.load(out)


def test_cluster_gives_the_serial_D(tmp_path, small_box, cluster, serial, monkeypatch):
    written = _counting_writes(monkeypatch)
    gf = hailstorm.runtime.load(build_bundle(tmp_path / "b", mesh=small_box, young=1e6, poisson=0.3,
                                             block_bytes=BLOCK, scheduler=cluster.scheduler_address))
    assert _rel(gf.D, serial.D) <= 1e-12
    stats = gf.manifest["solve_stats"]
    assert stats["workers"] == 2 and sorted(written) == list(range(stats["blocks"]))
    # K_ff factorized once per worker, not once per block
    assert stats["blocks"] == 10 and stats["factorizations"] <= 2
    # the workers' factor reports its nnz(L) and their sweeps their operations (one thread each, so
    # batched differently from the serial run's two: the pruned counts differ a little)
    here = serial.manifest["solve_stats"]
    assert stats["nnz_L"] == here["nnz_L"] and stats["full_solve_flops"] == here["full_solve_flops"]
    assert 0.9 * here["solve_flops"] <= stats["solve_flops"] <= 1.1 * here["solve_flops"]


def test_float32_blocks_are_rounded_on_the_workers(tmp_path, small_box, cluster, serial, monkeypatch):
    """With ``dtype="float32"`` each worker sends its block rounded (half the traffic): the
    store receives float32 RoundedBlocks, and the bundle is the serial float64 D rounded,
    with the cast's error recorded."""
    from hailstorm.runtime.bundle.format import RoundedBlock

    got: list = []
    _counting_writes(monkeypatch, got)
    gf = hailstorm.runtime.load(build_bundle(tmp_path / "b", mesh=small_box, young=1e6, poisson=0.3,
                                             block_bytes=BLOCK, scheduler=cluster.scheduler_address,
                                             dtype="float32"))
    assert got and all(isinstance(v, RoundedBlock) and v.values.dtype == np.float32 for v in got)
    D32, D64 = np.asarray(gf.D), np.asarray(serial.D)
    assert D32.dtype == np.float32
    cast = gf.manifest["dtype_cast"]
    scale = np.abs(D64).max()
    assert 0 < cast["max_abs_error"] <= 2.0 ** -24 * scale * (1 + 1e-9) and 0 < cast["max_rel_error"] <= 2.0 ** -24
    assert np.abs(D32.astype(np.float64) - D64).max() <= cast["max_abs_error"] + 1e-12 * scale


def test_a_killed_worker_has_its_blocks_redone(tmp_path, small_box, cluster, serial, monkeypatch):
    flag = tmp_path / "killed"
    client = distributed.Client(cluster, set_as_default=False)
    try:
        client.register_plugin(KillFirstBlock(str(flag)), name="kill-first-block")
        pids_before = set(client.run(os.getpid).values())
        written = _counting_writes(monkeypatch)
        gf = hailstorm.runtime.load(build_bundle(tmp_path / "b", mesh=small_box, young=1e6, poisson=0.3,
                                                 block_bytes=BLOCK, scheduler=cluster.scheduler_address))
        client.unregister_worker_plugin("kill-first-block")
        client.wait_for_workers(2, timeout=60)
        pids_after = set(client.run(os.getpid).values())
    finally:
        client.close()
    assert flag.exists() and pids_before - pids_after  # a worker died in its first block (and was restarted)
    assert sorted(written) == list(range(gf.manifest["solve_stats"]["blocks"]))  # each block once, none lost
    assert _rel(gf.D, serial.D) <= 1e-12


def test_a_run_interrupted_in_this_process_resumes_on_the_cluster(tmp_path, small_box, cluster, serial,
                                                                  monkeypatch, caplog):
    out = tmp_path / "b"
    real = BlockStore.write
    with monkeypatch.context() as m:
        def write(self, i, values):
            if len(self.done) == 4:
                raise KeyboardInterrupt
            real(self, i, values)

        m.setattr(BlockStore, "write", write)
        with pytest.raises(KeyboardInterrupt):
            build_bundle(out, mesh=small_box, young=1e6, poisson=0.3, block_bytes=BLOCK)
    written = _counting_writes(monkeypatch)
    with caplog.at_level(logging.INFO):
        gf = hailstorm.runtime.load(build_bundle(out, mesh=small_box, young=1e6, poisson=0.3, block_bytes=BLOCK,
                                                 scheduler=cluster.scheduler_address))
    n = gf.manifest["solve_stats"]["blocks"]
    assert f"resuming: 4 of {n} blocks done" in caplog.text
    assert sorted(written) == list(range(4, n))  # only the missing blocks were solved
    assert _rel(gf.D, serial.D) <= 1e-12


def test_local_workers_give_the_serial_D(tmp_path, small_box, serial):
    gf = hailstorm.runtime.load(build_bundle(tmp_path / "b", mesh=small_box, young=1e6, poisson=0.3,
                                             block_bytes=BLOCK, workers=2))
    assert _rel(gf.D, serial.D) <= 1e-12 and gf.manifest["solve_stats"]["workers"] == 2


def test_unreachable_scheduler_is_one_line_before_any_work(tmp_path, monkeypatch, capsys):
    import hailstorm.precompute.cluster as cluster_mod
    import hailstorm.precompute.pipeline as pipeline
    from hailstorm.cli import main

    monkeypatch.setattr(cluster_mod, "CONNECT_TIMEOUT_S", 1.0)

    def no_meshing(*a, **k):
        raise AssertionError("meshed before reaching the scheduler")

    monkeypatch.setattr(pipeline, "load_seat", no_meshing)
    rc = main(["precompute", "--scheduler", "tcp://127.0.0.1:9", "--out", str(tmp_path / "b"), "-q"])
    err = capsys.readouterr().err
    assert rc == 3 and err.count("\n") == 1 and "cannot reach the Dask scheduler" in err
    assert not (tmp_path / "b").exists()


def test_missing_distributed_is_a_clear_error(tmp_path, small_box, monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import fails
    with pytest.raises(MissingExtra, match=r"pip install 'hailstorm\[dask\]'"):
        build_bundle(tmp_path / "b", mesh=small_box, workers=2)
    assert not (tmp_path / "b").exists()


def test_cluster_gives_the_serial_compressed_d(tmp_path, small_box, cluster, serial):
    """``compress_tol`` on a Dask cluster: the same H-matrix as in one process (the columns it is built
    from agree to rounding, and its truncation and error sample are seeded)."""
    here = hailstorm.runtime.load(build_bundle(tmp_path / "here", mesh=small_box, young=1e6, poisson=0.3,
                                               block_bytes=BLOCK, compress_tol=1e-3))
    there = hailstorm.runtime.load(build_bundle(tmp_path / "there", mesh=small_box, young=1e6, poisson=0.3,
                                                block_bytes=BLOCK, scheduler=cluster.scheduler_address,
                                                compress_tol=1e-3))
    assert there.manifest["key"] == here.manifest["key"]
    def tiling(H):  # the blocks' places (a far block kept dense where its rank crosses the threshold moves)
        return sorted(map(tuple, H.blocks[:, :4].tolist()))

    assert tiling(there.hmatrix) == tiling(here.hmatrix)
    assert _rel(there.D, here.D) <= 1e-10 and _rel(there.D, serial.D) <= 1e-3
    assert there.manifest["compliance"]["error"]["max"] <= 1e-3


def test_a_block_the_cluster_cancels_is_submitted_again(tmp_path, small_box, cluster, serial, monkeypatch):
    """A block future the scheduler cancels (its shipped problem lost with a killed worker, seen under
    load) is submitted anew: the bundle is complete and the serial one, each block written once."""
    real = distributed.Client.submit
    cancelled = []

    def submit(self, *args, **kwargs):
        fut = real(self, *args, **kwargs)
        if not cancelled and str(kwargs.get("key", "")).startswith("hailstorm-block"):
            cancelled.append(kwargs["key"])
            fut.cancel()
        return fut

    monkeypatch.setattr(distributed.Client, "submit", submit)
    written = _counting_writes(monkeypatch)
    gf = hailstorm.runtime.load(build_bundle(tmp_path / "b", mesh=small_box, young=1e6, poisson=0.3,
                                             block_bytes=BLOCK, scheduler=cluster.scheduler_address))
    assert cancelled and sorted(written) == list(range(gf.manifest["solve_stats"]["blocks"]))
    assert _rel(gf.D, serial.D) <= 1e-12


def test_cluster_streams_the_serial_compressed_d_within_tol(tmp_path, small_box, cluster, serial):
    """``stream=True`` on a Dask cluster: the blocks come back in completion order, so the far blocks'
    updates come in another order than in one process; the tiling is the same and both are within
    the tolerance of the dense D (the same answer, to the tolerance asked)."""
    kw = dict(mesh=small_box, young=1e6, poisson=0.3, block_bytes=BLOCK, compress_tol=1e-3, stream=True)
    here = hailstorm.runtime.load(build_bundle(tmp_path / "here", **kw))
    there = hailstorm.runtime.load(build_bundle(tmp_path / "there", scheduler=cluster.scheduler_address, **kw))
    assert there.manifest["key"] == here.manifest["key"]
    def tiling(H):
        return sorted(map(tuple, H.blocks[:, :4].tolist()))

    assert tiling(there.hmatrix) == tiling(here.hmatrix)
    D = np.asarray(serial.D)
    for gf in (here, there):
        err = np.linalg.norm(gf.hmatrix.to_dense() - D, axis=0) / np.linalg.norm(D, axis=0)
        assert err.max() <= 1e-3
    assert _rel(there.D, here.D) <= 1e-3
