"""Writers for a storm's results: summary.json, impacts.csv, a ParaView time series.

What a storm writes, file by file; :mod:`hailstorm.runtime.output.storm_output` writes
them as a unit (:class:`~hailstorm.runtime.output.storm_output.StormOutput`: a temporary
sibling directory, one rename). The animation is :mod:`hailstorm.runtime.output.animation`'s
(:func:`write_animation` is re-exported here); it needs the ``video`` extra (matplotlib,
imageio), imported inside the writers. The ParaView series is written with numpy alone
(:mod:`hailstorm.runtime.output.vtu`): the core install writes everything but the animation.
"""

from __future__ import annotations

import json
import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hailstorm.runtime.bundle.atomic import write_text_atomic
from hailstorm.runtime.output.animation import write_animation
from hailstorm.runtime.output.render import shown_displacement as _shown
from hailstorm.runtime.output.vtu import read_vtu, write_vtu

__all__ = [
    "SUMMARY_UNITS",
    "FrameSeries",
    "ParaviewSeries",
    "impacts_csv",
    "summary",
    "write_animation",
    "write_impacts",
    "write_paraview",
    "write_summary",
]

_log = logging.getLogger(__name__)

def _jsonable(v: Any) -> Any:
    if isinstance(v, (np.integer,)):
        return int(v)
    if isinstance(v, (np.floating, float)):
        f = float(v)
        return f if math.isfinite(f) else None
    if isinstance(v, np.bool_):
        return bool(v)
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    return v


def _seat_of(gf: Any) -> dict[str, Any] | None:
    """The seat a bundle was actually computed for (from its manifest), in the scene's
    ``[seat]`` layout, or None when ``gf`` carries no manifest."""
    m = getattr(gf, "manifest", None)
    if not isinstance(m, dict):
        return None
    opts, mat = m.get("options", {}), m.get("material", {})
    seat = {"mesh_size": opts.get("mesh_size"), "order": opts.get("order"),
            "young": mat.get("young", opts.get("young")), "poisson": mat.get("poisson", opts.get("poisson"))}
    if opts.get("geometry") is not None:
        seat["geometry"] = str(opts["geometry"])
    return seat


#: the unit of each figure of ``summary.json`` (also written into it, as ``units``): SI units,
#: ``"count"`` for counts, ``"1"`` for dimensionless ratios, None for text and settings
SUMMARY_UNITS: dict[str, str | None] = {
    "hailstones": "count", "impacts": "count", "stones_hit": "count", "max_contact_force": "N",
    "max_indentation_m": "m", "max_simultaneous_contacts": "count",
    "max_penetration_m": "m", "steps": "count", "substeps": "count", "capacitance_rebuilds": "count",
    "wall_contacts": "count", "stone_collisions": "count", "max_stone_collision_force_N": "N", "retired": "count", "max_penetration_contact_m": "m", "max_penetration_free_m": "m",
    "max_penetration_contact_rel": "1", "patch": None, "patch_weights_computed": "count",
    "patch_weights_reused": "count", "patch_resizes": "count", "max_patch_radius_m": "m",
    "mean_penetration_contact_m": "m", "sim_time_s": "s", "wall_time_s": "s", "setup_time_s": "s",
    "compile_time_s": "s", "backend": None, "real_time_factor": "1", "seed": None, "dt": "s", "integrator": None,
    "mode": None, "restitution": "1", "n_vertices": "count", "n_triangles": "count", "resting_at_end": "count",
    "frames": "count", "output_time_s": "s", "inertia_time_s": "s",
    # the validity limits (hailstorm.runtime.storm.limits)
    "impacts_beyond_indentation_limit": "count", "impacts_beyond_radius_limit": "count",
    "impacts_beyond_strain_limit": "count", "impacts_beyond_any_limit": "count",
    "max_indentation_thickness_ratio": "1", "max_contact_radius_ratio": "1", "max_strain_ratio": "1",
    "min_impact_thickness_m": "m", "limit_indentation_thickness_ratio": "1", "limit_contact_radius_ratio": "1",
    "limit_strain_ratio": "1", "impacts_beyond_contact_time_limit": "count", "min_contact_time_ratio": "1",
    "limit_contact_time_ratio": "1", "pad_density": "kg/m^3",
    # the pad's inertia per impact (hailstorm.runtime.inertia)
    "impacts_beyond_inertia_limit": "count", "max_impact_force_N": "N", "max_impact_force_dynamic_N": "N",
    "min_inertia_force_factor": "1", "min_inertia_restitution_factor": "1", "limit_inertia_change": "1",
    "inertia_direct_runs": "count",
}


