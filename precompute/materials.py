"""Materials per volume group: which (E, nu) each tetrahedron gets.

A body is one material (``young``, ``poisson``: the single-material default) or
several, one per named volume group of the mesh (gmsh Physical Volumes, meshio
tetra cell sets): ``materials={"pad": (0.5e6, 0.3), "shell": (2e9, 0.4)}``.

* :func:`parse_material` - a ``NAME=E,nu`` command-line value;
* :func:`check_material_input` - what can be refused before meshing;
* :func:`resolve_materials` - a :class:`MaterialMap` (one material index per
  tetrahedron), refusing a volume group without a material, a material naming
  no volume, an invalid (E, nu) per group, tetrahedra in no group or two;
* :func:`check_layers` - a warning for a volume no thicker than one element;
* :func:`contact_material` - the material under the hail-facing surface (the
  bundle's ``young``/``poisson``, what Hertz radii use at run time).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from hailstorm.precompute.fem import DEFAULT_POISSON, DEFAULT_YOUNG, check_material
from hailstorm.precompute.tetmesh import TetMesh, boundary_triangles, tet_volumes

log = logging.getLogger(__name__)

#: Name of the single material of a body given by ``young``/``poisson`` only.
WHOLE_BODY = "*"


@dataclass(frozen=True, eq=False)
class MaterialMap:
    """One (E, nu) per material and one material per tetrahedron.

    Attributes
    ----------
    names : tuple of str
        Volume group of each material (:data:`WHOLE_BODY` for a single-material body).
    young, poisson : (k,) float ndarray
        Young's modulus [Pa] and Poisson's ratio of each material.
    tet_material : (T,) int ndarray
        Index into ``names`` of each tetrahedron.
    """

    names: tuple[str, ...]
    young: np.ndarray
    poisson: np.ndarray
    tet_material: np.ndarray

    @property
    def tet_young(self) -> np.ndarray:
        """(T,) Young's modulus of each tetrahedron [Pa]."""
        return self.young[self.tet_material]

    @property
    def tet_poisson(self) -> np.ndarray:
        """(T,) Poisson's ratio of each tetrahedron."""
        return self.poisson[self.tet_material]

    def key(self) -> dict[str, list[float]] | None:
        """The cache-key / options record: ``{name: [E, nu]}``, ``None`` for one material."""
        if self.names == (WHOLE_BODY,):
            return None
        return {n: [float(e), float(nu)] for n, e, nu in zip(self.names, self.young, self.poisson)}

    def record(self) -> list[dict]:
        """The manifest record: per material its volume, E, nu and tetrahedron range.

        Tetrahedra must be grouped by material (:func:`sort_tets_by_material`):
        material k owns ``volume_tets[start:stop]``.
        """
        counts = np.bincount(self.tet_material, minlength=len(self.names))
        if np.any(np.diff(self.tet_material) < 0):
            raise ValueError("tetrahedra are not grouped by material; call sort_tets_by_material first")
        stops = np.cumsum(counts)
        return [{"volume": n, "young": float(e), "poisson": float(nu), "tets": [int(b - c), int(b)]}
                for n, e, nu, c, b in zip(self.names, self.young, self.poisson, counts, stops)]


def parse_material(text: str) -> tuple[str, float, float]:
    """``"NAME=E,nu"`` (``pad=0.5e6,0.3``) -> ``(name, E, nu)``, checked.

    Raises
    ------
    ValueError
        Naming what is wrong with the text.
    """
    name, sep, values = str(text).partition("=")
    name = name.strip()
    parts = [v.strip() for v in values.split(",")]
    if not sep or not name or len(parts) != 2:
        raise ValueError(f"--material {text!r}: expected NAME=E,nu (a volume group, Young's modulus in Pa and "
                         "Poisson's ratio), e.g. pad=0.5e6,0.3")
    try:
        young, poisson = float(parts[0]), float(parts[1])
    except ValueError:
        raise ValueError(f"--material {text!r}: E and nu must be numbers, e.g. pad=0.5e6,0.3") from None
    young, poisson = _checked(name, young, poisson)
    return name, young, poisson


def _checked(name: str, young, poisson) -> tuple[float, float]:
    try:
        return check_material(young, poisson)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"material of volume {name!r}: {exc}") from None


