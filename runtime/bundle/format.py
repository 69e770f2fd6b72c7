"""The Green's-function bundle's on-disk format: its files, manifest, hashes and checks.

A bundle is a directory holding ``manifest.json`` and one ``.npy`` file per
array. It is the *only* thing the runtime reads, so this module depends on
numpy alone (no gmsh, no scikit-fem). The offline stage writes bundles through
:func:`hailstorm.runtime.bundle.write.write_bundle`; everybody reads them through
:func:`hailstorm.runtime.bundle.read.load`.

Layout (format version 2)::

    manifest.json            format, version, key, options, material, per-array file
                             name, shape, dtype, size in bytes and SHA-256, and the
                             SHA-256 of the manifest's own content
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
                                      (vertex-major, x, y, z per vertex) [m/N];
                                      float64, or float32 (half the size: the storage
                                      precision is a choice, see below)

D's storage type is the ``dtype`` of its ``arrays.compliance`` entry (covered by
the manifest hash), one of :data:`COMPLIANCE_DTYPES`; a bundle stored in another
precision than float64 also says so in ``options.dtype`` (``"float32"``), which
is part of what the cache key covers, and :func:`load` refuses a bundle whose
file, ``arrays`` entry and ``options.dtype`` disagree. A float64 bundle needs no
``options.dtype`` (every bundle written before the choice existed is one): the
format version stays 2 and both precisions are format 2. The runtime reads
either: its kernels read D in its own type and compute in float64
(:func:`hailstorm.runtime.bundle.write.convert_bundle` writes a bundle's float32 copy).
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from hailstorm.runtime.bundle.stamps import is_stamped, stamp

__all__ = [
    "ARRAY_SPECS",
    "BUNDLE_FILES",
    "COMPLIANCE_DTYPES",
    "FORMAT_NAME",
    "FORMAT_VERSION",
    "HMATRIX_ARRAY_SPECS",
    "HMATRIX_FORMAT_VERSION",
    "READ_VERSIONS",
    "MANIFEST",
    "MANIFEST_HASH",
    "BundleError",
    "RoundedBlock",
    "array_hash",
    "array_specs",
    "bundle_files",
    "bundle_key",
    "check_compliance_dtype",
    "check_manifest",
    "compliance_dtype",
    "is_bundle",
    "manifest_hash",
    "read_arrays",
    "read_manifest",
    "round_block",
    "scan_array",
]

FORMAT_NAME = "hailstorm-greens-bundle"
FORMAT_VERSION = 2
#: the format of a bundle whose D is stored compressed (:mod:`hailstorm.runtime.bundle.hmatrix`):
#: a reader of format 2 only refuses it by its version, never reads a wrong D
HMATRIX_FORMAT_VERSION = 3
#: the format versions this reader reads
READ_VERSIONS = (FORMAT_VERSION, HMATRIX_FORMAT_VERSION)
MANIFEST = "manifest.json"
#: manifest entry holding the SHA-256 of the rest of the manifest
MANIFEST_HASH = "manifest_sha256"

log = logging.getLogger(__name__)

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


#: The storage types D may have, by the name ``options.dtype`` gives them (native byte order:
#: the compiled kernels read D in place). float64 is the default and needs no ``options.dtype``.
COMPLIANCE_DTYPES: dict[str, np.dtype] = {"float64": np.dtype(np.float64), "float32": np.dtype(np.float32)}


#: The arrays of a compressed (format 3) bundle: D's H-matrix in place of ``compliance``.
HMATRIX_ARRAY_SPECS: dict[str, tuple[str, int]] = {
    **{k: v for k, v in ARRAY_SPECS.items() if k != "compliance"},
    "hmatrix_rows": ("i", 1),
    "hmatrix_cols": ("i", 1),
    "hmatrix_blocks": ("i", 2),
    "hmatrix_data": ("f", 1),
}


def array_specs(version: int) -> dict[str, tuple[str, int]]:
    """The arrays (name -> dtype kind, ndim) of a bundle of format ``version``."""
    return HMATRIX_ARRAY_SPECS if version == HMATRIX_FORMAT_VERSION else ARRAY_SPECS


def bundle_files(version: int) -> frozenset[str]:
    """The files of a complete bundle of format ``version``."""
    return frozenset({MANIFEST, *(f"{name}.npy" for name in array_specs(version))})


#: Every file a bundle writer writes into a bundle directory (dense or compressed).
BUNDLE_FILES = bundle_files(FORMAT_VERSION) | bundle_files(HMATRIX_FORMAT_VERSION)


class BundleError(ValueError):
    """A bundle is missing, truncated, corrupted or does not match a request."""


def _slabs(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The array in its own memory order (no copy) and its bytes as a flat uint8 view."""
    if a.flags.f_contiguous and not a.flags.c_contiguous:
        a = a.T
    a = np.ascontiguousarray(a)
    flat = a.reshape(-1).view(np.uint8) if a.size else np.zeros(0, np.uint8)
    return a.reshape(-1), flat


