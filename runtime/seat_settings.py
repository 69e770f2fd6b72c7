"""The default seat's precompute settings: the scene file's ``[seat]``.

:class:`SeatSettings` is the offline stage's input (what ``hailstorm storm``
without ``--gf`` asks :func:`hailstorm.precompute.pipeline.build_bundle` for), not
part of the storm's :class:`~hailstorm.runtime.storm.scene.Scene`. It lives in this
small module, which imports neither the storm nor the offline stage (nor its mesher),
because three readers need it: the scene file's reader checks a ``[seat]``
section, the command line reads it with the core install alone (to say a ``--gf``
bundle ignores it), and the offline stage builds the default seat from it. The
runtime never imports the offline stage, so the record cannot live there;
:mod:`hailstorm.runtime.storm.scene` re-exports it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar, Mapping

from hailstorm.runtime.sections import SceneError, Section, check_positive, check_types, packaged_toml, read_toml

__all__ = ["SeatSettings"]


@dataclass(frozen=True)
class SeatSettings(Section):
    """``[seat]``: the default seat's precompute settings, used when no bundle
    is given (``hailstorm storm`` without ``--gf`` builds, or reuses from the
    cache, the default saddle's Green's functions with them). Not part of the
    :class:`Scene`: a storm runs on whatever bundle it is given.

    Attributes
    ----------
    mesh_size : float
        Element size on the top [m].
    order : {1, 2}
        Element order.
    load : {"point", "hat"}
        What a column of D answers (``hailstorm precompute --load``).
    volume_size : float or None
        Volume grading [m]: tetrahedra inside the pad at most this size under
        the same surface mesh (``hailstorm precompute --volume-size``; at most
        ``mesh_size``). None (the key left out): no grading.
    coarsening : float
        How far the volume's elements grow away from the top, in mesh sizes
        (``hailstorm precompute --coarsening``; at least 1, default 2.5).
    young, poisson : float
        Material [Pa], [-].
    """

    SECTION: ClassVar[str] = "seat"

    mesh_size: float = 0.006
    order: int = 2
    load: str = "hat"
    volume_size: float | None = None
    coarsening: float = 2.5
    young: float = 2.0e6
    poisson: float = 0.35

    def __post_init__(self) -> None:
        check_types(self)
        check_positive(self, ("mesh_size", "young"))
        if self.order not in (1, 2) or isinstance(self.order, bool):
            raise SceneError(f"order must be 1 or 2, got {self.order!r}")
        if self.load not in ("point", "hat"):
            raise SceneError(f"load must be 'point' or 'hat', got {self.load!r}")
        if self.volume_size is not None:
            check_positive(self, ("volume_size",))
            if self.volume_size > self.mesh_size:
                raise SceneError(f"volume_size ({self.volume_size!r} m) must not exceed mesh_size "
                                 f"({self.mesh_size!r} m): it refines the volume under the same surface")
        if not self.coarsening >= 1 or not math.isfinite(self.coarsening):
            raise SceneError(f"coarsening must be a number of mesh sizes of at least 1, "
                             f"got {self.coarsening!r}")
        if isinstance(self.poisson, bool) or not isinstance(self.poisson, (int, float)) or not -1.0 < self.poisson < 0.5:
            raise SceneError(f"poisson must satisfy -1 < poisson < 0.5, got {self.poisson!r}")

    @classmethod
    def default(cls) -> "SeatSettings":
        """The packaged default scene file's ``[seat]``."""
        return cls.from_dict(packaged_toml().get("seat", {}), source="default_scene.toml")

    @classmethod
    def from_toml(cls, path: str | Path) -> "SeatSettings":
        """The ``[seat]`` of a scene file; keys it does not set take the packaged defaults.

        Raises
        ------
        SceneError
            The file cannot be read, is not TOML, or its ``[seat]`` is invalid.
        """
        body = read_toml(Path(path)).get("seat", {})
        if not isinstance(body, Mapping):
            raise SceneError(f"{path}: [seat] must be a table")
        return cls.from_dict({**cls.default().to_dict(), **body}, source=str(path))
