"""The compiled run of the steps without soft contacts (``Storm.run_free``) against the storm's
step in Python (``Storm.step``): the same storm, step for step.

Both paths call the same compiled phases in the same order with the same arithmetic, in one
process (no BLAS in the free phases), so their states agree to the last bit; the comparisons
below allow 1e-12 relative (a reordering of a sum would show as more than that, a changed rule
as far more).
"""

from __future__ import annotations

import numpy as np
import pytest

from hailstorm.runtime.storm.driver import Storm
from hailstorm.runtime.storm.run import run_storm
from hailstorm.runtime.storm.free_run import FreeRun
from hailstorm.runtime.storm.scene import Scene

#: the statistics a storm's summary reads that the free steps touch or follow from
KEYS = ("hailstones", "impacts", "steps", "substeps", "retired", "wall_contacts", "max_penetration_m",
        "max_penetration_contact_m", "max_penetration_free_m", "max_penetration_contact_rel",
        "mean_penetration_contact_m", "max_contact_force", "capacitance_rebuilds", "stones_hit")


def _python_steps(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(Storm, "run_free", lambda self, *args: (0, False))


def _counting(monkeypatch: pytest.MonkeyPatch) -> list[tuple[int, bool, bool, bool]]:
    """Record each compiled run's completed steps, how it left the next step (a contact opened;
    stones near the seat while a released contact set is held) and whether it dropped a held set."""
    done: list[tuple[int, bool, bool, bool]] = []
    run = FreeRun.run

    def counted(self, *args, **kwargs):
        res = run(self, *args, **kwargs)
        done.append((res.steps, res.opened, res.near_first, res.dropped))
        return res

    monkeypatch.setattr(FreeRun, "run", counted)
    return done


def _compare(a, b) -> None:
    for key in KEYS:
        assert getattr(a.stats, key) == pytest.approx(getattr(b.stats, key), rel=1e-12, abs=0.0), key
    np.testing.assert_allclose(a.history, b.history, rtol=1e-12, atol=0.0)
    assert [f.t for f in a.frames] == pytest.approx([f.t for f in b.frames], rel=1e-12)
    for fa, fb in zip(a.frames, b.frames):
        np.testing.assert_array_equal(fa.ids, fb.ids)
        np.testing.assert_allclose(fa.positions, fb.positions, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(fa.displacement, fb.displacement, rtol=1e-6, atol=1e-12)  # (float32 frames)


@pytest.mark.parametrize("integrator, patch, stones, seed", [("exact", "hertz", 20, 4), ("implicit", "hertz", 20, 4),
                                                          ("symplectic", "none", 20, 4), ("symplectic", "hertz", 40, 6)])
def test_free_run_is_the_python_step(gf, monkeypatch, integrator, patch, stones, seed):
    """A storm with impacts, flight and retirement: the compiled free steps give the storm of
    ``Storm.step`` (the steps a compiled run leaves half done where a contact opens, finished
    by the contact step; the released contact sets it drops where the step would), and they
    ran most of its steps."""
    sc = Scene.from_flat(duration=0.06, stones=stones, seed=seed, spawn_height=0.02, r_min=0.003, r_max=0.008,
                         fps=200.0, integrator=integrator, patch=patch, dt=5e-4)
    with monkeypatch.context() as m:
        done = _counting(m)
        fast = run_storm(gf, sc, progress=False)
    with monkeypatch.context() as m:
        _python_steps(m)
        slow = run_storm(gf, sc, progress=False)
    assert slow.stats["impacts"] > 0 and slow.stats["retired"] > 0  # (the storm exercises what it compares)
    _compare(fast, slow)
    assert sum(k + int(o or n) for k, o, n, _ in done) > 0.5 * fast.stats["steps"]
    assert any(o for _, o, _, _ in done)  # a step left half done where a contact opened
    if integrator == "exact":  # (contact sets held after their last release, dropped inside a compiled run)
        assert any(d for _, _, _, d in done)
    if stones == 40:  # (one held while stones come near: the sub-steps' sizing reads it, the step left to Python)
        assert any(n for _, _, n, _ in done)


def test_free_run_with_stones_added_by_hand(gf, monkeypatch):
    """Stones added by hand beside the spawn plan: the stones' buffers keep room for the plan
    (the kernel writes the plan's stones in place), and the drop is the Python step's."""
    sc = Scene.from_flat(duration=0.04, stones=8, seed=2, spawn_height=0.02, r_min=0.003, r_max=0.006, fps=100.0,
                         integrator="exact", dt=5e-4)
    runs = []
    for compiled in (True, False):
        storm = Storm(gf, sc)
        lo, hi = storm.lo, storm.hi
        k = 70  # more than the buffers' first capacity (64), at heights that land a few at a time
        rng = np.random.default_rng(0)
        pos = np.column_stack([rng.uniform(lo[0], hi[0], k), rng.uniform(lo[1], hi[1], k),
                               hi[2] + rng.uniform(0.01, 0.15, k)])
        storm.add_stones(pos, np.tile([0.0, 0.0, -3.0], (k, 1)), np.full(k, 0.002))
        hist = np.zeros((80, 3))
        i = 0
        while i < 80:
            n, half_done = storm.run_free(80 - i, i, 80, np.inf, hist) if compiled else (0, False)
            i += n
            if half_done or n == 0:
                storm.step()
                i += 1
        runs.append((storm.t, storm.stones.pos.copy(), storm.stones.alive.copy(), storm.stats["impacts"],
                     storm.stats["hailstones"]))
    (t1, p1, a1, i1, h1), (t2, p2, a2, i2, h2) = runs
    assert t1 == pytest.approx(t2, rel=1e-12)
    assert (i1, h1) == (i2, h2) and i1 > 0 and h1 == 78  # (hailstones: the plan's 8 and the 70)
    np.testing.assert_array_equal(a1, a2)
    np.testing.assert_allclose(p1, p2, rtol=1e-12, atol=1e-15)


def test_free_run_stops_where_a_stone_presses_the_seat(gf):
    """The compiled run does nothing while a contact set exists, and stops at the frame clock."""
    sc = Scene.from_flat(duration=0.2, stones=0, drag=False, dt=5e-4, integrator="exact", restitution=0.0)
    storm = Storm(gf, sc, spawn=False)
    c = 0.5 * (storm.lo + storm.hi)
    storm.add_stones(np.array([[c[0], c[1], storm.hi[2] + 0.004]]), np.zeros((1, 3)), np.array([0.003]))
    hist = np.zeros((400, 3))
    n, finished = storm.run_free(400, 0, 400, 5 * 5e-4 - 1e-9, hist)
    assert (n, finished) == (5, False)  # the frame clock: after the fifth step a frame is due
    assert hist[4, 0] == pytest.approx(5 * 5e-4) and not hist[:5, 1:].any()
    i = 5
    while storm.contacts.current is None and i < 400:  # until it lands: its contact set is built in Python
        n, half_done = storm.run_free(400 - i, i, 400, np.inf, hist)
        i += n
        if half_done:
            assert storm.run_free(400 - i, i, 400, np.inf, hist) == (0, False)  # (the half-done step first)
            storm.step()
            i += 1
    assert storm.contacts.current is not None and storm.stones.ctri[0] >= 0
    assert storm.run_free(400 - i, i, 400, np.inf, hist) == (0, False)
