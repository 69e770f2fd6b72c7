"""The storm's video (runtime/output/render.py): frame size, the count of stones in view, stones
drawn to scale, the force panel, the colour scale."""

import numpy as np
import pytest

from hailstorm.runtime.bundle.read import load
from hailstorm.runtime.output.animation import write_animation
from hailstorm.runtime.output.render import FRAME_SIZE, StormRenderer
from hailstorm.runtime.storm.scene import Scene
from hailstorm.runtime.storm.driver import Frame, Storm
from hailstorm.runtime.storm.run import run_storm

ICE = 917.0  # the default scene's ice density [kg/m^3]
G = 9.81


@pytest.fixture(scope="module")
def gf(box_bundle):
    """The 0.1 x 0.1 x 0.05 m box (top at z = 0.05)."""
    return load(box_bundle)


@pytest.fixture(scope="module")
def storm(gf):
    """A short storm on the box, its frames close enough (0.5 ms) to catch impacts (~1 ms)."""
    res = run_storm(gf, Scene.from_flat(duration=0.04, stones=6, seed=2, spawn_height=0.005, margin=0.0, fps=2000.0),
                    progress=False)
    assert any(f.contacts for f in res.frames)
    return res


def _some(storm):
    """The indices of the frames in contact and of every 8th frame."""
    return sorted({i for i, f in enumerate(storm.frames) if f.contacts} | set(range(0, len(storm.frames), 8)))


def _frame(gf, positions, radii, *, t=0.01, forces=None, peak=None):
    n = np.asarray(gf.vertices).shape[0]
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    k = pos.shape[0]
    return Frame(t=t, displacement=np.zeros((n, 3), np.float32), positions=pos,
                 radii=np.asarray(radii, dtype=np.float64).reshape(k), ids=np.arange(k), contacts=0,
                 peak_displacement=np.zeros((n, 3), np.float32) if peak is None else peak,
                 forces=np.zeros((k, 3)) if forces is None else np.asarray(forces, dtype=np.float64))


def _renderer(gf, **kw):
    return StormRenderer(gf, peak=kw.pop("peak", 1e-4), duration=kw.pop("duration", 0.05), **kw)


def test_frame_size(gf, storm, tmp_path):
    """Frames are 1280 x 720 (the default) or the size asked for; so is the MP4."""
    import imageio.v2 as imageio

    assert FRAME_SIZE[0] >= 1280 and FRAME_SIZE[1] >= 720
    assert _renderer(gf).render(storm.frames[0]).shape == (720, 1280, 3)
    assert _renderer(gf, size=(1600, 900), dpi=120).render(storm.frames[0]).shape == (900, 1600, 3)
    out = write_animation(storm, gf, tmp_path / "storm.mp4", max_frames=3)
    with imageio.get_reader(out) as r:
        shapes = [im.shape for im in r]
    assert shapes == [(720, 1280, 3)] * 3


def test_count_is_the_stones_in_the_view_box(gf):
    """The on-screen count, and the circles drawn, are the stones whose sphere meets the
    view box: the seat's bounding box grown by 10 mm, 60 mm more on top. Built case by
    case: in, far above, straddling the top face, just beyond a face, beyond an edge
    though within r of both faces (a bounding-cube test would count it), near an edge."""
    X = np.asarray(gf.vertices)
    lo, hi = X.min(axis=0) - 0.01, X.max(axis=0) + 0.01
    hi[2] += 0.06
    mid = 0.5 * (lo + hi)
    r = 0.005
    stones = [
        (mid, True),
        (mid + [0, 0, 1.0], False),
        ([mid[0], mid[1], hi[2] + 0.5 * r], True),
        ([hi[0] + 1.1 * r, mid[1], mid[2]], False),
        ([hi[0] + 0.8 * r, hi[1] + 0.8 * r, mid[2]], False),  # 1.13 r from the edge
        ([hi[0] + 0.6 * r, lo[1] - 0.6 * r, mid[2]], True),  # 0.85 r from the edge
        ([lo[0] - 0.5 * r, lo[1] - 0.5 * r, lo[2] - 0.5 * r], True),  # 0.87 r from the corner
        ([lo[0] - 0.6 * r, lo[1] - 0.6 * r, lo[2] - 0.6 * r], False),  # 1.04 r from the corner
    ]
    expect = sum(inside for _, inside in stones)
    R = _renderer(gf)
    R.render(_frame(gf, [p for p, _ in stones], np.full(len(stones), r)))
    assert R.n_in_view == expect == 4
    assert f"stones in view {expect:3d}" in R.caption.get_text()
    for ax in (R.ax_plan, R.ax_side):  # exactly those stones are drawn, in both views
        assert sum(len(c.get_paths()) for c in ax.collections if c in R.stones_drawn) == expect