def array_hash(a: np.ndarray) -> str:
    """SHA-256 of an array's dtype, shape, memory order and bytes.

    A Fortran-ordered array (the compliance D is stored column-major so that
    gathering the columns of a contact set is a contiguous copy) is hashed in
    its own order, without a copy.
    """
    return scan_array(a)[0]


def scan_array(a: np.ndarray) -> tuple[str, int]:
    """One pass over an array: its :func:`array_hash` and its number of non-finite entries."""
    h = hashlib.sha256()
    fortran = a.flags.f_contiguous and not a.flags.c_contiguous
    h.update(str(a.dtype.str).encode())
    h.update(str(a.shape).encode())
    if fortran:
        h.update(b"F")
    values, flat = _slabs(a)
    # in slabs, so that a memory-mapped D is not pulled into memory at once
    step = 1 << 26
    for start in range(0, flat.size, step):
        # numpy's stubs declare ndarray.__buffer__ only for Python >= 3.12
        h.update(flat[start:start + step])  # type: ignore[arg-type]
    bad = 0
    if a.dtype.kind == "f":
        per = max(1, step // a.dtype.itemsize)
        for start in range(0, values.size, per):
            bad += int(np.count_nonzero(~np.isfinite(values[start:start + per])))
    return h.hexdigest(), bad


def manifest_hash(manifest: Mapping[str, Any]) -> str:
    """SHA-256 of a manifest's content (canonical JSON, without its own hash entry)."""
    body = {k: v for k, v in manifest.items() if k != MANIFEST_HASH}
    return hashlib.sha256(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


@dataclass(frozen=True)
class RoundedBlock:
    """A block of D already cast to its storage type, with what the cast cost.

    Made by :func:`round_block` where the block is cast: a Dask worker sends its
    block rounded (half the traffic for float32), the offline stage's block store
    (:meth:`hailstorm.precompute.blocks.BlockStore.write`) writes it, and
    :func:`hailstorm.runtime.bundle.write.convert_bundle` casts a bundle's D by blocks.

    Attributes
    ----------
    values : (n_rows, k) ndarray
        Column-major, in the storage type.
    max_abs : float
        Largest |entry| of the float64 block.
    max_abs_error : float
        Largest |rounding error| of the cast (0 for float64).
    """

    values: np.ndarray
    max_abs: float
    max_abs_error: float


def round_block(values: np.ndarray, dtype: str | np.dtype) -> RoundedBlock:
    """Cast a float64 block of D to its storage type ``dtype``: the one cast (round to nearest).

    Parameters
    ----------
    values : (n_rows, k) float ndarray
        The solved block.
    dtype : {"float64", "float32"}

    Returns
    -------
    RoundedBlock

    Raises
    ------
    ValueError
        An entry does not fit in ``dtype`` (overflow).
    """
    values = np.asarray(values, dtype=np.float64)
    dtype = np.dtype(dtype)
    with np.errstate(over="ignore"):
        stored = np.asfortranarray(values, dtype=dtype)
    scale = float(np.abs(values).max()) if values.size else 0.0
    err = 0.0
    if stored.dtype != values.dtype and values.size:
        if np.isfinite(values).all() and not np.isfinite(stored).all():
            raise ValueError(f"a block of D does not fit in {dtype.name}: its entries (up to {scale:.3g}) overflow it")
        diff = stored.astype(np.float64)
        diff -= values
        err = float(np.abs(diff).max())
        del diff
    return RoundedBlock(stored, scale, err)


def bundle_key(path: str | os.PathLike) -> str | None:
    """The key of the bundle at ``path``, or None (no bundle there, or none readable)."""
    try:
        return str(read_manifest(path)["key"]) if is_bundle(path) else None
    except (OSError, ValueError, KeyError, TypeError):
        return None


def is_bundle(path: str | os.PathLike) -> bool:
    """True if ``path`` is a directory holding a hailstorm manifest (of any version)."""
    m = Path(path) / MANIFEST
    if not m.is_file():
        return False
    try:
        manifest = json.loads(m.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(manifest, dict) and manifest.get("format") == FORMAT_NAME


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def check_manifest(manifest: Any, m: Path) -> None:
    """Raise :class:`BundleError` naming the first key of ``manifest`` that is missing or mistyped."""
    def need(obj: Any, key: str, kind, where: str, check=None, what: str = "") -> Any:
        full = f"{where}{key}"
        if not isinstance(obj, dict) or key not in obj:
            raise BundleError(f"{m}: the manifest has no {full!r} entry; the bundle is damaged")
        value = obj[key]
        if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool or (check and not check(value)):
            raise BundleError(
                f"{m}: manifest entry {full!r} is {value!r}, expected {what or getattr(kind, '__name__', kind)}; "
                "the bundle is damaged"
            )
        return value

    if not isinstance(manifest, dict):
        raise BundleError(f"{m}: the manifest is a JSON {type(manifest).__name__}, not an object; the bundle is damaged")
    need(manifest, "key", str, "")
    options = need(manifest, "options", dict, "")
    need(options, "order", int, "options.", lambda v: v in (1, 2), "1 or 2")
    if "dtype" in options:
        need(options, "dtype", str, "options.", lambda v: v in COMPLIANCE_DTYPES,
             " or ".join(map(repr, COMPLIANCE_DTYPES)))
    material = need(manifest, "material", dict, "")
    for k in ("young", "poisson"):
        need(material, k, (int, float), "material.", _is_number, "a finite number")
    for k in ("mesh", "timings_s"):
        if k in manifest and not isinstance(manifest[k], dict):
            raise BundleError(f"{m}: manifest entry {k!r} is {manifest[k]!r}, expected an object; the bundle is damaged")
    for k in manifest.get("timings_s", {}):
        need(manifest["timings_s"], k, (int, float), "timings_s.", _is_number, "a number of seconds")
    _check_version_matches_arrays(manifest, m)
    if manifest.get("format_version") == HMATRIX_FORMAT_VERSION:
        comp = need(manifest, "compliance", dict, "", what="an object describing the compressed D")
        need(comp, "storage", str, "compliance.", lambda v: v == "hmatrix", "'hmatrix'")
        need(comp, "shape", list, "compliance.", lambda v: len(v) == 2 and all(
            isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in v), "two sizes")
        for k in ("tol", "stored_bytes", "dense_bytes", "far_blocks", "blocks", "max_rank"):
            need(comp, k, (int, float), "compliance.", _is_number, "a finite number")
        error = need(comp, "error", dict, "compliance.", what="an object")
        for k in ("columns", "max", "median"):
            need(error, k, (int, float), "compliance.error.", _is_number, "a finite number")
        if not 0 <= error["median"] <= error["max"]:  # figures the build measured, read as they say
            raise BundleError(f"{m}: the compressed D's recorded column errors are inconsistent (max "
                              f"{error['max']!r} below median {error['median']!r}, or negative); the manifest was "
                              "edited or damaged: re-run `hailstorm precompute`")
        if "options" in manifest and "dtype" in manifest["options"]:
            raise BundleError(f"{m}: a compressed bundle stores D in float64; its manifest names options.dtype; "
                              "the bundle is damaged")
    arrays = need(manifest, "arrays", dict, "", what="an object listing the arrays")
    for name in array_specs(manifest.get("format_version")):
        entry = need(arrays, name, dict, "arrays.", what="an object")
        where = f"arrays.{name}."
        need(entry, "file", str, where, _plain_name, "a file name inside the bundle")
        need(entry, "shape", list, where, lambda v: all(isinstance(n, int) and not isinstance(n, bool) and n >= 0
                                                        for n in v), "a list of sizes")
        need(entry, "dtype", str, where)
        need(entry, "sha256", str, where, lambda v: len(v) == 64, "a SHA-256 hex digest")
        need(entry, "bytes", int, where, lambda v: v >= 0, "a file size")
    need(manifest, MANIFEST_HASH, str, "", lambda v: len(v) == 64, "a SHA-256 hex digest")


def _check_version_matches_arrays(manifest: Mapping[str, Any], m: str) -> None:
    """A manifest whose arrays are wholly those of the other format version (a compressed bundle
    labelled 2, a dense one labelled 3): a version mismatch, said as such (not as a missing array)."""
    arrays, version = manifest.get("arrays"), manifest.get("format_version")
    if not isinstance(arrays, dict):
        return
    other = HMATRIX_FORMAT_VERSION if version == FORMAT_VERSION else FORMAT_VERSION
    if set(array_specs(version)) <= set(arrays) or not set(array_specs(other)) <= set(arrays):
        return
    kind = "a compressed D (hmatrix_*)" if other == HMATRIX_FORMAT_VERSION else "a dense D (compliance)"
    raise BundleError(f"{m}: format_version {version!r} does not match its arrays, which are version {other}'s "
                      f"({kind}); the manifest was edited or damaged: re-run `hailstorm precompute`")


def compliance_dtype(manifest: Mapping[str, Any]) -> np.dtype:
    """The storage type of D a manifest declares (``options.dtype``; float64 if absent).

    Raises
    ------
    BundleError
        ``options.dtype`` names no storage type of :data:`COMPLIANCE_DTYPES`.
    """
    name = (manifest.get("options") or {}).get("dtype", "float64")
    if name not in COMPLIANCE_DTYPES:
        raise BundleError(f"options.dtype is {name!r}, expected {' or '.join(map(repr, COMPLIANCE_DTYPES))}")
    return COMPLIANCE_DTYPES[name]


def check_compliance_dtype(manifest: Mapping[str, Any], dtype: np.dtype, where: Path) -> None:
    """Raise :class:`BundleError` unless D's actual ``dtype`` is a storage type and the one
    the manifest's ``arrays.compliance.dtype`` and ``options.dtype`` declare."""
    dtype = np.dtype(dtype)
    names = {v: k for k, v in COMPLIANCE_DTYPES.items()}
    if dtype not in names:
        raise BundleError(f"{where}: D (compliance) is stored as {dtype.str} ({dtype.name}); hailstorm reads D "
                          f"in {' or '.join(COMPLIANCE_DTYPES)} (native byte order) only")
    entry = manifest["arrays"]["compliance"]["dtype"]
    declared = compliance_dtype(manifest)
    if entry != dtype.str or declared != dtype:
        raise BundleError(
            f"{where}: D (compliance) is {names[dtype]}, but the manifest says arrays.compliance.dtype={entry!r}, "
            f"options.dtype={manifest['options'].get('dtype', 'float64 (absent)')!r}; "
            "the bundle is inconsistent (re-run `hailstorm precompute`)"
        )


def _plain_name(name: str) -> bool:
    """A file name that stays inside its directory (no separator, not '.', '..' or empty)."""
    return bool(name) and name not in (".", "..") and "/" not in name and os.sep not in name and "\0" not in name


def read_manifest(path: str | os.PathLike) -> dict[str, Any]:
    """Read and check a bundle's manifest: its structure and its content hash.

    Raises
    ------
    BundleError
        If the directory or manifest is missing, unreadable, of another format
        or version, lacks an entry or holds one of the wrong type (the message
        names it), or its content does not match its hash (it was edited).
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
    if not isinstance(manifest, dict):
        raise BundleError(f"{m}: the manifest is a JSON {type(manifest).__name__}, not an object; "
                          "it is not a hailstorm bundle manifest, or the bundle is damaged")
    if manifest.get("format") != FORMAT_NAME:
        raise BundleError(f"{m} is not a hailstorm bundle manifest (format={manifest.get('format')!r})")
    version = manifest.get("format_version")
    if version not in READ_VERSIONS:
        newer = isinstance(version, int) and not isinstance(version, bool) and version > max(READ_VERSIONS)
        raise BundleError(
            f"bundle {path} has format version {version!r}; this hailstorm reads versions "
            f"{' and '.join(map(str, READ_VERSIONS))}. "
            + ("A newer hailstorm wrote it: upgrade hailstorm to read it." if newer
               else "Re-run `hailstorm precompute`.")
        )
    check_manifest(manifest, m)
    if manifest_hash(manifest) != manifest[MANIFEST_HASH]:
        raise BundleError(f"{m}: the manifest's content does not match its hash (edited or corrupted); "
                          "re-run `hailstorm precompute`")
    return manifest


def read_arrays(path: str | os.PathLike, *, verify: bool = True, mmap: bool = True,
                rehash: bool = False) -> tuple[dict[str, Any], dict[str, np.ndarray]]:
    """Read a bundle's manifest and arrays, checking each file against the manifest.

    Every file's presence, place, size, shape and dtype are checked; with
    ``verify`` its content hash and (floating point) finiteness too, once per
    change of the file (:mod:`hailstorm.runtime.bundle.stamps`) unless ``rehash``.
    :func:`hailstorm.runtime.bundle.read.load` adds the checks across arrays.

    Returns
    -------
    manifest : dict
    arrays : dict of str to ndarray
        By :data:`ARRAY_SPECS` name; the compliance memory-mapped if ``mmap``.

    Raises
    ------
    BundleError
        Naming the file and what is wrong with it.
    """
    path = Path(path)
    manifest = read_manifest(path)
    entries = manifest["arrays"]
    data: dict[str, np.ndarray] = {}
    for name, (kind, ndim) in array_specs(manifest["format_version"]).items():
        entry = entries[name]
        f = path / entry["file"]
        if not f.is_file():
            raise BundleError(f"bundle {path}: array file {entry['file']} is missing")
        if f.is_symlink() or f.resolve().parent != path.resolve():
            raise BundleError(f"bundle {path}: array file {entry['file']} lies outside the bundle")
        size = f.stat().st_size
        if size != entry["bytes"]:
            raise BundleError(
                f"bundle {path}: {entry['file']} has {size} bytes, manifest says {entry['bytes']} "
                "(truncated, extended or replaced file)"
            )
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
        if name == "compliance":
            check_compliance_dtype(manifest, a.dtype, path)
        if name == "hmatrix_data" and a.dtype != np.float64:
            raise BundleError(f"bundle {path}: {name} is {a.dtype}, expected float64")
        if verify and (rehash or not is_stamped(f, entry["sha256"])):
            digest, bad = scan_array(a)
            if digest != entry["sha256"]:
                raise BundleError(f"bundle {path}: {entry['file']} content hash does not match the manifest (corrupted)")
            if bad:
                raise BundleError(f"bundle {path}: {name} holds {bad} non-finite (NaN or inf) values")
            stamp(f, entry["sha256"])
        data[name] = a if name in ("compliance", "hmatrix_data") else np.asarray(a)

    return manifest, data