def summary(result: Any, gf: Any = None) -> dict[str, Any]:
    """The summary as a dict (what :func:`write_summary` writes).

    Keys (every key and its unit is listed in the documentation, "Outputs"):
    ``hailstones`` (spawned), ``impacts`` (contact onsets faster than
    the scene's ``time.rest_speed``), ``stones_hit`` (stones that touched the seat
    at least once, slow touches included), ``max_contact_force`` [N] (the contract's key: the
    largest force any contact carried in any sub-step, impacts, slow touches and resting stones
    alike; ``max_impact_force_N`` below is the largest impact's alone, never more),
    ``max_indentation_m`` (largest normal contact displacement),
    ``max_simultaneous_contacts``, ``max_penetration_m`` (deepest overlap of a
    stone with the deformed surface), ``steps``, ``substeps``,
    ``capacitance_rebuilds``, ``frames`` (recorded, = files in each series),
    ``sim_time_s``, ``wall_time_s`` (the stepping, recording the frames
    included, writing them not), ``output_time_s`` (writing the frames as they
    were recorded), ``inertia_time_s`` (the impacts' inertia factors, after the storm),
    ``real_time_factor`` (simulated / wall-clock time; > 1 is faster than real
    time), ``setup_time_s`` (building the storm: spatial index, spawn plan,
    loading the compiled kernels), ``compile_time_s`` (the one-time compile of
    the kernels, the first run after an install; 0 when they were loaded),
    ``backend``, ``seed``, ``dt``, ``integrator``, ``mode``, and the scene;
    ``units``, each key's unit (:data:`SUMMARY_UNITS`). The validity limits
    (:mod:`hailstorm.runtime.storm.limits`, docs/validity.md):
    ``impacts_beyond_indentation_limit``, ``impacts_beyond_radius_limit``,
    ``impacts_beyond_strain_limit``, ``impacts_beyond_any_limit`` (impacts whose
    peak indentation over the local pad thickness, Hertz contact radius over
    stone radius or estimated peak strain exceeded the limit),
    ``max_indentation_thickness_ratio``, ``max_contact_radius_ratio``,
    ``max_strain_ratio`` (the worst values, [-]), ``min_impact_thickness_m``
    (the thinnest pad under an impact) and the limits
    ``limit_indentation_thickness_ratio``, ``limit_contact_radius_ratio``,
    ``limit_strain_ratio`` [-]; the contact-time limit's and the pad's inertia's keys
    (:func:`hailstorm.runtime.storm.limits.summarise`: ``max_impact_force_N`` and
    ``max_impact_force_dynamic_N``, the largest impact's peak force quasi-static and
    with the pad's inertia).

    Parameters
    ----------
    result : StormResult
    gf : GreensFunctions, optional
        The bundle the storm ran on. Given, the scene's ``[seat]`` section
        records the seat the bundle was computed for (its manifest: mesh size,
        order, material; the scene file's ``[seat]`` request,
        :class:`~hailstorm.runtime.storm.scene.SeatSettings`, is not part of the
        :class:`~hailstorm.runtime.storm.scene.Scene`), and ``bundle`` records its
        path and key. Without it the scene has no ``[seat]``.
    """
    d = dict(result.stats)
    d["units"] = {k: SUMMARY_UNITS.get(k) for k in d}
    d["scene"] = result.scene.to_dict()
    seat = _seat_of(gf) if gf is not None else None
    if seat is not None:
        d["scene"]["seat"] = seat
        d["bundle"] = {"path": str(getattr(gf, "path", "")), "key": gf.manifest.get("key")}
    return _jsonable(d)