def test_count_on_storm_frames_against_sampled_balls(gf, storm):
    """On a storm's frames: a stone is counted iff some point of its ball (sampled on a
    grid) lies in the view box; stones within 2 % of the radius of grazing it are left out."""
    X = np.asarray(gf.vertices)
    lo, hi = X.min(axis=0) - 0.01, X.max(axis=0) + 0.01
    hi[2] += 0.06
    g = np.linspace(-1, 1, 41)
    ball = np.stack(np.meshgrid(g, g, g), axis=-1).reshape(-1, 3)
    ball = ball[np.linalg.norm(ball, axis=1) <= 1]
    R = _renderer(gf)
    seen = 0
    for i in _some(storm):
        f = storm.frames[i]
        R.render(f)
        count = 0
        for c, r in zip(f.positions, f.radii):
            d = np.linalg.norm(c - np.clip(c, lo, hi))
            if abs(d - r) < 0.02 * r:
                pytest.skip("a stone grazes the view box")  # not met on this storm
            count += bool(np.any(np.all((c + r * ball >= lo) & (c + r * ball <= hi), axis=1)))
        assert R.n_in_view == count
        seen += count
    assert seen > 0


def _circle_radii_px(ax, collection):
    """Half the pixel width and height of each circle of a collection, through ``ax.transData``."""
    out = []
    for path in collection.get_paths():
        v = ax.transData.transform(path.vertices)
        out.append(0.5 * (v.max(axis=0) - v.min(axis=0)))
    return np.array(out)


@pytest.mark.parametrize("r", [0.004, 0.01])
def test_stones_are_drawn_at_their_true_radius(gf, r):
    """A stone of radius r is a circle of r metres in both views: through each view's axis
    transform (both axes at the same scale, equal in x and y), and in the pixels of the image
    (the side view, over the sky: the area of the stone's pixels)."""
    c = np.array([0.05, 0.05, 0.09])  # above the box's top (0.05): sky behind it in the side view
    R = _renderer(gf)
    img = R.render(_frame(gf, [c], [r]))
    scales = []
    for ax, (i, j) in ((R.ax_plan, (0, 1)), (R.ax_side, (0, 2))):
        (coll,) = [c_ for c_ in ax.collections if c_ in R.stones_drawn]
        px = ax.transData.transform([[c[i], c[j]], [c[i] + 1.0, c[j]], [c[i], c[j] + 1.0]])
        sx, sy = px[1, 0] - px[0, 0], px[2, 1] - px[0, 1]  # pixels per metre
        assert sy == pytest.approx(sx, rel=1e-3)  # equal aspect
        scales.append(sx)
        assert _circle_radii_px(ax, coll) == pytest.approx(np.full((1, 2), r * sx), rel=1e-3)
    assert scales[0] == pytest.approx(scales[1], rel=1e-3)  # one scale for both views
    # the image: pixels in a window around the centre that differ from the sky by more than
    # half the ice-sky contrast, counted as an area (antialiased edges average out)
    h = img.shape[0]
    cx, cy = R.ax_side.transData.transform([c[0], c[2]])
    rpx = r * scales[1]
    half = int(rpx + 6)
    win = img[int(h - cy) - half:int(h - cy) + half + 1, int(cx) - half:int(cx) + half + 1].astype(float)
    sky = np.array([0xC9, 0xD3, 0xDD], float)
    ice = np.array([0xF4, 0xF8, 0xFC], float)
    n = np.count_nonzero(np.abs(win - sky).sum(axis=-1) > 0.5 * np.abs(ice - sky).sum())
    # the edge line (0.8 pt = 1.1 px wide) reaches 0.55 px beyond the circle
    assert np.sqrt(n / np.pi) == pytest.approx(rpx + 0.55, abs=1.0)


