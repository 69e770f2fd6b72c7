"""Verification stamps: hash a bundle's array file once per change of the file, not on every load.

:func:`hailstorm.runtime.load` checks every array's SHA-256 (and that D is
finite): about a second per GB, seven seconds for the D of a 10 000-vertex
seat, on *every* load. A stamp records that a file was verified, together with
what identifies that version of the file: device, inode, size, modification
and status-change times (``st_ctime_ns`` moves on any write or ``utime``
and cannot be set back by a user), and the hash it matched. A later load whose
file still has that identity and expects that hash skips the scan; any change
to the file, the manifest's hash or the stamp itself means a full scan again.
A corrupted file is thus refused before it is used, as before, unless it was
corrupted without any change of its metadata (bit rot under an unchanged
inode): ``load(..., rehash=True)`` and ``hailstorm info`` always re-hash.

Stamps live in ``<cache>/verified/`` (:func:`default_cache_dir`), one small
JSON file per array file, written atomically. An unwritable cache only costs
the speed-up.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path

from hailstorm.runtime.bundle.atomic import write_text_atomic

log = logging.getLogger(__name__)

__all__ = ["default_cache_dir", "forget", "is_stamped", "stamp", "stamped_hash"]


def default_cache_dir() -> Path:
    """Where hailstorm caches what it computes: ``$HAILSTORM_CACHE``, else
    ``$XDG_CACHE_HOME/hailstorm``, else ``~/.cache/hailstorm``."""
    env = os.environ.get("HAILSTORM_CACHE")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(Path.home(), ".cache")
    return Path(base) / "hailstorm"


def _identity(path: Path) -> dict[str, int | str]:
    st = path.stat()
    return {"path": str(path.resolve()), "dev": st.st_dev, "ino": st.st_ino, "size": st.st_size,
            "mtime_ns": st.st_mtime_ns, "ctime_ns": st.st_ctime_ns}


def _stamp_file(path: Path) -> Path:
    key = hashlib.sha256(str(path.resolve()).encode()).hexdigest()[:32]
    return default_cache_dir() / "verified" / f"{key}.json"


def is_stamped(path: str | os.PathLike, sha256: str) -> bool:
    """True if ``path``, as it is now, was verified against ``sha256``."""
    return stamped_hash(path) == sha256


def stamped_hash(path: str | os.PathLike) -> str | None:
    """The hash ``path``, as it is now, was stamped with, or None (no stamp, or the file changed since)."""
    path = Path(path)
    try:
        rec = json.loads(_stamp_file(path).read_text())
        if isinstance(rec, dict) and {k: v for k, v in rec.items() if k != "sha256"} == _identity(path):
            sha = rec.get("sha256")
            return sha if isinstance(sha, str) else None
    except (OSError, ValueError):
        pass
    return None


def forget(path: str | os.PathLike) -> None:
    """Remove the stamp of ``path`` (best effort; the file itself is not touched)."""
    try:
        _stamp_file(Path(path)).unlink(missing_ok=True)
    except OSError as exc:
        log.debug("could not remove the stamp of %s: %s", path, exc)


def stamp(path: str | os.PathLike, sha256: str) -> None:
    """Record that ``path``, as it is now, matched ``sha256`` (best effort)."""
    path = Path(path)
    try:
        target = _stamp_file(path)
        target.parent.mkdir(parents=True, exist_ok=True)
        write_text_atomic(target, json.dumps({**_identity(path), "sha256": sha256}))
    except OSError as exc:
        log.debug("could not record the verification of %s: %s", path, exc)
