"""Where the storm's model stops being true: validity limits checked on every impact.

The storm is quasi-static, linear elasticity on the undeformed pad, with the
sphere's contact law sizing each contact's pressure disc. Each of those assumptions has a range;
this module measures, per impact, how far outside it the run went, and the
storm's statistics (:class:`~hailstorm.runtime.storm.recording.StormStats`,
``summary.json``) count the impacts beyond each limit. What a result beyond a
limit means is in ``docs/validity.md``.

Per impact (a contact that opened faster than the scene's ``time.rest_speed``,
the storm's ``impacts``, followed until that contact is released):

* ``delta / h`` -- the peak indentation ``delta`` (the largest normal contact
  displacement, the storm's ``max_indentation_m`` per impact) over the local
  pad thickness ``h`` under the contact point (:func:`hailstorm.runtime.bundle.thickness.surface_thickness`);
* ``a / R`` -- the sphere's contact radius of the impact's peak force
  (:func:`hailstorm.runtime.contact.weights.sphere_radius`, Sneddon's; Hertz's
  ``(3 F R / (4 E*))^(1/3)`` for ``a << R``: the radius the patch model sizes its
  disc by, before its floor), over the stone radius;
* the estimated peak strain (:func:`peak_strain`);
* ``t_c / T`` -- the impact's contact time over the period of the pad's lowest
  thickness resonance (:func:`contact_time_ratio`): ``t_c`` Hertz's contact time of
  the elastic impact of a sphere of mass ``m`` and radius ``R`` at the impact's
  normal speed ``v`` on a half-space of the pad's material,
  ``t_c = 2.87 (m^2 / (R E*^2 v))^(1/5)`` (Johnson, *Contact Mechanics*, 1985,
  section 11.4), and ``T = 4 h / c_s``, ``c_s = sqrt(E / (2 (1 + nu) rho))`` the
  shear wave speed of the pad foam of density ``rho`` (the scene's
  ``[validity] pad_density``: the model itself has no mass).

The limits (:class:`ValidityLimits`, each with its source):

* ``a / R <= 0.8``: measured. The patch law is the sphere's own (Sneddon 1965,
  :mod:`hailstorm.runtime.compiled.sphere`), not Hertz's paraboloid (which
  assumes ``a << R``, Johnson, *Contact Mechanics*, 1985, section 4.2, and is
  2.8 % too stiff at ``a/R`` 0.5, 9.7 % at 0.8), and an impact's patch meets the
  sphere's own impact on a half-space at every ``a/R``
  (:func:`hailstorm.runtime.contact.weights.impact_radius`); what stays approximate is
  the pressure's shape (Hertz's, in the weights, where the sphere's is not at large
  ``a/R``) and the half-space sizing on a finite pad. Against the dynamic peer's
  quasi-static column (the sphere pressed node by node into the converged 15 mm pad;
  ``python tests/benchmarks/dynamic_peer.py --terminal --storm-block``) the storm's impacts
  of ``a/R`` 0.58-0.80 are within 2.6 % in peak force, 1.2 % in contact time and 1.3 % in
  dent. Past it, at 0.88-0.93 (30 m/s; ``dynamic_peer.py --full --speeds 30
  --storm-block``), the storm is within 3.5 % in peak force and 1.2 % in dent: the error
  grows past 0.8 (there with the pad's thickness, ``delta/h`` 0.4-0.75).
* peak strain ``<= 0.05``: flexible (elastomeric) foams are linear elastic in
  compression up to about 5 % strain; beyond it the cell walls buckle and the
  stress-strain curve flattens into the plateau (Gibson & Ashby, *Cellular
  Solids*, 2nd ed. 1997, ch. 5, elastomeric foams in compression).
* ``delta / h <= 0.1``: the Green's functions are those of the undeformed pad.
  A pad on a rigid base compressed by ``delta`` is stiffer than the undeformed
  one by about ``h / (h - delta)`` (its stiffness goes as ``1 / h``), 11 % at
  ``delta / h = 0.1``; the half-space and layer models behind Hertz's law and
  the patch weights hold for indentations small against the thickness.

* ``t_c / T >= 1.6``: measured, by the dynamic peer of the pad
  (:mod:`studies.dynamic_study`: a 15 mm pad of the default foam on a rigid
  base, with its mass; rigid ice spheres of 2.5-12.5 mm at 1-30 m/s, foam of 70 and
  200 kg/m^3; ``python tests/benchmarks/dynamic_peer.py --limit``). In every one of its
  impacts with ``t_c / T >= 1.6`` (26 of 60) the quasi-static model's peak force, contact
  time, rebound speed and largest dent are within 3.5 % of the peer's; every impact where
  one of them is off by more than 5 % (23, by up to 43 %) has ``t_c / T < 1.6``. An impact shorter than the
  pad's wave period drives waves the quasi-static pad cannot carry: its peak force is
  over-estimated and its contact too short. ``t_c`` is the elastic impact's, not the
  storm's (whose dashpot shortens the dent, not the pad's wave period); Hertz's
  half-space is softer than a thin pad, so it is the longer estimate of the two for
  large stones, which the measured limit accounts for.

These are conservative engineering bounds, not sharp ones: a result beyond one
is not necessarily wrong, but nothing in the model vouches for it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from hailstorm.runtime.bundle.thickness import PadThickness
from hailstorm.runtime.contact.sphere_patch import sphere_radius
from hailstorm.runtime.inertia.pad import PAD_DENSITY

if TYPE_CHECKING:  # (imported when first measured: the local pad's assembly is not needed to start a storm)
    from hailstorm.runtime.inertia.factors import InertiaFactors

__all__ = [
    "IMPACT_COLUMNS",
    "ImpactLimits",
    "PAD_DENSITY",
    "ValidityLimits",
    "VALIDITY_KEYS",
    "boundary_faces",
    "contact_time_ratio",
    "peak_strain",
    "summarise",
    "validity_warning",
]




@dataclass(frozen=True)
class ValidityLimits:
    """The stated limits of the storm's model (sources: the module docstring).

    Attributes
    ----------
    indentation_thickness : float
        Largest peak indentation over local pad thickness, ``delta / h`` [-].
    contact_radius : float
        Largest contact radius over stone radius, ``a / R`` [-] (the sphere's radius of the
        impact's peak force).
    strain : float
        Largest estimated peak strain [-] (:func:`peak_strain`).
    contact_time : float
        Smallest contact time over the pad's wave period, ``t_c / T`` [-]
        (:func:`contact_time_ratio`).
    inertia : float
        Largest change the pad's inertia makes to an impact's peak force, contact time,
        rebound speed or largest dent, ``|factor - 1|`` [-]
        (:class:`hailstorm.runtime.inertia.factors.InertiaFactors`).
    """

    indentation_thickness: float = 0.1
    contact_radius: float = 0.8
    strain: float = 0.05
    contact_time: float = 1.6
    inertia: float = 0.05


def boundary_faces(tets: np.ndarray) -> np.ndarray:
    """The boundary triangles of a tetrahedral mesh (faces of exactly one tetrahedron), (k, 3).

    Parameters
    ----------
    tets : (T, 4) int ndarray
        Corner connectivity.

    Returns
    -------
    (k, 3) int ndarray
        Node indices (orientation not normalised).
    """
    tets = np.asarray(tets, dtype=np.int64)
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]])
    _, inv, counts = np.unique(np.sort(faces, axis=1), axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inv.ravel()] == 1]




def peak_strain(contact_radius_ratio: Any, indentation_thickness: Any, poisson: float) -> np.ndarray:
    """Estimated peak strain of an impact [-]: the larger of Hertz's and the layer's.

    * Hertz: at the centre of a Hertz contact the surface stresses are
      ``sigma_z = -p0``, ``sigma_r = sigma_theta = -(1 + 2 nu) p0 / 2``, with
      ``p0 = 2 E* a / (pi R)`` (Johnson, *Contact Mechanics*, 1985, sections 3.4 and
      4.2), so the compressive strain there is
      ``eps_z = (2 / pi) (1 - 2 nu) / (1 - nu) a / R`` (0.29 a/R at nu = 0.35; of
      the order of Tabor's representative strain 0.2 a/R, Tabor, *The Hardness of
      Metals*, 1951).
    * Layer: a dent ``delta`` into a pad of thickness ``h`` on a rigid base
      compresses the column under the stone by ``delta / h`` on average.

    Parameters
    ----------
    contact_radius_ratio : float or ndarray
        ``a / R``.
    indentation_thickness : float or ndarray
        ``delta / h``.
    poisson : float
    """
    hertz = 2.0 / np.pi * (1.0 - 2.0 * poisson) / (1.0 - poisson) * np.asarray(contact_radius_ratio, dtype=np.float64)
    return np.maximum(hertz, np.asarray(indentation_thickness, dtype=np.float64))


def contact_time_ratio(mass: Any, radius: Any, speed: Any, thickness: Any, young: float, poisson: float,
                       density: float) -> np.ndarray:
    """An impact's contact time over the period of the pad's lowest thickness resonance, ``t_c / T`` [-].

    ``t_c = 2.9432 delta_max / v = 2.87 (m^2 / (R E*^2 v))^(1/5)`` is Hertz's contact time of the
    elastic impact of a sphere of mass ``m`` and radius ``R`` at normal speed ``v`` on a half-space
    (:func:`hailstorm.runtime.contact.hertz.hertz_impact`, vectorised); ``T = 4 h / c_s`` is the period of
    the lowest cutoff of a pad of thickness ``h`` on a rigid base (a quarter shear wavelength
    across it), ``c_s = sqrt(E / (2 (1 + nu) rho))``. Below the limit (:class:`ValidityLimits`)
    the pad cannot follow the impact quasi-statically.

    Parameters
    ----------
    mass, radius : float or ndarray
        The stone's [kg], [m].
    speed : float or ndarray
        Normal impact speed ``v`` [m/s] (its magnitude; 0 gives an infinite ratio).
    thickness : float or ndarray
        Local pad thickness ``h`` [m] (inf gives 0: no pad under the impact to vouch for).
    young, poisson : float
        The pad's material [Pa], [-].
    density : float
        The pad's density [kg/m^3].
    """
    c_s = math.sqrt(young / (2.0 * (1.0 + poisson) * density))
    e_star = young / (1.0 - poisson**2)
    m = np.asarray(mass, dtype=np.float64)
    R = np.asarray(radius, dtype=np.float64)
    v = np.abs(np.asarray(speed, dtype=np.float64))
    h = np.asarray(thickness, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        vv = np.where(v > 0.0, v, 1.0)
        depth = (15.0 * m * vv * vv / (16.0 * e_star * np.sqrt(R))) ** 0.4  # hertz_impact's delta_max
        t_c = np.where(v > 0.0, _HERTZ_DURATION * depth / vv, np.inf)
        return np.where(np.isfinite(h), t_c * c_s / (4.0 * h), 0.0)


#: Hertz's impact duration over ``delta_max / v``, ``(4/5) B(2/5, 1/2)`` = 2.9432 (as :func:`hertz_impact`)
_HERTZ_DURATION = 0.8 * math.gamma(0.4) * math.gamma(0.5) / math.gamma(0.9)


class ImpactLimits:
    """The validity measures of a storm's impacts (module docstring), kept per impact.

    :meth:`observe` is called with every soft-contact sub-step; an impact's record
    opens with the contact (the storm's ``impacts`` rule: the contact opens,
    carries force and comes in faster than ``rest_speed``) and takes the
    contact's peaks while it stays open (until the stone's next contact opens).
    The statistics' validity keys (:meth:`summary`) are computed from the records
    when read, the local thickness under each impact then too (:class:`hailstorm.runtime.bundle.thickness.PadThickness`).
    A sub-step holds a handful of contacts, so the bookkeeping is plain Python
    over them (numpy's per-call cost would be most of it).

    Parameters
    ----------
    gf : ElasticSource
        The bundle (surface, material).
    rest_speed : float
        The scene's ``time.rest_speed`` [m/s].
    limits : ValidityLimits, optional
    pad_density : float
        The pad foam's density [kg/m^3] (the contact-time limit and the inertia factors; the
        scene's ``[validity] pad_density``).
    inertia : bool
        Measure the pad's inertia in each impact (:meth:`inertia`; the scene's
        ``[validity] inertia``).
    """

    def __init__(self, gf: Any, rest_speed: float, limits: ValidityLimits | None = None,
                 pad_density: float = PAD_DENSITY, inertia: bool = True) -> None:
        self.limits = ValidityLimits() if limits is None else limits
        self.pad_density = float(pad_density)
        self.measure_inertia = bool(inertia)
        self.young, self.poisson = float(gf.young), float(gf.poisson)
        self.triangles = np.asarray(gf.triangles, dtype=np.int64)
        self.vertices = np.asarray(gf.vertices)
        self.rest_speed = float(rest_speed)
        #: local pad thickness under the surface vertices [m], cast when first read
        self.pad = PadThickness(gf)
        #: stone id -> its open impact record
        self.record_of: dict[int, int] = {}
        #: per impact: the stone's id, its radius [m], contact triangle and barycentric coordinates at onset,
        #: stone mass [kg], normal speed at onset [m/s], peak indentation [m], peak force [N]
        self.stone: list[int] = []
        self.radius: list[float] = []
        self.mass: list[float] = []
        self.speed: list[float] = []
        self.where: list[tuple[int, list[float]]] = []
        self.indentation: list[float] = []
        self.force: list[float] = []
        #: per impact: the start of the sub-step its contact opened in, and the end of the sub-step
        #: that held its peak force [s]
        self.t_onset: list[float] = []
        self.t_peak: list[float] = []
        self._thickness = np.zeros(0)
        self._inertia: InertiaFactors | None = None  # of the impacts so far, computed when first read
        self._changes = 0  # bumped by every change of a record (the summary's cache key)
        self._summary: tuple[int, dict[str, float | int]] | None = None

    @property
    def n(self) -> int:
        """Impacts recorded."""
        return len(self.radius)

    def onset_speed(self, vel: np.ndarray, soft: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Normal velocity of the stones ``soft`` before the contact step (negative: approaching)."""
        return np.einsum("kd,kd->k", vel[soft], normals)

    def watching(self, soft: list[int], opening: bool) -> bool:
        """Does a sub-step of the stones ``soft`` (some contact ``opening``) concern a record?"""
        return opening or any(j in self.record_of for j in soft)

    def observe(self, soft: list[int], radius: list[float], mass: list[float], tris: list[int], bary: list[list[float]],
                opening: list[bool], vin: list[float] | None, touched: list[bool], indentation: list[float],
                force: list[float], t: float = 0.0, h: float = 0.0) -> None:
        """Record one contact sub-step ``[t, t + h]`` of the stones ``soft`` (sequences of length s).

        Parameters
        ----------
        soft : stone ids
        radius : their radii [m]
        mass : their masses [kg]
        tris, bary : their contact triangles and barycentric coordinates
        opening : the contact opened in this sub-step
        vin : normal velocity at the sub-step's start [m/s] (:meth:`onset_speed`;
            needed only where ``opening``, None when none is)
        touched : the contact carried force within the sub-step
        indentation : largest normal contact displacement within the sub-step [m]
        force : largest contact force magnitude within the sub-step [N]
        t, h : the sub-step's start and length [s] (the records' times, ``t_onset_s`` and ``t_peak_s``)
        """
        rec_of = self.record_of
        self._changes += 1
        for i, j in enumerate(soft):
            if not touched[i]:
                continue
            if opening[i]:
                rec_of.pop(j, None)  # a slow touch opens no record (and ends the stone's last one)
                if vin is not None and vin[i] < -self.rest_speed:
                    rec_of[j] = self.n
                    self.stone.append(int(j))
                    self.radius.append(float(radius[i]))
                    self.where.append((int(tris[i]), list(bary[i])))
                    self.mass.append(float(mass[i]))
                    self.speed.append(-float(vin[i]))
                    self.indentation.append(0.0)
                    self.force.append(0.0)
                    self.t_onset.append(float(t))
                    self.t_peak.append(float(t + h))
            k = rec_of.get(j)
            if k is not None:
                if indentation[i] > self.indentation[k]:
                    self.indentation[k] = float(indentation[i])
                if force[i] > self.force[k]:
                    self.force[k] = float(force[i])
                    self.t_peak[k] = float(t + h)

    @property
    def thickness(self) -> np.ndarray:
        """The local thickness under every impact so far [m], (n,) (cast for the new ones)."""
        old = self._thickness.size
        if self.n > old:
            tri = np.array([w[0] for w in self.where[old:]], dtype=np.int64)
            bary = np.array([w[1] for w in self.where[old:]], dtype=np.float64).reshape(-1, 3)
            h = self.pad(self.triangles[tri])  # (m, 3); inf: the ray met nothing
            finite = np.isfinite(h)
            new = np.where(finite.all(axis=1), np.einsum("kj,kj->k", bary, np.where(finite, h, 0.0)), np.inf)
            self._thickness = np.concatenate([self._thickness, new])
        return self._thickness

    def inertia(self, progress: Any = False) -> InertiaFactors:
        """The inertia factors of every impact so far (computed for the new ones: a dynamic and a
        quasi-static impact each on the pad under it, :func:`hailstorm.runtime.inertia.factors.inertia_factors`;
        ``progress`` as there).

        Returns
        -------
        InertiaFactors
        """
        from hailstorm.runtime.inertia.factors import InertiaFactors, inertia_factors

        done = InertiaFactors.empty() if self._inertia is None else self._inertia
        if self.n > done.impacts:
            k = done.impacts
            new = inertia_factors(self.radius[k:], self.mass[k:], self.speed[k:], self.thickness[k:], self.young,
                                  self.poisson, self.pad_density, progress=progress)
            done = done + new
        self._inertia = done
        return done

    def ratios(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``delta / h``, ``a / R`` and the estimated peak strain of every impact so far, (n,) each."""
        R = np.array(self.radius, dtype=np.float64)
        dh = np.clip(np.array(self.indentation, dtype=np.float64), 0.0, None) / self.thickness
        aR = sphere_radius(np.array(self.force, dtype=np.float64), R, self.young, self.poisson) / R
        return dh, aR, peak_strain(aR, dh, self.poisson)

    def time_ratios(self) -> np.ndarray:
        """``t_c / T`` of every impact so far, (n,) (:func:`contact_time_ratio`)."""
        return contact_time_ratio(self.mass, self.radius, self.speed, self.thickness, self.young, self.poisson,
                                  self.pad_density)

    def table(self) -> dict[str, np.ndarray]:
        """Every impact so far, one entry per column, (n,) each (``impacts.csv``).

        Columns: ``stone`` (its id), ``t_onset_s`` (the start of the sub-step its contact opened
        in), ``t_peak_s`` (the end of the sub-step that held its peak force: the peak lies at most
        one sub-step before), ``x_m``, ``y_m``, ``z_m`` (the contact point at onset, on
        the undeformed surface), ``radius_m``, ``mass_kg``, ``speed_m_s`` (normal, at onset),
        ``thickness_m`` (the pad under it), ``peak_force_N`` (the storm's), ``peak_force_dynamic_N``
        (times the inertia factor; NaN where not measured), ``indentation_m``, ``indentation_thickness_ratio``,
        ``contact_radius_ratio``, ``strain_ratio``, ``contact_time_ratio`` and the inertia factors
        ``inertia_force``, ``inertia_duration``, ``inertia_restitution``, ``inertia_dent``
        (NaN where not measured); ``beyond`` (the limits it is beyond, ``;``-separated:
        ``indentation``, ``radius``, ``strain``, ``contact_time``, ``inertia``).
        """
        n = self.n
        tri = np.array([w[0] for w in self.where], dtype=np.int64)
        bary = np.array([w[1] for w in self.where], dtype=np.float64).reshape(n, 3)
        X = np.einsum("kj,kjd->kd", bary, self.vertices[self.triangles[tri]]) if n else np.zeros((0, 3))
        dh, aR, eps = self.ratios()
        tr = self.time_ratios()
        f = self.inertia() if self.measure_inertia else None
        nan = np.full(n, np.nan)
        fac = f.astuple() if f is not None else (nan, nan, nan, nan)
        F = np.array(self.force, dtype=np.float64)
        lim = self.limits
        with np.errstate(invalid="ignore"):
            over = {"indentation": dh > lim.indentation_thickness, "radius": aR > lim.contact_radius,
                    "strain": eps > lim.strain, "contact_time": tr < lim.contact_time,
                    "inertia": f.largest_change() > lim.inertia if f is not None else np.zeros(n, dtype=bool)}
        beyond = np.array([";".join(k for k, v in over.items() if v[i]) for i in range(n)], dtype=object)
        table = {"stone": np.array(self.stone, dtype=np.int64), "t_onset_s": np.array(self.t_onset, dtype=np.float64),
                 "t_peak_s": np.array(self.t_peak, dtype=np.float64), "x_m": X[:, 0], "y_m": X[:, 1], "z_m": X[:, 2],
                 "radius_m": np.array(self.radius, dtype=np.float64), "mass_kg": np.array(self.mass, dtype=np.float64),
                 "speed_m_s": np.array(self.speed, dtype=np.float64), "thickness_m": self.thickness.copy(),
                 "peak_force_N": F, "peak_force_dynamic_N": F * fac[0],
                 "indentation_m": np.array(self.indentation, dtype=np.float64), "indentation_thickness_ratio": dh,
                 "contact_radius_ratio": aR, "strain_ratio": eps, "contact_time_ratio": tr,
                 "inertia_force": fac[0], "inertia_duration": fac[1], "inertia_restitution": fac[2],
                 "inertia_dent": fac[3], "beyond": beyond}
        assert tuple(table) == IMPACT_COLUMNS
        return table

    def summary(self) -> dict[str, float | int]:
        """The statistics' validity keys (see :class:`~hailstorm.runtime.storm.recording.StormStats`):
        impacts beyond each limit, the worst values and the limits."""
        if self._summary is None or self._summary[0] != self._changes:
            self._summary = (self._changes, summarise(*self.ratios(), self.thickness, self.limits,
                                                      time_ratio=self.time_ratios(), pad_density=self.pad_density,
                                                      force=np.array(self.force, dtype=np.float64),
                                                      inertia=self.inertia() if self.measure_inertia else None))
        return dict(self._summary[1])


def summarise(dh: np.ndarray, aR: np.ndarray, eps: np.ndarray, thickness: np.ndarray,
              limits: ValidityLimits | None = None, *, time_ratio: np.ndarray | None = None,
              pad_density: float = PAD_DENSITY, force: np.ndarray | None = None,
              inertia: InertiaFactors | None = None) -> dict[str, float | int | None]:
    """The validity keys of a storm's statistics from its impacts' measures.

    Parameters
    ----------
    dh, aR, eps, thickness : (n,) ndarray
        Per impact: ``delta / h``, ``a / R``, the estimated peak strain, the local
        thickness [m].
    limits : ValidityLimits, optional
    time_ratio : (n,) ndarray, optional
        Per impact, ``t_c / T`` (:func:`contact_time_ratio`; default: none measured, inf).
    pad_density : float
        The pad's density the ratios assumed [kg/m^3] (recorded).
    force : (n,) ndarray, optional
        Per impact, the storm's (quasi-static) peak force [N] (default: none measured, 0).
    inertia : InertiaFactors, optional
        Per impact, the pad's inertia factors
        (:class:`hailstorm.runtime.inertia.factors.InertiaFactors`; default: none measured, 1).

    Returns
    -------
    dict
        ``impacts_beyond_indentation_limit``, ``impacts_beyond_radius_limit``,
        ``impacts_beyond_strain_limit``, ``impacts_beyond_contact_time_limit``,
        ``impacts_beyond_inertia_limit`` (the pad's inertia changes the impact's peak force,
        contact time, rebound speed or dent by more than ``limits.inertia``),
        ``impacts_beyond_any_limit`` (counts),
        ``max_indentation_thickness_ratio``, ``max_contact_radius_ratio``,
        ``max_strain_ratio`` (the worst values, 0 without impacts),
        ``min_contact_time_ratio`` (the worst, the smallest; 0 without impacts or none measurable),
        ``min_impact_thickness_m`` (None without impacts: no pad was under one; null in summary.json),
        ``max_impact_force_N`` (the largest impact peak force, quasi-static, the storm's),
        ``max_impact_force_dynamic_N`` (the largest impact peak force times its inertia factor),
        ``min_inertia_force_factor``, ``min_inertia_restitution_factor`` (the smallest factors,
        1 without impacts; the three NaN, and the count 0, when there were impacts but no
        ``inertia``), ``inertia_direct_runs`` (impacts whose factors were run on their own pad,
        outside the material's table; 0 without ``inertia``), the limits
        ``limit_indentation_thickness_ratio``, ``limit_contact_radius_ratio``,
        ``limit_strain_ratio``, ``limit_contact_time_ratio``, ``limit_inertia_change`` and ``pad_density``.
    """
    lim = ValidityLimits() if limits is None else limits
    tr = np.full(dh.shape, np.inf) if time_ratio is None else np.asarray(time_ratio, dtype=np.float64)
    F = np.zeros(dh.shape) if force is None else np.asarray(force, dtype=np.float64)
    ones = np.ones(dh.shape)
    measured = inertia is not None or dh.size == 0  # (nothing to measure without impacts)
    rF, re, change = (ones, ones, ones - 1.0) if inertia is None else (
        np.where(np.isfinite(inertia.force), inertia.force, 1.0),
        np.where(np.isfinite(inertia.restitution), inertia.restitution, 1.0),
        np.nan_to_num(inertia.largest_change(), nan=0.0))
    over = (dh > lim.indentation_thickness, aR > lim.contact_radius, eps > lim.strain, tr < lim.contact_time,
            change > lim.inertia)
    return {
        "impacts_beyond_indentation_limit": int(over[0].sum()),
        "impacts_beyond_radius_limit": int(over[1].sum()),
        "impacts_beyond_strain_limit": int(over[2].sum()),
        "impacts_beyond_contact_time_limit": int(over[3].sum()),
        "impacts_beyond_inertia_limit": int(over[4].sum()),
        "impacts_beyond_any_limit": int(np.logical_or.reduce(over).sum()),
        "max_indentation_thickness_ratio": float(dh.max(initial=0.0)),
        "max_contact_radius_ratio": float(aR.max(initial=0.0)),
        "max_strain_ratio": float(eps.max(initial=0.0)),
        "min_contact_time_ratio": float(tr.min()) if tr.size and np.isfinite(tr.min()) else 0.0,
        "min_impact_thickness_m": float(thickness.min()) if thickness.size else None,  # (no impact: no pad)
        "max_impact_force_N": float(F.max(initial=0.0)),
        "max_impact_force_dynamic_N": float((F * rF).max(initial=0.0)) if measured else math.nan,
        "min_inertia_force_factor": float(rF.min(initial=1.0)) if measured else math.nan,
        "min_inertia_restitution_factor": float(re.min(initial=1.0)) if measured else math.nan,
        "inertia_direct_runs": 0 if inertia is None else inertia.direct_runs,
        "limit_indentation_thickness_ratio": float(lim.indentation_thickness),
        "limit_contact_radius_ratio": float(lim.contact_radius),
        "limit_strain_ratio": float(lim.strain),
        "limit_contact_time_ratio": float(lim.contact_time),
        "limit_inertia_change": float(lim.inertia),
        "pad_density": float(pad_density),
    }


#: the columns of :meth:`ImpactLimits.table` (``impacts.csv``), in their order
IMPACT_COLUMNS = ("stone", "t_onset_s", "t_peak_s", "x_m", "y_m", "z_m", "radius_m", "mass_kg", "speed_m_s", "thickness_m", "peak_force_N",
                  "peak_force_dynamic_N", "indentation_m", "indentation_thickness_ratio", "contact_radius_ratio",
                  "strain_ratio", "contact_time_ratio", "inertia_force", "inertia_duration", "inertia_restitution",
                  "inertia_dent", "beyond")

#: the validity keys of a storm's statistics, in their order (:func:`summarise`)
VALIDITY_KEYS = tuple(summarise(np.zeros(0), np.zeros(0), np.zeros(0), np.zeros(0)))


def validity_warning(stats: Any, *, brief: bool = False) -> str | None:
    """One line naming how many impacts were beyond the validity limits, with the numbers
    (None: none was).

    Parameters
    ----------
    stats : mapping
        A storm's statistics (or its ``summary.json``).
    brief : bool
        The count and where the numbers are, without them (``hailstorm -q``).
    """
    n = int(stats.get("impacts_beyond_any_limit", 0) or 0)
    if n == 0:
        return None
    if brief:
        return (f"{n} of {int(stats['impacts'])} impacts are beyond the model's validity limits "
                "(summary.json and impacts.csv have the numbers; see docs/validity.md)")

    def part(what: str, worst: str, limit: str, count: str) -> str:
        return (f"{what} up to {float(stats[worst]):.3g} (limit {float(stats[limit]):.3g}, "
                f"{int(stats[count])} impacts beyond)")

    parts = [part("indentation/thickness", "max_indentation_thickness_ratio", "limit_indentation_thickness_ratio",
                  "impacts_beyond_indentation_limit"),
             part("contact radius/stone radius", "max_contact_radius_ratio", "limit_contact_radius_ratio",
                  "impacts_beyond_radius_limit"),
             part("estimated peak strain", "max_strain_ratio", "limit_strain_ratio", "impacts_beyond_strain_limit")]
    if "impacts_beyond_contact_time_limit" in stats:  # (a summary.json of an older version has none)
        parts.append(f"contact time/pad wave period down to {float(stats['min_contact_time_ratio']):.3g} (limit "
                     f"{float(stats['limit_contact_time_ratio']):.3g} at {float(stats['pad_density']):g} kg/m^3, "
                     f"{int(stats['impacts_beyond_contact_time_limit'])} impacts beyond)")
    dyn = stats.get("max_impact_force_dynamic_N")
    if dyn is not None and math.isfinite(float(dyn)):  # (measured: not off, nor a summary of an older version)
        parts.append(f"the pad's inertia changes {int(stats['impacts_beyond_inertia_limit'])} impacts by more than "
                     f"{100 * float(stats['limit_inertia_change']):.3g} % (peak forces down to "
                     f"x{float(stats['min_inertia_force_factor']):.3g}; the largest "
                     f"{float(stats['max_impact_force_dynamic_N']):.4g} N dynamic against "
                     f"{float(stats['max_impact_force_N']):.4g} N quasi-static)")
    return (f"{n} of {int(stats['impacts'])} impacts are beyond the model's validity limits: " + "; ".join(parts)
            + " (quasi-static linear elasticity and its contact law no longer vouch for these impacts; see docs/validity.md)")