def test_force_panel_ends_at_the_frame_total(gf, storm, tmp_path):
    """The force panel's last point is the frame's total contact force (its stones' force
    magnitudes summed), which is also the storm's per-step history at that instant; so
    for frames read back from the ParaView files, and without a history."""
    from hailstorm.runtime.output.files import ParaviewSeries

    hist = storm.history
    R = StormRenderer.for_frames(storm.frames, gf, history=hist)
    R0 = StormRenderer.for_frames(storm.frames, gf)  # frames only: the totals of the frames so far
    series = ParaviewSeries(gf, tmp_path / "pv")
    some = _some(storm)
    for i in some:
        series.add(storm.frames[i])
    back = series.frames()
    pressed = 0
    for j, i in enumerate(some):
        f = storm.frames[i]
        total = float(np.linalg.norm(f.forces, axis=1).sum())
        pressed += total > 0
        for renderer, frame in ((R, f), (R0, f), (R, back[j])):
            renderer.render(frame)
            t, y = renderer.force_line.get_data()
            assert t[-1] == pytest.approx(f.t * 1e3) and y[-1] == pytest.approx(total, rel=1e-12, abs=1e-12)
        if i:  # the history, recorded by run_storm at each step
            k = int(np.argmin(np.abs(hist[:, 0] - f.t)))
            assert hist[k, 0] == pytest.approx(f.t) and hist[k, 1] == pytest.approx(total, rel=1e-12)
            t, y = R.force_line.get_data()
            assert np.allclose(y[:-1], hist[hist[:, 0] < f.t - 1e-12, 1])  # the whole history before
    assert pressed > 0


def test_frame_forces_hold_a_resting_stone(gf):
    """Independent of the storm's bookkeeping: a stone at rest on the seat presses with m g."""
    r = 0.006
    st = Storm(gf, Scene.from_flat(duration=0.2, stones=0, drag=False), spawn=False)
    st.add_stones(np.array([0.05, 0.05, 0.05 + r + 0.002]), np.array([0.0, 0.0, -0.2]), r)
    while st.t < 0.1:
        st.step()
    f = st.frame()
    m = ICE * 4.0 / 3.0 * np.pi * r**3
    assert f.contacts == 1 and f.forces.shape == (1, 3)
    assert np.linalg.norm(f.forces, axis=1).sum() == pytest.approx(m * G, rel=1e-3)


def test_colour_scale_spans_the_run(gf, storm):
    """The colour bar is logarithmic, from the largest peak |u| of the frames (in the unit
    it names) down two decades; no pixel of the seat exceeds it, and the frame with the
    largest dent reaches near its top."""
    peaks = [float(np.linalg.norm(f.peak_displacement, axis=1).max()) for f in storm.frames]
    peak = max(peaks)
    assert peak > 0
    unit, factor = ("mm", 1e3) if peak >= 1e-3 else ("µm", 1e6)
    R = StormRenderer.for_frames(storm.frames, gf, history=storm.history)
    from matplotlib.colors import LogNorm

    norm = R.colorbar.norm
    assert isinstance(norm, LogNorm)
    assert norm.vmax == pytest.approx(peak * factor, rel=1e-6)
    assert norm.vmin == pytest.approx(peak * factor / 100, rel=1e-6)
    label = R.colorbar.ax.get_ylabel()
    assert "peak |u|" in label and f"[{unit}]" in label and "log" in label
    R.render(storm.frames[int(np.argmax(peaks))])
    shown = np.nanmax(R.shown)
    assert shown <= norm.vmax * (1 + 1e-9) and shown > 0.5 * norm.vmax
    # the colours are the colour bar's: the pixel of the largest value has the colour bar's colour of it
    j = np.nanargmax(R.shown)
    rgba = np.asarray(R.surface.get_array()).reshape(-1, 4)[j]
    assert np.array_equal(rgba, R.colorbar.cmap(norm(shown), bytes=True))
    # the subsampled frames set the scale (what is rendered)
    some = [0, len(storm.frames) - 1]
    R2 = StormRenderer.for_frames(storm.frames, gf, which=some)
    expect = max(peaks[i] for i in some)
    assert R2.colorbar.norm.vmax == pytest.approx(expect * R2.factor if expect > 0 else 1.0, rel=1e-6)


