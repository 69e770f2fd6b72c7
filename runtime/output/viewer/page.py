"""The storm as one self-contained HTML page (``hailstorm view``).

:func:`build_page` reads a storm's output folder (:mod:`.source`) and writes everything the page
shows into it: the seat's surface (float32 points, uint32 triangles), per frame the displacement
at the frame's time and the peak since the previous frame (int16, each frame and field scaled
by its own largest component: the error is at most 1/65534 of that), the live stones (position,
radius, id, force), and ``impacts.csv``'s lines verbatim with the frame each impact shows in. The arrays
and the lines are zlib-compressed and base64-encoded into the page, as are the vendored three.js modules
(``vendor/three/``, the npm package's files unmodified) and the viewer's own module
(``app.js``); the browser inflates them (``DecompressionStream``). Nothing is fetched when the page
is viewed, from a file or from :func:`serve`.

A storm too long for the page's frame budget (:data:`FRAME_BYTES`) is subsampled by a stride
the page states; its ``peak`` field then holds the largest displacement since the previous
frame *held*, so no dent is skipped.
"""

from __future__ import annotations

import base64
import functools
import html
import json
import math
import os
import re
import zlib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from hailstorm.runtime.output.viewer.source import StormOut, ViewerInputError, open_storm_out

__all__ = ["FRAME_BYTES", "PageInfo", "THREE_VERSION", "build_page", "serve", "write_page"]

#: the vendored three.js (vendor/three/VENDOR.md)
THREE_VERSION = "0.187.0"
#: the budget of the page's per-frame arrays, uncompressed [bytes]: a longer storm is subsampled
#: (12 MiB: with base64's 4/3 the page stays under 20 MB even if nothing compressed)
FRAME_BYTES = 12 * 2**20
#: the displacement scales the page's slider offers
SCALES = (0, 1, 2, 3, 5, 10, 20, 30, 50, 100, 200)
#: the page's file name in a storm's output folder (the default of ``hailstorm view``)
PAGE_NAME = "viewer.html"

_HERE = "hailstorm.runtime.output.viewer"


@dataclass
class PageInfo:
    """What :func:`write_page` wrote."""

    path: Path
    bytes: int
    frames: int
    frames_total: int
    stride: int
    impacts: int


def _asset(name: str) -> str:
    return resources.files(_HERE).joinpath(name).read_text(encoding="utf-8")


def _pack(data: bytes) -> str:
    """zlib (what ``DecompressionStream('deflate')`` inflates), then base64 in lines of 76."""
    b64 = base64.b64encode(zlib.compress(data, 9)).decode("ascii")
    return "\n".join(b64[i:i + 76] for i in range(0, len(b64), 76))


@functools.lru_cache(maxsize=1)
def _vendored() -> dict[str, str]:
    """The three.js modules, packed (once per process)."""
    base = resources.files(_HERE).joinpath("vendor", "three")
    out = {}
    for key, name in (("THREE_CORE", "three.core.js"), ("THREE_MODULE", "three.module.js"),
                      ("THREE_ORBIT", "OrbitControls.js")):
        out[key] = _pack(base.joinpath(name).read_bytes())
    return out


def _stride_for(n_vertices: int, frames: int, mean_stones: float, budget: int) -> int:
    per_frame = n_vertices * 3 * 2 * 2 + mean_stones * 24  # two int16 fields; the stones' 6 x 4 bytes
    return max(1, math.ceil(frames * per_frame / max(budget, 1)))


def _nice_scale(umax: float, length: float) -> int:
    """The slider's default: the largest offered scale that shows the largest displacement at
    most 3 % of the seat's size (at least 1)."""
    best = 1
    for s in SCALES[1:]:
        if umax > 0 and s * umax <= 0.03 * length:
            best = s
    return best


