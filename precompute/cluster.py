"""Column blocks of D solved in this process or on a Dask cluster.

:func:`solve_blocks` runs a list of column blocks of a
:class:`hailstorm.precompute.greens.ColumnProblem` and hands each finished
block to a callback (the block store writes it to disk). Where they run:

* in this process (``client=None``, the default): one factorization, then the
  blocks in order, each handed to the callback in a writer thread while the
  next one is solved (the disk time overlaps the solves). Nothing to start, so this is the default for every mesh
  that one machine can do: a local Dask cluster costs seconds to start and a
  second factorization per extra process;
* on a Dask cluster (:func:`cluster_client`: ``workers=N`` starts a
  ``distributed.LocalCluster`` of N single-threaded processes on this machine,
  ``scheduler=ADDRESS`` connects to a running cluster). The problem (K_ff and
  the load/read maps) is sent to every worker once (``scatter(broadcast=True)``);
  each worker factorizes it on its first block and keeps the factorization in
  a per-process cache keyed by the problem's key, so later blocks on that
  worker only solve. A worker that dies takes its running blocks with it:
  the scheduler reruns them elsewhere (and the nanny restarts the worker).
  At most two blocks per worker are in flight, so the client holds a few
  blocks at a time, never all of D.

``distributed`` is the optional ``[dask]`` extra; asking for a cluster without
it raises :class:`hailstorm.runtime.resources.MissingExtra` naming the extra to install.
"""

from __future__ import annotations

import logging
import os
import threading
import time
import uuid
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Iterator, Protocol, Sequence

import numpy as np

from hailstorm.runtime.bundle.format import RoundedBlock, round_block
from hailstorm.runtime.resources import require_extra



class ColumnProblem(Protocol):
    """What the block loop needs of a column problem
    (:class:`hailstorm.precompute.greens.ColumnProblem` is the one implementation):
    a factorization, and the solve of the columns ``start:stop`` with it."""

    def factor(self, threads: int | None = None) -> Any:
        """Factorize the system (once per process)."""

    def solve(self, factor: Any, start: int, stop: int) -> np.ndarray:
        """The (rows, stop - start) block of D."""

log = logging.getLogger(__name__)

__all__ = ["ClusterError", "SolveStats", "check_scheduler", "cluster_client", "require_distributed", "solve_blocks", "solve_on_worker"]

#: Seconds to wait for a scheduler (an unreachable one is refused after this).
CONNECT_TIMEOUT_S = 10.0
#: times one block is submitted again after the cluster cancelled it (its shipped problem lost with a
#: worker; seen under load when a worker is killed) before the run gives up
CANCEL_RETRIES = 3


class ClusterError(ValueError):
    """A Dask cluster cannot be used: ``distributed`` is missing, the scheduler is
    unreachable, or blocks kept failing on the workers."""


@dataclass
class SolveStats:
    """What :func:`solve_blocks` did.

    Attributes
    ----------
    blocks, columns : int
        Blocks and columns solved in this call.
    factor_s : float
        Wall time of the factorization (in this process; on a cluster the
        workers' own, the largest).
    solve_s : float
        Wall time from the first block submitted to the last one written.
    first_block_s : float
        Wall time until the first block came back (factorization included).
    workers : int
        Processes that solved blocks (1 in this process).
    factorizations : int
        Factorizations of K_ff done (one per process that solved blocks,
        unless a worker died and was restarted).
    nnz_L : int or None
        Entries of the factorization's L, if the solver reports it (the
        supernodal one does).
    solve_flops : int
        Floating-point operations of the triangular solves the solver counted
        (0 if it does not count them).
    factors : dict
        Factorization seconds by worker (on a cluster).
    """

    blocks: int = 0
    columns: int = 0
    factor_s: float = 0.0
    solve_s: float = 0.0
    first_block_s: float = float("nan")
    workers: int = 1
    factorizations: int = 0
    nnz_L: int | None = None
    solve_flops: int = 0
    factors: dict[str, float] = field(default_factory=dict)


def require_distributed():
    """The ``distributed`` module, or :class:`hailstorm.runtime.resources.MissingExtra` naming the dask extra."""
    return require_extra("distributed", "dask", "--workers and --scheduler (Dask's distributed)")


