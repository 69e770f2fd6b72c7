"""The storm's 3-D video (runtime/output/video3d.py, seat_view.py, force_panel.py, impacts.py,
offscreen.py): rendered pixels of a plate and of a short storm on the box, the force panel's
numbers against impacts.csv and the frames, the fallback to the 2-D video."""

import logging
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("vtkmodules", reason="the 3-D video needs VTK (the video extra)")

from hailstorm.runtime.output.offscreen import three_d_available  # noqa: E402

if three_d_available() is None:  # VTK installed but no off-screen OpenGL on this machine
    pytest.skip("no off-screen OpenGL for VTK here (libEGL or libOSMesa)", allow_module_level=True)

from hailstorm.runtime.bundle.read import load  # noqa: E402
from hailstorm.runtime.output.files import impacts_csv  # noqa: E402
from hailstorm.runtime.output.impacts import impact_times, read_impacts  # noqa: E402
from hailstorm.runtime.output.seat_view import SeatView, dent_colours, displacement_scale  # noqa: E402
from hailstorm.runtime.output.video3d import Storm3DRenderer  # noqa: E402
from hailstorm.runtime.storm.driver import Frame  # noqa: E402
from hailstorm.runtime.storm.run import run_storm
from hailstorm.runtime.storm.scene import Scene  # noqa: E402

SIZE = (480, 320)  # small frames: the tests stay fast


def _plate(n=25, size=0.1, z=0.02):
    """A square plate at height z, triangles facing +z (a mesh without a bundle)."""
    g = np.linspace(0.0, size, n)
    xx, yy = np.meshgrid(g, g)
    V = np.column_stack([xx.ravel(), yy.ravel(), np.full(n * n, z)])
    T = []
    for j in range(n - 1):
        for i in range(n - 1):
            a = j * n + i
            T += [(a, a + 1, a + n + 1), (a, a + n + 1, a + n)]
    return SimpleNamespace(vertices=V, triangles=np.array(T))


def _dent(plate, centre, depth=2e-3, width=0.012):
    X = plate.vertices
    r2 = ((X[:, :2] - centre[:2]) ** 2).sum(axis=1)
    u = np.zeros_like(X)
    u[:, 2] = -depth * np.exp(-r2 / width**2)
    return u.astype(np.float32)


def _frame(plate, u=None, positions=(), radii=(), forces=None, t=0.01, ids=None):
    n = plate.vertices.shape[0]
    pos = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
    k = pos.shape[0]
    return Frame(t=t, displacement=np.zeros((n, 3), np.float32) if u is None else u, positions=pos,
                 radii=np.asarray(radii, dtype=np.float64).reshape(k), ids=np.arange(k) if ids is None else ids,
                 contacts=0 if forces is None else int((np.abs(forces).sum(axis=1) > 0).sum()),
                 peak_displacement=None, forces=np.zeros((k, 3)) if forces is None else np.asarray(forces, float))


def _seat_mask(view: SeatView) -> np.ndarray:
    """The pixels the seat covers in the main view: the picture with it against one without it."""
    view.set_stones(np.zeros((0, 3)), np.zeros(0))
    with_seat = view.draw(None).astype(int)
    actors = view.renderer.GetActors()
    actors.InitTraversal()
    seat = actors.GetNextActor()
    seat.VisibilityOff()
    without = view.draw(None).astype(int)
    seat.VisibilityOn()
    return np.abs(with_seat - without).sum(axis=2) > 24


def _main_view(R, changed):
    """``changed`` (the 3-D view's pixels) less the inset and the caption's lines (they change with the frame)."""
    from hailstorm.runtime.output.seat_view import INSET_VIEWPORT

    h, w = changed.shape
    x0, y0, x1, y1 = INSET_VIEWPORT
    out = changed.copy()
    out[int(h - y1 * h) - 2:int(h - y0 * h) + 2, int(x0 * w) - 2:int(x1 * w) + 2] = False
    out[:int(0.14 * h)] = False
    return out


@pytest.fixture(scope="module")
def plate():
    return _plate()


