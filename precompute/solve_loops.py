"""The two loops that solve D's column blocks (:func:`hailstorm.precompute.pipeline.build_bundle`'s solve).

* :func:`solve_dense` -- D dense, block by block into the work directory beside
  the bundle (:class:`hailstorm.precompute.blocks.BlockStore`), each block durable
  when written, so that the same call resumes what an interrupted run left;
* :func:`solve_streamed` -- D compressed as its blocks are solved
  (:class:`hailstorm.precompute.hstream.StreamedH`), never whole on disk or in
  memory, its state checkpointed every :data:`CHECKPOINT_SECONDS`.

Both solve in this process or on a Dask cluster
(:func:`hailstorm.precompute.cluster.solve_blocks`) and record what the solve did
in the manifest's ``solve_stats`` (:func:`solve_record`).
"""

from __future__ import annotations

import logging
import time
from contextlib import AbstractContextManager, nullcontext
from pathlib import Path
from typing import Any

import numpy as np

from hailstorm.precompute.blocks import CHECKPOINT, BlockStore, remove_work_dir, work_dir
from hailstorm.precompute.cluster import SolveStats, cluster_client, solve_blocks
from hailstorm.precompute.greens import ColumnProblem, cholesky_nnz, column_blocks
from hailstorm.precompute.hmatrix import DEFAULT_ETA, DEFAULT_LEAF, ERROR_COLUMNS, Compressed
from hailstorm.precompute.hstream import StreamedH, tree_order
from hailstorm.precompute.htree import admissible_blocks, cluster_tree
from hailstorm.precompute.resources import BASE_BYTES, TooLargeError, available_memory, check_disk, estimate_memory, gib
from hailstorm.precompute.settings import RunSettings
from hailstorm.runtime.bundle.format import BundleError, RoundedBlock
from hailstorm.runtime.bundle.write import StagedArray

log = logging.getLogger(__name__)

__all__ = ["CHECKPOINT_SECONDS", "logging_beside", "progress_bar", "solve_dense", "solve_record", "solve_streamed"]

#: how often (seconds of solving) a streamed compression checkpoints its state
CHECKPOINT_SECONDS = 120.0


def solve_dense(out: Path, problem: ColumnProblem, key: str, run: RunSettings, dtype: str,
                what: str) -> tuple[StagedArray, dict, tuple[float, float]]:
    """Solve D block by block into the work directory beside ``out``, resuming what a
    previous run of the same key left.

    Parameters
    ----------
    out : pathlib.Path
        The bundle directory (its work directory is ``.NAME.work/`` beside it).
    problem : ColumnProblem
        The stiffness, loads and rows of D (:func:`hailstorm.precompute.greens.column_problem`).
    key : str
        The dense bundle's cache key: each block is tagged with it.
    run : RunSettings
        Block size, progress, the disk check, the Dask cluster.
    dtype : {"float64", "float32"}
        D's storage type (blocks are solved in float64 and rounded as they are written).
    what : str
        The solve, for the progress bar's label.

    Returns
    -------
    D : StagedArray
        The finished D, staged for :func:`hailstorm.runtime.bundle.write.write_bundle`.
    stats : dict
        The manifest's ``solve_stats`` (:func:`solve_record`, with nnz(L) and the flop counts when known).
    rounding : tuple of float
        (largest |entry|, largest rounding error) of the cast to ``dtype``.
    """
    n_rows, ncols = problem.shape
    blocks = column_blocks(n_rows, ncols, run.block_bytes, problem.batch)
    store = BlockStore(work_dir(out), key, (n_rows, ncols), blocks, dtype)
    todo = store.missing
    done = len(blocks) - len(todo)
    if done:
        log.info("resuming: %d of %d blocks done (in %s)", done, len(blocks), store.path)
    d_disk = store.data_bytes
    block_disk = d_disk / max(len(blocks), 1)
    try:
        check_disk(block_disk * len(todo), store.path, f"D ({n_rows} x {ncols})", allow_large=run.allow_large)
    except TooLargeError:
        if not done:  # refused before any work: leave no empty work directory behind
            remove_work_dir(store.path)
        raise
    n_dofs = problem.Kff.shape[0]
    block_solved = 8 * n_rows * (blocks[0][1] - blocks[0][0])  # a block is solved in float64 whatever D's type
    est = estimate_memory(n_dofs, block_solved, 1 if run.in_process else 2)
    # the nnz(L) count factors K_ff once more here (SuperLU): skipped when that would not fit comfortably
    count_fill = problem.spec.proxy_fill and bool(todo) and 2 * (est - BASE_BYTES) < available_memory()
    nnz_l = cholesky_nnz(problem.Kff) if count_fill else None
    log.info("D: %d x %d %s, %s on disk (%d blocks of %d columns, %d to compute); "
             "peak memory about %s%s", n_rows, ncols, dtype, gib(d_disk), len(blocks), blocks[0][1] - blocks[0][0],
             len(todo), gib(est), "" if nnz_l is None else f"; nnz(L) about {nnz_l:,}")
    bar = progress_bar(len(blocks), done, what) if run.progress and todo else None

    def on_first(stats: SolveStats) -> None:
        rest = len(todo) - 1
        per = stats.first_block_s - stats.factor_s
        eta = per * rest / max(stats.workers, 1)
        log.info("first block: %.2f s (factorization %.2f s); estimated %.0f s for the other %d blocks",
                 stats.first_block_s, stats.factor_s, eta, rest)

    def on_block(i: int, values: np.ndarray | RoundedBlock) -> None:
        store.write(i, values)
        if bar is not None:
            bar.update(1)

    try:
        with cluster_client(workers=run.workers, scheduler=run.scheduler) if todo else nullcontext() as client, \
                logging_beside(bar):
            stats = solve_blocks(problem, blocks, todo, on_block, client=client, key=key, on_first=on_first,
                                 dtype=dtype)
    except KeyboardInterrupt:
        log.warning("interrupted: %d of %d blocks of D are kept in %s; run the same command again to resume",
                    len(store.done), len(blocks), store.path)
        raise
    except OSError as exc:
        raise BundleError(f"cannot write D to {store.path}: {exc.strerror or exc}; {len(store.done)} of "
                          f"{len(blocks)} finished blocks are kept there (the same command resumes)") from exc
    except Exception:
        if not store.done:  # failed before any block (e.g. the factorization): nothing to resume
            remove_work_dir(store.path)
        raise
    finally:
        if bar is not None:
            bar.close()
    info = solve_record(stats, problem, len(blocks), done)
    if np.isfinite(stats.first_block_s):
        info["first_block_s"] = stats.first_block_s
    nnz_l = stats.nnz_L if stats.nnz_L is not None else nnz_l
    if nnz_l is not None and stats.columns:
        seconds = max(stats.solve_s - stats.factor_s, 1e-9)
        full = 4.0 * nnz_l * stats.columns  # a full forward and backward solve per column
        done_flops = float(stats.solve_flops) if stats.solve_flops else full
        info.update(nnz_L=nnz_l, solve_flops=done_flops, full_solve_flops=full,
                    solve_gflop_per_s=done_flops / seconds / 1e9)
        log.info("solved %d blocks (%d columns) in %.1f s on %d worker(s): nnz(L) %s; triangular solves %.3g GFLOP "
                 "(%.0f %% of 4 nnz(L) per column), %.2f GFLOP/s", stats.blocks, stats.columns, stats.solve_s,
                 stats.workers, f"{nnz_l:,}", done_flops / 1e9, 100 * done_flops / full, done_flops / seconds / 1e9)
    return store.finish(), info, store.rounding


