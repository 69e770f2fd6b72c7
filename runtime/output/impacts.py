"""The impacts of ``impacts.csv`` on the video's time axis.

``impacts.csv`` (:func:`hailstorm.runtime.output.files.impacts_csv`) gives each impact's
stone, when its contact opened and when it peaked (``t_onset_s``, ``t_peak_s``), its contact
point at onset, its normal speed and its peak force. The video's force panel marks each
impact's peak force at its time, :func:`impact_times`: the file's ``t_peak_s``. A file
written before the storm recorded the times has none; for it the times are estimated: the stone's gap to the onset point in the last
recorded frame before it touched, crossed at the impact's speed, gives the onset; the
peak is the largest total force of the storm's per-step history in the contact's first
:data:`PEAK_WINDOW` seconds after it (where no history is given: the onset). An impact
whose stone is in no frame before its onset is put at the history's step whose force is
nearest its peak. The numbers (the peak forces) are the file's; only the times are
estimated.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["PEAK_WINDOW", "impact_times", "read_impacts"]

#: after an impact's estimated onset, the span searched for its peak in the force history [s]
#: (the default storm's impacts last 0.3-1.5 ms)
PEAK_WINDOW = 2.0e-3


def read_impacts(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """``impacts.csv`` as columns: numbers as float arrays (an empty field is NaN), ``stone`` as int,
    ``beyond`` as strings.

    Parameters
    ----------
    path : path

    Returns
    -------
    dict
        Column name -> (n,) array, in the file's order.
    """
    with Path(path).open(newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        return {}
    names, body = rows[0], rows[1:]
    out: dict[str, np.ndarray] = {}
    for j, name in enumerate(names):
        col = [r[j] if j < len(r) else "" for r in body]
        if name == "beyond":
            out[name] = np.array(col, dtype=str)
        elif name == "stone":
            out[name] = np.array([int(v) for v in col], dtype=np.int64)
        else:
            out[name] = np.array([float(v) if v else np.nan for v in col], dtype=np.float64)
    return out


def impact_times(impacts: dict[str, np.ndarray], frames: Sequence[Any],
                 history: np.ndarray | None = None) -> np.ndarray:
    """When each impact of ``impacts`` peaked [s] (the file's ``t_peak_s``, else estimated: the module notes).

    Parameters
    ----------
    impacts : dict
        Columns of ``impacts.csv`` (:func:`read_impacts`): ``stone``, ``x_m``, ``y_m``,
        ``z_m``, ``radius_m``, ``speed_m_s``, ``peak_force_N``; a ``t_peak_s`` column (the storm
        records it), where present, is taken as the times themselves.
    frames : sequence of Frame
        The storm's recorded frames (``t``, ``ids``, ``positions``), in time order.
    history : (m, 3) ndarray, optional
        The storm's per-step (time, total contact force, open contacts).

    Returns
    -------
    (n,) ndarray
        One time per impact [s], in the file's order.
    """
    if "t_peak_s" in impacts:
        return np.asarray(impacts["t_peak_s"], dtype=np.float64)
    n = len(impacts.get("stone", ()))
    if n == 0:
        return np.zeros(0)
    stone = np.asarray(impacts["stone"], dtype=np.int64)
    onset = np.stack([impacts["x_m"], impacts["y_m"], impacts["z_m"]], axis=1).astype(np.float64)
    radius = np.asarray(impacts["radius_m"], dtype=np.float64)
    speed = np.maximum(np.asarray(impacts["speed_m_s"], dtype=np.float64), 1e-3)
    force = np.asarray(impacts["peak_force_N"], dtype=np.float64)
    # each stone's track through the frames: (t, centre)
    tracks: dict[int, list[tuple[float, np.ndarray]]] = {int(s): [] for s in np.unique(stone)}
    for f in frames:
        ids = np.asarray(f.ids, dtype=np.int64).reshape(-1)
        pos = np.asarray(f.positions, dtype=np.float64).reshape(-1, 3)
        for j in np.flatnonzero(np.isin(ids, stone)):
            tracks[int(ids[j])].append((float(f.t), pos[j]))
    hist = None if history is None or len(history) == 0 else np.asarray(history, dtype=np.float64).reshape(-1, 3)
    out = np.full(n, np.nan)
    t_prev = -np.inf  # impacts are in onset order: each onset is no earlier than the previous one
    for k in range(n):
        est = _onset(tracks.get(int(stone[k]), []), onset[k], radius[k], speed[k], t_prev)
        if est is None:
            if hist is not None:  # no track: the history's step whose force is nearest this peak
                out[k] = float(hist[int(np.argmin(np.abs(hist[:, 1] - force[k]))), 0])
            else:
                out[k] = t_prev if np.isfinite(t_prev) else 0.0
            continue
        t_prev = max(t_prev, est)
        out[k] = est
        if hist is not None:
            win = (hist[:, 0] >= est - 0.25 * PEAK_WINDOW) & (hist[:, 0] <= est + PEAK_WINDOW)
            if win.any() and hist[win, 1].max() > 0:
                out[k] = float(hist[win, 0][int(np.argmax(hist[win, 1]))])
    return out


#: gravity [m/s^2] (the stones' flight between frames)
_G = np.array([0.0, 0.0, -9.81])


def _onset(track: list[tuple[float, np.ndarray]], point: np.ndarray, radius: float, speed: float,
           not_before: float) -> float | None:
    """When a stone of track ``track`` (frame time, centre) first came within ``radius`` of ``point``:
    from the last frame before it, in free flight at the velocity of the frame pair that ends there
    (at ``speed`` towards the point when the stone has no earlier frame). None: no frame before."""
    if not track:
        return None
    ts = np.array([t for t, _ in track])
    ps = np.array([p for _, p in track])
    gap = np.linalg.norm(ps - point, axis=1) - radius
    best: tuple[float, float] | None = None  # (miss distance, time)
    for j in range(len(ts)):
        if gap[j] < -0.5 * radius or ts[j] < not_before - 1e-3:
            continue
        if j > 0 and ts[j] > ts[j - 1]:
            dt = ts[j] - ts[j - 1]
            v = (ps[j] - ps[j - 1]) / dt + 0.5 * _G * dt
        else:
            d = point - ps[j]
            v = d / max(np.linalg.norm(d), 1e-12) * speed
        span = (ts[j + 1] - ts[j]) if j + 1 < len(ts) else 0.05
        tau = np.linspace(0.0, span, 401)
        path = ps[j] + v * tau[:, None] + 0.5 * _G * tau[:, None] ** 2
        dist = np.linalg.norm(path - point, axis=1) - radius
        i = int(np.argmax(dist <= 0.0)) if (dist <= 0.0).any() else int(np.argmin(dist))
        miss = max(float(dist[i]), 0.0)
        if best is None or miss < best[0] - 1e-9:
            best = (miss, float(ts[j] + tau[i]))
    return None if best is None else best[1]
