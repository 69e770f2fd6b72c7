"""The Green's-function bundle as the runtime reads it: :func:`load` and :class:`GreensFunctions`.

A bundle's files and manifest are :mod:`hailstorm.runtime.bundle.format`; it is
written by :func:`hailstorm.runtime.bundle.write.write_bundle`, and
:func:`convert_bundle` writes a copy with D in another storage type
(:func:`hailstorm.precompute.hmatrix.compress_bundle` a compressed one). It
writes nothing into a bundle: only verification stamps and, for a compressed
bundle, the expansion of its D, both in the cache. This module depends on numpy
alone (no gmsh, no scikit-fem).
"""

from __future__ import annotations

import functools
import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import numpy as np

from hailstorm.runtime.bundle.format import (
    HMATRIX_FORMAT_VERSION,
    BundleError,
    is_bundle,
    read_arrays,
)
from hailstorm.runtime.bundle.hmatrix import HMatrix, expanded, expansion_dtype
from hailstorm.runtime.bundle.compliance import apply_columns, column_dofs, dof3, gather

__all__ = ["EXPAND_UP_TO", "CompressedGreensFunctions", "GreensFunctions", "load", "stranded_copies",
           "vertex_normals"]


@dataclass(frozen=True, eq=False)
class GreensFunctions:
    """A loaded Green's-function bundle (see :func:`load`).

    Attributes
    ----------
    vertices : (n, 3) float ndarray
        Surface corner vertices [m].
    triangles : (m, 3) int ndarray
        Surface triangles, counter-clockwise seen from outside.
    fixed : (n,) bool ndarray
        Vertices on the clamp (zero displacement).
    contactable : (n,) bool ndarray
        Vertices that own a column block of D (forces may be applied there).
    areas : (n,) float ndarray
        Lumped vertex areas a_i, a third of the adjacent triangle areas [m^2].
    volume_points, volume_tets, surface_nodes : ndarray
        The volume mesh the bundle was computed on and the map
        surface vertex -> volume point.
    young, poisson : float
        Material under the contactable surface (Pa, -).
    tet_young, tet_poisson : (T,) float ndarray
        Material of each volume tetrahedron (several for a layered body).
    D : (3 n, 3 c) float64 or float32 ndarray
        The compliance, column-major (memory-mapped by default), in its storage
        type (:attr:`dtype`); read it through :meth:`compliance`, which returns
        float64 blocks.
    manifest : dict
        Everything the offline stage recorded (options, key, timings).
    hmatrix : HMatrix or None
        A compressed bundle's stored D (format 3: an H-matrix within
        ``manifest["compliance"]["tol"]`` of the exact D per column); None for a
        dense bundle. :attr:`D` is then its dense expansion (float32 for a
        tolerance of 1e-5 or more, else float64), made on first use
        (:class:`CompressedGreensFunctions`), once into the cache and
        memory-mapped from there (:func:`hailstorm.runtime.bundle.hmatrix.expanded`;
        in memory with ``mmap=False``): the runtime touches the pages of D it
        reads, as with a dense bundle, and the compression saves the bundle's bytes.
    """

    path: Path
    manifest: dict[str, Any]
    vertices: np.ndarray
    triangles: np.ndarray
    fixed: np.ndarray
    contactable: np.ndarray
    areas: np.ndarray
    volume_points: np.ndarray
    volume_tets: np.ndarray
    surface_nodes: np.ndarray
    D: np.ndarray = field(repr=False)
    #: column block of D for each surface vertex, -1 where not contactable
    column_of: np.ndarray = field(repr=False)
    hmatrix: HMatrix | None = field(default=None, repr=False)

    @property
    def young(self) -> float:
        return float(self.manifest["material"]["young"])

    @property
    def poisson(self) -> float:
        return float(self.manifest["material"]["poisson"])

    @property
    def dtype(self) -> np.dtype:
        """D's storage type (float64 or float32; the contact results are float64 either way)."""
        return self.D.dtype

    @property
    def tet_young(self) -> np.ndarray:
        """(T,) Young's modulus of each volume tetrahedron [Pa] (the manifest's ``materials`` ranges)."""
        return self._tet_material_field("young")

    @property
    def tet_poisson(self) -> np.ndarray:
        """(T,) Poisson's ratio of each volume tetrahedron."""
        return self._tet_material_field("poisson")

    def _tet_material_field(self, name: str) -> np.ndarray:
        out = np.full(self.volume_tets.shape[0], float(self.manifest["material"][name]))
        for m in self.manifest.get("materials") or ():  # bundles before materials per volume: one material
            start, stop = m["tets"]
            out[start:stop] = float(m[name])
        return out

    @property
    def order(self) -> int:
        return int(self.manifest["options"]["order"])

    @property
    def n_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def contact_vertices(self) -> np.ndarray:
        """Indices of the contactable vertices, in D's column order."""
        return np.flatnonzero(self.contactable)

    def vertex_normals(self) -> np.ndarray:
        """Area-weighted outward unit normals at the surface vertices, (n, 3)."""
        return vertex_normals(self.vertices, self.triangles)

    def _check_vertices(self, idx: np.ndarray, what: str) -> np.ndarray:
        idx = np.asarray(idx)
        if idx.ndim != 1 or (idx.size and not np.issubdtype(idx.dtype, np.integer)):
            raise ValueError(f"{what} must be a 1-D array of vertex indices, got shape {idx.shape} dtype {idx.dtype}")
        if idx.size and (idx.min() < 0 or idx.max() >= self.n_vertices):
            raise IndexError(f"{what} holds vertex indices outside 0..{self.n_vertices - 1}")
        return idx.astype(np.intp, copy=False)

    def compliance(self, rows, cols) -> np.ndarray:
        """The block D[rows, cols] of the compliance matrix, D.

        Parameters
        ----------
        rows, cols : array_like of int
            Surface vertex indices. ``cols`` must be contactable or fixed
            (a force on a clamped vertex goes straight into the support:
            its columns are zero).

        Returns
        -------
        ndarray, shape (3 len(rows), 3 len(cols))
            Vertex-major (x, y, z per vertex): entry (3i+a, 3j+b) is the
            displacement of ``rows[i]`` in direction a per newton applied at
            ``cols[j]`` in direction b [m/N].
        """
        rows = self._check_vertices(rows, "rows")
        cols = self._check_vertices(cols, "cols")
        cblock = self.column_of[cols]
        bad = (cblock < 0) & ~self.fixed[cols]
        if bad.any():
            raise ValueError(
                f"vertices {cols[bad][:5].tolist()} are neither contactable nor fixed: "
                "the bundle holds no column of D for them"
            )
        return gather(self, dof3(rows), column_dofs(self, cols))

    def traction_greens(self, rows, cols) -> np.ndarray:
        """The block Ξ[rows, cols] = D[rows, cols] A[cols] (traction Green's function).

        ``u = Ξ p``: displacement per unit *traction* (Pa) at the lumped
        vertex areas, as in the course hint (u = Ξ p = D A p = D f).
        """
        cols = self._check_vertices(cols, "cols")
        return self.compliance(rows, cols) * np.repeat(self.areas[cols], 3)[None, :]

    def displacement(self, vertices, forces: np.ndarray, rows=None) -> np.ndarray:
        """Surface displacement caused by point forces at surface vertices.

        Parameters
        ----------
        vertices : (k,) int
            Contactable (or fixed) vertices carrying the forces.
        forces : (k, 3) float
            Forces applied to the seat [N].
        rows : (r,) int, optional
            Where to read the displacement; default: every surface vertex.

        Returns
        -------
        ndarray, shape (r, 3) (or (n, 3))
        """
        vertices = self._check_vertices(vertices, "vertices")
        forces = np.asarray(forces, dtype=np.float64).reshape(vertices.size, 3)
        self.compliance(vertices[:0], vertices)  # raises the clear error for columns D lacks
        rows = None if rows is None else self._check_vertices(rows, "rows")
        return apply_columns(self, column_dofs(self, vertices), forces.ravel(), rows)


