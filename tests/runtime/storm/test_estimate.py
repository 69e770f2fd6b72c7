"""The storm's pre-flight estimate (:mod:`hailstorm.runtime.storm.estimate`): its parts and its shape.

The rates themselves are measurements (``tests/benchmarks/bench_estimate.py`` prints the
estimate beside the measured wall time); these tests hold what does not depend on the
machine: the seat's share of the footprint against a closed form, a long storm's cost
linear in its duration (stones retire), crowded impacts dearer each, the parts summing up.
"""

import numpy as np
import pytest

from hailstorm.runtime.storm.estimate import (CROWD_CONTACTS, IMPACT_SECONDS, NEAR_TIME, StormEstimate,
                                              hit_fraction)
from hailstorm.runtime.storm.scene import Scene


def _plate(w: float, n: int = 4):
    """A w x w square plate of thickness w / 10: top triangles facing up, bottom ones down."""
    x = np.linspace(0.0, w, n + 1)
    X, Y = np.meshgrid(x, x, indexing="ij")
    top = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, w / 10)])
    bottom = top * [1.0, 1.0, 0.0]
    idx = np.arange(X.size).reshape(n + 1, n + 1)
    tris = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = idx[i, j], idx[i + 1, j], idx[i + 1, j + 1], idx[i, j + 1]
            tris += [(a, b, c), (a, c, d)]
    up = np.array(tris)
    down = up[:, ::-1] + X.size
    return np.vstack([top, bottom]), np.vstack([up, down])


def test_the_seat_s_share_of_the_footprint_is_its_projected_area():
    """A 0.1 m plate in a footprint grown by 0.01 m: (0.1 / 0.12)^2 of the stones hit;
    the downward faces do not count twice; no margin: all of them."""
    V, T = _plate(0.1)
    assert hit_fraction(V, T, 0.01) == pytest.approx((0.1 / 0.12) ** 2, rel=1e-12)
    assert hit_fraction(V, T, 0.0) == pytest.approx(1.0, rel=1e-12)


def test_a_long_storm_costs_in_proportion_to_its_duration():
    """Stones retire after their bounce, so 30 s cost 3x 10 s (the old estimate, every stone
    counted from its spawn to the end, grew with the square of the duration)."""
    e10, e30 = (Scene.default().with_(duration=d).estimate(1659, hit_fraction=0.5) for d in (10.0, 30.0))
    assert e30.seconds / e10.seconds == pytest.approx(3.0, rel=0.02)
    assert e30.stepping_seconds / e10.stepping_seconds == pytest.approx(3.0, rel=0.02)


def test_impacts_landing_together_cost_more_each():
    """At a fixed duration, ten times the stones are more than ten times the stepping, by the
    crowding factor 1 + s / CROWD_CONTACTS of the stated rule."""
    a, b = (Scene.from_flat(stones=n, duration=0.05, inertia=False).estimate(hit_fraction=0.5) for n in (300, 3000))
    assert b.near_at_once == pytest.approx(10 * a.near_at_once)
    assert b.near_at_once == pytest.approx(1500 / 0.05 * NEAR_TIME)
    ratio = (1 + b.near_at_once / CROWD_CONTACTS) / (1 + a.near_at_once / CROWD_CONTACTS)
    assert b.stepping_seconds / a.stepping_seconds == pytest.approx(10 * ratio, rel=0.01)


def test_the_parts_add_up_and_are_announced():
    e = StormEstimate(steps=5000, stones=1000, frames=251, memory_bytes=1, duration=1.0, dt=2e-4, n_vertices=1000,
                      hit_fraction=0.5, inertia=True)
    assert e.seconds == pytest.approx(e.stepping_seconds + e.frame_seconds + e.inertia_seconds)
    assert e.stepping_seconds > 500 * IMPACT_SECONDS
    text = e.describe()
    assert "about " in text and "stepping" in text and "frames" in text and "inertia" in text
    no_inertia = StormEstimate(**{**e.__dict__, "inertia": False})
    assert no_inertia.inertia_seconds == 0.0 and "inertia" not in no_inertia.describe()
    # before the bundle is read: every stone counted as an impact, no frame time
    pre = Scene.default().estimate()
    assert pre.hit_fraction == 1.0 and pre.frame_seconds == 0.0


def test_the_video_costs_its_subsampled_frames():
    """The video renders at most ``VIDEO_FRAMES`` frames (the renderer's ``max_frames``), so a
    30 s storm's video costs what a 10 s storm's does; only the series' files grow."""
    import inspect

    from hailstorm.runtime.output.animation import write_animation
    from hailstorm.runtime.storm.estimate import FRAME_SECONDS_PER_VERTEX, VIDEO_FRAMES, VIDEO_SECONDS_PER_FRAME

    assert inspect.signature(write_animation).parameters["max_frames"].default == VIDEO_FRAMES
    e10, e30 = (Scene.default().with_(duration=d).estimate(1659, hit_fraction=0.5, video=True) for d in (10.0, 30.0))
    video = VIDEO_FRAMES * VIDEO_SECONDS_PER_FRAME
    assert e10.frame_seconds == pytest.approx(e10.frames * 1659 * FRAME_SECONDS_PER_VERTEX + video, rel=1e-12)
    assert e30.frame_seconds - e10.frame_seconds == pytest.approx(
        (e30.frames - e10.frames) * 1659 * FRAME_SECONDS_PER_VERTEX, rel=1e-12)


def test_the_disk_estimate_follows_the_series():
    """The one-file series takes a fifth of the .vtu pairs' disk per frame (bench_series.py
    measures both); an unknown series is refused."""
    from hailstorm.runtime.storm.estimate import DISK_BYTES_FIXED, DISK_BYTES_PER_VERTEX

    sc = Scene.default().with_(duration=1.0)
    one, pairs = (sc.estimate(1659, series=s).disk_bytes for s in ("vtkhdf", "vtu"))
    assert one == sc.estimate(1659).disk_bytes  # the default
    frames = sc.estimate(1659).frames
    assert one == frames * (DISK_BYTES_PER_VERTEX["vtkhdf"] * 1659 + 4096) + DISK_BYTES_FIXED["vtkhdf"]
    assert 4 * one < pairs
    with pytest.raises(ValueError, match="unknown series format 'pvd'"):
        sc.estimate(1659, series="pvd")
