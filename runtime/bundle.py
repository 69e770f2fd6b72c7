"""The Green's-function bundle: its on-disk format, writer and reader.

A bundle is a directory holding ``manifest.json`` and one ``.npy`` file per
array. It is the *only* thing the runtime reads, so this module depends on
numpy alone (no gmsh, no scikit-fem). The offline stage writes bundles through
:func:`write_bundle`; everybody reads them through :func:`load`.

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
(:func:`convert_bundle` writes a bundle's float32 copy).

The bundle is written atomically: into a temporary sibling directory first,
then renamed into place, so a reader never sees half a bundle. Writers of one
bundle directory take turns through a lock file next to it
(``.NAME.lock``, :func:`bundle_lock`); a writer that finds temporaries left by
a killed writer removes them, and a bundle stranded by a crash between the
writer's two renames is put back in place (:func:`recover`). A directory is
only ever replaced if it holds exactly the files a bundle writer writes:
nothing else is deleted.
"""

from __future__ import annotations

import ctypes
import errno
import hashlib
import json
import logging
import math
import os
import shutil
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from hailstorm.runtime.atomic import probe_writable
from hailstorm.runtime.contact.compliance import apply_columns, column_dofs, dof3, gather
from hailstorm.runtime.stamps import is_stamped, stamp

FORMAT_NAME = "hailstorm-greens-bundle"
FORMAT_VERSION = 2
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


#: Every file a bundle writer writes into a bundle directory.
BUNDLE_FILES = frozenset({MANIFEST, *(f"{name}.npy" for name in ARRAY_SPECS)})


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
    return _scan(a)[0]


def _scan(a: np.ndarray) -> tuple[str, int]:
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


def _check_structure(manifest: Any, m: Path) -> None:
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
    arrays = need(manifest, "arrays", dict, "", what="an object listing the arrays")
    for name in ARRAY_SPECS:
        entry = need(arrays, name, dict, "arrays.", what="an object")
        where = f"arrays.{name}."
        need(entry, "file", str, where, _plain_name, "a file name inside the bundle")
        need(entry, "shape", list, where, lambda v: all(isinstance(n, int) and not isinstance(n, bool) and n >= 0
                                                        for n in v), "a list of sizes")
        need(entry, "dtype", str, where)
        need(entry, "sha256", str, where, lambda v: len(v) == 64, "a SHA-256 hex digest")
        need(entry, "bytes", int, where, lambda v: v >= 0, "a file size")
    need(manifest, MANIFEST_HASH, str, "", lambda v: len(v) == 64, "a SHA-256 hex digest")


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


def _check_compliance_dtype(manifest: Mapping[str, Any], dtype: np.dtype, where: Path) -> None:
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
    if manifest.get("format_version") != FORMAT_VERSION:
        raise BundleError(
            f"bundle {path} has format version {manifest.get('format_version')!r}; "
            f"this hailstorm reads version {FORMAT_VERSION}. Re-run `hailstorm precompute`."
        )
    _check_structure(manifest, m)
    if manifest_hash(manifest) != manifest[MANIFEST_HASH]:
        raise BundleError(f"{m}: the manifest's content does not match its hash (edited or corrupted); "
                          "re-run `hailstorm precompute`")
    return manifest


# --------------------------------------------------------------------------- writers: locks, debris, replacement

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX: no locking
    fcntl = None  # type: ignore[assignment]

_TMP, _OLD = ".tmp-", ".old-"
_held: dict[tuple[Path, int], int] = {}


def lock_path(out: str | os.PathLike) -> Path:
    """The lock file that writers of bundle directory ``out`` share: ``.NAME.lock`` beside it."""
    out = Path(out).absolute()
    return out.parent / f".{out.name}.lock"


@contextmanager
def bundle_lock(out: str | os.PathLike, *, wait: bool = True) -> Iterator[Path]:
    """Hold the exclusive writer's lock of bundle directory ``out``.

    Creates ``out``'s parent and the lock file if needed (which also proves,
    before any work, that the place is writable). Re-entrant within a thread.

    Parameters
    ----------
    out
        The bundle directory.
    wait
        If another process (or thread) holds the lock: wait for it (logging
        who holds it), or raise :class:`BundleError` at once.

    Yields
    ------
    pathlib.Path
        ``out`` as an absolute path.
    """
    import threading

    out = Path(out).absolute()
    me = (out, threading.get_ident())
    if me in _held:
        _held[me] += 1
        try:
            yield out
        finally:
            _held[me] -= 1
        return
    lock = lock_path(out)
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise BundleError(f"cannot write a bundle at {out}: {exc.strerror or exc}: {exc.filename or out.parent}") from exc
    fd = _acquire(lock, out, wait)
    try:
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        _held[me] = 1
        try:
            yield out
        finally:
            del _held[me]
            # unlinked while held: a process waiting on this file finds it gone and retries (see _acquire)
            try:
                os.unlink(lock)
            except OSError:
                pass
    finally:
        os.close(fd)  # releases the lock