@contextmanager
def cluster_client(*, workers: int | None = None, scheduler: str | None = None) -> Iterator[Any]:
    """A ``distributed.Client`` for ``workers`` local processes or the cluster at ``scheduler``.

    Yields ``None`` if neither is given (solve in this process). The local
    cluster's workers are single-threaded processes (dashboard on a free port); the
    cluster and client are closed on exit.

    Raises
    ------
    ClusterError
        ``distributed`` is not installed, both or a bad value were given, or
        the scheduler did not answer within :data:`CONNECT_TIMEOUT_S`.
    """
    if workers is not None and scheduler is not None:
        raise ClusterError("give --workers (a local cluster) or --scheduler (an existing one), not both")
    if workers is None and scheduler is None:
        yield None
        return
    if workers is not None and (not isinstance(workers, int) or workers < 1):
        raise ClusterError(f"--workers must be a positive number of processes, got {workers!r}")
    distributed = require_distributed()
    if scheduler is not None:
        try:
            client = distributed.Client(scheduler, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
        except (OSError, TimeoutError, ValueError, TypeError) as exc:
            raise ClusterError(f"cannot reach the Dask scheduler at {scheduler!r} "
                               f"({type(exc).__name__}: {' '.join(str(exc).split())[:200]})") from None
        try:
            yield client
        finally:
            client.close()
        return
    # one BLAS thread per worker: the workers are the parallelism
    env = {k: "1" for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")}
    cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                       dashboard_address=":0", silence_logs=logging.ERROR, env=env)
    try:
        client = distributed.Client(cluster, set_as_default=False)
        try:
            yield client
        finally:
            client.close()
    finally:
        cluster.close()


def check_scheduler(scheduler: str) -> None:
    """Connect to the Dask scheduler at ``scheduler`` and disconnect: :class:`ClusterError`
    (one line) if ``distributed`` is missing or nobody answers."""
    with cluster_client(scheduler=scheduler):
        pass


def solve_blocks(
    problem: ColumnProblem,
    blocks: Sequence[tuple[int, int]],
    todo: Iterable[int],
    on_block: Callable[[int, "np.ndarray | RoundedBlock"], None],
    *,
    client: Any = None,
    key: str = "",
    on_first: Callable[[SolveStats], None] | None = None,
    dtype: str = "float64",
) -> SolveStats:
    """Solve the column blocks ``todo`` (indices into ``blocks``) and pass each to ``on_block``.

    Parameters
    ----------
    problem
        The system and columns (:func:`hailstorm.precompute.greens.column_problem`).
    blocks
        (start, stop) column range of every block.
    todo
        Which blocks to solve.
    on_block
        Called in this process as ``on_block(i, values)`` with block ``i``'s
        (n_rows, stop - start) values, in completion order, one call at a
        time; an exception it raises (a full disk) stops the run. In this
        process (``client=None``) it runs in a writer thread while the next
        block is solved, so its error surfaces after that solve.
    client
        A ``distributed.Client`` (:func:`cluster_client`), or ``None``: here.
    key
        Identifies ``problem`` in the workers' factorization cache: equal keys
        must mean equal K_ff (the bundle's cache key); a new key evicts the
        old factorization. Default: a fresh one (no reuse across calls).
    on_first
        Called once after the first block, with the statistics so far (for
        an estimate of the remaining time).
    dtype
        D's storage type. On a cluster each worker rounds its block to it
        (:func:`hailstorm.runtime.bundle.format.round_block`) before sending it, and
        ``on_block`` receives a :class:`~hailstorm.runtime.bundle.format.RoundedBlock`
        (float32: half the network traffic); here it receives the float64 values.

    Returns
    -------
    SolveStats
    """
    todo = list(todo)
    stats = SolveStats()
    if not todo:
        return stats
    if client is None:
        return _solve_here(problem, blocks, todo, on_block, on_first, stats)
    return _solve_on_cluster(problem, blocks, todo, on_block, client, key or uuid.uuid4().hex, on_first, stats,
                             dtype)


def _solve_here(problem, blocks, todo, on_block, on_first, stats: SolveStats) -> SolveStats:
    # Write-behind: block k is handed to on_block (the store: cast, pwrite, fdatasync, SHA-256, all of
    # which release the GIL) in a writer thread while block k + 1 is solved here, so the disk time
    # (measured 15-25 % of the solve at 3 mm) overlaps the solves instead of adding to them. One
    # write in flight at most: two blocks in memory (resources.BLOCKS_IN_MEMORY counts them). A
    # write that fails is raised here when the next block is solved; an interruption waits for the
    # write in flight, so every block handed over is on disk or reported.
    t0 = time.perf_counter()
    factor = problem.factor()
    stats.factor_s = time.perf_counter() - t0
    stats.factorizations = 1
    stats.nnz_L = factor.nnz_L
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="hailstorm-writer") as writer:
        pending = None
        for n, i in enumerate(todo):
            start, stop = blocks[i]
            flops = factor.flops
            values = problem.solve(factor, start, stop)
            stats.solve_flops += factor.flops - flops
            if pending is not None:
                pending.result()  # the previous block is on disk, or its error is raised here
            pending = writer.submit(on_block, i, values)
            del values
            stats.blocks += 1
            stats.columns += stop - start
            if n == 0:
                stats.first_block_s = time.perf_counter() - t0
                if on_first is not None:
                    on_first(stats)
        if pending is not None:
            pending.result()
    stats.solve_s = time.perf_counter() - t0
    return stats