def write_summary(result: Any, path: str | os.PathLike, gf: Any = None) -> Path:
    """Write ``summary.json`` for a :class:`hailstorm.runtime.storm.recording.StormResult`; returns the path.
    ``gf``: see :func:`summary`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(path, json.dumps(summary(result, gf), indent=2, sort_keys=True) + "\n")


def impacts_csv(stats: Any) -> str:
    """Every impact of a storm as CSV text (``impacts.csv``): a header of column names, then one
    line per impact (:meth:`hailstorm.runtime.storm.limits.ImpactLimits.table`; a value not
    measured is an empty field). A storm without impacts gives the header alone."""
    from hailstorm.runtime.storm.limits import IMPACT_COLUMNS

    rec = getattr(stats, "validity", None)
    cols = rec.table() if rec is not None else {k: np.zeros(0) for k in IMPACT_COLUMNS}
    names = list(cols)

    def cell(v: Any) -> str:
        if isinstance(v, (float, np.floating)):
            return "" if math.isnan(float(v)) else f"{float(v):.9g}"  # (inf stays: "no measure", as in the summary)
        return str(v)

    n = len(cols[names[0]]) if names else 0
    lines = [",".join(names)] + [",".join(cell(cols[k][i]) for k in names) for i in range(n)]
    return "\n".join(lines) + "\n"


def write_impacts(stats: Any, path: str | os.PathLike) -> Path:
    """Write :func:`impacts_csv` to ``path`` atomically; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(path, impacts_csv(stats))


def _pvd(entries: list[tuple[float, str]]) -> str:
    rows = "\n".join(f'    <DataSet timestep="{t:.9g}" group="" part="0" file="{fn}"/>' for t, fn in entries)
    return ('<?xml version="1.0"?>\n<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">\n'
            f"  <Collection>\n{rows}\n  </Collection>\n</VTKFile>\n")


class ParaviewSeries:
    """A ParaView time series written frame by frame (:meth:`add`), then closed (:meth:`close`).

    The seat (``frames/surface_NNNN.vtu``) carries point data ``displacement``
    (vector, [m]), ``|u|``, ``peak_displacement`` and ``|u| peak`` (the largest
    displacement since the previous frame); its points are the *undeformed*
    vertices (use ParaView's "Warp By Vector" to see the deformation). The
    stones (``frames/stones_NNNN.vtu``) are vertex cells with point data
    ``radius`` [m], ``id`` and ``force`` (the force each applies to the seat
    [N], zero out of contact) (use a "Glyph" filter, sphere, scale by
    ``radius``, factor 2). A frame without stones holds one placeholder point
    of radius 0, id -1 and force 0 (a VTU without cells cannot be read back by meshio).
    Only the running list of file names and times is kept, not the frames.

    Parameters
    ----------
    gf : GreensFunctions
    outdir : path
        Directory of the series (created).
    name : str
        The collections are ``<name>.pvd`` (seat) and ``<name>_stones.pvd``.
    """

    def __init__(self, gf: Any, outdir: str | os.PathLike, *, name: str = "storm") -> None:
        self.outdir = Path(outdir)
        self.name = name
        (self.outdir / "frames").mkdir(parents=True, exist_ok=True)
        self._X = np.asarray(gf.vertices, dtype=np.float64)
        self._tri = np.asarray(gf.triangles, dtype=np.int64)
        self._dummy = self._X.mean(axis=0)[None, :] if len(self._X) else np.zeros((1, 3))
        #: per frame: (t, surface file, stones file, open contacts, max |shown displacement|)
        self.entries: list[tuple[float, str, str, int, float]] = []

    def __len__(self) -> int:
        return len(self.entries)

    def add(self, frame: Any) -> None:
        """Write one :class:`hailstorm.runtime.storm.recording.Frame` (both files)."""
        i = len(self.entries)
        u = np.asarray(frame.displacement, dtype=np.float64)
        peak = np.asarray(_shown(frame), dtype=np.float64)
        sname = f"frames/surface_{i:04d}.vtu"
        write_vtu(self.outdir / sname, self._X, "triangle", self._tri,
                  {"displacement": u, "|u|": np.linalg.norm(u, axis=1), "peak_displacement": peak,
                   "|u| peak": np.linalg.norm(peak, axis=1)})
        pos = np.asarray(frame.positions, dtype=np.float64).reshape(-1, 3)
        radii = np.asarray(frame.radii, dtype=np.float64)
        ids = np.asarray(frame.ids, dtype=np.int64)
        forces = getattr(frame, "forces", None)
        forces = np.zeros((pos.shape[0], 3)) if forces is None else np.asarray(forces, dtype=np.float64)
        if pos.shape[0] == 0:  # placeholder: meshio cannot read a VTU without cells
            pos, radii, ids, forces = self._dummy, np.zeros(1), np.full(1, -1, dtype=np.int64), np.zeros((1, 3))
        k = pos.shape[0]
        stname = f"frames/stones_{i:04d}.vtu"
        write_vtu(self.outdir / stname, pos, "vertex", np.arange(k, dtype=np.int64)[:, None],
                  {"radius": radii, "id": ids, "force": forces})
        # (in float64, as the renderer takes the norms: its colour scale's top bounds every pixel)
        umax = float(np.linalg.norm(np.asarray(peak, dtype=np.float64), axis=1).max()) if len(peak) else 0.0
        self.entries.append((float(frame.t), sname, stname, int(frame.contacts), umax))

    def close(self) -> Path:
        """Write the two ``.pvd`` collections; returns ``<name>.pvd``."""
        main = self.outdir / f"{self.name}.pvd"
        main.write_text(_pvd([(t, s) for t, s, _, _, _ in self.entries]))
        (self.outdir / f"{self.name}_stones.pvd").write_text(_pvd([(t, s) for t, _, s, _, _ in self.entries]))
        return main

    def files(self) -> list[str]:
        """Every file of the series, relative to :attr:`outdir`."""
        names = [f"{self.name}.pvd", f"{self.name}_stones.pvd"]
        for _, s, st, _, _ in self.entries:
            names += [s, st]
        return names

    def frames(self) -> "FrameSeries":
        """The written frames, read back on access."""
        return FrameSeries(self)


