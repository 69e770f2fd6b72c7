"""What a storm records, on its own (:mod:`hailstorm.runtime.storm.recording`): the statistics as a
mapping (:class:`StormStats`), the frame clock and the force history (:class:`Recorder`), the frames
(:class:`Frame`) against the state they were taken from, and a run's :class:`StormResult`, whose
frames, history and statistics must agree with one another.

The storm runs on the synthetic plate (``helpers.plate_gf``, the ``gf`` fixture of tests/runtime).
"""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest

from hailstorm.runtime.storm.driver import Storm
from hailstorm.runtime.storm.run import run_storm
from hailstorm.runtime.storm.limits import VALIDITY_KEYS, ValidityLimits
from hailstorm.runtime.storm.recording import Frame, Recorder, StormResult, StormStats
from hailstorm.runtime.storm.scene import Scene


# ----------------------------------------------------------------------------------------------
# StormStats
# ----------------------------------------------------------------------------------------------
def test_stats_read_like_a_mapping_of_their_counters():
    """The parts' counters, read as a mapping: updates show, the accumulators are no keys, unknown
    keys raise, and ``dict(stats)`` is what ``summary.json`` gets (JSON numbers and strings)."""
    st = StormStats(patch="none")
    keys = list(st)
    assert len(st) == len(keys) == len(set(keys))
    assert keys[0] == "hailstones" and st["patch"] == "none"
    for acc in ("pen_contact_sum", "pen_contact_n", "validity"):
        assert acc not in keys
        with pytest.raises(KeyError):
            st[acc]
    with pytest.raises(KeyError):
        st["no_such_key"]
    # the counters the parts update, read back
    st.impacts += 3
    st.max_contact_force = max(st.max_contact_force, 12.5)
    st.max_contact_force = max(st.max_contact_force, 7.0)
    st.capacitance_rebuilds += 2
    assert st["impacts"] == 3 and st["max_contact_force"] == 12.5 and st["capacitance_rebuilds"] == 2
    d = dict(st)
    assert list(d) == keys and d["impacts"] == 3
    assert dict(st.items()) == d
    assert json.loads(json.dumps(d)) == d
    assert "impacts=3" in repr(st)


def test_mean_penetration_in_contact_is_the_sum_over_the_count():
    st = StormStats()
    assert st["mean_penetration_contact_m"] == 0.0  # no contact step: 0, not a division by zero
    overlaps = [2e-5, 0.0, 7e-5, 1.5e-5]  # what penetration() accumulates, step by step
    for o in overlaps:
        st.pen_contact_sum += o
        st.pen_contact_n += 1
    assert st["mean_penetration_contact_m"] == pytest.approx(sum(overlaps) / len(overlaps), rel=1e-15)
    keys = list(st)
    assert keys.index("mean_penetration_contact_m") + 1 == keys.index("sim_time_s")


def test_validity_keys_follow_the_patch_keys_and_default_to_no_impacts():
    """Without impact records, the validity keys count no impact beyond any limit, report zero worst
    values and the default limits; they sit right after ``max_patch_radius_m``."""
    st = StormStats()
    keys = list(st)
    i = keys.index("max_patch_radius_m")
    assert tuple(keys[i + 1:i + 1 + len(VALIDITY_KEYS)]) == VALIDITY_KEYS
    lim = ValidityLimits()
    assert st["impacts_beyond_any_limit"] == 0 and st["max_contact_radius_ratio"] == 0.0
    assert st["limit_contact_radius_ratio"] == lim.contact_radius
    assert st["limit_indentation_thickness_ratio"] == lim.indentation_thickness
    assert st["limit_strain_ratio"] == lim.strain


# ----------------------------------------------------------------------------------------------
# Recorder
# ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("fps, dt, n_steps", [(100.0, 1e-3, 100), (30.0, 1e-3, 100), (1000.0, 2.5e-3, 8),
                                              (250.0, 2e-4, 1000)])