def _solve_on_cluster(problem, blocks, todo, on_block, client, key, on_first, stats: SolveStats,
                      dtype: str) -> SolveStats:
    distributed = require_distributed()
    t0 = time.perf_counter()
    n_workers = max(1, len(client.scheduler_info().get("workers", {})))
    stats.workers = n_workers
    ship = {"problem": client.scatter(problem, broadcast=True, hash=False)}  # once per worker
    queue = list(todo)
    window = 2 * n_workers
    meta: dict[Any, int] = {}
    retries: dict[int, int] = {}

    def submit(i: int):
        start, stop = blocks[i]
        again = f"-again{retries[i]}" if retries.get(i) else ""
        fut = client.submit(solve_on_worker, ship["problem"], key, start, stop, dtype, pure=False,
                            key=f"hailstorm-block-{key[:12]}-{i}{again}")
        meta[fut] = i
        return fut

    pending = distributed.as_completed([submit(queue.pop(0)) for _ in range(min(window, len(queue)))], loop=client.loop)
    try:
        for fut in pending:
            i = meta.pop(fut)
            try:
                values, worker, factor_s, (nnz_L, flops) = fut.result()
            except distributed.client.FutureCancelledError as exc:
                # the scheduler dropped the block: a worker that died took the shipped problem with it
                # (seen under load), or the client is closing. Blocks are idempotent: ship the problem
                # again if it is gone and submit the block anew, a few times at most.
                retries[i] = retries.get(i, 0) + 1
                if retries[i] > CANCEL_RETRIES or client.status != "running":
                    raise ClusterError(f"block {i} was cancelled on the cluster ({exc})") from None
                if ship["problem"].status != "finished":
                    ship["problem"] = client.scatter(problem, broadcast=True, hash=False)
                log.info("block %d was cancelled on the cluster (%s); submitting it again", i, exc)
                pending.add(submit(i))
                continue
            except ValueError as exc:  # round_block: an entry overflows the storage type
                raise ValueError(f"block {i}: {exc}") from None
            except Exception as exc:
                if type(exc).__name__ == "KilledWorker":
                    raise ClusterError(f"block {i} killed the Dask workers that ran it several times "
                                       f"(out of memory? each worker needs one factorization and one block): "
                                       f"{' '.join(str(exc).split())[:200]}") from None
                raise
            fut.release()
            if factor_s:
                stats.factors[worker] = factor_s
                stats.factorizations += 1
            stats.nnz_L = nnz_L
            stats.solve_flops += flops
            on_block(i, values)
            del values
            start, stop = blocks[i]
            stats.blocks += 1
            stats.columns += stop - start
            if stats.blocks == 1:
                stats.first_block_s = time.perf_counter() - t0
                stats.factor_s = max(stats.factors.values(), default=0.0)
                if on_first is not None:
                    on_first(stats)
            if queue:
                pending.add(submit(queue.pop(0)))
    finally:
        for fut in list(meta):
            fut.cancel()
        ship["problem"].release()
    stats.factor_s = max(stats.factors.values(), default=stats.factor_s)
    stats.solve_s = time.perf_counter() - t0
    return stats


# --------------------------------------------------------------------------- worker side

_cache_lock = threading.Lock()
_factors: dict[str, Any] = {}


def solve_on_worker(problem: ColumnProblem, key: str, start: int, stop: int,
                    dtype: str = "float64") -> tuple[RoundedBlock, str, float, tuple[int | None, int]]:
    """The task a Dask worker runs: columns ``start:stop`` of D, rounded to ``dtype``.

    Factorizes ``problem`` on this worker's first block of ``key`` and keeps
    the factorization for the next ones (one per process: a new key evicts
    the old). Solves are serialized per process (run workers with one
    thread: ``dask worker ADDRESS --nthreads 1``), each on one thread. The block is cast to D's
    storage type here (:func:`hailstorm.runtime.bundle.format.round_block`), so a
    float32 block travels at half the size.

    Returns
    -------
    block : RoundedBlock
        The (n_rows, stop - start) values in ``dtype`` and the cast's error.
    worker : str
        Which process computed it (host:pid).
    factor_s : float
        Seconds spent factorizing for this block (0 if the factorization was cached).
    work : (int or None, int)
        The factor's nnz(L) and the floating-point operations of this block's
        triangular solves (see :class:`SolveStats`).

    Raises
    ------
    ValueError
        An entry overflows ``dtype``.
    """
    factor_s = 0.0
    with _cache_lock:
        factor = _factors.get(key)
        if factor is None:
            _factors.clear()
            t0 = time.perf_counter()
            factor = problem.factor(threads=1)
            factor_s = time.perf_counter() - t0
            _factors[key] = factor
        flops = factor.flops
        values = problem.solve(factor, start, stop)
        work = (factor.nnz_L, factor.flops - flops)
    return round_block(values, dtype), f"{os.uname().nodename}:{os.getpid()}", factor_s, work