def _acquire(lock: Path, out: Path, wait: bool) -> int:
    """Open and flock ``lock``; retry while the file that was locked is no longer the one at ``lock``."""
    while True:
        try:
            fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            raise BundleError(f"cannot write a bundle at {out}: {exc.strerror or exc}: {exc.filename or lock}") from exc
        if fcntl is None:  # pragma: no cover
            return fd
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
                if not wait:
                    raise BundleError(f"bundle {out} is being written by another process (pid {holder}); "
                                      "try again when it has finished") from None
                log.warning("waiting for another hailstorm (pid %s) to finish writing %s ...", holder, out)
                fcntl.flock(fd, fcntl.LOCK_EX)
            st = os.fstat(fd)
            try:
                now = os.stat(lock)
            except FileNotFoundError:
                now = None
            if now is not None and (now.st_dev, now.st_ino) == (st.st_dev, st.st_ino):
                return fd
        except BaseException:
            os.close(fd)
            raise
        os.close(fd)  # the previous holder removed the file we locked: lock the new one


def _ours(d: Path) -> bool:
    """True if directory ``d`` holds nothing but files a bundle writer writes."""
    try:
        return all(e.name in BUNDLE_FILES and e.is_file(follow_symlinks=False) for e in os.scandir(d))
    except OSError:
        return False


def _debris(parent: Path) -> dict[str, list[Path]]:
    """Writer temporaries (``.NAME.tmp-*``, ``.NAME.old-*``) and lock files (``.NAME.lock``)
    in ``parent``: the temporaries of each target name (an empty list for a lock file alone)."""
    found: dict[str, list[Path]] = {}
    try:
        entries = list(os.scandir(parent))
    except OSError:
        return found
    for e in entries:
        n = e.name
        if not n.startswith("."):
            continue
        if n.endswith(".lock") and len(n) > 6 and e.is_file(follow_symlinks=False):
            found.setdefault(n[1:-5], [])
            continue
        i = max(n.rfind(_TMP), n.rfind(_OLD))
        if i > 1 and e.is_dir(follow_symlinks=False):
            found.setdefault(n[1:i], []).append(Path(e.path))
    return found


def check_writable(directory: str | os.PathLike) -> None:
    """Raise :class:`BundleError` unless a bundle can be created in ``directory``.

    Probes the directory (or, if it does not exist yet, its nearest existing
    ancestor) by creating and removing an empty file in it, so that an
    unwritable output is refused before any work; creates nothing else.
    """
    directory = Path(directory).absolute()
    try:
        probe_writable(directory)
    except NotADirectoryError as exc:
        raise BundleError(f"cannot write a bundle in {directory}: {exc.filename} is not a directory") from None
    except OSError as exc:
        raise BundleError(f"cannot write a bundle in {directory}: {exc.strerror or exc} "
                          f"({Path(exc.filename).parent if exc.filename else directory})") from exc


def _recover_locked(out: Path, temps: list[Path] | None = None) -> None:
    """With ``out``'s lock held: put a bundle stranded between the two renames of a killed
    writer back at ``out``, and remove that writer's temporaries."""
    if temps is None:
        temps = _debris(out.parent).get(out.name, [])
    temps = [t for t in temps if _ours(t)]
    if not temps:
        return
    if not out.exists():
        # newest complete copy first: a finished temporary (.tmp-) before the previous bundle (.old-)
        for cand in sorted(temps, key=lambda t: (_OLD in t.name, -t.stat().st_mtime)):
            try:
                load(cand, verify=True)
            except BundleError:
                continue
            os.replace(cand, out)
            log.warning("recovered bundle %s from %s, left by an interrupted writer", out, cand.name)
            temps.remove(cand)
            break
    for t in temps:
        log.info("removing %s, left by an interrupted bundle writer", t)
        shutil.rmtree(t, ignore_errors=True)