def check_material_input(materials: Mapping[str, tuple[float, float]] | None = None, *,
                         young: float | None = None, poisson: float | None = None) -> None:
    """The checks of :func:`resolve_materials` that need no mesh (run before meshing).

    Raises
    ------
    ValueError
        ``materials`` together with ``young``/``poisson``, an invalid
        (E, nu) (naming its volume group), a name that is not a string.
    """
    if not materials:
        check_material(DEFAULT_YOUNG if young is None else young, DEFAULT_POISSON if poisson is None else poisson)
        return
    if young is not None or poisson is not None:
        raise ValueError("give either materials per volume (--material NAME=E,nu) or one material "
                         "(--young/--poisson), not both")
    if not isinstance(materials, Mapping):
        raise ValueError(f"materials must map volume group names to (E, nu) pairs, got {type(materials).__name__}")
    for name, value in materials.items():
        if not isinstance(name, str) or not name:
            raise ValueError(f"material names must be volume group names (strings), got {name!r}")
        if isinstance(value, (str, bytes)) or np.ndim(value) != 1 or len(value) != 2:
            raise ValueError(f"material of volume {name!r} must be a pair (E, nu), got {value!r}")
        _checked(name, *value)


def resolve_materials(mesh: TetMesh, materials: Mapping[str, tuple[float, float]] | None = None, *,
                      young: float | None = None, poisson: float | None = None) -> MaterialMap:
    """The material of every tetrahedron of ``mesh``.

    Parameters
    ----------
    mesh
        With its volume groups (``mesh.volumes``).
    materials
        ``{volume group: (E [Pa], nu)}``, one entry for every volume group of
        the mesh. ``None`` or empty: the whole body is one material
        (``young``, ``poisson``; their defaults :data:`DEFAULT_YOUNG`,
        :data:`DEFAULT_POISSON`).
    young, poisson
        The single material; not allowed together with ``materials``.

    Raises
    ------
    ValueError
        A volume group without a material, a material naming no volume group,
        invalid (E, nu) (naming the group), tetrahedra in no group or in two
        groups, or ``materials`` together with ``young``/``poisson``.
    """
    n_tets = mesh.tets.shape[0]
    check_material_input(materials, young=young, poisson=poisson)
    if not materials:
        e, nu = check_material(DEFAULT_YOUNG if young is None else young,
                               DEFAULT_POISSON if poisson is None else poisson)
        return MaterialMap((WHOLE_BODY,), np.array([e]), np.array([nu]), np.zeros(n_tets, dtype=np.int64))
    where = mesh.source or "the mesh"
    if not mesh.volumes:
        raise ValueError(f"{where} has no volume groups, so materials {sorted(materials)} name nothing; "
                         "name the volumes (gmsh Physical Volume) or give one material with --young/--poisson")
    unknown = [n for n in materials if n not in mesh.volumes]
    if unknown:
        raise ValueError(f"material for {', '.join(map(repr, unknown))} names no volume group of {where} "
                         f"(its volume groups: {', '.join(map(repr, sorted(mesh.volumes)))})")
    missing = [n for n in sorted(mesh.volumes) if n not in materials]
    if missing:
        raise ValueError(f"volume group {', '.join(map(repr, missing))} of {where} has no material; give one with "
                         f"--material {missing[0]}=E,nu (API: materials={{{missing[0]!r}: (E, nu)}})")
    names = tuple(sorted(materials))
    values = [_checked(n, *materials[n]) for n in names]
    tet_material = np.full(n_tets, -1, dtype=np.int64)
    for k, n in enumerate(names):
        ids = np.asarray(mesh.volumes[n], dtype=np.int64)
        clash = ids[tet_material[ids] >= 0]
        if clash.size:
            other = names[int(tet_material[clash[0]])]
            raise ValueError(f"{where}: {clash.size} tetrahedra are in both volume groups {other!r} and {n!r} "
                             f"(e.g. tet {int(clash[0])}); a tetrahedron has one material")
        tet_material[ids] = k
    orphans = np.flatnonzero(tet_material < 0)
    if orphans.size:
        raise ValueError(f"{where}: {orphans.size} tetrahedra (e.g. tet {int(orphans[0])}) are in no volume group, "
                         "so they have no material; put every volume in a named group")
    young_k, poisson_k = (np.array(v) for v in zip(*values))
    return MaterialMap(names, young_k, poisson_k, tet_material)


