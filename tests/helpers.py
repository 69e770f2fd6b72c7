"""Helpers shared by several test folders (fixtures are in ``conftest.py``).

``tests/`` is on the import path (``pythonpath`` in ``pyproject.toml``), so a test
imports these as ``from helpers import plate_gf``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hailstorm.precompute.blocks import BlockStore
from hailstorm.precompute.greens import ColumnProblem
from hailstorm.runtime.bundle.read import GreensFunctions

__all__ = ["Interrupt", "count_solves", "ctrl_c_at_frame", "drop_on_seat_top", "interrupt_after", "plate_gf"]


def plate_gf(n: int = 13, size: float = 0.12, young: float = 2e6, poisson: float = 0.35,
             thickness: float | None = None, fold: float = 0.0) -> GreensFunctions:
    """A flat square plate at z = 0 (normal +z) with a Boussinesq-like compliance.

    ``D_ij = (1 - nu^2) / (pi E r_ij) I3`` between distinct vertices and
    ``1 / (E h)`` on the diagonal (``h`` the grid spacing); the boundary ring
    is clamped, the interior contactable. ``fold`` [rad] bends it along the grid line
    ``x = size / 2`` (``n`` odd): ``z = -tan(fold) |x - size / 2|``, a ridge (``fold > 0``,
    a convex edge whose faces' normals differ by ``2 fold``) or a valley (``fold < 0``).
    """
    x = np.linspace(0.0, size, n)
    X, Y = np.meshgrid(x, x - size / 2, indexing="ij")
    V = np.column_stack([X.ravel(), Y.ravel(), -np.tan(fold) * np.abs(X.ravel() - size / 2)])
    tris = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            tris += [(a, b, c), (a, c, d)]
    T = np.array(tris)
    ii, jj = np.divmod(np.arange(n * n), n)
    fixed = (ii == 0) | (jj == 0) | (ii == n - 1) | (jj == n - 1)
    contactable = ~fixed
    h = size / (n - 1)
    r = np.linalg.norm(V[:, None] - V[None], axis=2)
    S = np.where(r > 0, (1 - poisson**2) / (np.pi * young * np.where(r > 0, r, 1.0)), 1.0 / (young * h))
    S[fixed, :] = 0.0
    S[:, fixed] = 0.0
    D = np.kron(S, np.eye(3))[:, np.repeat(contactable, 3)]
    column_of = np.full(n * n, -1)
    column_of[contactable] = np.arange(contactable.sum())
    areas = np.full(n * n, h * h)
    return GreensFunctions(
        path=Path("."), manifest={"material": {"young": young, "poisson": poisson}, "options": {"order": 1}},
        vertices=V, triangles=T, fixed=fixed, contactable=contactable, areas=areas,
        volume_points=V, volume_tets=np.zeros((0, 4), dtype=np.intp), surface_nodes=np.arange(n * n),
        D=D, column_of=column_of,
    )


def drop_on_seat_top(gf, scene, steps: int, *, r: float = 0.005, v0: float = 9.0, at_vertex: bool = True):
    """One stone of radius ``r`` dropped at ``v0`` along the inward normal onto the top of the
    seat (its highest soft vertex, or the centre of a soft triangle there), 2 mm above it, in a
    storm of ``scene`` without spawning; stepped until it has left the seat, at most ``steps``
    steps (used by tests/runtime/storm/test_storm.py and tests/benchmarks/bench_storm.py).

    Returns ``(storm, v_in, v_out, in_one_step)``: the normal speeds into and out of the impact
    (None where not seen), and whether the whole impact fell inside one step's sub-steps (a
    stiff seat: no contact at a step's end, the normal velocity reversed over the step; the
    speeds are the step's, gravity changing them by ``g dt``).
    """
    from hailstorm.runtime.storm.driver import Storm

    st = Storm(gf, scene, spawn=False)
    soft_v = np.unique(gf.triangles[st.soft])
    top = soft_v[np.argmax(gf.vertices[soft_v, 2])]
    if at_vertex:
        x, nrm = gf.vertices[top], gf.vertex_normals()[top]
    else:
        t = int(np.flatnonzero(st.soft & (gf.triangles == top).any(axis=1))[0])
        x, nrm = gf.vertices[gf.triangles[t]].mean(axis=0), st.index.normals[t]
    st.add_stones(x + (r + 2e-3) * nrm, -v0 * nrm, r)
    v_in = v_out = None
    was = False
    for _ in range(steps):
        vb = st.vel[0].copy()
        st.step()
        now = st.ctri[0] >= 0
        if now and not was and v_in is None:
            v_in = float(-vb @ nrm)
        if was and not now and v_in is not None:
            v_out = float(st.vel[0] @ nrm)
            break
        if not was and not now and vb @ nrm < 0 < st.vel[0] @ nrm:
            return st, float(-vb @ nrm), float(st.vel[0] @ nrm), True
        was = now
    return st, v_in, v_out, False


class Interrupt(KeyboardInterrupt):
    pass


def count_solves(monkeypatch):
    """Count the column blocks solved (in this process) from now on."""
    calls = []
    real = ColumnProblem.solve

    def counting(self, factor, start, stop):
        calls.append((start, stop))
        return real(self, factor, start, stop)

    monkeypatch.setattr(ColumnProblem, "solve", counting)
    return calls


def interrupt_after(monkeypatch, n):
    """Make the block store raise Ctrl-C after ``n`` blocks were written (they stay written)."""
    real = BlockStore.write
    written = []

    def write(self, i, values):
        if len(written) == n:
            raise Interrupt()
        real(self, i, values)
        written.append(i)

    monkeypatch.setattr(BlockStore, "write", write)
    return written


def ctrl_c_at_frame(n):
    """A storm's ``on_frame`` callback that raises Ctrl-C (KeyboardInterrupt) at its ``n``-th frame."""
    seen = []

    def on_frame(frame):
        seen.append(frame.t)
        if len(seen) == n:
            raise KeyboardInterrupt

    return on_frame