def clean_stale_temporaries(parent: str | os.PathLike) -> None:
    """Remove the temporaries of killed bundle writers in ``parent`` and recover stranded bundles.

    A temporary is only touched if its target's lock is free (no live writer)
    and it holds nothing but bundle files.
    """
    parent = Path(parent).absolute()
    import threading

    for name, temps in _debris(parent).items():
        out = parent / name
        if (out, threading.get_ident()) in _held:
            _recover_locked(out, temps)
            continue
        try:
            with bundle_lock(out, wait=False):
                _recover_locked(out, temps)
        except BundleError:
            continue  # a live writer, or an unwritable place: leave it


def check_replaceable(out: str | os.PathLike) -> None:
    """Raise :class:`BundleError` unless ``out`` may be (re)written as a bundle.

    ``out`` may be missing, an empty directory, or a directory holding exactly
    the files a bundle writer writes with a hailstorm manifest. Anything else
    (a file; a directory with other files, such as the user's notes or results;
    a manifest alone) is refused, naming what is in the way.
    """
    out = Path(out)
    if not out.exists() and not out.is_symlink():
        return
    if not out.is_dir() or out.is_symlink():
        raise BundleError(f"--out {out} exists and is not a directory; refusing to overwrite it")
    try:
        entries = list(os.scandir(out))
    except OSError as exc:
        raise BundleError(f"cannot read --out {out}: {exc.strerror or exc}") from exc
    if not entries:
        return
    foreign = sorted(e.name for e in entries if e.name not in BUNDLE_FILES or not e.is_file(follow_symlinks=False))
    if foreign:
        shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
        raise BundleError(
            f"--out {out} holds files that are not part of a hailstorm bundle ({shown}); "
            "refusing to replace it (move them away, or choose another directory)"
        )
    missing = sorted(BUNDLE_FILES - {e.name for e in entries})
    if missing or not is_bundle(out):
        raise BundleError(
            f"--out {out} is not a complete hailstorm bundle ("
            + (f"no {', '.join(missing[:3])}" + (" ..." if len(missing) > 3 else "") if missing else "no hailstorm manifest")
            + "); refusing to replace it (remove it yourself, or choose another directory)"
        )