def test_a_frame_is_not_blank_and_frames_the_seat(plate):
    """The picture has the frame's size, a sky, the seat in the middle of the main view (not cut by
    the picture's edges), the colour bar and the force panel."""
    R = Storm3DRenderer(plate, top=2e-3, duration=0.05, size=SIZE)
    img = R.render(_frame(plate))
    assert img.shape == (SIZE[1], SIZE[0], 3) and img.dtype == np.uint8
    assert img.std() > 20 and len(np.unique(img.reshape(-1, 3), axis=0)) > 200
    mask = _seat_mask(R.view)
    h, w = mask.shape
    assert 0.05 < mask.mean() < 0.6
    rows, cols = np.nonzero(mask)
    assert rows.min() > 0 and rows.max() < h - 1 and cols.min() > 0 and cols.max() < w - 1  # framed, not cut
    assert R.render(_frame(plate), alpha=True).shape == (SIZE[1], SIZE[0], 4)


def test_a_dent_shows_where_it_is_in_the_dent_colours(plate):
    """A dent changes the picture around its projected place, in the colour scale's warm colours
    where the undented seat is grey; the colour bar and the drawing scale are on the frame."""
    R = Storm3DRenderer(plate, top=2e-3, duration=0.05, size=SIZE)
    centre = np.array([0.05, 0.05, 0.02])
    flat = R.render(_frame(plate)).astype(int)
    dented = R.render(_frame(plate, _dent(plate, centre))).astype(int)
    h3 = R.view.height
    diff = _main_view(R, np.abs(dented - flat)[:h3].sum(axis=2) > 40)
    assert diff.sum() > 200
    rows, cols = np.nonzero(diff)
    (cx, cy), = R.view.project(centre)
    assert abs(np.median(cols) - cx) < 0.1 * SIZE[0] and abs(np.median(rows) - cy) < 0.15 * h3
    # warm where it changed (red above blue), grey before
    d, f = dented[:h3][diff], flat[:h3][diff]
    assert np.median(d[:, 0] - d[:, 2]) > 40 and np.median(np.abs(f[:, 0] - f[:, 2])) < 25
    # the scale: 2 mm on a 0.14 m plate is drawn x2 (2 % of the size); it is printed, with the colour bar in mm
    assert R.scale == displacement_scale(2e-3, plate.vertices) == 2.0
    assert "drawn x2" in R.caption
    assert "[mm]" in R.view.colour_bar.GetTitle()
    # the colour bar's column: from the dent colours' top (yellow) down to the seat's grey
    bar = R.view.colour_bar
    x0, y0 = bar.GetPositionCoordinate().GetComputedDisplayValue(R.view.renderer)
    x1, y1 = bar.GetPosition2Coordinate().GetComputedDisplayValue(R.view.renderer)
    col = dented[:h3, int(x0) + 3, :]
    top_rgb = (dent_colours(256)[-1] * 255).astype(int)
    assert np.abs(col - top_rgb).sum(axis=1).min() < 30


def test_a_stone_appears_at_its_projected_position(plate):
    """A stone above the plate draws an ice-white disc centred on its projection, of about its
    projected radius; in the picture without it the sky or the seat is there."""
    R = Storm3DRenderer(plate, top=2e-3, duration=0.05, size=SIZE)
    c = np.array([0.07, 0.03, 0.05])
    r = 0.006
    without = R.render(_frame(plate)).astype(int)
    img = R.render(_frame(plate, positions=[c], radii=[r])).astype(int)
    assert R.n_in_view == 1
    (px, py), = R.view.project(c)
    (ex, ey), = R.view.project(c + R.view.renderer.GetActiveCamera().GetViewUp() * np.array(r))
    rpx = np.hypot(ex - px, ey - py)
    assert rpx > 4
    changed = _main_view(R, np.abs(img - without)[:R.view.height].sum(axis=2) > 40)
    rows, cols = np.nonzero(changed)
    assert abs(cols.mean() - px) < 0.25 * rpx + 1 and abs(rows.mean() - py) < 0.25 * rpx + 1
    assert np.sqrt(changed.sum() / np.pi) == pytest.approx(rpx, rel=0.25)
    assert img[int(round(py)), int(round(px))].min() > 150  # lit ice, not the grey seat


