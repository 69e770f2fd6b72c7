"""Atomic file writes: a file is either its old self or complete, never half-written.

Use::

    from runtime.atomic import replacing, write_text_atomic
    write_text_atomic("summary.json", text)
    with replacing("reference.npz") as tmp:   # any writer that takes a path
        np.savez(tmp, u=u)

(Bundles, which are directories, have their own atomic writer in
:mod:`runtime.bundle`.)
"""

from __future__ import annotations

import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

__all__ = ["replacing", "write_text_atomic"]


@contextmanager
def replacing(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary sibling of ``path`` to write; it replaces ``path`` when the
    block ends normally (one rename) and is removed if the block raises.

    The temporary keeps ``path``'s suffix (writers such as ``numpy.savez`` add
    theirs otherwise). The parent folder must exist.
    """
    path = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` atomically (see :func:`replacing`); returns the path."""
    with replacing(path) as tmp:
        tmp.write_text(text)
    return Path(path)
