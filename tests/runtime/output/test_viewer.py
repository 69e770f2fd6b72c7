"""``hailstorm view``: the page's data equal the storm's outputs, the vendored three.js is the npm
package's, long storms are subsampled by a stated stride, bad input is one line and exit 3, and
``--serve`` serves the page on localhost. (The page in a real browser: test_viewer_browser.py.)"""

from __future__ import annotations

import base64
import csv
import hashlib
import json
import re
import shutil
import subprocess
import sys
import tomllib
import urllib.error
import urllib.request
import zlib
from html.parser import HTMLParser
from importlib import resources
from pathlib import Path

import numpy as np
import pytest

from hailstorm.cli import main
from hailstorm.runtime.output.storm_output import check_storm_out
from hailstorm.runtime.output.viewer import FRAME_BYTES, ViewerInputError, build_page, write_page
from hailstorm.runtime.output.viewer.page import THREE_VERSION
from hailstorm.runtime.output.vtkhdf import VTKHDFFrames

ROOT = Path(__file__).resolve().parents[3]
VIEWER = ROOT / "runtime" / "output" / "viewer"
VENDOR = VIEWER / "vendor" / "three"


def decode(page: str) -> tuple[dict, dict[str, np.ndarray]]:
    """The page's meta data and its arrays (what the browser inflates)."""
    meta = json.loads(re.search(r'<script type="application/json" id="hs-meta">(.*?)</script>', page, re.S).group(1))
    b64 = re.search(r'<script type="application/octet-stream" id="hs-data">(.*?)</script>', page, re.S).group(1)
    raw = zlib.decompress(base64.b64decode("".join(b64.split())))
    dt = {"float32": "<f4", "int16": "<i2", "int32": "<i4", "uint32": "<u4"}
    arrays = {name: np.frombuffer(raw, dtype=dt[a["dtype"]], count=a["length"], offset=a["offset"])
              for name, a in meta["arrays"].items()}
    b64 = re.search(r'<script type="application/octet-stream" id="hs-impacts">(.*?)</script>', page, re.S).group(1)
    text = zlib.decompress(base64.b64decode("".join(b64.split()))).decode()
    meta["impacts"]["lines"] = text.split("\n") if meta["impacts"]["count"] else []
    return meta, arrays


def displacement(meta: dict, arrays: dict, field: str, j: int) -> np.ndarray:
    n = meta["n_vertices"]
    q = arrays[f"u_{field}"].reshape(-1, n, 3)[j].astype(np.float64)
    return q * meta["quant"][field][j]


# ---- the vendored library ---------------------------------------------------------------------

def test_vendored_three_is_the_npm_package_unmodified():
    """Each vendored file's SHA-256 is the one VENDOR.md records for the npm package's file; the
    licence is MIT; the loader's rewrites find the import specifiers they expect."""
    notes = (VENDOR / "VENDOR.md").read_text()
    assert f"version **{THREE_VERSION}**" in notes
    rows = re.findall(r"\| `([^`]+)` \| `[^`]+` \| [\d ]+ \| `([0-9a-f]{64})` \|", notes)
    assert {name for name, _ in rows} == {"three.core.js", "three.module.js", "OrbitControls.js", "LICENSE"}
    for name, digest in rows:
        assert hashlib.sha256((VENDOR / name).read_bytes()).hexdigest() == digest, name
    assert (VENDOR / "LICENSE").read_text().startswith("The MIT License")
    boot = (VIEWER / "boot.js").read_text()
    module = (VENDOR / "three.module.js").read_text()
    assert module.count("'./three.core.js'") == 2 and "\"'./three.core.js'\", JSON.stringify(coreUrl), 2" in boot
    assert (VENDOR / "OrbitControls.js").read_text().count("from 'three'") == 1
    app = (VIEWER / "app.js").read_text()
    assert app.count("from 'three'") == 1 and app.count("from 'three/addons/controls/OrbitControls.js'") == 1