def sort_tets_by_material(mesh: TetMesh, materials: MaterialMap) -> tuple[TetMesh, MaterialMap]:
    """The same body with its tetrahedra grouped by material (a stable sort).

    The bundle records each material as a range of ``volume_tets``. An
    already grouped mesh is returned as it is.
    """
    if not np.any(np.diff(materials.tet_material) < 0):
        return mesh, materials
    perm = np.argsort(materials.tet_material, kind="stable")
    inv = np.empty_like(perm)
    inv[perm] = np.arange(perm.size)
    volumes = {n: np.sort(inv[np.asarray(v, dtype=np.int64)]) for n, v in mesh.volumes.items()}
    sorted_mesh = TetMesh(mesh.points, mesh.tets[perm], mesh.groups, mesh.source, volumes)
    return sorted_mesh, MaterialMap(materials.names, materials.young, materials.poisson,
                                    materials.tet_material[perm])


def layer_thickness(mesh: TetMesh, tet_ids: np.ndarray) -> tuple[float, float, float]:
    """(thickness, element size, interior fraction) of a set of tetrahedra.

    Thickness is 2 V / A [m] (volume over boundary area: exact for a thin slab
    of any outline); element size the median edge length [m]; the interior
    fraction is the share of the set's nodes not on its boundary: 0 for a
    layer one element thick.
    """
    tets = mesh.tets[np.asarray(tet_ids, dtype=np.int64)]
    vol = float(np.abs(tet_volumes(mesh.points, tets)).sum())
    tris = boundary_triangles(tets)
    p = mesh.points[tris]
    area = float(0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1).sum())
    edges = np.concatenate([mesh.points[tets[:, i]] - mesh.points[tets[:, j]]
                            for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))])
    nodes = np.unique(tets)
    interior = 1.0 - np.unique(tris).size / nodes.size
    return 2.0 * vol / area, float(np.median(np.linalg.norm(edges, axis=1))), float(interior)


def check_layers(mesh: TetMesh, materials: MaterialMap) -> list[str]:
    """Warn (log) about each material volume no thicker than one element; return the warnings.

    A volume whose nodes nearly all (>= 95 %) lie on its own boundary has one
    element across its thickness: its bending and its dent are poorly resolved.
    """
    said = []
    if materials.names == (WHOLE_BODY,):
        return said
    for k, name in enumerate(materials.names):
        ids = np.flatnonzero(materials.tet_material == k)
        thickness, size, interior = layer_thickness(mesh, ids)
        if interior < 0.05:
            msg = (f"volume {name!r} of {mesh.source or 'the mesh'} is thinner than one element: about "
                   f"{thickness * 1e3:.3g} mm thick (2 volume / area) with elements of {size * 1e3:.3g} mm "
                   f"(median edge), {interior:.0%} of its nodes inside it; its stiffness is poorly resolved: "
                   "refine the mesh or thicken the layer")
            log.warning("warning: %s", msg)
            said.append(msg)
    return said


def contact_material(mesh: TetMesh, materials: MaterialMap, contact_group: str = "top") -> tuple[float, float]:
    """(E, nu) of the material under the hail-facing surface.

    The material of the tetrahedra behind the ``contact_group`` triangles
    (every boundary triangle for ``"all"``); when several materials reach
    that surface, the one covering the largest area (logged).
    """
    if len(materials.names) == 1:
        return float(materials.young[0]), float(materials.poisson[0])
    tets = mesh.tets
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]])
    owner = np.tile(np.arange(tets.shape[0]), 4)
    tris = boundary_triangles(tets) if contact_group == "all" or contact_group not in mesh.groups \
        else mesh.groups[contact_group]
    n = np.int64(mesh.points.shape[0]) + 1
    fs, ts = np.sort(faces, axis=1).astype(np.int64), np.sort(tris, axis=1).astype(np.int64)
    fkey, tkey = (fs[:, 0] * n + fs[:, 1]) * n + fs[:, 2], (ts[:, 0] * n + ts[:, 1]) * n + ts[:, 2]
    order = np.argsort(fkey)
    pos = np.minimum(np.searchsorted(fkey[order], tkey), fkey.size - 1)
    mat = materials.tet_material[owner[order[pos]]]
    p = mesh.points[tris]
    area = 0.5 * np.linalg.norm(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), axis=1)
    per = np.bincount(mat, weights=area, minlength=len(materials.names))
    k = int(np.argmax(per))
    if np.count_nonzero(per) > 1:
        log.info("several materials reach the %r surface (%s); the bundle's young/poisson are %r's", contact_group,
                 ", ".join(f"{n}: {a * 1e4:.3g} cm^2" for n, a in zip(materials.names, per) if a > 0),
                 materials.names[k])
    return float(materials.young[k]), float(materials.poisson[k])