def _exchange(a: Path, b: Path) -> bool:
    """Atomically swap two paths (Linux renameat2 RENAME_EXCHANGE); False if unsupported."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    at_fdcwd, rename_exchange = -100, 2
    if fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.EPERM, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), str(b))


@dataclass(frozen=True)
class StagedArray:
    """An array already written as a ``.npy`` file on the bundle's file system, with
    its :func:`array_hash` (computed by its writer, who checked it is finite).

    :func:`write_bundle` moves the file into the bundle instead of writing the
    array again (the offline stage streams D to disk block by block).
    """

    path: Path
    shape: tuple[int, ...]
    dtype: str
    sha256: str


def write_bundle(
    out: str | os.PathLike,
    arrays: Mapping[str, np.ndarray | StagedArray],
    manifest: Mapping[str, Any],
) -> Path:
    """Write a bundle atomically.

    Parameters
    ----------
    out
        Target directory. If it already holds a bundle, that bundle is replaced
        (atomically: the old one stays intact until the new one is complete).
        If it holds anything but a bundle's files, nothing is touched and
        :class:`BundleError` is raised naming the files in the way. Writers of
        one ``out`` take turns (:func:`bundle_lock`); temporaries left by a
        killed writer are removed first.
    arrays
        Every array named in :data:`ARRAY_SPECS`; floating-point arrays must be
        finite. A :class:`StagedArray` is moved into the bundle as it is (and
        moved back if the bundle cannot be completed).
    manifest
        Metadata (options, material, key, timings...). ``format``,
        ``format_version``, ``arrays`` and ``manifest_sha256`` entries are
        added here.

    Returns
    -------
    pathlib.Path
        The bundle directory.
    """
    out = Path(out).absolute()
    missing = set(ARRAY_SPECS) - set(arrays)
    if missing:
        raise BundleError(f"cannot write bundle: arrays missing: {sorted(missing)}")
    d_in = arrays["compliance"]
    # before any hashing: D's storage type and the manifest agree (a staged D names its own)
    dtype = np.dtype(d_in.dtype) if isinstance(d_in, StagedArray) else np.asarray(d_in).dtype
    _check_compliance_dtype({"options": manifest.get("options") or {}, "arrays": {"compliance": {"dtype": dtype.str}}},
                            dtype, out)
    prepared = {}
    for name in ARRAY_SPECS:
        if isinstance(arrays[name], StagedArray):
            prepared[name] = (arrays[name], arrays[name].sha256)
            continue
        a = np.asarray(arrays[name])
        if not (a.flags.c_contiguous or a.flags.f_contiguous):
            a = np.ascontiguousarray(a)
        digest, bad = _scan(a)
        if bad:
            raise BundleError(f"cannot write bundle {out}: {name} holds {bad} non-finite (NaN or inf) values")
        prepared[name] = (a, digest)
    with bundle_lock(out):
        clean_stale_temporaries(out.parent)
        check_replaceable(out)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}{_TMP}", dir=out.parent))
        try:
            entries = {}
            for name, (a, digest) in prepared.items():
                fname = f"{name}.npy"
                if isinstance(a, StagedArray):
                    os.replace(a.path, tmp / fname)
                    entries[name] = {"file": fname, "shape": list(a.shape), "dtype": a.dtype, "sha256": digest,
                                     "bytes": (tmp / fname).stat().st_size}
                    continue
                with open(tmp / fname, "wb") as fh:
                    np.save(fh, a, allow_pickle=False)
                    fh.flush()
                    os.fsync(fh.fileno())
                    size = os.fstat(fh.fileno()).st_size
                entries[name] = {"file": fname, "shape": list(a.shape), "dtype": a.dtype.str, "sha256": digest,
                                 "bytes": size}
            full = dict(manifest)
            full.pop(MANIFEST_HASH, None)
            full.update(format=FORMAT_NAME, format_version=FORMAT_VERSION, arrays=entries)
            full[MANIFEST_HASH] = manifest_hash(full)
            _check_structure(full, out / MANIFEST)  # never write a bundle that load would refuse
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
                if not _exchange(tmp, out):  # tmp now holds the old bundle
                    old = Path(tempfile.mkdtemp(prefix=f".{out.name}{_OLD}", dir=out.parent))
                    old.rmdir()
                    os.replace(out, old)
                    os.replace(tmp, out)
                    tmp = old
                shutil.rmtree(tmp, ignore_errors=True)
            else:
                os.replace(tmp, out)
        except BaseException:
            for name, (a, _) in prepared.items():  # a staged array goes back where it came from
                if isinstance(a, StagedArray) and (tmp / f"{name}.npy").is_file() and not a.path.exists():
                    try:
                        os.replace(tmp / f"{name}.npy", a.path)
                    except OSError:
                        pass
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    return out


#: Columns of D cast per block by :func:`convert_bundle` (bounds its float64 temporaries).
CONVERT_BLOCK = 1024


def dtype_cast_record(source_key: str, source_dtype: str, max_abs_error: float, max_abs: float) -> dict[str, Any]:
    """The manifest's ``dtype_cast`` entry of a D stored in a narrower type than it was computed in.

    Parameters
    ----------
    source_key, source_dtype : str
        The cache key and storage type of the D it was rounded from.
    max_abs_error, max_abs : float
        The largest rounding of an entry and the largest |entry| [m/N].
    """
    return {"source_key": source_key, "source_dtype": source_dtype, "max_abs_error": max_abs_error,
            "max_rel_error": max_abs_error / max_abs if max_abs > 0 else 0.0}


def convert_bundle(
    src: str | os.PathLike,
    out: str | os.PathLike,
    dtype: str | np.dtype = "float32",
    *,
    key: str | None = None,
) -> Path:
    """Write a copy of the bundle ``src`` at ``out`` with D stored as ``dtype``.

    The cast step of the bundle writer: everything but D is copied as is; D is
    rounded to ``dtype`` (to nearest) column block by column block, and the copy
    is written like any bundle (:func:`write_bundle`: hashed, atomic, locked), its
    manifest saying ``options.dtype`` and, under ``dtype_cast``, the source's key
    and storage type and the largest rounding of an entry of D, absolute [m/N] and
    relative to the largest entry. The source is verified first.

    Parameters
    ----------
    src
        A bundle directory.
    out
        Where to write the copy (may be ``src`` itself: replaced atomically once
        the copy is complete).
    dtype : {"float32", "float64"} or numpy dtype
        D's storage type (:data:`COMPLIANCE_DTYPES`).
    key
        The copy's cache key. Default: the source's key if ``dtype`` is its own,
        else the SHA-256 of the source's key and ``dtype`` (a float32 copy never
        passes for its float64 source, nor a float64 copy of a float32 one for the
        float64 original). The offline stage passes the key it computed itself.

    Returns
    -------
    pathlib.Path
        The new bundle's directory.

    Raises
    ------
    BundleError
        ``src`` is not a valid bundle, ``dtype`` is not a storage type, an entry of
        D does not fit in ``dtype`` (overflow), or ``out`` cannot be written.
    """
    names = {v: k for k, v in COMPLIANCE_DTYPES.items()}
    try:
        target = np.dtype(dtype)
    except TypeError:
        target = None
    if target not in names:
        raise BundleError(f"cannot store D as {dtype!r}: the storage types are {' and '.join(COMPLIANCE_DTYPES)}")
    out = Path(out).absolute()
    check_writable(out.parent)
    gf = load(src, verify=True)
    D = gf.D
    name, source = names[target], names[D.dtype]
    cast = np.empty(D.shape, dtype=target, order="F")
    scale = err = 0.0
    for j in range(0, D.shape[1], CONVERT_BLOCK):
        block = np.asarray(D[:, j:j + CONVERT_BLOCK])
        with np.errstate(over="ignore"):
            cast[:, j:j + CONVERT_BLOCK] = block
        if not np.isfinite(cast[:, j:j + CONVERT_BLOCK]).all():
            raise BundleError(f"cannot store D of {gf.path} as {name}: its entries (up to "
                              f"{np.abs(block).max():.3g}) overflow {name}")
        if block.size:
            scale = max(scale, float(np.abs(block).max()))
            err = max(err, float(np.abs(cast[:, j:j + CONVERT_BLOCK] - block).max()))
    manifest = {k: v for k, v in gf.manifest.items() if k not in ("format", "format_version", "arrays", MANIFEST_HASH)}
    manifest["options"] = {k: v for k, v in manifest["options"].items() if k != "dtype"}
    if name != "float64":
        manifest["options"]["dtype"] = name
    if key is None:
        key = gf.manifest["key"] if target == D.dtype else hashlib.sha256(
            f"{gf.manifest['key']}\0compliance dtype {name}".encode()).hexdigest()
    manifest["key"] = key
    manifest["dtype_cast"] = dtype_cast_record(gf.manifest["key"], source, err, scale)
    arrays = {k: getattr(gf, k) for k in ARRAY_SPECS if k != "compliance"}
    arrays["compliance"] = cast
    return write_bundle(out, arrays, manifest)


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


def vertex_normals(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals of an oriented triangle surface, (n, 3)."""
    p = vertices[triangles]
    fn = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])  # 2 * area * unit normal
    vn = np.zeros_like(vertices, dtype=np.float64)
    for k in range(3):
        np.add.at(vn, triangles[:, k], fn)
    norm = np.linalg.norm(vn, axis=1, keepdims=True)
    return vn / np.where(norm > 0, norm, 1.0)