def test_frame_clock_by_hand(fps, dt, n_steps):
    """A frame is due after the first step whose time reaches each multiple of 1 / fps (one per step
    at most: a clock slower than the frames falls behind and takes every step) and after the last
    step. Written out with integers: step i (time (i + 1) dt) is the first to reach k / fps when
    i = ceil(k / (fps dt)) - 1."""
    rec = Recorder(n_steps, fps, None, keep=True)
    due = [i for i in range(n_steps) if rec.frame_due((i + 1) * dt, i)]
    per = 1.0 / (fps * dt)  # steps per frame
    if per >= 1.0:
        want = sorted({math.ceil(k * per - 1e-9) - 1 for k in range(1, int(n_steps / per + 1e-9) + 1)}
                      | {n_steps - 1})
    else:
        want = list(range(n_steps))
    assert due == want
    assert len(due) == {(100.0, 1e-3): 10, (30.0, 1e-3): 3, (1000.0, 2.5e-3): 8, (250.0, 2e-4): 50}[(fps, dt)]


def test_force_history_by_hand():
    """Each step's row: its time, the total magnitude of the contact forces on the seat, the count."""
    rec = Recorder(4, 100.0, None, keep=False)
    f = np.array([[0.0, 0.0, -3.0], [1.0, -2.0, -2.0], [0.0, 0.6, -0.8]])
    rec.forces(0, 1e-3, f)
    rec.forces(1, 2e-3, np.zeros((0, 3)))
    rec.forces(3, 4e-3, f[:1])
    np.testing.assert_allclose(rec.history, [[1e-3, 3.0 + 3.0 + 1.0, 3], [2e-3, 0.0, 0], [0.0, 0.0, 0.0],
                                             [4e-3, 3.0, 1]], rtol=1e-15, atol=0)


def _frame(t, n=5, k=2):
    return Frame(t=t, displacement=np.zeros((n, 3), np.float32), positions=np.zeros((k, 3)), radii=np.ones(k),
                 ids=np.arange(k), contacts=0)


@pytest.mark.parametrize("keep", [True, False])
def test_record_streams_keeps_and_times_the_sink(keep):
    """Every frame goes to ``on_frame`` (the same object), is kept only with ``keep``, is counted either
    way; the sink's time (here a 20 ms sleep per frame) is ``sink_time``."""
    got = []

    def sink(fr):
        got.append(fr)
        time.sleep(0.02)

    rec = Recorder(10, 50.0, sink, keep=keep)
    frames = [_frame(0.02 * i) for i in range(3)]
    for fr in frames:
        rec.record(fr)
    assert rec.n_frames == 3
    assert all(a is b for a, b in zip(got, frames)) and len(got) == 3
    assert rec.frames == (frames if keep else [])
    assert 0.06 <= rec.sink_time < 5.0  # at least the three sleeps (a busy machine may add to them)
    quiet = Recorder(10, 50.0, None, keep=True)
    quiet.record(frames[0])
    assert quiet.sink_time == 0.0 and quiet.frames == [frames[0]]


def test_frame_defaults_and_result_defaults():
    fr = _frame(0.5)
    assert fr.peak_displacement is None and fr.forces is None
    res = StormResult(scene=Scene.default(), frames=[fr], stats=StormStats())
    assert res.history.shape == (0, 3) and res.frames == [fr]


# ----------------------------------------------------------------------------------------------
# frames against the state they were taken from; a run's result against itself
# ----------------------------------------------------------------------------------------------
#: ten stones on the plate; restitution 0: they come to rest on it, so that most frames hold contacts
SCENE = dict(duration=0.06, stones=10, seed=4, spawn_height=0.01, r_min=0.003, r_max=0.006, fps=1000.0, dt=5e-4,
             restitution=0.0)


