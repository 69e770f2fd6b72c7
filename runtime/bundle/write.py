"""Writing a bundle directory safely: the writers' lock, a killed writer's debris, atomic replacement.

The bundle is written atomically: into a temporary sibling directory first,
then renamed into place, so a reader never sees half a bundle. Writers of one
bundle directory take turns through a lock file next to it
(``.NAME.lock``, :func:`bundle_lock`); a writer that finds temporaries left by
a killed writer removes them, and a bundle stranded by a crash between the
writer's two renames is put back in place (:func:`clean_stale_temporaries`). A directory is
only ever replaced if it holds exactly the files a bundle writer writes:
nothing else is deleted.

Why a lock of its own and not ``filelock``: both hold ``flock`` on a file, but
``filelock``'s Unix lock leaves its ``.NAME.lock`` file behind in the user's
directory after every build (it cannot remove the file safely), and a waiting
writer cannot say whom it waits for. :func:`bundle_lock` unlinks the file while
still holding it (a waiter that then locks the unlinked file notices and retries
on the new one) and writes the holder's pid into it, which the waiting message
and the refusal name (``tests/precompute/test_bad_input_precompute.py`` holds
both: no file left, the pid named).

:func:`write_bundle` writes the files of the format
(:mod:`hailstorm.runtime.bundle.format`) into a temporary sibling and renames it
into place; :class:`StagedArray` lets the offline stage hand over a D it has
already streamed to disk.
"""

from __future__ import annotations

import ctypes
import hashlib
import errno
import json
import logging
import os
import shutil
import stat
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from hailstorm.runtime.bundle import format as bundle_format
from hailstorm.runtime.bundle.atomic import probe_writable, sibling_name_problem
from hailstorm.runtime.bundle.format import (
    ARRAY_SPECS,
    BUNDLE_FILES,
    COMPLIANCE_DTYPES,
    FORMAT_NAME,
    FORMAT_VERSION,
    HMATRIX_FORMAT_VERSION,
    MANIFEST,
    MANIFEST_HASH,
    BundleError,
    READ_VERSIONS,
    array_specs,
    bundle_files,
    bundle_key,
    check_compliance_dtype,
    check_manifest,
    is_bundle,
    manifest_hash,
    round_block,
)
from hailstorm.runtime.bundle.read import load

log = logging.getLogger(__name__)

__all__ = [
    "CONVERT_BLOCK",
    "StagedArray",
    "convert_bundle",
    "dtype_cast_record",
    "bundle_lock",
    "check_replaceable",
    "check_writable",
    "clean_stale_temporaries",
    "lock_path",
    "write_bundle",
]

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
                log.info("waiting for another hailstorm (pid %s) to finish writing %s ...", holder, out)
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
                bundle_format.read_arrays(cand, verify=True)
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
    a manifest alone) is refused, naming what is in the way; so is a name too long for the
    writer's temporaries beside it (:func:`~hailstorm.runtime.bundle.atomic.sibling_name_problem`).
    """
    out = Path(out)
    too_long = sibling_name_problem(out, max(_TMP, _OLD, key=len))
    if too_long is not None:
        raise BundleError(f"cannot write --out: {too_long}")
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
    names = {e.name for e in entries}
    missing = min((sorted(bundle_files(v) - names) for v in READ_VERSIONS), key=len)  # of the nearer layout
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
    *,
    expect_key: str | None = None,
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
        Every array named in :data:`ARRAY_SPECS` (a dense bundle, format 2) or in
        :data:`HMATRIX_ARRAY_SPECS` (D stored as an H-matrix, format 3; chosen by
        the presence of ``hmatrix_data``); floating-point arrays must be
        finite. A :class:`StagedArray` is moved into the bundle as it is (and
        moved back if the bundle cannot be completed).
    manifest
        Metadata (options, material, key, timings...). ``format``,
        ``format_version``, ``arrays`` and ``manifest_sha256`` entries are
        added here.
    expect_key : str, optional
        The key of the bundle this one replaces (its source, for a copy written over it):
        once the lock is held, a bundle at ``out`` with another key than it or this one's
        was written by another run meanwhile, and is not replaced (:class:`BundleError`).

    Returns
    -------
    pathlib.Path
        The bundle directory.
    """
    out = Path(out).absolute()
    version, prepared = _prepared(out, arrays, manifest)
    with bundle_lock(out):
        clean_stale_temporaries(out.parent)
        check_replaceable(out)
        if expect_key is not None:
            now = bundle_key(out)
            if now is not None and now not in (expect_key, manifest.get("key")):
                raise BundleError(f"--out {out} was just written by another run with other inputs (key {now[:12]}) "
                                  "while this one worked on it; not replacing that run's bundle: choose another "
                                  "--out, or run again to replace it")
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
            full.update(format=FORMAT_NAME, format_version=version, arrays=entries)
            full[MANIFEST_HASH] = manifest_hash(full)
            check_manifest(full, out / MANIFEST)  # never write a bundle that load would refuse
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
                _discard_old_copy(tmp, out)
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