def test_the_inset_follows_the_largest_impact_in_view(plate):
    """Two stones pressing: the inset aims at the one pressing harder and names it; a stone out of
    view is not followed."""
    R = Storm3DRenderer(plate, top=2e-3, duration=0.05, size=SIZE)
    pos = [[0.02, 0.02, 0.024], [0.08, 0.07, 0.024], [0.5, 0.5, 0.5]]
    forces = [[0, 0, -3.0], [0, 0, -7.5], [0, 0, -50.0]]
    R.render(_frame(plate, positions=pos, radii=[0.004] * 3, forces=forces, ids=np.array([4, 9, 11])))
    assert "stone 9" in R.inset_label and "7.5 N" in R.inset_label
    assert np.allclose(R.view.inset.GetActiveCamera().GetFocalPoint(), pos[1], atol=1e-3)
    assert R.n_in_view == 2 and R.n_pressing == 2


@pytest.fixture(scope="module")
def box_storm(box_bundle, tmp_path_factory):
    """A short storm on the box and its impacts.csv (read back as the video reads it)."""
    gf = load(box_bundle)
    res = run_storm(gf, Scene.from_flat(duration=0.04, stones=6, seed=2, spawn_height=0.005, margin=0.0, fps=2000.0),
                    progress=False, keep_frames=True)
    path = tmp_path_factory.mktemp("imp") / "impacts.csv"
    path.write_text(impacts_csv(res.stats))
    imp = read_impacts(path)
    assert len(imp["stone"]) >= 1
    return gf, res, imp


def test_the_force_panel_shows_the_impacts_numbers_and_the_frames_totals(box_storm):
    """The markers are impacts.csv's peak forces (its numbers as written), each at a time its stone
    was in the storm; the line is the per-step history, ending at each frame's own total (which
    the caption states)."""
    gf, res, imp = box_storm
    R = Storm3DRenderer.for_frames(res.frames, gf, history=res.history, impacts=imp, size=SIZE)
    text = impacts_csv(res.stats).splitlines()
    col = text[0].split(",").index("peak_force_N")
    written = np.array([float(line.split(",")[col]) for line in text[1:]])
    for f in res.frames[::4] + [res.frames[-1]]:
        R.render(f)
        t, y = R.panel.line.get_data()
        total = float(np.linalg.norm(f.forces, axis=1).sum())
        assert t[-1] == pytest.approx(f.t * 1e3) and y[-1] == pytest.approx(total, rel=1e-12, abs=1e-12)
        assert f"{total:7.2f} N" in R.caption
    mt, my = R.panel.markers.get_data()
    assert np.array_equal(np.sort(my), np.sort(written))  # every impact, by the end
    assert R.panel.impacts_shown == len(written)
    # each marker is at a time its stone was in the storm (within a frame interval of its frames)
    times = impact_times(imp, res.frames, res.history)
    assert np.allclose(np.sort(np.asarray(mt) / 1e3), np.sort(times))
    gap = res.frames[1].t - res.frames[0].t
    for s_id, t in zip(imp["stone"], times):
        seen = [f.t for f in res.frames if s_id in np.asarray(f.ids)]
        assert seen[0] - gap - 1e-9 <= t <= seen[-1] + gap + 1e-9


def test_impact_times_from_a_stone_falling_straight(plate):
    """A stone falling at 5 m/s from 20 mm above the onset point: onset 4 ms after the frame
    (gravity adds 0.08 mm); a t_peak_s column is taken as it is."""
    r = 0.004
    point = np.array([0.05, 0.05, 0.02])
    frames = []
    for t in (0.0, 0.002):
        z = point[2] + r + 0.02 - 5.0 * t - 4.905 * t * t
        frames.append(SimpleNamespace(t=t, ids=np.array([3]), positions=np.array([[0.05, 0.05, z]])))
    imp = {"stone": np.array([3]), "x_m": point[:1], "y_m": point[1:2], "z_m": point[2:], "radius_m": np.array([r]),
           "speed_m_s": np.array([5.0]), "peak_force_N": np.array([10.0])}
    t = impact_times(imp, frames)
    assert t[0] == pytest.approx(0.004, abs=5e-5)
    assert impact_times({**imp, "t_peak_s": np.array([0.5])}, frames)[0] == 0.5


