"""``hailstorm view``'s page in a real browser: Debian's Chromium (``/usr/bin/chromium``, or
``$HAILSTORM_CHROMIUM``) headless, driven by Playwright's Python API (never a browser Playwright
downloads). The page loads with no console error and fetches nothing, its canvas is not blank,
scrubbing, the displacement scale and orbiting change the picture, play and pause do, and a click
on a known dent shows that impact's numbers, as impacts.csv has them.

Without Chromium or Playwright these tests are skipped locally, saying why, and fail under CI
(``CI`` set), where ``.ci/run`` installs both.
"""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path

import numpy as np
import pytest

from hailstorm.runtime.output.viewer import write_page

CHROMIUM = Path(os.environ.get("HAILSTORM_CHROMIUM", "/usr/bin/chromium"))
#: what the machine notes ask of a headless Chromium here: no sandbox as root, no GPU (WebGL on
#: SwiftShader, the same pixels everywhere), none of its own network traffic
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--no-first-run", "--disable-quic", "--disable-default-apps"]
VIEWPORT = {"width": 1280, "height": 800}
BACKGROUND = np.array([0x1b, 0x1e, 0x24])  # the scene's background colour
#: the page's panels, hidden in the screenshots that measure the canvas
PANELS = "#hs-title, #hs-colorbar, #hs-info, #hs-controls { visibility: hidden !important; }"


def _browser_or_skip() -> None:
    problems = []
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        problems.append("playwright is not installed (pip install -e '.[test]')")
    if not CHROMIUM.is_file():
        problems.append(f"{CHROMIUM} is missing (apt-get install chromium)")
    if problems:
        why = "the viewer's browser tests cannot run: " + "; ".join(problems)
        if os.environ.get("CI"):
            pytest.fail(why + "; CI installs both (.ci/run)")
        pytest.skip(why)


@pytest.fixture(scope="module")
def page_file(viewer_storm, tmp_path_factory):
    return write_page(viewer_storm, tmp_path_factory.mktemp("page") / "viewer.html").path


@pytest.fixture(scope="module")
def impacts(viewer_storm):
    with open(viewer_storm / "impacts.csv", newline="") as f:
        lines = f.read().splitlines()
    return lines, list(csv.DictReader(lines))


@pytest.fixture(scope="module")
def browser():
    _browser_or_skip()
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture(scope="module")
def viewer(browser, page_file, tmp_path_factory):
    """The page loaded in a fresh context, with what it logged and requested."""
    context = browser.new_context(viewport=VIEWPORT, device_scale_factor=1)
    page = context.new_page()
    log = {"console": [], "errors": [], "requests": []}
    page.on("console", lambda m: log["console"].append((m.type, m.text)))
    page.on("pageerror", lambda e: log["errors"].append(str(e)))
    page.on("request", lambda r: log["requests"].append(r.url))
    page.goto(page_file.as_uri())
    page.wait_for_function("document.body.dataset.ready === '1'", timeout=60_000)
    page.log = log
    yield page
    context.close()


def _rendered(page) -> int:
    return page.evaluate("window.hailstormViewer.rendered")


def _then_render(page, action) -> None:
    """Do ``action``, then wait until the page has drawn the result."""
    before = _rendered(page)
    action()
    page.wait_for_function(f"window.hailstormViewer.rendered > {before}", timeout=30_000)


def _shot(page) -> np.ndarray:
    """A screenshot of the canvas (the panels hidden) as an (h, w, 3) uint8 array."""
    from PIL import Image

    png = page.locator("#hs-canvas").screenshot(style=PANELS, animations="disabled")
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))


def _scrub(page, frame: int) -> None:
    """Move the frame slider (the page's own control) to ``frame``."""
    _then_render(page, lambda: page.locator("#hs-frame").fill(str(frame)))
    assert page.evaluate("window.hailstormViewer.frame") == frame


def _changed(a: np.ndarray, b: np.ndarray) -> float:
    """The fraction of pixels that differ visibly between two pictures."""
    return float((np.abs(a.astype(int) - b.astype(int)).max(axis=2) > 24).mean())


def test_page_loads_with_no_console_error_and_fetches_nothing(viewer, page_file):
    assert viewer.log["errors"] == []
    assert [m for m in viewer.log["console"] if m[0] == "error"] == []
    assert viewer.locator("#hs-error").is_hidden()
    own = page_file.as_uri()
    assert [u for u in viewer.log["requests"] if u != own and not u.startswith(("blob:", "data:"))] == []
    assert viewer.evaluate("window.hailstormViewer.frames") > 1


