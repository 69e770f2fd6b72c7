"""The Green's-function bundle: its on-disk format, writer and reader.

A bundle is a directory holding ``manifest.json`` and one ``.npy`` file per
array. It is the *only* thing the runtime reads, so this module depends on
numpy alone (no gmsh, no scikit-fem). The offline stage writes bundles through
:func:`write_bundle`; everybody reads them through :func:`load`.

Layout (format version 1)::

    manifest.json            format, version, key, options, material, hashes
    vertices.npy             (n, 3)   surface corner vertices [m]
    triangles.npy            (m, 3)   outward-oriented surface triangles
    areas.npy                (n,)     lumped vertex areas a_i [m^2] (A = diag(a) ⊗ I3)
    fixed.npy                (n,)     bool, vertex lies on the clamp
    contactable.npy          (n,)     bool, vertex has a column in D
    volume_points.npy        (N, 3)   volume mesh points [m]
    volume_tets.npy          (T, 4)   tetrahedra (corner connectivity)
    surface_nodes.npy        (n,)     index of each surface vertex in volume_points
    compliance.npy           (3n, 3c) D, column-major: displacement of every surface vertex
                                      per unit force at each contactable vertex
                                      (vertex-major, x, y, z per vertex) [m/N]

The bundle is written atomically: into a temporary sibling directory first,
then renamed into place, so a reader never sees half a bundle.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from runtime.gather import _apply_columns, _column_dofs, _dof3, _gather

FORMAT_NAME = "hailstorm-greens-bundle"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"

#: Arrays every bundle holds, with their dtype kind and number of dimensions.
ARRAY_SPECS: dict[str, tuple[str, int]] = {
    "vertices": ("f", 2),
    "triangles": ("i", 2),
    "areas": ("f", 1),
    "fixed": ("b", 1),
    "contactable": ("b", 1),
    "volume_points": ("f", 2),
    "volume_tets": ("i", 2),
    "surface_nodes": ("i", 1),
    "compliance": ("f", 2),
}


class BundleError(ValueError):
    """A bundle is missing, truncated, corrupted or does not match a request."""


def array_hash(a: np.ndarray) -> str:
    """SHA-256 of an array's dtype, shape, memory order and bytes.

    A Fortran-ordered array (the compliance D is stored column-major so that
    gathering the columns of a contact set is a contiguous copy) is hashed in
    its own order, without a copy.
    """
    h = hashlib.sha256()
    order = "F" if (a.flags.f_contiguous and not a.flags.c_contiguous) else "C"
    h.update(str(a.dtype.str).encode())
    h.update(str(a.shape).encode())
    if order == "F":
        h.update(b"F")
        a = a.T
    a = np.ascontiguousarray(a)
    # hash in slabs so a memory-mapped D is not pulled into memory at once
    flat = a.reshape(-1).view(np.uint8) if a.size else np.zeros(0, np.uint8)
    step = 1 << 26
    for start in range(0, flat.size, step):
        # numpy's stubs declare ndarray.__buffer__ only for Python >= 3.12
        h.update(flat[start:start + step])  # type: ignore[arg-type]
    return h.hexdigest()


def is_bundle(path: str | os.PathLike) -> bool:
    """True if ``path`` is a directory holding a hailstorm manifest."""
    m = Path(path) / MANIFEST
    if not m.is_file():
        return False
    try:
        return json.loads(m.read_text()).get("format") == FORMAT_NAME
    except (OSError, ValueError):
        return False


def read_manifest(path: str | os.PathLike) -> dict[str, Any]:
    """Read and sanity-check a bundle's manifest.

    Raises
    ------
    BundleError
        If the directory or manifest is missing, unreadable, or of another
        format or version.
    """
    path = Path(path)
    if not path.exists():
        raise BundleError(f"bundle directory {path} does not exist")
    if not path.is_dir():
        raise BundleError(f"bundle path {path} is not a directory")
    m = path / MANIFEST
    if not m.is_file():
        raise BundleError(f"{path} is not a hailstorm bundle: {MANIFEST} is missing")
    try:
        manifest = json.loads(m.read_text())
    except (OSError, ValueError) as exc:
        raise BundleError(f"{m} is not valid JSON ({exc}); the bundle is corrupted") from exc
    if manifest.get("format") != FORMAT_NAME:
        raise BundleError(f"{m} is not a hailstorm bundle manifest (format={manifest.get('format')!r})")
    if manifest.get("format_version") != FORMAT_VERSION:
        raise BundleError(
            f"bundle {path} has format version {manifest.get('format_version')!r}; "
            f"this hailstorm reads version {FORMAT_VERSION}. Re-run `hailstorm precompute`."
        )
    return manifest


def write_bundle(
    out: str | os.PathLike,
    arrays: Mapping[str, np.ndarray],
    manifest: Mapping[str, Any],
) -> Path:
    """Write a bundle atomically.

    Parameters
    ----------
    out
        Target directory. If it already holds a bundle, that bundle is replaced
        (atomically: the old one stays intact until the new one is complete).
        If it is a non-empty directory that is not a bundle, nothing is touched
        and :class:`BundleError` is raised.
    arrays
        Every array named in :data:`ARRAY_SPECS`.
    manifest
        Metadata (options, material, key, timings...). ``format``,
        ``format_version`` and ``arrays`` entries are added here.

    Returns
    -------
    pathlib.Path
        The bundle directory.
    """
    out = Path(out).absolute()
    missing = set(ARRAY_SPECS) - set(arrays)
    if missing:
        raise BundleError(f"cannot write bundle: arrays missing: {sorted(missing)}")
    if out.exists() and not out.is_dir():
        raise BundleError(f"--out {out} exists and is not a directory; refusing to overwrite it")
    if out.is_dir() and any(out.iterdir()) and not is_bundle(out):
        raise BundleError(
            f"--out {out} is a non-empty directory that is not a hailstorm bundle; "
            "refusing to overwrite it (choose an empty or new directory)"
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.tmp-", dir=out.parent))
    try:
        entries = {}
        for name in ARRAY_SPECS:
            a = np.asarray(arrays[name])
            if not (a.flags.c_contiguous or a.flags.f_contiguous):
                a = np.ascontiguousarray(a)
            fname = f"{name}.npy"
            with open(tmp / fname, "wb") as fh:
                np.save(fh, a, allow_pickle=False)
                fh.flush()
                os.fsync(fh.fileno())
            entries[name] = {
                "file": fname,
                "shape": list(a.shape),
                "dtype": a.dtype.str,
                "sha256": array_hash(a),
            }
        full = dict(manifest)
        full.update(format=FORMAT_NAME, format_version=FORMAT_VERSION, arrays=entries)
        with open(tmp / MANIFEST, "w") as fh:
            json.dump(full, fh, indent=2, sort_keys=True)
            fh.flush()
            os.fsync(fh.fileno())
        # mkdtemp makes a private (0o700) directory: give the bundle the mode a plain
        # mkdir would (0o777 minus the umask), as the files in it have
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
            old.rmdir()
            os.replace(out, old)
            os.replace(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


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
        Material (Pa, -).
    manifest : dict
        Everything the offline stage recorded (options, key, timings).
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

    @property
    def young(self) -> float:
        return float(self.manifest["material"]["young"])

    @property
    def poisson(self) -> float:
        return float(self.manifest["material"]["poisson"])

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
        return _gather(self, _dof3(rows), _column_dofs(self, cols))

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
        return _apply_columns(self, _column_dofs(self, vertices), forces.ravel(), rows)


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals of an oriented triangle surface, (n, 3)."""
    p = vertices[triangles]
    fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # 2 * area * unit normal
    vn = np.zeros_like(vertices, dtype=np.float64)
    for k in range(3):
        np.add.at(vn, triangles[:, k], fn)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return vn / np.where(norm > 0, norm, 1.0)