@pytest.mark.parametrize("dents", ["now", "peak"])
def test_dents_cover_the_seat_while_it_is_dented(box_storm, dents):
    """The issue's target on a storm: in each frame whose seat is dented (at its instant, or since
    the previous frame with dents='peak') by at least 10 % of the colour scale's top (0.26-0.98 mm
    here), the pixels that the dent changes cover at least 0.2 % of the seat's."""
    from hailstorm.runtime.output.video3d import dents_of

    gf, res, imp = box_storm
    R = Storm3DRenderer.for_frames(res.frames, gf, history=res.history, impacts=imp, size=SIZE, dents=dents)
    mask = _seat_mask(R.view)
    dented = [f for f in res.frames if np.linalg.norm(dents_of(f, dents), axis=1).max() >= 0.1 * R.top]
    assert len(dented) >= 2
    for f in dented[:6]:
        zero = np.zeros_like(f.displacement)
        flat = Frame(t=f.t, displacement=zero, positions=f.positions, radii=f.radii, ids=f.ids,
                     contacts=f.contacts, forces=f.forces, peak_displacement=zero)
        a = R.render(flat)[:R.view.height].astype(int)
        b = R.render(f)[:R.view.height].astype(int)
        changed = _main_view(R, np.abs(a - b).sum(axis=2) > 40) & mask
        assert changed.sum() >= 0.002 * mask.sum(), (f.t, changed.sum(), mask.sum())


def test_write_animation_is_3d_and_falls_back_to_2d(box_storm, tmp_path, monkeypatch, caplog):
    """write_animation draws in 3-D where it can (the 3-D renderer's frames, in the MP4) and in 2-D
    with one warning where VTK cannot draw; style='3d' there raises."""
    import imageio.v2 as imageio

    import hailstorm.runtime.output.offscreen as offscreen
    from hailstorm.runtime.output.animation import write_animation

    gf, res, imp = box_storm
    out = write_animation(res, gf, tmp_path / "a.mp4", max_frames=3, size=SIZE, impacts=imp)
    with imageio.get_reader(out) as r:
        frames = [im for im in r]
    assert [im.shape for im in frames] == [(SIZE[1], SIZE[0], 3)] * 3
    monkeypatch.setattr(offscreen, "three_d_available", lambda: None)

    def no_window(*a, **k):
        raise offscreen.ThreeDUnavailable("no off-screen OpenGL (test)")

    monkeypatch.setattr("hailstorm.runtime.output.seat_view.offscreen_window", no_window)
    with caplog.at_level(logging.WARNING):
        out2 = write_animation(res, gf, tmp_path / "b.mp4", max_frames=2, size=SIZE)
    warns = [r for r in caplog.records if "2-D video instead" in r.getMessage()]
    assert len(warns) == 1 and "\n" not in warns[0].getMessage()
    assert out2.exists()
    with pytest.raises(offscreen.ThreeDUnavailable):
        write_animation(res, gf, tmp_path / "c.mp4", max_frames=2, size=SIZE, style="3d")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="EGL's vendor files are glvnd's (Linux)")
def test_no_usable_opengl_is_reported_not_crashed():
    """With EGL's vendors hidden (and no libOSMesa, no display) the probe says None or names a
    window that draws: it never crashes the process (VTK's OSMesa window, tried without
    libOSMesa, segfaults in its first render)."""
    code = ("from hailstorm.runtime.output.offscreen import three_d_available as a; print(a())")
    env = {"__EGL_VENDOR_LIBRARY_FILENAMES": "/nonexistent.json", "PATH": "/usr/bin:/bin"}
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stdout.strip().splitlines()[-1] in ("None", "vtkOSOpenGLRenderWindow", "vtkEGLRenderWindow")