def test_package_data_ships_the_page_and_the_library():
    """pyproject's package data covers every file of the viewer that is not Python (so that a
    wheel, not only an editable install, carries them), and the installed package finds them."""
    conf = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert "hailstorm.runtime.output.viewer" in conf["packages"]
    globs = conf["package-data"]["hailstorm.runtime.output.viewer"]
    assets = [p.relative_to(VIEWER) for p in VIEWER.rglob("*") if p.is_file() and p.suffix not in (".py", ".pyc")
              and "__pycache__" not in p.parts]
    assert len(assets) >= 8
    for a in assets:
        assert any(a.match(g) for g in globs), f"{a} is not package data"
    here = resources.files("hailstorm.runtime.output.viewer")
    for a in assets:
        assert here.joinpath(*a.parts).is_file(), a


# ---- the page's data ---------------------------------------------------------------------------

def test_page_holds_the_storm(viewer_storm):
    """Every frame's displacement (at its time and the peak since the previous frame), within the
    int16 step; the stones as the series has them; impacts.csv verbatim; and each impact shows in
    the frame the page names (its dent is there; the largest impact's frame is where its dent peaks)."""
    page, facts = build_page(viewer_storm)
    meta, arrays = decode(page)
    summary = json.loads((viewer_storm / "summary.json").read_text())
    frames = VTKHDFFrames(viewer_storm / "storm.vtkhdf")
    assert meta["frames"] == meta["frames_total"] == len(frames) == summary["frames"] == facts["frames"]
    assert meta["stride"] == 1 and "every one the storm recorded" in meta["frames_note"]
    n = meta["n_vertices"]
    first = frames[0]
    assert n == first.displacement.shape[0]
    offsets = meta["stone_offsets"]
    peak_norms = []
    for j in range(len(frames)):
        f = frames[j]
        assert meta["times"][j] == pytest.approx(f.t)
        for field, want in (("state", f.displacement), ("peak", f.peak_displacement)):
            got = displacement(meta, arrays, field, j)
            step = meta["quant"][field][j]
            assert np.abs(got - want).max() <= 0.5 * step + 1e-12
            assert step == pytest.approx(np.abs(want).max() / 32767, rel=1e-6, abs=1e-15)
        peak_norms.append(np.linalg.norm(f.peak_displacement, axis=1))
        a, b = offsets[j], offsets[j + 1]
        assert b - a == len(f.ids)
        np.testing.assert_array_equal(arrays["stone_id"][a:b], f.ids)
        np.testing.assert_allclose(arrays["stone_pos"].reshape(-1, 3)[a:b], f.positions, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(arrays["stone_radius"][a:b], f.radii, rtol=1e-6)
        np.testing.assert_allclose(arrays["stone_force"][a:b], np.linalg.norm(f.forces, axis=1), rtol=1e-6, atol=1e-6)
        assert meta["contacts"][j] == f.contacts
    frames.close()
    lines = (viewer_storm / "impacts.csv").read_text().splitlines()
    assert meta["impacts"]["columns"] == lines[0].split(",") and meta["impacts"]["lines"] == lines[1:]
    assert len(lines) - 1 == summary["impacts"] > 0
    rows = list(csv.DictReader(lines))
    X = arrays["vertices"].reshape(-1, 3).astype(np.float64)
    peaks = np.array(peak_norms)
    for i, r in enumerate(rows):  # around the impact point (its nearest vertex may be clamped)
        f = meta["impacts"]["frame"][i]
        around = np.argsort(np.linalg.norm(X - [float(r["x_m"]), float(r["y_m"]), float(r["z_m"])], axis=1))[:4]
        assert peaks[f, around].max() > 0, f"impact {i}: no dent in its frame {f}"
    big = max(range(len(rows)), key=lambda i: float(rows[i]["peak_force_N"]))
    v = int(np.argmin(np.linalg.norm(X - [float(rows[big][c]) for c in ("x_m", "y_m", "z_m")], axis=1)))
    assert peaks[meta["impacts"]["frame"][big], v] == pytest.approx(peaks[:, v].max(), rel=0.02)
    assert meta["u_max"]["peak"] == pytest.approx(peaks.max(), rel=1e-6)


def test_page_fetches_nothing():
    """The page's markup loads nothing: no element has a src or href (three.js, the viewer and the
    data are inside it)."""
    class Tags(HTMLParser):
        refs: list = []

        def handle_starttag(self, tag, attrs):
            self.refs += [(tag, k, v) for k, v in attrs if k in ("src", "href", "data", "srcset", "poster")]

    page = (VIEWER / "page.html").read_text()
    parser = Tags()
    parser.feed(page)
    assert parser.refs == []
    assert "<script src" not in page and "<link" not in page


def test_vtu_series_gives_the_same_page(viewer_storm, viewer_storm_vtu):
    """A storm written as .vtu files per frame makes the page a VTKHDF storm makes (the same storm)."""
    m1, a1 = decode(build_page(viewer_storm)[0])
    m2, a2 = decode(build_page(viewer_storm_vtu)[0])
    assert m2["series"] == "vtu" and m1["series"] == "vtkhdf"
    assert m1["frames"] == m2["frames"] and m1["times"] == pytest.approx(m2["times"])
    np.testing.assert_array_equal(a1["triangles"], a2["triangles"])
    np.testing.assert_allclose(a1["vertices"], a2["vertices"])
    for j in range(m1["frames"]):
        for field in ("state", "peak"):
            u1, u2 = displacement(m1, a1, field, j), displacement(m2, a2, field, j)
            assert np.abs(u1 - u2).max() <= m1["quant"][field][j] + 1e-12
    np.testing.assert_array_equal(a1["stone_id"], a2["stone_id"])
    np.testing.assert_allclose(a1["stone_force"], a2["stone_force"], rtol=1e-5, atol=1e-6)
    assert m1["impacts"] == m2["impacts"]
    assert m2["contacts"] is None  # the .vtu series does not record them


def test_long_storm_is_subsampled_by_a_stated_stride(viewer_storm):
    """Over its frame budget the page holds every k-th frame and says so; the peak field of a held
    frame is the largest since the previous held frame (no dent is skipped); --stride chooses k."""
    full_meta, full = decode(build_page(viewer_storm)[0])
    n, M = full_meta["n_vertices"], full_meta["frames"]
    budget = 6 * n * 12  # room for about 6 frames
    page, facts = build_page(viewer_storm, budget=budget)
    meta, arrays = decode(page)
    k = meta["stride"]
    assert k > 1 and facts["stride"] == k and meta["frames"] == len(range(0, M, k)) == facts["frames"]
    assert meta["frames_total"] == M and f"every {k}th" in meta["frames_note"] and f"of the storm's {M}" in meta["frames_note"]
    assert meta["frames"] * n * 12 <= budget
    full_norm = [np.linalg.norm(displacement(full_meta, full, "peak", g), axis=1) for g in range(M)]
    for j, g in enumerate(range(0, M, k)):
        window = np.max(full_norm[max(0, g - k + 1):g + 1], axis=0)
        got = np.linalg.norm(displacement(meta, arrays, "peak", j), axis=1)
        tol = meta["quant"]["peak"][j] + max(full_meta["quant"]["peak"][max(0, g - k + 1):g + 1])
        assert np.abs(got - window).max() <= 2 * tol + 1e-12
        np.testing.assert_allclose(displacement(meta, arrays, "state", j), displacement(full_meta, full, "state", g),
                                   atol=2 * full_meta["quant"]["state"][g] + 1e-12)
        assert meta["times"][j] == full_meta["times"][g]
    assert decode(build_page(viewer_storm, stride=3)[0])[0]["stride"] == 3


def test_frame_budget_keeps_the_page_under_20_MB():
    """The budget of the per-frame arrays, base64 of even incompressible data, stays under 20 MB
    with the library and the seat beside it."""
    assert FRAME_BYTES * 4 / 3 + 2e6 < 20e6


# ---- the command -------------------------------------------------------------------------------

@pytest.fixture
def out_copy(viewer_storm, tmp_path):
    """A private copy of the storm's output folder (``hailstorm view`` adds its page to it)."""
    return Path(shutil.copytree(viewer_storm, tmp_path / "out"))


def test_view_writes_the_page_into_the_storm_output(out_copy, tmp_path, capsys):
    """``hailstorm view OUT`` writes OUT/viewer.html and lists it in the storm's manifest, so that a
    rerun of the storm into OUT replaces it; ``-o`` writes elsewhere and leaves OUT as it was."""
    assert main(["view", str(out_copy)]) == 0
    printed = capsys.readouterr().out
    page = out_copy / "viewer.html"
    frames = json.loads((out_copy / "summary.json").read_text())["frames"]
    assert page.is_file() and str(page) in printed and f"{frames} frames" in printed
    assert "viewer.html" in json.loads((out_copy / "hailstorm-storm.json").read_text())["files"]
    check_storm_out(out_copy)  # a storm may replace the folder, page included
    before = (out_copy / "hailstorm-storm.json").read_text()
    other = tmp_path / "elsewhere.html"
    assert main(["view", "-q", str(out_copy), "-o", str(other)]) == 0
    assert capsys.readouterr().out == ""
    assert other.read_bytes() == page.read_bytes()
    assert (out_copy / "hailstorm-storm.json").read_text() == before
    assert main(["view", "-q", str(out_copy)]) == 0  # again: the manifest lists it once
    assert json.loads((out_copy / "hailstorm-storm.json").read_text())["files"].count("viewer.html") == 1


def _truncate(path: Path, keep: float) -> None:
    data = path.read_bytes()
    path.write_bytes(data[:int(len(data) * keep)])


BAD = {
    "no such folder": (lambda out: out / "nope", "no such folder"),
    "a file": (lambda out: out / "summary.json", "is not a folder"),
    "another folder": (lambda out: out.parent, "hailstorm-storm.json is missing"),
    "no series file": (lambda out: (out / "storm.vtkhdf").unlink() or out, "storm.vtkhdf missing"),
    "series cut short": (lambda out: _truncate(out / "storm.vtkhdf", 0.5) or out, "storm.vtkhdf"),
    "impacts cut short": (lambda out: _truncate(out / "impacts.csv", 0.5) or out, "impacts.csv"),
    "summary cut short": (lambda out: _truncate(out / "summary.json", 0.5) or out, "summary.json"),
    "manifest damaged": (lambda out: (out / "hailstorm-storm.json").write_text("{") and out, "hailstorm-storm.json"),
    "no impacts.csv": (lambda out: (out / "impacts.csv").unlink() or out, "impacts.csv missing"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_is_one_line_and_exit_3(out_copy, case, capsys):
    """A folder that is not a storm's output, or one whose files are missing or cut short: one line
    on stderr naming what is wrong, exit 3, nothing written."""
    make, words = BAD[case]
    target = make(out_copy)
    before = sorted(p.name for p in out_copy.iterdir()) if out_copy.is_dir() else None
    assert main(["view", str(target)]) == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("hailstorm: error: ") and words in err, err
    assert "Traceback" not in err
    if out_copy.is_dir():
        assert sorted(p.name for p in out_copy.iterdir()) == before


def test_view_errors_are_viewer_input_errors(tmp_path):
    with pytest.raises(ViewerInputError, match="not a storm's output"):
        build_page(tmp_path)


def test_serve_serves_the_page_on_localhost(out_copy, tmp_path):
    """``--serve`` prints its address and serves the page there (and nothing else) until stopped."""
    html = tmp_path / "page.html"
    proc = subprocess.Popen([sys.executable, "-m", "hailstorm", "view", str(out_copy), "-o", str(html), "--serve",
                             "--port", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        url = None
        for line in proc.stdout:
            m = re.search(r"serving\s+(http://127\.0\.0\.1:\d+/)", line)
            if m:
                url = m.group(1)
                break
        assert url is not None, f"no address printed (exit {proc.poll()})"
        with urllib.request.urlopen(url, timeout=30) as r:
            assert r.status == 200 and r.headers["Content-Type"].startswith("text/html")
            assert r.read() == html.read_bytes()
        with pytest.raises(urllib.error.HTTPError) as e:
            urllib.request.urlopen(url + "storm.vtkhdf", timeout=30)
        assert e.value.code == 404
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=60)
    assert proc.returncode in (0, 143, -15), err


@pytest.mark.slow
def test_default_storm_page_is_under_20_MB(tmp_path):
    """The default storm (the default seat, as bare ``hailstorm`` runs it): its page is under 20 MB."""
    out = tmp_path / "out"
    assert main(["-q", "--no-video", "--out", str(out)]) == 0
    info = write_page(out)
    print(f"\nthe default storm's page: {info.bytes / 1e6:.2f} MB, {info.frames} frames, {info.impacts} impacts")
    assert info.bytes < 20e6 and info.stride == 1