def load(path: str | os.PathLike, *, verify: bool = True, mmap: bool = True) -> GreensFunctions:
    """Load a Green's-function bundle written by ``hailstorm precompute``.

    Parameters
    ----------
    path
        Bundle directory.
    verify
        Check every array's content hash against the manifest (reads every
        byte once; about a second per GB). Shapes, dtypes and cross-array
        consistency are always checked.
    mmap
        Memory-map the compliance matrix instead of reading it into memory.

    Returns
    -------
    GreensFunctions

    Raises
    ------
    BundleError
        With a message naming the problem if the bundle is missing, truncated,
        corrupted, of another format version or internally inconsistent.
    """
    path = Path(path)
    manifest = read_manifest(path)
    entries = manifest.get("arrays", {})
    data: dict[str, np.ndarray] = {}
    for name, (kind, ndim) in ARRAY_SPECS.items():
        entry = entries.get(name)
        if entry is None:
            raise BundleError(f"bundle {path}: manifest lists no array {name!r}")
        f = path / entry["file"]
        if not f.is_file():
            raise BundleError(f"bundle {path}: array file {entry['file']} is missing")
        try:
            a = np.load(f, mmap_mode="r" if mmap else None, allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise BundleError(f"bundle {path}: {entry['file']} is truncated or corrupted ({exc})") from exc
        if list(a.shape) != list(entry["shape"]) or a.dtype.str != entry["dtype"]:
            raise BundleError(
                f"bundle {path}: {entry['file']} has shape {a.shape} dtype {a.dtype.str}, "
                f"manifest says {tuple(entry['shape'])} {entry['dtype']} (truncated or replaced file)"
            )
        if a.dtype.kind != kind or a.ndim != ndim:
            raise BundleError(f"bundle {path}: {name} has dtype kind {a.dtype.kind}/ndim {a.ndim}, expected {kind}/{ndim}")
        if verify and array_hash(a) != entry["sha256"]:
            raise BundleError(f"bundle {path}: {entry['file']} content hash does not match the manifest (corrupted)")
        data[name] = a if name == "compliance" else np.asarray(a)

    n = data["vertices"].shape[0]
    nc = int(data["contactable"].sum())
    problems = []
    if data["vertices"].shape[1] != 3:
        problems.append("vertices is not (n, 3)")
    for name in ("areas", "fixed", "contactable", "surface_nodes"):
        if data[name].shape != (n,):
            problems.append(f"{name} has shape {data[name].shape}, expected ({n},)")
    if data["triangles"].size and (data["triangles"].min() < 0 or data["triangles"].max() >= n):
        problems.append("triangles index outside the vertices")
    if data["compliance"].shape != (3 * n, 3 * nc):
        problems.append(f"compliance has shape {data['compliance'].shape}, expected {(3 * n, 3 * nc)}")
    if np.any(data["fixed"] & data["contactable"]):
        problems.append("some vertices are both fixed and contactable")
    if data["surface_nodes"].size and data["surface_nodes"].max() >= data["volume_points"].shape[0]:
        problems.append("surface_nodes index outside volume_points")
    if problems:
        raise BundleError(f"bundle {path} is inconsistent: " + "; ".join(problems))

    column_of = np.full(n, -1, dtype=np.intp)
    column_of[data["contactable"]] = np.arange(nc)
    return GreensFunctions(
        path=path,
        manifest=manifest,
        vertices=data["vertices"],
        triangles=data["triangles"],
        fixed=data["fixed"],
        contactable=data["contactable"],
        areas=data["areas"],
        volume_points=data["volume_points"],
        volume_tets=data["volume_tets"],
        surface_nodes=data["surface_nodes"],
        D=data["compliance"],
        column_of=column_of,
    )