def test_canvas_is_not_blank(viewer):
    """The seat and the stones cover a good part of the canvas, in more than one shade."""
    img = _shot(viewer)
    assert img.shape[:2] == (VIEWPORT["height"], VIEWPORT["width"])
    off_background = (np.abs(img.astype(int) - BACKGROUND).max(axis=2) > 30).mean()
    luminance = img.astype(float) @ [0.2126, 0.7152, 0.0722]
    assert off_background > 0.08, off_background
    assert luminance.std() > 20, luminance.std()
    assert len(np.unique(img.reshape(-1, 3) // 16, axis=0)) > 20  # shading, not a flat fill


def _largest(impacts) -> int:
    _, rows = impacts
    return max(range(len(rows)), key=lambda i: float(rows[i]["peak_force_N"]))


def test_scrubbing_changes_the_picture(viewer, impacts):
    """Frame 0 (no dent yet) and the frame of the storm's largest impact look different, and the
    time shown follows the slider."""
    k = viewer.evaluate(f"window.hailstormViewer.impactFrame({_largest(impacts)})")
    assert k > 0
    _scrub(viewer, 0)
    first, label0 = _shot(viewer), viewer.inner_text("#hs-time")
    _scrub(viewer, k)
    later, label = _shot(viewer), viewer.inner_text("#hs-time")
    assert _changed(first, later) > 0.003
    assert label0.startswith("t = 0.0000 s") and f"frame {k + 1} of" in label


def test_displacement_scale_changes_the_picture(viewer, impacts):
    k = viewer.evaluate(f"window.hailstormViewer.impactFrame({_largest(impacts)})")
    _scrub(viewer, k)
    default = viewer.locator("#hs-scale").input_value()
    _then_render(viewer, lambda: viewer.locator("#hs-scale").fill("0"))
    flat = _shot(viewer)
    assert viewer.inner_text("#hs-scale-value") == "×0"
    top = viewer.evaluate("document.getElementById('hs-scale').max")
    _then_render(viewer, lambda: viewer.locator("#hs-scale").fill(top))
    deep = _shot(viewer)
    assert viewer.inner_text("#hs-scale-value") == "×200"
    assert _changed(flat, deep) > 0.002
    _then_render(viewer, lambda: viewer.locator("#hs-scale").fill(default))


def test_orbit_and_zoom_change_the_view(viewer):
    _scrub(viewer, 0)
    before = _shot(viewer)
    cx, cy = VIEWPORT["width"] / 2, VIEWPORT["height"] / 2
    viewer.mouse.move(cx, cy)
    viewer.mouse.down()
    viewer.mouse.move(cx + 200, cy + 40, steps=8)
    viewer.mouse.up()
    viewer.wait_for_timeout(200)
    turned = _shot(viewer)
    assert _changed(before, turned) > 0.02
    _then_render(viewer, lambda: viewer.mouse.wheel(0, -600))
    assert _changed(turned, _shot(viewer)) > 0.02
    _then_render(viewer, lambda: viewer.locator("#hs-home").click())
    assert _changed(before, _shot(viewer)) < 0.002  # back home


def test_play_and_pause(viewer):
    _scrub(viewer, 0)
    viewer.locator("#hs-fps").select_option("25")
    viewer.locator("#hs-play").click()
    viewer.wait_for_function("window.hailstormViewer.frame >= 3", timeout=10_000)
    assert viewer.evaluate("window.hailstormViewer.playing")
    viewer.locator("#hs-play").click()
    stopped = viewer.evaluate("window.hailstormViewer.frame")
    viewer.wait_for_timeout(400)
    assert not viewer.evaluate("window.hailstormViewer.playing")
    assert viewer.evaluate("window.hailstormViewer.frame") == stopped


def test_a_click_on_a_known_dent_shows_its_impact(viewer, impacts):
    """The storm's largest impact: at its frame its dent is coloured where it struck; a click
    there opens the panel on that impact, with impacts.csv's values and its row."""
    lines, rows = impacts
    i = _largest(impacts)
    r = rows[i]
    k = viewer.evaluate(f"window.hailstormViewer.impactFrame({i})")
    _scrub(viewer, k)
    p = viewer.evaluate(f"window.hailstormViewer.project({r['x_m']}, {r['y_m']}, {r['z_m']})")
    img = _shot(viewer)
    x, y = int(round(p["x"])), int(round(p["y"]))
    red, green, blue = img[y - 2:y + 3, x - 2:x + 3].reshape(-1, 3).astype(int).mean(axis=0)
    assert red - blue > 60, (red, green, blue)  # the dent's colour, not the grey of the seat at rest
    viewer.mouse.click(p["x"], p["y"])
    viewer.wait_for_function(f"window.hailstormViewer.selected === {i}", timeout=10_000)
    panel = viewer.locator("#hs-info")
    assert panel.is_visible() and panel.get_attribute("data-impact") == str(i)
    shown = {}
    for cell in panel.locator("td[data-key]").all():
        shown[cell.get_attribute("data-key")] = (cell.get_attribute("data-value"), cell.inner_text())
    for key in ("stone", "radius_m", "mass_kg", "speed_m_s", "peak_force_N", "peak_force_dynamic_N",
                "indentation_m", "thickness_m", "indentation_thickness_ratio", "contact_radius_ratio",
                "strain_ratio", "contact_time_ratio", "inertia_force", "beyond"):
        assert shown[key][0] == r[key], key  # the CSV's own text
    factor = {"radius_m": 1e3, "mass_kg": 1e3, "indentation_m": 1e3, "thickness_m": 1e3}
    for key in ("radius_m", "speed_m_s", "peak_force_N", "peak_force_dynamic_N", "indentation_m", "strain_ratio"):
        number = float(shown[key][1].split()[0])
        assert number == pytest.approx(float(r[key]) * factor.get(key, 1.0), rel=5e-4), key
    assert shown["stone"][1] == r["stone"]
    text = panel.inner_text()
    assert f"impact {i + 1} of {len(rows)}" in text
    assert viewer.inner_text("#hs-csv-row") == f"{lines[0]}\n{lines[i + 1]}"
    assert [m for m in viewer.log["console"] if m[0] == "error"] == [] and viewer.log["errors"] == []