def load(path: str | os.PathLike, *, verify: bool = True, mmap: bool = True, rehash: bool = False) -> GreensFunctions:
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
        and status-change times; :mod:`hailstorm.runtime.stamps`) is not
        read again. The manifest's structure and content hash, every file's
        size, shapes, dtypes and cross-array consistency are always checked.
        A bundle stranded beside ``path`` by a writer killed between its two
        renames is put back first.
    mmap
        Memory-map the compliance matrix instead of reading it into memory.
    rehash
        With ``verify``: hash every file even if it was verified unchanged
        before (``hailstorm info`` does).

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
    if not path.exists() and path.parent.is_dir():
        # a writer killed between its two renames leaves the bundle beside its place
        clean_stale_temporaries(path.parent)
    manifest = read_manifest(path)
    entries = manifest["arrays"]
    data: dict[str, np.ndarray] = {}
    for name, (kind, ndim) in ARRAY_SPECS.items():
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
            _check_compliance_dtype(manifest, a.dtype, path)
        if verify and (rehash or not is_stamped(f, entry["sha256"])):
            digest, bad = _scan(a)
            if digest != entry["sha256"]:
                raise BundleError(f"bundle {path}: {entry['file']} content hash does not match the manifest (corrupted)")
            if bad:
                raise BundleError(f"bundle {path}: {name} holds {bad} non-finite (NaN or inf) values")
            stamp(f, entry["sha256"])
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