class _Arrays:
    """Arrays laid end to end in one buffer (each at a multiple of 4 bytes), with their places."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.places: dict[str, dict[str, Any]] = {}
        self.size = 0

    def add(self, name: str, a: np.ndarray) -> None:
        a = np.ascontiguousarray(a)
        dtype = {np.dtype(np.float32): "float32", np.dtype(np.int16): "int16", np.dtype(np.int32): "int32",
                 np.dtype(np.uint32): "uint32"}[a.dtype]
        raw = a.astype(a.dtype.newbyteorder("<"), copy=False).tobytes()
        self.places[name] = {"dtype": dtype, "offset": self.size, "length": int(a.size)}
        pad = -len(raw) % 4
        self.parts.append(raw + b"\0" * pad)
        self.size += len(raw) + pad

    def bytes(self) -> bytes:
        return b"".join(self.parts)


def _quantise(u: np.ndarray) -> tuple[np.ndarray, float]:
    """(n, 3) float -> int16 and the metres per step (0 for a frame at rest)."""
    top = float(np.abs(u).max()) if u.size else 0.0
    if not top > 0 or not math.isfinite(top):
        return np.zeros(u.shape, dtype=np.int16), 0.0
    step = top / 32767.0
    return np.clip(np.rint(u / step), -32767, 32767).astype(np.int16), step


def build_page(out: str | os.PathLike, *, stride: int | None = None, budget: int = FRAME_BYTES,
               title: str | None = None) -> tuple[str, dict[str, Any]]:
    """The page of the storm in the output folder ``out``, as text, and its facts
    (``frames``, ``frames_total``, ``stride``, ``impacts``).

    Parameters
    ----------
    out : path
        A storm's output folder (``hailstorm storm --out``).
    stride : int, optional
        Hold every ``stride``-th frame; default: every frame if they fit ``budget``, else the
        smallest stride that does.
    budget : int
        Bytes of per-frame arrays (uncompressed) the page may hold when ``stride`` is not given.
    title : str, optional
        The page's title (default: the folder's name).

    Raises
    ------
    ViewerInputError
        ``out`` is not a complete storm output (one line naming what is missing).
    """
    storm = open_storm_out(out)
    M, n = storm.n_frames, storm.vertices.shape[0]
    if stride is None:
        if storm.stone_counts is not None:
            mean_stones = float(storm.stone_counts.mean())
        else:  # (the .vtu series: not without reading every stones file; a bound that holds for the default scene)
            mean_stones = float(min(storm.summary.get("hailstones", 0) or 0, 500))
        stride = _stride_for(n, M, mean_stones, budget)
    if stride < 1:
        raise ValueError(f"stride must be at least 1, got {stride}")
    held = list(range(0, M, stride))
    data = _frames(storm, held, stride)
    arrays = _Arrays()
    arrays.add("vertices", storm.vertices.astype(np.float32))
    arrays.add("triangles", storm.triangles.astype(np.uint32))
    for name in ("u_state", "u_peak", "stone_pos", "stone_radius", "stone_id", "stone_force"):
        arrays.add(name, data[name])
    s = storm.summary
    limits = {k: s.get(k) for k in ("limit_indentation_thickness_ratio", "limit_contact_radius_ratio",
                                    "limit_strain_ratio", "limit_contact_time_ratio", "limit_inertia_change")}
    length = float(np.ptp(storm.vertices, axis=0).max()) if n else 1.0
    name = title or Path(os.path.abspath(storm.path)).name
    held_note = (f"{len(held)} frames, every one the storm recorded" if stride == 1 else
                 f"{len(held)} of the storm's {M} frames: every {stride}th (the peak field holds the largest "
                 f"displacement since the previous frame held)")
    meta = {
        "format": "hailstorm-viewer", "version": 1, "title": f"hailstorm: {name}",
        "summary_line": _summary_line(s),
        "frames_note": held_note,
        "n_vertices": n, "n_triangles": int(storm.triangles.shape[0]),
        "frames": len(held), "frames_total": M, "stride": stride,
        "times": [float(storm.times[g]) for g in held],
        "contacts": data["contacts"],
        "quant": {"state": data["q_state"], "peak": data["q_peak"]},
        "u_max": {"state": max(data["n_state"], default=0.0), "peak": max(data["n_peak"], default=0.0)},
        "stone_offsets": data["stone_offsets"], "max_stones": data["max_stones"],
        "scales": list(SCALES), "default_scale": _nice_scale(max(data["n_peak"], default=0.0), length),
        "default_field": "peak", "default_fps": 10,
        "limits": limits,
        "impacts": {"columns": storm.impact_columns, "count": len(storm.impact_lines), "frame": data["impact_frames"]},
        "arrays": arrays.places, "series": storm.series,
    }
    meta_text = json.dumps(meta, separators=(",", ":"), allow_nan=False).replace("</", "<\\/").replace("<!--", "<\\!--")
    app = _asset("app.js")
    boot = _asset("boot.js")
    if "</script" in boot.lower():
        raise AssertionError("boot.js must not hold '</script'")
    fields = {"VERSION": _version(), "TITLE": html.escape(meta["title"]), "CSS": _asset("page.css"),
              "META": meta_text, "DATA": _pack(arrays.bytes()), "THREE_VERSION": THREE_VERSION,
              "IMPACTS": _pack("\n".join(storm.impact_lines).encode("utf-8")),
              "APP": _pack(app.encode("utf-8")), "BOOT": boot, **_vendored()}
    page = re.sub(r"\{\{([A-Z_]+)\}\}", lambda m: fields[m.group(1)], _asset("page.html"))
    facts = {"frames": len(held), "frames_total": M, "stride": stride, "impacts": len(storm.impact_lines)}
    return page, facts


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("hailstorm")
    except Exception:  # pragma: no cover - not installed
        return "?"


def _summary_line(s: dict[str, Any]) -> str:
    def g(key: str, fmt: str = "{}") -> str:
        v = s.get(key)
        return "?" if v is None else fmt.format(v)

    return (f"{g('sim_time_s', '{:.3g}')} s of hail: {g('hailstones')} stones, {g('impacts')} impacts; "
            f"largest impact {g('max_impact_force_N', '{:.4g}')} N quasi-static, "
            f"{g('max_impact_force_dynamic_N', '{:.4g}')} N with the pad's inertia; deepest indentation "
            f"{g('max_indentation_m', '{:.3g}').replace('e-0', 'e-')} m")


def _frames(storm: StormOut, held: list[int], stride: int) -> dict[str, Any]:
    """Read every frame once: quantise the held ones (the peak field over each stride's window) and
    find the frame each impact shows in."""
    from scipy.spatial import cKDTree

    n = storm.vertices.shape[0]
    table = storm.impact_table()
    n_imp = len(storm.impact_lines)
    pts = np.column_stack([table["x_m"], table["y_m"], table["z_m"]]) if n_imp else np.zeros((0, 3))
    # the vertices around each impact point (the nearest alone may be clamped, at the seat's edge)
    near = min(4, n)
    vert = (cKDTree(storm.vertices).query(pts, k=near)[1].reshape(n_imp, near) if n_imp and n
            else np.zeros((n_imp, 1), dtype=np.int64))
    stone_of = table["stone"].astype(np.int64) if n_imp else np.zeros(0, dtype=np.int64)
    by_stone: dict[int, list[int]] = {}
    for i, sid in enumerate(stone_of):
        by_stone.setdefault(int(sid), []).append(i)
    best_val = np.full(n_imp, -1.0)
    best_frame = np.full(n_imp, -1, dtype=np.int64)
    any_val = np.full(n_imp, -1.0)
    any_frame = np.zeros(n_imp, dtype=np.int64)

    held_set = {g: j for j, g in enumerate(held)}
    u_state, u_peak, q_state, q_peak, contacts = [], [], [], [], []
    n_state: list[float] = []  # per held frame, the largest |u| of each field [m]
    n_peak: list[float] = []
    stone_pos, stone_r, stone_id, stone_f, offsets = [], [], [], [], [0]
    window: np.ndarray | None = None  # the peak field over the frames since the previous held one
    window_norm: np.ndarray | None = None
    prev_ids: np.ndarray = np.zeros(0, dtype=np.int64)
    any_contacts = True
    for g, fr in enumerate(storm.frames()):
        if g >= storm.n_frames:
            break
        peak = np.asarray(fr.peak, dtype=np.float32).reshape(n, 3)
        pnorm = np.linalg.norm(peak, axis=1)
        if window is None:
            window, window_norm = peak.copy(), pnorm
        else:
            bigger = pnorm > window_norm
            window[bigger] = peak[bigger]
            window_norm = np.where(bigger, pnorm, window_norm)
        if n_imp:  # the frame each impact shows in: its stone is about, the seat under it most displaced
            live = np.union1d(fr.ids, prev_ids)
            cand = [i for sid in live for i in by_stone.get(int(sid), ())]
            v_all = pnorm[vert].max(axis=1)
            better_any = v_all > any_val * 1.01
            any_val[better_any], any_frame[better_any] = v_all[better_any], g
            if cand:
                c = np.asarray(cand)
                v = pnorm[vert[c]].max(axis=1)
                up = v > best_val[c] * 1.01
                best_val[c[up]] = v[up]
                best_frame[c[up]] = g
        prev_ids = np.asarray(fr.ids, dtype=np.int64)
        j = held_set.get(g)
        if j is None:
            continue
        u = np.asarray(fr.displacement, dtype=np.float32).reshape(n, 3)
        n_state.append(float(np.linalg.norm(u.astype(np.float64), axis=1).max()) if n else 0.0)
        n_peak.append(float(window_norm.max()) if n else 0.0)
        q, step = _quantise(u)
        u_state.append(q)
        q_state.append(step)
        q, step = _quantise(window)
        u_peak.append(q)
        q_peak.append(step)
        window = window_norm = None
        stone_pos.append(np.asarray(fr.positions, dtype=np.float32).reshape(-1, 3))
        stone_r.append(np.asarray(fr.radii, dtype=np.float32))
        stone_id.append(np.asarray(fr.ids, dtype=np.int32))
        stone_f.append(np.asarray(fr.force, dtype=np.float32))
        offsets.append(offsets[-1] + len(fr.ids))
        if fr.contacts is None:
            any_contacts = False
        contacts.append(fr.contacts)
    if len(u_state) != len(held):
        raise ViewerInputError(f"{storm.path}: the series ended after {len(u_state)} held frames of {len(held)}; "
                               "cut short?")
    found = np.where(best_frame >= 0, best_frame, any_frame)
    # the page frame that shows it: the first held frame at or after it
    held_arr = np.asarray(held)
    page_frame = np.minimum(np.searchsorted(held_arr, found, side="left"), len(held) - 1)
    counts = np.diff(offsets)
    return {
        "u_state": np.stack(u_state) if u_state else np.zeros((0, n, 3), np.int16),
        "u_peak": np.stack(u_peak) if u_peak else np.zeros((0, n, 3), np.int16),
        "q_state": q_state, "q_peak": q_peak, "n_state": n_state, "n_peak": n_peak,
        "stone_pos": np.concatenate(stone_pos) if stone_pos else np.zeros((0, 3), np.float32),
        "stone_radius": np.concatenate(stone_r) if stone_r else np.zeros(0, np.float32),
        "stone_id": np.concatenate(stone_id) if stone_id else np.zeros(0, np.int32),
        "stone_force": np.concatenate(stone_f) if stone_f else np.zeros(0, np.float32),
        "stone_offsets": [int(o) for o in offsets], "max_stones": int(counts.max()) if counts.size else 0,
        "contacts": [int(c) for c in contacts] if any_contacts else None,
        "impact_frames": [int(f) for f in page_frame],
    }


def write_page(out: str | os.PathLike, path: str | os.PathLike | None = None, *, stride: int | None = None,
               budget: int = FRAME_BYTES) -> PageInfo:
    """Write the page of the storm in ``out`` to ``path`` (default ``out/viewer.html``, then listed
    in the storm's manifest so that a rerun of the storm replaces it) and return what was written.

    Raises
    ------
    ViewerInputError
        ``out`` is not a complete storm output.
    """
    from hailstorm.runtime.bundle.atomic import replacing

    page, facts = build_page(out, stride=stride, budget=budget)
    out = Path(out)
    target = Path(path) if path is not None else out / PAGE_NAME
    if target.is_dir():
        target = target / PAGE_NAME
    with replacing(target) as tmp:
        tmp.write_bytes(page.encode("utf-8"))
    if path is None or target.resolve().parent == out.resolve():
        _list_in_manifest(out, target.name)
    return PageInfo(path=target, bytes=target.stat().st_size, **facts)


def _list_in_manifest(out: Path, name: str) -> None:
    """Add ``name`` to the storm's manifest's files: a storm rerun into ``out`` then replaces the
    page with the rest instead of refusing a folder that holds a file it did not write."""
    from hailstorm.runtime.bundle.atomic import write_text_atomic
    from hailstorm.runtime.output.viewer.source import MANIFEST

    p = out / MANIFEST
    m = json.loads(p.read_text())
    if name not in m["files"]:
        m["files"] = sorted([*m["files"], name])
        write_text_atomic(p, json.dumps(m, indent=1) + "\n")


def serve(path: str | os.PathLike, *, host: str = "127.0.0.1", port: int = 8000,
          ready: Any = None) -> None:
    """Serve the page ``path`` on ``http://host:port/`` until interrupted (the page alone: any
    other address is 404). ``ready(url)`` is called once the server listens."""
    from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

    body = Path(path).read_bytes()

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 (http.server's name)
            if self.path.split("?")[0] in ("/", f"/{Path(path).name}"):
                self.send_response(200)
                self.send_header("Content-Type", "text/html; charset=utf-8")
                self.send_header("Content-Length", str(len(body)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(body)
            else:
                self.send_error(404)

        def log_message(self, format: str, *args: Any) -> None:  # quiet
            pass

    import threading

    with ThreadingHTTPServer((host, port), Handler) as httpd:
        url = f"http://{host}:{httpd.server_address[1]}/"
        # the server in a thread of its own, this thread waiting: a signal's exception (Ctrl-C, the
        # CLI's SIGTERM) then ends the wait here, where socketserver's handler of a request's
        # errors cannot swallow it
        server = threading.Thread(target=httpd.serve_forever, name="hailstorm-view", daemon=True)
        server.start()
        try:
            if ready is not None:
                ready(url)
            while server.is_alive():
                server.join(0.5)
        finally:
            httpd.shutdown()