class CompressedGreensFunctions(GreensFunctions):
    """A compressed bundle's Green's functions: :attr:`D` is expanded from :attr:`hmatrix` on first use.

    Loading reads and checks the H-matrix only; what reads :attr:`D` (the storm and the
    contact core, unless :attr:`reads_hmatrix`) triggers the expansion, once (:func:`load`'s
    ``mmap``: into the cache and memory-mapped, else in memory). What needs only the
    bundle's metadata (``hailstorm info``) never expands it. :attr:`expanded` says
    whether it happened.
    """

    @classmethod
    def lazy(cls, expand: Callable[[], np.ndarray], dtype: np.dtype, *, reads_hmatrix: bool = False,
             **fields: Any) -> "CompressedGreensFunctions":
        """The bundle with ``fields`` (every :class:`GreensFunctions` field but D) and ``expand()`` making D
        in ``dtype``; ``reads_hmatrix``: the runtime reads the H-matrix, not the expansion."""
        gf = cls(D=None, **fields)  # type: ignore[arg-type]
        gf.__dict__["_expand"] = expand
        gf.__dict__["_dtype"] = np.dtype(dtype)
        gf.__dict__["_reads_hmatrix"] = bool(reads_hmatrix)
        return gf

    @property
    def reads_hmatrix(self) -> bool:
        """True: the runtime reads D from :attr:`hmatrix`'s blocks, never expanding it
        (:func:`load`'s ``expand``; :func:`hailstorm.runtime.bundle.compliance.reader`)."""
        return bool(self.__dict__.get("_reads_hmatrix", False))

    @property  # type: ignore[override]
    def D(self) -> np.ndarray:
        """The dense expansion of :attr:`hmatrix` (column-major, in :attr:`dtype`), made on first use."""
        dense = self.__dict__.get("_dense")
        if dense is None:
            dense = self.__dict__["_expand"]()
            self.__dict__["_dense"] = dense
        return dense

    @D.setter
    def D(self, value: np.ndarray | None) -> None:
        self.__dict__["_dense"] = value

    @property
    def expanded(self) -> bool:
        """True once :attr:`D` has been made."""
        return self.__dict__.get("_dense") is not None

    @property
    def dtype(self) -> np.dtype:
        """The expansion's type (:func:`hailstorm.runtime.bundle.hmatrix.expansion_dtype`: float32 for a
        tolerance of 1e-5 or more, else float64; the H-matrix itself is stored in float64)."""
        dense = self.__dict__.get("_dense")
        return dense.dtype if dense is not None else self.__dict__.get("_dtype", np.dtype(np.float64))


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Unit vertex normals: the area-weighted mean of the incident triangles' normals, (n, 3).

    The triangles' orientation sets the side (outward triangles give outward
    normals); a vertex of no triangle gets a zero vector.
    """
    X = np.asarray(vertices, dtype=np.float64)
    T = np.asarray(triangles, dtype=np.int64)
    cross = np.cross(X[T[:, 1]] - X[T[:, 0]], X[T[:, 2]] - X[T[:, 0]])  # 2 x area x unit normal
    n = np.zeros_like(X)
    for j in range(3):
        np.add.at(n, T[:, j], cross)
    norm = np.linalg.norm(n, axis=1)
    return np.divide(n, norm[:, None], out=np.zeros_like(n), where=norm[:, None] > 0)


def stranded_copies(path: str | os.PathLike) -> list[Path]:
    """The bundles a killed writer left beside ``path`` (``.NAME.tmp-*`` / ``.NAME.old-*``), newest first.

    Only looks: :func:`hailstorm.runtime.bundle.write.clean_stale_temporaries` puts them back.
    """
    path = Path(path)
    try:
        found = [p for p in path.parent.glob(f".{path.name}.*") if p.name.startswith(
            (f".{path.name}.tmp-", f".{path.name}.old-")) and is_bundle(p)]
    except OSError:
        return []
    return sorted(found, key=lambda p: p.stat().st_mtime, reverse=True)


#: a compressed bundle whose dense D would take more bytes than this (in its expansion's type) is read
#: from its H-matrix by the runtime unless ``load(..., expand=True)``
EXPAND_UP_TO = 1 << 30


def load(path: str | os.PathLike, *, verify: bool = True, mmap: bool = True, rehash: bool = False,
         expand: bool | None = None) -> GreensFunctions:
    """Load a Green's-function bundle written by ``hailstorm precompute``.

    Parameters
    ----------
    path
        Bundle directory.
    verify
        Check every array's content hash against the manifest, and that
        floating-point arrays (D among them) are finite (reads every byte
        once; about a second per GB), once per change of each file: a file
        verified before and unchanged since (same inode, size, modification
        and status-change times; :mod:`hailstorm.runtime.bundle.stamps`) is not
        read again. The manifest's structure and content hash, every file's
        size, shapes, dtypes and cross-array consistency are always checked.
        Reading changes nothing: a bundle stranded beside ``path`` by a
        writer killed between its two renames is named in the error, and put
        back by the next writer or :func:`hailstorm.runtime.bundle.write.recover`.
    mmap
        Memory-map the compliance matrix instead of reading it into memory.
    rehash
        With ``verify``: hash every file even if it was verified unchanged
        before (``hailstorm info`` does).
    expand
        A compressed bundle only: how the runtime (the storm,
        :func:`~hailstorm.runtime.contact.solve_contacts`, ``press_spheres``,
        :meth:`GreensFunctions.compliance`, ...) reads D. True: from the dense
        expansion, made once on first use (fastest per solve once made; its memory is the dense
        D's). False: from the H-matrix's blocks, never expanding D
        (:class:`~hailstorm.runtime.bundle.hreader.HMatrixReader`; the memory is the H-matrix's).
        None (default): False when the expansion would exceed :data:`EXPAND_UP_TO`, else True.
        The storm reads D the same way. A dense bundle has no other way to be read (it is
        memory-mapped with ``mmap``).

    Returns
    -------
    GreensFunctions

    Raises
    ------
    BundleError
        With a message naming the problem if the bundle is missing, truncated,
        corrupted, of another format version or internally inconsistent.
    ValueError
        ``expand`` not True, False or None.
    """
    if expand not in (None, True, False):
        raise ValueError(f"expand must be True, False or None (decided by the size), got {expand!r}")
    path = Path(path)
    if not path.exists():
        stranded = stranded_copies(path)
        if stranded:
            raise BundleError(f"bundle {path} not found: a writer interrupted between its two renames left it "
                              f"at {stranded[0]}; the next `hailstorm precompute --out {path}` puts it back")
    manifest, data = read_arrays(path, verify=verify, mmap=mmap, rehash=rehash)

    n = data["vertices"].shape[0]
    nc = int(data["contactable"].sum())
    hmatrix = None
    if manifest["format_version"] == HMATRIX_FORMAT_VERSION:
        try:
            hmatrix = HMatrix.from_arrays(tuple(manifest["compliance"]["shape"]), data)
        except ValueError as exc:
            raise BundleError(f"bundle {path} is inconsistent: {exc}") from None
    shape = hmatrix.shape if hmatrix is not None else data["compliance"].shape
    problems = []
    if data["vertices"].shape[1] != 3:
        problems.append("vertices is not (n, 3)")
    for name in ("areas", "fixed", "contactable", "surface_nodes"):
        if data[name].shape != (n,):
            problems.append(f"{name} has shape {data[name].shape}, expected ({n},)")
    if data["triangles"].size and (data["triangles"].min() < 0 or data["triangles"].max() >= n):
        problems.append("triangles index outside the vertices")
    if tuple(shape) != (3 * n, 3 * nc):
        problems.append(f"compliance has shape {tuple(shape)}, expected {(3 * n, 3 * nc)}")
    if np.any(data["fixed"] & data["contactable"]):
        problems.append("some vertices are both fixed and contactable")
    if data["surface_nodes"].size and data["surface_nodes"].max() >= data["volume_points"].shape[0]:
        problems.append("surface_nodes index outside volume_points")
    if problems:
        raise BundleError(f"bundle {path} is inconsistent: " + "; ".join(problems))

    column_of = np.full(n, -1, dtype=np.intp)
    column_of[data["contactable"]] = np.arange(nc)
    fields = dict(path=path, manifest=manifest, vertices=data["vertices"], triangles=data["triangles"],
                  fixed=data["fixed"], contactable=data["contactable"], areas=data["areas"],
                  volume_points=data["volume_points"], volume_tets=data["volume_tets"],
                  surface_nodes=data["surface_nodes"], column_of=column_of, hmatrix=hmatrix)
    if hmatrix is None:
        return GreensFunctions(D=data["compliance"], **fields)
    # checked: expanded on first use (once, into the cache) for the compiled kernels
    tag = hashlib.sha256(f"{manifest['key']}\0{manifest['arrays']['hmatrix_data']['sha256']}".encode()).hexdigest()
    dtype = expansion_dtype(float(manifest["compliance"]["tol"]))
    make = (functools.partial(expanded, hmatrix, tag, dtype=dtype, rebuild=rehash) if mmap
            else functools.partial(hmatrix.to_dense, dtype))
    if expand is None:
        expand = shape[0] * shape[1] * dtype.itemsize <= EXPAND_UP_TO
    return CompressedGreensFunctions.lazy(make, dtype, reads_hmatrix=not expand, **fields)

