"""Atomic file writes: a file is either its old self or complete, never half-written.

Use::

    from hailstorm.runtime.bundle.atomic import replacing, write_text_atomic
    write_text_atomic("summary.json", text)
    with replacing("reference.npz") as tmp:   # any writer that takes a path
        np.savez(tmp, u=u)

(Bundles, which are directories, have their own atomic writer in
:mod:`hailstorm.runtime.bundle.read`.)
"""

from __future__ import annotations

import os
import secrets
import stat
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

__all__ = ["probe_writable", "replacing", "sibling_name_problem", "write_text_atomic"]


@contextmanager
def replacing(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary sibling of ``path`` to write; it replaces ``path`` when the
    block ends normally (one rename) and is removed if the block raises.

    The temporary keeps ``path``'s suffix (writers such as ``numpy.savez`` add
    theirs otherwise). The result has the permissions a plain write would give:
    those of the file it replaces, else the default for new files (the umask
    applies). The parent folder must exist.
    """
    path = Path(path)
    tmp = _create_sibling(path)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _create_sibling(path: Path) -> Path:
    """Create an empty, uniquely named hidden sibling of ``path`` (mode of ``path`` if it
    exists, else ``0o666`` minus the umask, as ``open(path, "w")`` would)."""
    for _ in range(100):
        tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}{path.suffix}"
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        except FileExistsError:  # pragma: no cover - a 48-bit name collision
            continue
        os.close(fd)
        try:
            os.chmod(tmp, stat.S_IMODE(path.stat().st_mode))
        except FileNotFoundError:
            pass
        return tmp
    raise FileExistsError(f"no free temporary name next to {path}")  # pragma: no cover


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (see :func:`replacing`); returns the path."""
    with replacing(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def _nearest_existing(path: Path) -> Path:
    """``path`` (made absolute), or its nearest ancestor that exists."""
    probe = path.absolute()
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    return probe


def probe_writable(directory: str | os.PathLike) -> Path:
    """Check that ``directory`` can be written, or created, before any work is done.

    Probes the directory, or if it does not exist yet its nearest existing
    ancestor, by creating and removing an empty hidden file in it (a real
    probe: permissions, read-only file systems and root's exceptions alike).
    Creates nothing else.

    Returns
    -------
    pathlib.Path
        The directory probed.

    Raises
    ------
    NotADirectoryError
        The nearest existing ancestor is not a directory (its path is the
        exception's ``filename``).
    OSError
        It cannot be written.
    """
    probe = _nearest_existing(Path(directory))
    if not probe.is_dir():
        raise NotADirectoryError(0, "not a directory", str(probe))
    fd, name = tempfile.mkstemp(prefix=".hailstorm-probe-", dir=probe)
    os.close(fd)
    os.unlink(name)
    return probe


#: the random part ``tempfile`` adds to a temporary's name
_RANDOM_CHARS = 8


def sibling_name_problem(path: str | os.PathLike, infix: str) -> str | None:
    """Why the temporaries hailstorm writes beside ``path`` (``.NAME<infix>XXXXXXXX``) cannot
    exist in its folder (their name would exceed the file system's limit), or None.

    A name the user may legally give can be too long for its temporary sibling: said at the
    edge, with the limit, instead of the file system's ``File name too long`` on a name the user
    never gave.
    """
    path = Path(path)
    probe = _nearest_existing(path.absolute().parent)
    try:
        limit = os.pathconf(probe, "PC_NAME_MAX")
    except (OSError, ValueError, AttributeError):  # pragma: no cover - not POSIX, or no such limit
        limit = 255
    extra = len(os.fsencode("." + infix)) + _RANDOM_CHARS
    size = len(os.fsencode(path.name))
    if size + extra <= limit:
        return None
    name = path.name if len(path.name) <= 60 else f"{path.name[:28]}...{path.name[-28:]}"
    return (f"the name {name} is {size} bytes long; hailstorm writes beside it under the name plus {extra} "
            f"(.NAME{infix}XXXXXXXX), so in {probe} it may be at most {limit - extra} bytes long")