def _prepared(out: Path, arrays: Mapping[str, np.ndarray | StagedArray],
              manifest: Mapping[str, Any]) -> tuple[int, dict[str, tuple[Any, str]]]:
    """:func:`write_bundle`'s checks before the lock: the format version the arrays make (all there),
    D's storage type against the manifest, and each array (or :class:`StagedArray`) with its hash."""
    version = HMATRIX_FORMAT_VERSION if "compliance" not in arrays and "hmatrix_data" in arrays else FORMAT_VERSION
    specs = array_specs(version)
    missing = set(specs) - set(arrays)
    if missing:
        raise BundleError(f"cannot write bundle: arrays missing: {sorted(missing)}")
    if version == FORMAT_VERSION:
        d_in = arrays["compliance"]
        # before any hashing: D's storage type and the manifest agree (a staged D names its own)
        dtype = np.dtype(d_in.dtype) if isinstance(d_in, StagedArray) else np.asarray(d_in).dtype
        check_compliance_dtype({"options": manifest.get("options") or {},
                                "arrays": {"compliance": {"dtype": dtype.str}}}, dtype, out)
    prepared: dict[str, tuple[Any, str]] = {}
    for name in specs:
        if isinstance(arrays[name], StagedArray):
            prepared[name] = (arrays[name], arrays[name].sha256)
            continue
        a = np.asarray(arrays[name])
        if not (a.flags.c_contiguous or a.flags.f_contiguous):
            a = np.ascontiguousarray(a)
        digest, bad = bundle_format.scan_array(a)
        if bad:
            raise BundleError(f"cannot write bundle {out}: {name} holds {bad} non-finite (NaN or inf) values")
        prepared[name] = (a, digest)
    return version, prepared


def _discard_old_copy(old: Path, out: Path) -> None:
    """Remove the replaced bundle's copy (our files: the bundle just exchanged out); a
    read-only copy is made writable first; what still cannot be removed is reported."""
    def writable_then_retry(func: Any, path: str, exc: Any) -> None:
        parent = os.path.dirname(path)
        try:
            os.chmod(parent, os.stat(parent).st_mode | stat.S_IWUSR | stat.S_IXUSR)
            if os.path.isdir(path) and not os.path.islink(path):
                os.chmod(path, os.stat(path).st_mode | stat.S_IRWXU)
            func(path)
        except OSError:
            pass

    try:
        os.chmod(old, os.stat(old).st_mode | stat.S_IRWXU)
    except OSError:
        pass
    shutil.rmtree(old, onerror=writable_then_retry)
    if old.exists():
        log.warning("warning: the previous bundle of %s was replaced but its old copy %s could not be removed; "
                    "delete it by hand", out, old)


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
    if gf.hmatrix is not None:
        raise BundleError(f"{gf.path} stores D compressed (an H-matrix in float64); convert its dense source")
    D = gf.D
    name, source = names[target], names[D.dtype]
    cast = np.empty(D.shape, dtype=target, order="F")
    scale = err = 0.0
    for j in range(0, D.shape[1], CONVERT_BLOCK):
        block = np.asarray(D[:, j:j + CONVERT_BLOCK])
        try:
            rounded = round_block(block, target)
        except ValueError:
            raise BundleError(f"cannot store D of {gf.path} as {name}: its entries (up to "
                              f"{np.abs(block).max():.3g}) overflow {name}") from None
        cast[:, j:j + CONVERT_BLOCK] = rounded.values
        scale = max(scale, rounded.max_abs)
        err = max(err, rounded.max_abs_error)
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
