"""The serial block loop writes block k while it solves block k + 1 (solve_blocks, client=None)."""

import threading

import numpy as np
import pytest
import scipy.sparse as sp

from hailstorm.precompute.cluster import solve_blocks
from hailstorm.precompute.greens import column_blocks, column_problem

N = 60


def _problem():
    """A small SPD system (a 1-D Laplacian plus a diagonal shift): every dof loaded, every dof read."""
    K = sp.diags([-np.ones(N - 1), 2.5 * np.ones(N), -np.ones(N - 1)], [-1, 0, 1], format="csr")
    dofs = np.arange(N)
    return K, column_problem(K, np.array([], dtype=np.int64), dofs, dofs, batch=4)


class _Watched:
    """A ColumnProblem that tells which blocks have started solving."""

    def __init__(self, problem):
        self.problem = problem
        self.started: list[int] = []
        self.second_started = threading.Event()

    def factor(self):
        return self.problem.factor()

    def solve(self, factor, start, stop):
        self.started.append(start)
        if len(self.started) == 2:
            self.second_started.set()
        return self.problem.solve(factor, start, stop)


def test_serial_blocks_are_the_inverse_and_arrive_in_order():
    K, problem = _problem()
    blocks = column_blocks(N, N, block_bytes=8 * N * 8, batch=4)  # 8 columns a block
    assert len(blocks) > 3
    got: dict[int, np.ndarray] = {}
    order: list[int] = []

    def on_block(i, values):
        order.append(i)
        got[i] = values

    stats = solve_blocks(problem, blocks, range(len(blocks)), on_block)
    assert order == list(range(len(blocks)))
    assert stats.blocks == len(blocks) and stats.columns == N
    D = np.hstack([got[i] for i in range(len(blocks))])
    np.testing.assert_allclose(D, np.linalg.inv(K.toarray()), rtol=0, atol=1e-12)


def test_the_next_block_is_solved_while_a_block_is_written():
    _, problem = _problem()
    watched = _Watched(problem)
    blocks = column_blocks(N, N, block_bytes=8 * N * 8, batch=4)
    overlapped = []

    def on_block(i, values):
        if i == 0:  # a slow disk: the first write waits (deadlock guard: 30 s) for the second solve
            overlapped.append(watched.second_started.wait(timeout=30))

    solve_blocks(watched, blocks, range(len(blocks)), on_block)
    assert overlapped == [True]


def test_a_failed_write_stops_the_run_and_keeps_the_blocks_before():
    _, problem = _problem()
    watched = _Watched(problem)
    blocks = column_blocks(N, N, block_bytes=8 * N * 8, batch=4)
    written: list[int] = []

    def on_block(i, values):
        if i == 1:
            raise OSError(28, "No space left on device")
        written.append(i)

    with pytest.raises(OSError, match="No space"):
        solve_blocks(watched, blocks, range(len(blocks)), on_block)
    assert written == [0]
    assert len(watched.started) <= 3  # at most the block after the failed one was solved in vain