def solve_streamed(out: Path, problem: ColumnProblem, vertices: np.ndarray, contact_vertices: np.ndarray,
                   tol: float, key: str, run: RunSettings, what: str) -> tuple[Compressed, dict]:
    """Solve D's columns in the column tree's order and compress them as they come.

    The far blocks are truncated to ``tol / 2`` each
    (:class:`hailstorm.precompute.hstream.StreamedH`); the result is measured on
    :data:`hailstorm.precompute.hmatrix.ERROR_COLUMNS` exact columns drawn at random
    (seed 0) before the solve. The state is checkpointed beside ``out``
    (``.NAME.work/stream.npz``) every :data:`CHECKPOINT_SECONDS` of solving and when the
    solve stops on an error or an interruption; a run with the same key, tolerance and
    blocks resumes from it.

    Parameters
    ----------
    out : pathlib.Path
        The bundle directory (its work directory is beside it).
    problem : ColumnProblem
        The stiffness, loads and rows of D.
    vertices : (n, 3) ndarray
        The surface vertices (D's rows); ``contact_vertices`` (its columns) index them.
    contact_vertices : (m,) ndarray of int
    tol : float
        The compression's target column error.
    key : str
        The dense source's cache key (the checkpoint is tagged with it).
    run : RunSettings
        Block size, progress, the Dask cluster.
    what : str
        The solve, for the progress bar's label.

    Returns
    -------
    compressed : Compressed
        The H-matrix, its tolerances and its measured column error.
    stats : dict
        The manifest's ``solve_stats`` (:func:`solve_record`).

    Raises
    ------
    ValueError
        The measured column error exceeds ``tol`` (naming the error reached).
    """
    t0 = time.perf_counter()
    V = np.asarray(vertices, dtype=np.float64)
    rows, cols = cluster_tree(V, leaf=DEFAULT_LEAF), cluster_tree(V[contact_vertices], leaf=DEFAULT_LEAF)
    part = admissible_blocks(rows, cols, DEFAULT_ETA)
    n_rows, ncols = problem.shape
    blocks = column_blocks(n_rows, ncols, run.block_bytes, problem.batch)
    picked = np.sort(np.random.default_rng(0).choice(ncols, size=min(ERROR_COLUMNS, ncols), replace=False))
    streamed = StreamedH(rows, cols, part, tol / 2, blocks, keep=picked)
    wd = work_dir(out)
    checkpoint = wd / CHECKPOINT
    tag = {"key": key, "tol": tol, "blocks": [list(b) for b in blocks], "error_columns": picked.tolist()}
    if checkpoint.is_file() and not streamed.resume(checkpoint, tag):
        log.info("checkpoint %s was for other inputs (or unreadable); starting afresh", checkpoint)
    have = set(streamed.starts)
    todo = [i for i, (start, _) in enumerate(blocks) if start not in have]
    done = len(blocks) - len(todo)
    if done:
        log.info("resuming: %d of %d blocks done (checkpoint %s)", done, len(blocks), checkpoint)
    log.info("D: %d x %d, compressed as it is solved (%d blocks of %d columns, %d to compute; the dense D "
             "would be %s)", n_rows, ncols, len(blocks), blocks[0][1] - blocks[0][0], len(todo),
             gib(8 * n_rows * ncols))
    bar = progress_bar(len(blocks), done, what) if run.progress else None
    saving = {"last": time.monotonic(), "ok": True}

    def save() -> bool:
        """Checkpoint the state; a failed write warns once and the run goes on without."""
        if not saving["ok"] or not streamed.starts:
            return False
        t = time.perf_counter()
        try:
            wd.mkdir(exist_ok=True)
            saved = streamed.save(checkpoint, tag)
        except OSError as exc:
            saving["ok"] = False
            log.warning("cannot checkpoint the streamed compression to %s (%s); going on without: an "
                        "interruption will start the solve afresh", checkpoint, exc.strerror or exc)
            return False
        saving["last"] = time.monotonic()
        if saved:
            log.info("checkpoint: %d of %d blocks, %s in %.1f s", len(streamed.starts), len(blocks),
                     gib(checkpoint.stat().st_size), time.perf_counter() - t)
        return saved

    def on_block(i: int, values: np.ndarray | RoundedBlock) -> None:
        streamed.add(blocks[i][0], values)
        if time.monotonic() - saving["last"] >= CHECKPOINT_SECONDS:
            save()
        if bar is not None:
            bar.update(1)

    try:
        with cluster_client(workers=run.workers, scheduler=run.scheduler) if todo else nullcontext() as client, \
                logging_beside(bar):
            # its own solve key: the workers cache the problem by key, and these columns are in another order
            stats = solve_blocks(tree_order(problem, cols), blocks, todo, on_block, client=client,
                                 key=f"{key}:tree", dtype="float64")
    except BaseException:
        if save():
            log.warning("stopped: %d of %d blocks of D are compressed in %s; run the same command again to resume",
                        len(streamed.starts), len(blocks), checkpoint)
        raise
    finally:
        if bar is not None:
            bar.close()
    H = streamed.finish()
    _, err = streamed.errors(H)
    checkpoint.unlink(missing_ok=True)  # what is left is deterministic: a resumed run would end the same
    try:
        wd.rmdir()  # only if empty: an interrupted dense build of the same bundle keeps its blocks
    except OSError:
        pass
    worst = float(err.max(initial=0.0))
    if worst > tol:
        raise ValueError(f"the compression tolerance {tol:g} is unreachable while streaming: the H-matrix "
                         f"(per-block truncation {tol / 2:g}) has columns off by up to {worst:.3g}")
    error = {"columns": int(err.size), "max": worst, "median": float(np.median(err)) if err.size else 0.0, "seed": 0}
    return Compressed(H, tol, tol / 2, error, time.perf_counter() - t0), solve_record(stats, problem, len(blocks), done)


def solve_record(stats: SolveStats, problem: ColumnProblem, blocks: int, resumed: int) -> dict[str, Any]:
    """The manifest's ``solve_stats`` of a block loop: blocks, columns, workers, seconds, solver."""
    return {"blocks": blocks, "blocks_solved": stats.blocks, "blocks_resumed": resumed,
            "columns_solved": stats.columns, "workers": stats.workers, "factorizations": stats.factorizations,
            "factor_s": stats.factor_s, "solve_s": stats.solve_s, "solver": problem.solver, "batch": problem.batch}


def progress_bar(total: int, done: int, what: str) -> Any:
    """A progress bar over D's ``total`` column blocks, ``done`` of them already done
    (tqdm's; ``what``: the solve, for its label)."""
    from tqdm.auto import tqdm

    return tqdm(total=total, initial=done, desc=f"Green's functions ({what})", unit="block")


def logging_beside(bar: Any) -> AbstractContextManager:
    """Log messages above the progress bar ``bar`` instead of through it (None: no bar)."""
    if bar is None:
        return nullcontext()
    from tqdm.contrib.logging import logging_redirect_tqdm

    return logging_redirect_tqdm()