def test_render_costs_no_state_of_the_caller(gf, storm):
    """The renderer's figure is its own (Agg): pyplot has no new figure."""
    import matplotlib.pyplot as plt

    before = plt.get_fignums()
    StormRenderer.for_frames(storm.frames, gf).render(storm.frames[-1])
    assert plt.get_fignums() == before


def test_a_seat_that_did_not_move(gf):
    """No displacement in any frame: the colour bar says so and the seat is all grey."""
    R = StormRenderer.for_frames([_frame(gf, [[0.05, 0.05, 0.09]], [0.005])], gf)
    img = R.render(_frame(gf, [[0.05, 0.05, 0.09]], [0.005]))
    assert "did not move" in R.colorbar.ax.get_ylabel()
    under = np.array(R.colorbar.cmap.get_under()[:3]) * 255
    seat = np.asarray(R.surface.get_array()).reshape(-1, 4)[np.isfinite(R.shown.ravel())]
    assert seat.size and np.allclose(seat[:, :3], under, atol=1.0)
    assert img.shape == (720, 1280, 3)


def _watchable(gf, scene):
    """Of a storm's recorded frames: the fraction whose shown (peak) displacement reaches the colour
    scale's bottom (a dent a viewer sees: at least 10^-COLOUR_DECADES of the run's largest), and the
    fraction in which a stone in view presses on the seat (drawn filled in orange)."""
    from hailstorm.runtime.output.render import COLOUR_DECADES, in_view, shown_displacement, view_box

    frames = run_storm(gf, scene, progress=False, keep_frames=True).frames
    peaks = np.array([np.linalg.norm(shown_displacement(f), axis=1).max() for f in frames])
    lo, hi = view_box(gf.vertices)
    pressing = [bool((np.linalg.norm(np.asarray(f.forces).reshape(-1, 3)[in_view(f.positions, f.radii, lo, hi)],
                                     axis=1) > 0).any()) for f in frames]
    return float(np.mean(peaks >= 10.0 ** -COLOUR_DECADES * peaks.max())), float(np.mean(pressing))


def test_the_default_storm_shows_a_dent_in_most_frames(seat_bundle):
    """The default scene on the default saddle (coarse mesh): a dent shows in at least 80 % of the
    recorded frames and a stone in contact in at least 10 % (counted from the frames' data); the
    old default rate (200 stones/s) gave ~37 % and ~2 % on the default seat. (The pressing frames
    are a count out of 51, about +-3 frames of sampling noise at 20 %: 12 % here and 25 % on the
    default seat, 16 % and 29 % before each spawned stone started at its own spawn time.)"""
    gf = load(seat_bundle)
    dents, pressing = _watchable(gf, Scene.default())
    assert dents >= 0.8 and pressing >= 0.10, (dents, pressing)
    sparse, _ = _watchable(gf, Scene.default().with_(rate=200.0))  # the old default: mostly a grey seat
    assert sparse < 0.6, sparse


def test_the_caption_states_the_playback_time_scale(gf, storm):
    """The time scale on screen: frames 4 ms apart played at 20 fps run 12.5x slower than real
    time; the first frame (no interval yet) states none; a pressing stone is counted."""
    from hailstorm.runtime.output.render import playback_slowdown

    s = playback_slowdown(np.array([0.0, 0.004, 0.008, 0.2]), 20.0)
    assert np.isnan(s[0]) and np.allclose(s[1:], [12.5, 12.5, 1 / (20 * 0.192)])
    r = _renderer(gf)
    r.render(storm.frames[0], slowdown=12.5)
    assert "playback 12.5x slower than real time" in r.caption.get_text()
    r.render(storm.frames[0], slowdown=0.25)
    assert "playback 4x faster than real time" in r.caption.get_text()
    r.render(storm.frames[0])
    assert "playback" not in r.caption.get_text()
    k = next(i for i, f in enumerate(storm.frames) if np.abs(f.forces).sum() > 0)
    r.render(storm.frames[k])
    assert r.n_pressing >= 1
