"""The scene's sections: one typed record per TOML section of a scene file.

:class:`StormSettings` (``[storm]``), :class:`HailSettings` (``[hail]``),
:class:`ContactSettings` (``[contact]``), :class:`TimeSettings` (``[time]``),
:class:`OutputSettings` (``[output]``) and :class:`ValiditySettings` (``[validity]``),
each validated on its own when made (a bad value raises :class:`SceneError`);
:class:`hailstorm.runtime.storm.scene.Scene` composes them and checks the rules across
sections. The default seat's ``[seat]`` is :class:`hailstorm.runtime.seat_settings.SeatSettings`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

from hailstorm.runtime.contact.near_field import NEAR_FIELDS
from hailstorm.runtime.contact.validate import ContactMode, Mode
from hailstorm.runtime.sections import (Section as _Section, check_bool as _bool, check_positive as _positive,
                                        check_types as _check_types)
from hailstorm.runtime.storm.errors import SceneError
from hailstorm.runtime.storm.hail import INTEGRATORS, Integrator, SizeDistribution
from hailstorm.runtime.storm.limits import PAD_DENSITY

__all__ = ["ContactSettings", "HailSettings", "OutputSettings", "StormSettings", "TimeSettings", "ValiditySettings"]


@dataclass(frozen=True)
class StormSettings(_Section):
    """``[storm]``: how many stones, where and when (SI units).

    Attributes
    ----------
    duration : float
        Simulated time [s].
    rate : float
        Stones spawned per second over the seat's footprint (Poisson process).
    stones : int or None
        If given, exactly this many stones are spawned, uniformly over the
        duration (overrides ``rate``).
    seed : int
        Random seed: the storm is reproducible from it.
    spawn_height : float
        Stones appear this far above the seat's highest point [m].
    margin : float
        The spawn footprint is the seat's xy bounding box grown by this [m];
        stones that leave it (or fall below the seat) are retired.
    wind : (3,) float
        Air velocity [m/s] (drag acts on the velocity relative to it; stones
        start with its horizontal part and are spawned upwind so they land
        on the seat).
    """

    SECTION: ClassVar[str] = "storm"

    duration: float = 0.2
    rate: float = 1000.0
    stones: int | None = None
    seed: int = 0
    spawn_height: float = 0.05
    margin: float = 0.01
    wind: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        _check_types(self)
        _positive(self, ("duration", "spawn_height"))
        _positive(self, ("rate", "margin"), allow_zero=True)
        if self.stones is not None and (isinstance(self.stones, bool) or not isinstance(self.stones, int) or self.stones < 0):
            raise SceneError(f"stones must be a non-negative integer, got {self.stones!r}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise SceneError(f"seed must be a non-negative integer, got {self.seed!r}")
        try:
            w = tuple(float(x) for x in self.wind)
        except (TypeError, ValueError):
            raise SceneError(f"wind must be three numbers [m/s], got {self.wind!r}") from None
        if len(w) != 3 or not all(math.isfinite(x) for x in w):
            raise SceneError(f"wind must be three finite numbers [m/s], got {self.wind!r}")
        object.__setattr__(self, "wind", w)


@dataclass(frozen=True)
class HailSettings(_Section):
    """``[hail]``: the stones' sizes, ice and air.

    Attributes
    ----------
    distribution, r_min, r_max, scale
        Radius distribution (:class:`hailstorm.runtime.storm.hail.SizeDistribution`) [m].
    density : float
        Ice density [kg/m^3].
    drag : bool
        Quadratic air drag in flight (stones start at terminal velocity either way).
    cd, rho_air : float
        Drag coefficient and air density.
    collisions : bool
        Stones collide with each other: two elastic ice spheres, Hertz in compression and
        the scene's ``[contact] restitution`` (:mod:`hailstorm.runtime.storm.stone_collisions`;
        frictionless). Off by default: stones pass through each other.
    """

    SECTION: ClassVar[str] = "hail"

    distribution: str = "exponential"
    r_min: float = 0.0025
    r_max: float = 0.0125
    scale: float = 0.002
    density: float = 917.0
    drag: bool = True
    cd: float = 0.6
    rho_air: float = 1.2
    collisions: bool = False

    def __post_init__(self) -> None:
        _check_types(self)
        _positive(self, ("density", "cd", "rho_air"))
        _bool(self, ("drag", "collisions"))
        try:
            self.size_distribution()
        except ValueError as exc:
            raise SceneError(str(exc)) from None

    def size_distribution(self) -> SizeDistribution:
        """The radius distribution of these stones."""
        return SizeDistribution(kind=self.distribution, r_min=float(self.r_min), r_max=float(self.r_max), scale=float(self.scale))


@dataclass(frozen=True)
class ContactSettings(_Section):
    """``[contact]``: the contact model.

    Attributes
    ----------
    mode : {"frictionless", "sticky"}
        Contact model: normal force only, or all three components.
    unilateral : bool
        Release contacts that would pull.
    restitution : float
        Target coefficient of restitution of an impact (0..1), realised by a
        contact damping (see :func:`hailstorm.runtime.storm.hail.damping_coefficients`).
    patch : {"hertz", "none"}
        Force distribution of a soft contact. ``"hertz"`` (default): a patch
        contact, the stone's force spread over a disc with the Hertz pressure
        profile (:func:`hailstorm.runtime.contact.weights.patch_weights`), of radius
        :func:`hailstorm.runtime.contact.weights.hertz_radius` of the contact's *peak* force
        (see the module notes); ``"none"``: a point contact (barycentric
        weights on the contacted triangle; the dent is a one-vertex spike).
    patch_min_radius : float
        Floor of the patch radius [m] (default 1 mm: the Hertz radius of the
        smallest default stone, 2.5 mm, resting under its own weight on the
        2 MPa seat is 0.8 mm, so the floor only acts on contacts that are
        opening or closing). A length, not a fraction of the mesh size: the
        contact model must not change with the mesh.
    patch_tolerance : float
        Relative change of a contact's target radius that re-weights it
        (default 0.2: 20%). Within it the contact keeps its weights and the
        capacitance is not rebuilt (a 20% radius error changes the patch's
        stiffness by ~20% but the radius itself only as ``F^(1/3)``).
    near_field : {"auto", "layer", "halfspace", "none"}
        Patches smaller than the surface elements resolved at their own scale
        (:mod:`hailstorm.runtime.contact.near_field`): ``"auto"`` (default) the
        layer kernel (the half-space's plus the pad on its rigid base) on a
        bundle whose columns answer hat loads (the default seat's),
        ``"halfspace"`` the half-space's alone, ``"none"`` the patch as the mesh
        carries it.
    """

    SECTION: ClassVar[str] = "contact"

    mode: Mode = "frictionless"
    unilateral: bool = True
    restitution: float = 0.5
    patch: str = "hertz"
    patch_min_radius: float = 1e-3
    patch_tolerance: float = 0.2
    near_field: str = "auto"

    def __post_init__(self) -> None:
        _check_types(self)
        _positive(self, ("patch_min_radius", "patch_tolerance"), allow_zero=True)
        _bool(self, ("unilateral",))
        if self.mode not in tuple(ContactMode):
            raise SceneError(f"mode must be 'frictionless' or 'sticky', got {self.mode!r}")
        if self.patch not in ("hertz", "none"):
            raise SceneError(f"patch must be 'hertz' or 'none', got {self.patch!r}")
        if self.near_field not in NEAR_FIELDS:
            raise SceneError(f"near_field must be one of {', '.join(map(repr, NEAR_FIELDS))}, got {self.near_field!r}")
        if isinstance(self.restitution, bool) or not isinstance(self.restitution, (int, float)) or not 0.0 <= self.restitution <= 1.0:
            raise SceneError(f"restitution must lie in [0, 1], got {self.restitution!r}")

    @property
    def contact_mode(self) -> ContactMode:
        """The mode resolved (:class:`~hailstorm.runtime.contact.validate.ContactMode`)."""
        return ContactMode(self.mode)

    @property
    def sticky(self) -> bool:
        """All three force components (:attr:`ContactMode.sticky`)."""
        return self.contact_mode.sticky


@dataclass(frozen=True)
class TimeSettings(_Section):
    """``[time]``: the step and the integrator.

    Attributes
    ----------
    dt : float
        Step [s] (frame/broad-phase step; near stones may be sub-stepped).
    integrator : {"exact", "implicit", "symplectic"}
        Contact integrator (:func:`hailstorm.runtime.storm.hail.contact_step`). ``"exact"``
        (the default) solves the damped linear contact dynamics in closed form over
        the step (no numerical damping, no stability limit, events located inside
        the step), so it needs no ``omega_dt`` sub-steps and its peak forces are the
        model's own; ``"implicit"`` (backward Euler) and ``"symplectic"`` report peak
        forces first order in ``omega_dt`` (the default storm's implicit peak is
        12.1 % above the exact one at ``omega_dt = 0.2``, see docs/how-it-works.md).
    adaptive : bool
        Sub-step near stones (see :mod:`hailstorm.runtime.storm.driver`). ``False``: fixed ``dt``.
    omega_dt : float
        Target ``omega dt`` for moving contacts (``"symplectic"`` sub-steps to
        half of it: its explicit dashpot's peak-force error is first order in
        ``omega dt``).
    approach_fraction : float
        Largest travel per sub-step of an approaching stone, in radii.
    max_substeps : int
        Cap on sub-steps per step.
    rest_speed : float
        Normal speed below which a contact counts as resting [m/s].
    """

    SECTION: ClassVar[str] = "time"

    dt: float = 2e-4
    integrator: Integrator = "exact"
    adaptive: bool = True
    omega_dt: float = 0.2
    approach_fraction: float = 0.1
    max_substeps: int = 64
    rest_speed: float = 0.05

    def __post_init__(self) -> None:
        _check_types(self)
        _positive(self, ("dt", "omega_dt", "approach_fraction"))
        _positive(self, ("rest_speed",), allow_zero=True)
        _bool(self, ("adaptive",))
        if isinstance(self.max_substeps, bool) or not isinstance(self.max_substeps, int) or self.max_substeps < 1:
            raise SceneError(f"max_substeps must be a positive integer, got {self.max_substeps!r}")
        if self.integrator not in INTEGRATORS:
            raise SceneError(f"integrator must be 'implicit', 'symplectic' or 'exact', got {self.integrator!r}")

    @property
    def min_substep(self) -> float:
        """The shortest sub-step [s]: ``dt / max_substeps`` (the one place it is computed)."""
        return self.dt / self.max_substeps


@dataclass(frozen=True)
class OutputSettings(_Section):
    """``[output]``: what is recorded.

    Attributes
    ----------
    fps : float
        Recorded frames per simulated second.
    """

    SECTION: ClassVar[str] = "output"

    fps: float = 250.0

    def __post_init__(self) -> None:
        _check_types(self)
        _positive(self, ("fps",))


@dataclass(frozen=True)
class ValiditySettings(_Section):
    """``[validity]``: what the validity limits need to know of the seat that the
    storm's model does not use (:mod:`hailstorm.runtime.storm.limits`).

    Attributes
    ----------
    pad_density : float
        The pad foam's density [kg/m^3]. The quasi-static model has no mass in the
        seat; the density sets the pad's wave speeds, so how long an impact must last
        for the pad to follow it quasi-statically (the contact-time limit), and the
        pad's inertia in each impact (``inertia``).
    inertia : bool
        Measure the pad's inertia in each impact after the storm: a dynamic and a
        quasi-static impact on the pad under it (:mod:`hailstorm.runtime.inertia`), whose
        ratios correct the impact's peak force (``max_impact_force_dynamic_N``). About a
        tenth of a second per impact; false leaves those keys empty.
    """

    SECTION: ClassVar[str] = "validity"

    pad_density: float = PAD_DENSITY
    inertia: bool = True

    def __post_init__(self) -> None:
        _check_types(self)
        _positive(self, ("pad_density",))