class FrameSeries(Sequence):
    """The frames of a :class:`ParaviewSeries`, read back from its files on access
    (a sequence of :class:`hailstorm.runtime.storm.recording.Frame`; nothing is cached)."""

    def __init__(self, series: ParaviewSeries) -> None:
        self._series = series

    def __len__(self) -> int:
        return len(self._series.entries)

    def peak_norm(self, i: int) -> float:
        """Largest ``|peak displacement|`` of frame ``i`` [m], without reading it."""
        return self._series.entries[i][4]

    def __getitem__(self, i: int) -> Any:  # type: ignore[override]
        from hailstorm.runtime.storm.recording import Frame

        t, sname, stname, contacts, _ = self._series.entries[i]
        _, s = read_vtu(self._series.outdir / sname)
        st_points, st = read_vtu(self._series.outdir / stname)
        ids = np.asarray(st["id"], dtype=np.int64)
        keep = ids >= 0
        force = st.get("force")  # absent from the files of older versions
        return Frame(t=t, displacement=s["displacement"], positions=st_points[keep],
                     radii=np.asarray(st["radius"])[keep], ids=ids[keep], contacts=contacts,
                     peak_displacement=s["peak_displacement"],
                     forces=None if force is None else np.asarray(force, dtype=np.float64)[keep])


def write_paraview(result: Any, gf: Any, outdir: str | os.PathLike, *, name: str = "storm") -> Path:
    """Write a ParaView time series of a storm's frames (see :class:`ParaviewSeries`).

    Parameters
    ----------
    result : StormResult or sequence of Frame
    gf : GreensFunctions
    outdir : path
    name : str

    Returns
    -------
    pathlib.Path
        ``outdir/<name>.pvd`` (the collection to open in ParaView); the stones'
        series is ``outdir/<name>_stones.pvd``.
    """
    series = ParaviewSeries(gf, outdir, name=name)
    for f in getattr(result, "frames", result):
        series.add(f)
    return series.close()