def test_a_frame_holds_the_storms_state(gf):
    """Step a storm until stones are in contact; its frame is that instant's state: the live stones'
    centres, radii and ids, the open contacts counted by hand, the seat's displacement (float32), the
    forces of the stones in soft contact in their rows (zero elsewhere), a peak field at least as
    large as the displacement at every vertex."""
    st = Storm(gf, Scene.from_flat(**SCENE))
    while st.t < 0.06 - 1e-12:
        st.step()
        if st.contact_forces()[0].size:
            break
    ids_c, f_c = st.contact_forces()
    assert ids_c.size  # the premise: a frame with contacts
    u = st.u.copy()
    fr = st.frame()
    live = np.flatnonzero(st.alive)
    assert fr.t == st.t
    np.testing.assert_array_equal(fr.ids, live)
    np.testing.assert_array_equal(fr.positions, st.pos[live])
    np.testing.assert_array_equal(fr.radii, st.radius[live])
    assert fr.contacts == int(np.sum(st.ctri[live] >= 0))
    assert fr.displacement.dtype == np.float32 and fr.displacement.shape == (gf.vertices.shape[0], 3)
    np.testing.assert_array_equal(fr.displacement, u.astype(np.float32))
    assert np.abs(fr.displacement).max() > 0.0
    want = np.zeros((live.size, 3))
    for sid, f in zip(ids_c, f_c):
        want[np.flatnonzero(live == sid)[0]] = f
    np.testing.assert_array_equal(fr.forces, want)
    assert fr.peak_displacement.dtype == np.float32
    # (the peak field holds the current displacement or a larger one, per vertex; float32 rounding)
    mag = np.linalg.norm(fr.displacement.astype(np.float64), axis=1)
    peak = np.linalg.norm(fr.peak_displacement.astype(np.float64), axis=1)
    assert np.all(peak >= mag * (1.0 - 1e-6))


@pytest.fixture(scope="module")
def result(gf):
    return run_storm(gf, Scene.from_flat(**SCENE), progress=False)


def test_result_frames_follow_the_frame_clock(gf, result):
    """The first instant plus one frame every 1 / fps = 2 steps of 0.5 ms (the last at the end):
    61 frames at t = 0, 0.001, ..., 0.06; ``stats["frames"]`` counts them."""
    times = np.array([fr.t for fr in result.frames])
    np.testing.assert_allclose(times, np.arange(61) * 0.001, rtol=0, atol=1e-12)  # <= 120 additions of 5e-4
    assert result.stats["frames"] == len(result.frames) == 61
    assert result.history.shape == (120, 3)
    np.testing.assert_allclose(result.history[:, 0], (np.arange(120) + 1) * 5e-4, rtol=0, atol=1e-12)
    assert result.stats["steps"] == 120 and result.stats["sim_time_s"] == result.frames[-1].t


def test_result_history_is_what_the_frames_show(gf, result):
    """At each frame's step, the history's total force is the sum of the frame's per-stone force
    magnitudes and its count the frame's open contacts; no stone's force in any frame, nor any step's
    single-contact total, exceeds the largest contact force of the statistics; the stones that rest
    at the end are the last frame's contacts; the ids are spawn numbers below the stone count."""
    hist, st = result.history, result.stats
    seen_contacts = 0
    for fr in result.frames[1:]:
        i = int(round(fr.t / 5e-4)) - 1
        assert hist[i, 0] == pytest.approx(fr.t, rel=1e-12)
        total = np.linalg.norm(fr.forces, axis=1).sum()
        # the same forces, summed in another order: rounding ~1e-16 relative
        assert hist[i, 1] == pytest.approx(total, rel=1e-12, abs=1e-300)
        assert hist[i, 2] == fr.contacts
        seen_contacts += fr.contacts
        if fr.ids.size:
            assert np.all(np.diff(fr.ids) > 0) and fr.ids.max() < st["hailstones"]
            assert np.linalg.norm(fr.forces, axis=1).max() <= st["max_contact_force"] * (1 + 1e-12)
    assert seen_contacts > 50  # the premise: the frames show contacts (several at once in many)
    single = hist[:, 2] == 1
    assert single.any() and np.any(hist[:, 2] >= 2) and np.all(hist[single, 1] <= st["max_contact_force"] * (1 + 1e-12))
    assert st["max_contact_force"] > 0.0 and st["impacts"] >= 1
    assert st["hailstones"] == 10 and st["resting_at_end"] == result.frames[-1].contacts
    assert st["n_vertices"] == gf.vertices.shape[0] and st["n_triangles"] == len(gf.triangles)
    assert st["dt"] == 5e-4 and st["integrator"] == result.scene.time.integrator
    # the first frame: the start, before any stone is due
    first = result.frames[0]
    assert first.t == 0.0 and first.contacts == 0 and not np.any(first.displacement)
