"""Storm settings: the :class:`Scene` and its TOML file.

A scene file has the sections ``[storm]``, ``[hail]``, ``[contact]``,
``[time]``, ``[output]``, ``[validity]`` and ``[seat]``; every key is optional and takes the
packaged default (``meshes/default_scene.toml``, installed as
``hailstorm.meshes``) when absent. Unknown sections or keys and bad values
raise :class:`SceneError` naming the file, the key and the problem.

Use::

    from hailstorm.runtime.storm.scene import Scene
    scene = Scene.from_toml("scene.toml")      # or Scene.default(), Scene.from_flat(duration=0.2, ...)
    scene.storm.duration, scene.time.dt        # one typed record per section
    scene.with_(dt=1e-4).to_toml("copy.toml")  # a flat key goes to its section
    seat = SeatSettings.from_toml("scene.toml")  # [seat]: the default seat's precompute settings
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from hailstorm.runtime.bundle.atomic import write_text_atomic
from hailstorm.runtime.seat_settings import SeatSettings  # (re-exported: it lived here)
from hailstorm.runtime.sections import Section as _Section, packaged_toml as _packaged_toml, read_toml as _read_toml
from hailstorm.runtime.storm.errors import SceneError, StormTooLarge
from hailstorm.runtime.storm.estimate import (BYTES_PER_STEP, BYTES_PER_STONE, DISK_BYTES_FIXED, DISK_BYTES_PER_VERTEX,
                                              StormEstimate)
from hailstorm.runtime.storm.hail import GRAVITY, terminal_velocity
from hailstorm.runtime.storm.scene_sections import (ContactSettings, HailSettings, OutputSettings, StormSettings,
                                                    TimeSettings, ValiditySettings)

__all__ = ["Scene", "SceneError", "SeatSettings", "StormEstimate", "StormTooLarge"]


#: the records of a :class:`Scene`, by TOML section
_RECORDS: dict[str, type[_Section]] = {
    "storm": StormSettings, "hail": HailSettings, "contact": ContactSettings, "time": TimeSettings,
    "output": OutputSettings, "validity": ValiditySettings,
}
#: section of every flat key (:meth:`Scene.from_flat`, :meth:`Scene.with_`)
_SECTION_OF: dict[str, str] = {k: sec for sec, rec in _RECORDS.items() for k in rec.keys()}


@dataclass(frozen=True)
class Scene:
    """Storm settings (all SI units), one typed record per section of the TOML
    file. Load with :meth:`from_toml` / :meth:`default`; build from flat keys
    with :meth:`from_flat`, change with :meth:`with_`.

    Attributes
    ----------
    storm : StormSettings
        ``[storm]``: duration, rate or stones, seed, spawn height, margin, wind.
    hail : HailSettings
        ``[hail]``: radius distribution, ice density, drag.
    contact : ContactSettings
        ``[contact]``: mode, unilateral release, restitution, patch.
    time : TimeSettings
        ``[time]``: dt, integrator, sub-steps, rest speed.
    output : OutputSettings
        ``[output]``: frame rate.
    validity : ValiditySettings
        ``[validity]``: the pad's density (for the validity limits only).

    The scene file's ``[seat]`` (the default seat's precompute settings) is
    not part of the scene: see :class:`SeatSettings`.

    Examples
    --------
    >>> sc = Scene.from_flat(duration=0.1, stones=12, dt=5e-4)   # each key to its section
    >>> sc.storm.duration, sc.time.dt
    (0.1, 0.0005)
    >>> sc.with_(integrator="exact").time.integrator
    'exact'
    """

    storm: StormSettings = dataclasses.field(default_factory=StormSettings)
    hail: HailSettings = dataclasses.field(default_factory=HailSettings)
    contact: ContactSettings = dataclasses.field(default_factory=ContactSettings)
    time: TimeSettings = dataclasses.field(default_factory=TimeSettings)
    output: OutputSettings = dataclasses.field(default_factory=OutputSettings)
    validity: ValiditySettings = dataclasses.field(default_factory=ValiditySettings)

    def __post_init__(self) -> None:
        for sec, rec in _RECORDS.items():
            if not isinstance(getattr(self, sec), rec):
                raise SceneError(f"{sec} must be a {rec.__name__}, got {getattr(self, sec)!r}")
        if self.time.dt > self.storm.duration:
            raise SceneError(f"dt ({self.time.dt!r} s) must not exceed duration ({self.storm.duration!r} s)")
        if not math.isfinite(self.storm.duration / self.time.dt):
            raise SceneError(f"duration / dt ({self.storm.duration!r} s / {self.time.dt!r} s) is not a finite "
                             "number of steps; lower the duration")

    @staticmethod
    def _route(kw: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
        by_section: dict[str, dict[str, Any]] = {sec: {} for sec in _RECORDS}
        for k, v in kw.items():
            if k not in _SECTION_OF:
                hint = " (a [seat] setting: see SeatSettings)" if k in SeatSettings.keys() else ""
                raise SceneError(f"unknown scene setting {k!r}{hint}")
            by_section[_SECTION_OF[k]][k] = v
        return by_section

    @classmethod
    def from_flat(cls, **kw: Any) -> "Scene":
        """A scene from flat keys, each routed to its section; the rest take the
        records' defaults (the values of :meth:`default`).

        ``Scene.from_flat(duration=0.1, dt=5e-4)`` is
        ``Scene(storm=StormSettings(duration=0.1), time=TimeSettings(dt=5e-4))``.

        Raises
        ------
        SceneError
            An unknown key, or a bad value.
        """
        return cls(**{sec: _RECORDS[sec](**body) for sec, body in cls._route(kw).items()})

    def with_(self, **kw: Any) -> "Scene":
        """A copy with flat keys changed, each in its section (like
        :func:`dataclasses.replace`): ``scene.with_(dt=5e-4, stones=3)``.

        Raises
        ------
        SceneError
            An unknown key, or a bad value.
        """
        changes = {sec: dataclasses.replace(getattr(self, sec), **body)
                   for sec, body in self._route(kw).items() if body}
        return dataclasses.replace(self, **changes)

    # -- helpers ---------------------------------------------------------------
    def n_steps(self) -> int:
        """Time steps of the storm (as :func:`hailstorm.runtime.storm.run.run_storm` takes them)."""
        return max(1, int(round(self.storm.duration / self.time.dt)))

    def estimate(self, n_vertices: int | None = None, *, keep_frames: bool = False,
                 hit_fraction: float | None = None, video: bool = False, startup: bool = False,
                 series: str = "vtkhdf") -> StormEstimate:
        """Steps, stones, frames, memory, disk and wall time of this storm, before it runs.

        Parameters
        ----------
        n_vertices : int, optional
            Surface vertices of the bundle (for the frames' memory, disk and time).
        keep_frames : bool
            Frames held in memory (the Python API's default) rather than
            streamed to disk.
        hit_fraction : float, optional
            The share of the stones that hit the seat
            (:func:`hailstorm.runtime.storm.estimate.hit_fraction`); default 1, an
            upper bound.
        video : bool
            The frames are rendered into a video after the storm (the command line's default).
        startup : bool
            Count a warm start of the process (the command line's estimate).
        series : {"vtkhdf", "vtu"}
            The ParaView series the frames are written as (their disk).
        """
        if series not in DISK_BYTES_PER_VERTEX:
            raise ValueError(f"unknown series format {series!r}; choose from {', '.join(DISK_BYTES_PER_VERTEX)}")
        sc = self.storm
        steps = self.n_steps()
        stones = sc.stones if sc.stones is not None else int(round(sc.rate * sc.duration))
        frames = min(steps, int(math.ceil(sc.duration * self.output.fps - 1e-9))) + 1
        # the stone count of a rate is Poisson: allow five standard deviations
        high = stones if sc.stones is not None else stones + 5 * math.sqrt(stones) + 16
        memory = BYTES_PER_STEP * steps + BYTES_PER_STONE * high
        if keep_frames and n_vertices is not None:
            memory += frames * (24 * n_vertices + 64)  # two float32 fields per vertex
        disk = None if n_vertices is None else (frames * (DISK_BYTES_PER_VERTEX[series] * n_vertices + 4096)
                                                + DISK_BYTES_FIXED[series])
        extra = {} if hit_fraction is None else {"hit_fraction": float(hit_fraction)}
        return StormEstimate(steps=steps, stones=int(stones), frames=frames, memory_bytes=int(memory),
                             disk_bytes=disk, duration=float(sc.duration), dt=float(self.time.dt),
                             n_vertices=n_vertices, inertia=bool(self.validity.inertia), video=bool(video),
                             startup=bool(startup), from_rate=sc.stones is None, **extra)

    def physical_warnings(self, vertices: Any) -> list[str]:
        """Settings that are valid but make the storm physically meaningless on this seat.

        Checks: stones wider than the seat, a contact patch wider than the seat
        (patch weights then fall back to a point contact), and wind or drag
        settings with which no stone reaches the seat (an updraft, or a wind
        without drag that carries every stone past it, or stones that fall
        too slowly to arrive within the duration). The flight is integrated
        here, independently of the storm's own flight code.

        Parameters
        ----------
        vertices : (n, 3) array
            The seat's surface vertices [m].

        Returns
        -------
        list of str
            One sentence per problem (empty: nothing found).
        """
        X = np.asarray(vertices, dtype=np.float64)
        lo, hi = X.min(axis=0), X.max(axis=0)
        width = float(min(hi[0] - lo[0], hi[1] - lo[1]))
        sc, hail, contact = self.storm, self.hail, self.contact
        out = []
        if 2.0 * hail.r_max > width:
            out.append(f"stones are larger than the seat: diameters up to {2e3 * hail.r_max:.4g} mm "
                       f"on a seat {1e3 * width:.4g} mm wide ([hail] r_max)")
        if contact.patch != "none" and 2.0 * contact.patch_min_radius > width:
            out.append(f"the contact patch ({2e3 * contact.patch_min_radius:.4g} mm across, [contact] "
                       f"patch_min_radius) is wider than the seat ({1e3 * width:.4g} mm): every contact "
                       "falls back to a point contact")
        if (sc.stones is None and sc.rate == 0) or sc.stones == 0:
            return out
        if not self._some_stone_lands(lo, hi):
            out.append("no stone reaches the seat within the storm: with this wind and drag "
                       f"([storm] wind = {list(sc.wind)}, [hail] drag = {str(hail.drag).lower()}, "
                       f"cd = {hail.cd:g}, rho_air = {hail.rho_air:g}) every stone misses or arrives after "
                       f"{sc.duration:g} s")
        return out

    def _some_stone_lands(self, lo: np.ndarray, hi: np.ndarray) -> bool:
        """Whether a stone dropped from the spawn plane over the middle of the seat
        (with the storm's upwind offset) reaches the seat's mid-height inside the
        spawn footprint within the duration, for some radius."""
        sc, hail = self.storm, self.hail
        r = np.linspace(hail.r_min, hail.r_max, 9) if hail.distribution != "fixed" else np.array([hail.r_min])
        vt = terminal_velocity(r, cd=hail.cd, rho_air=hail.rho_air, density=hail.density)
        zmid = 0.5 * (lo[2] + hi[2])
        z0 = hi[2] + sc.spawn_height + r
        wind = np.asarray(sc.wind, dtype=np.float64)
        t_fall = (z0 - zmid) / np.maximum(vt, 1e-9)
        centre = 0.5 * (lo[:2] + hi[:2])
        pos = np.column_stack([centre[None, :] - wind[None, :2] * t_fall[:, None], z0])
        vel = np.column_stack([np.broadcast_to(wind[:2], (len(r), 2)), -vt])
        if hail.drag and not np.any(wind):  # straight down at terminal speed
            return bool(t_fall.min() <= sc.duration)
        k = 3.0 * hail.cd * hail.rho_air / (8.0 * hail.density * r) if hail.drag else np.zeros_like(r)
        n = 1000
        h = sc.duration / n
        g = np.array([0.0, 0.0, -GRAVITY])
        for _ in range(n):
            # drag implicit (stable for any h): v' = v + h (g - k |v - w| (v' - w))
            kr = h * k * np.linalg.norm(vel - wind, axis=1)
            vel = (vel + h * g + kr[:, None] * wind) / (1.0 + kr)[:, None]
            pos = pos + h * vel
            down = pos[:, 2] <= zmid
            if down.any():
                xy = pos[down, :2]
                inside = np.all((xy >= lo[:2] - sc.margin) & (xy <= hi[:2] + sc.margin), axis=1)
                if inside.any():
                    return True
                pos[down, 2] = np.inf  # missed: stop following it
                vel[down] = 0.0
            if np.all(~np.isfinite(pos[:, 2])):
                return False
        return False

    def to_dict(self) -> dict[str, dict[str, Any]]:
        """Nested ``{section: {key: value}}`` as in the TOML file (``stones`` omitted if None;
        no ``[seat]``: see :class:`SeatSettings`)."""
        return {sec: getattr(self, sec).to_dict() for sec in _RECORDS}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, source: str = "scene") -> "Scene":
        """Build from a nested ``{section: {key: value}}`` mapping (TOML layout);
        absent sections and keys take the records' defaults. A ``[seat]``
        section is validated (:class:`SeatSettings`) but not kept.

        Raises
        ------
        SceneError
            On an unknown section or key, or a bad value.
        """
        records: dict[str, Any] = {}
        for sec, body in data.items():
            if sec == "compute":
                raise SceneError(f"{source}: [compute] backend is gone: the storm always runs its compiled (numba) "
                                 "kernels; remove the [compute] section (NUMBA_DISABLE_JIT=1 runs them as Python, "
                                 "for debugging)")
            if sec == SeatSettings.SECTION:
                SeatSettings.from_dict(body, source=source)
                continue
            if sec not in _RECORDS:
                raise SceneError(f"{source}: unknown section [{sec}]; known sections: "
                                 f"{', '.join([*_RECORDS, SeatSettings.SECTION])}")
            records[sec] = _RECORDS[sec].from_dict(body, source=source)
        try:
            return cls(**records)
        except SceneError as exc:
            raise SceneError(f"{source}: {exc}") from None

    @classmethod
    def from_toml(cls, path: str | Path, *, base: "Scene | None" = None,
                  overrides: Mapping[str, Mapping[str, Any]] | None = None) -> "Scene":
        """Load a scene TOML file. Keys it does not set take the values of ``base``
        (default: :meth:`default`, the packaged ``default_scene.toml``); ``overrides``
        (``{section: {key: value}}``, e.g. the command line's options) replace the file's
        values once the file's own sections are checked, and the scene's rules across
        sections (``dt`` at most ``duration``) are checked with them.
        Its ``[seat]`` is checked, not kept (read it with :meth:`SeatSettings.from_toml`)."""
        path = Path(path)
        data = _read_toml(path)
        merged: dict[str, Any] = (base or cls.default()).to_dict()
        for sec, body in data.items():
            if isinstance(body, Mapping) and sec in merged:
                merged[sec] = {**merged[sec], **body}
            else:
                merged[sec] = body
        storm = data.get("storm", {})
        if isinstance(storm, Mapping) and "stones" not in storm and (base is None or base.storm.stones is None):
            merged["storm"].pop("stones", None)
        if overrides:
            for sec, body in merged.items():  # the file's own values first, section by section
                if sec in _RECORDS:
                    _RECORDS[sec].from_dict(body, source=str(path))
            for sec, body in overrides.items():
                merged[sec] = {**merged.get(sec, {}), **body}
        return cls.from_dict(merged, source=str(path) + (" with the command line's options" if overrides else ""))

    @classmethod
    def default(cls) -> "Scene":
        """The packaged default scene (``hailstorm.meshes/default_scene.toml``)."""
        return cls.from_dict(_packaged_toml(), source="default_scene.toml")

    def to_toml(self, path: str | Path | None = None, *, seat: SeatSettings | None = None) -> str:
        """TOML text of this scene (written to ``path`` if given), with ``seat``
        as its ``[seat]`` section if given."""

        def fmt(v: Any) -> str:
            if isinstance(v, bool):
                return "true" if v else "false"
            if isinstance(v, str):
                return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
            if isinstance(v, (list, tuple)):
                return "[" + ", ".join(fmt(x) for x in v) + "]"
            if isinstance(v, float):
                return repr(v)
            return str(v)

        sections = self.to_dict()
        if seat is not None:
            sections[SeatSettings.SECTION] = seat.to_dict()
        lines = []
        for sec, body in sections.items():
            lines.append(f"[{sec}]")
            lines += [f"{k} = {fmt(v)}" for k, v in body.items()]
            lines.append("")
        text = "\n".join(lines)
        if path is not None:
            write_text_atomic(path, text)
        return text
