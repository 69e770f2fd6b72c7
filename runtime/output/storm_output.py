"""A storm's outputs written as a unit: :class:`StormOutput`.

Frames are streamed to disk as the storm records them (memory stays flat in the
duration), everything goes into a hidden temporary sibling of the output
directory, and one rename puts the complete set in place. An interrupted or
failed run leaves nothing; a rerun replaces only a directory that holds
exactly a previous storm output (recognised by :data:`STORM_MANIFEST`, the list
of files the project wrote), and refuses any other non-empty directory; the
temporary directories of killed storms are swept (:func:`clean_stale_partials`).

Use::

    from hailstorm.runtime.output.storm_output import StormOutput
    with StormOutput("run1", gf) as out:           # checks "run1" can be written, first
        result = hailstorm.runtime.run_storm(gf, scene, on_frame=out.add)
        out.finish(result)                         # the series, summary.json, storm.mp4: then in place

What goes into the files is :mod:`hailstorm.runtime.output.files`'.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

from hailstorm.runtime.bundle.atomic import probe_writable, sibling_name_problem
from hailstorm.runtime.output.animation import write_animation
from hailstorm.runtime.output.files import ParaviewSeries, write_impacts, write_summary
from hailstorm.runtime.output.impacts import read_impacts
from hailstorm.runtime.resources import missing_module, require_extras

__all__ = ["SERIES_FORMATS", "STORM_MANIFEST", "OutputError", "StormOutput", "check_storm_out",
           "clean_stale_partials"]

_log = logging.getLogger(__name__)

#: the file, in a storm's output directory, that lists every file the storm wrote
STORM_MANIFEST = "hailstorm-storm.json"
#: the ParaView time series a storm output may hold: one VTKHDF file, or ``.vtu`` files per frame
SERIES_FORMATS = ("vtkhdf", "vtu")
_MANIFEST_FORMAT = "hailstorm-storm-output"

def _bytes(n: float) -> str:
    """A byte count in the largest fitting unit, three digits: '3.2 GiB', '150 KiB', '512 B'."""
    for unit, k in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n >= k:
            return f"{n / k:.3g} {unit}"
    return f"{int(n)} B"


class OutputError(ValueError):
    """An output directory cannot be written, or writing it would overwrite files
    hailstorm did not write."""


def _listing(out: Path) -> tuple[list[str], list[str]]:
    """Files and directories under ``out`` (relative POSIX paths), depth first."""
    files, dirs = [], []
    for root, dnames, fnames in os.walk(out):
        rel = Path(root).relative_to(out)
        files += [(rel / f).as_posix() for f in fnames]
        dirs += [(rel / d).as_posix() for d in dnames]
    return sorted(files), sorted(dirs)


def _our_files(out: Path) -> set[str] | None:
    """The files a previous storm output in ``out`` lists (its manifest included), or
    None if ``out`` holds no readable storm manifest."""
    try:
        m = json.loads((out / STORM_MANIFEST).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(m, dict) or m.get("format") != _MANIFEST_FORMAT or not isinstance(m.get("files"), list):
        return None
    return {str(f) for f in m["files"]} | {STORM_MANIFEST}


#: how many foreign entries :func:`_foreign` collects before it stops (the message names five)
_FOREIGN_SHOWN = 6


def _foreign(out: Path, limit: int = _FOREIGN_SHOWN) -> list[str]:
    """What in the existing directory ``out`` hailstorm did not write (empty: ``out`` is
    empty or holds exactly a previous storm output), at most ``limit`` entries.

    The scan is bounded: without a storm manifest the first entries of ``out`` are
    foreign (nothing is descended into); with one, only the directories the manifest
    lists are descended into, a file it does not list or a directory that holds none
    of its files is foreign (and not descended into), and the scan stops at the
    ``limit``-th foreign entry. So it visits at most the manifest's entries plus
    ``limit``, whatever lies under ``out`` (``--out $HOME`` is refused at once).
    """
    ours = _our_files(out)
    found: list[str] = []
    if ours is None:
        with os.scandir(out) as it:
            for e in it:
                found.append(e.name + ("/" if e.is_dir(follow_symlinks=False) else ""))
                if len(found) >= limit:
                    break
        return sorted(found)
    parents = {p.as_posix() for f in ours for p in Path(f).parents} - {"."}
    todo = [""]
    while todo and len(found) < limit:
        rel = todo.pop()
        with os.scandir(out / rel if rel else out) as it:
            for e in it:
                name = f"{rel}/{e.name}" if rel else e.name
                if e.is_dir(follow_symlinks=False):
                    if name in parents:
                        todo.append(name)
                        continue
                    found.append(name + "/")
                elif name not in ours:
                    found.append(name)
                if len(found) >= limit:
                    break
    return sorted(found)


def check_storm_out(out: str | os.PathLike) -> None:
    """Check that a storm may write its outputs to ``out`` (nothing is written).

    ``out`` may be new, an empty directory, or a directory holding exactly a
    previous storm output (the files listed by its :data:`STORM_MANIFEST`),
    which a new run replaces as a whole.

    Raises
    ------
    OutputError
        ``out`` is a file, is not writable, or holds files hailstorm did not
        write (named in the message, which is one line).
    """
    out = Path(out)
    too_long = sibling_name_problem(out, _PARTIAL)
    if too_long is not None:
        raise OutputError(f"cannot write --out: {too_long}")
    if out.exists() or out.is_symlink():
        if not out.is_dir():
            raise OutputError(f"--out {out} exists and is not a directory; refusing to overwrite it")
        foreign = _foreign(out)
        if foreign:
            shown = ", ".join(foreign[:5]) + (" and more" if len(foreign) > 5 else "")
            raise OutputError(f"--out {out} holds files that are not a hailstorm storm output ({shown}); "
                              "refusing to overwrite it (choose an empty or new directory)")
        if not os.access(out, os.W_OK | os.X_OK):
            raise OutputError(f"--out {out} is not writable")
    try:
        probe_writable(out.absolute().parent)
    except NotADirectoryError as exc:
        raise OutputError(f"cannot create --out {out}: {exc.filename} is not a directory") from None
    except OSError as exc:
        where = Path(exc.filename).parent if exc.filename else out.absolute().parent
        raise OutputError(f"cannot write --out {out}: {where}: {exc.strerror or exc}") from None


class StormOutput:
    """A storm's output directory, written as a unit.

    :meth:`open` (or ``with``) checks ``out`` (:func:`check_storm_out`) and
    the free disk space, then creates a hidden temporary sibling of ``out``;
    :meth:`add` writes each frame there as the storm records it; :meth:`finish`
    writes the ``.pvd`` collections, ``summary.json``, the animation and the
    manifest :data:`STORM_MANIFEST`, and ``impacts.csv`` (:func:`impacts_csv`), and renames the directory into place
    (replacing a previous storm output). Leaving the ``with`` block without
    :meth:`finish` (an error, Ctrl-C) removes the temporary directory and
    leaves ``out`` as it was.

    Parameters
    ----------
    out : path
        The output directory.
    gf : GreensFunctions
        The bundle the storm runs on.
    video : bool
        Render ``storm.mp4`` (GIF fallback) from the written frames.
    disk_bytes : int, optional
        Expected size of the outputs (:meth:`hailstorm.runtime.storm.scene.Scene.estimate`):
        refused up front if the file system has less free space.
    progress : bool
        A tqdm bar while rendering.
    series : {"vtkhdf", "vtu"}, optional
        The ParaView time series: one ``storm.vtkhdf`` (:class:`hailstorm.runtime.output.vtkhdf.VTKHDFSeries`,
        the ``series`` extra) or ``storm.pvd`` with two ``.vtu`` files per frame
        (:class:`ParaviewSeries`, for readers older than VTK 9.4 / ParaView 5.13); default:
        ``"vtkhdf"`` when h5py is installed, else ``"vtu"``.
    video_options : dict, optional
        Keywords of :func:`write_animation` (``style``, ``dents``, ``max_frames``, ``size``, ...);
        its ``impacts`` are the ``impacts.csv`` written beside it.

    Raises
    ------
    ValueError
        An unknown ``series``.
    """

    def __init__(self, out: str | os.PathLike, gf: Any, *, video: bool = True, disk_bytes: int | None = None,
                 progress: bool = False, series: str | None = None,
                 video_options: dict[str, Any] | None = None) -> None:
        if series is None:
            series = "vtkhdf" if missing_module("series") is None else "vtu"
        if series not in SERIES_FORMATS:
            raise ValueError(f"unknown series format {series!r}; choose from {', '.join(SERIES_FORMATS)}")
        self.series_format = series
        self.out = Path(out)
        self.gf = gf
        self.video = video
        self.video_options = dict(video_options or {})
        self.disk_bytes = disk_bytes
        self.progress = progress
        self.staging: Path | None = None
        self.series: ParaviewSeries | None = None
        self.files: list[str] = []
        self.committed = False
        self._lock_fd: int | None = None
        self._before: tuple | None = None

    def __enter__(self) -> "StormOutput":
        try:
            self.open()
        except BaseException:  # (a signal inside open(): __exit__ would not run)
            self.abort()
            raise
        return self

    def __exit__(self, *exc: Any) -> None:
        if not self.committed:
            self.abort()

    def open(self) -> None:
        """Check ``out`` and create the temporary directory (see the class notes).

        Raises
        ------
        OutputError
            See :func:`check_storm_out`; or not enough free disk space.
        MissingExtra
            ``video`` without the video extra installed (before anything is written).
        """
        if self.video:
            require_extras("video", "the storm's animation", hint="(or skip it: video=False, --no-video)")
        if self.series_format == "vtkhdf":
            require_extras("series", "the storm's one-file time series (storm.vtkhdf)",
                           hint="(or the per-frame files: series='vtu', --series vtu)")
        check_storm_out(self.out)
        parent = self.out.absolute().parent
        try:
            parent.mkdir(parents=True, exist_ok=True)
            if self.disk_bytes is not None:
                free = shutil.disk_usage(parent).free
                if self.disk_bytes > free:
                    raise OutputError(f"the outputs need about {_bytes(self.disk_bytes)} but {parent} has "
                                      f"{_bytes(free)} free (lower [output] fps or the duration)")
            clean_stale_partials(self.out)
            running = _running_partials(self.out)
            if running:
                raise OutputError(f"another storm is writing --out {self.out} now ({running[0]}); wait for it "
                                  "or choose another --out")
            self._before = _state(self.out)
            self.staging = Path(tempfile.mkdtemp(prefix=f".{self.out.name}{_PARTIAL}", dir=parent))
            self._lock_fd = _hold_lock(self.staging / _PARTIAL_LOCK)
        except OSError as exc:
            raise OutputError(f"cannot write --out {self.out}: {exc.strerror or exc}") from None
        if self.series_format == "vtkhdf":
            from hailstorm.runtime.output.vtkhdf import VTKHDFSeries

            self.series = VTKHDFSeries(self.gf, self.staging)
        else:
            self.series = ParaviewSeries(self.gf, self.staging)

    def add(self, frame: Any) -> None:
        """Write one recorded frame (the storm's ``on_frame`` callback)."""
        assert self.series is not None, "StormOutput.open() first"
        self.series.add(frame)

    def __call__(self, frame: Any) -> None:
        self.add(frame)

    def finish(self, result: Any) -> dict[str, Path]:
        """Write the collections, the summary and the animation; put the directory in place.

        Returns
        -------
        dict
            ``{"summary", "impacts", "paraview", "stones", "video"}`` -> final paths
            (``paraview``: ``storm.vtkhdf`` or ``storm.pvd``; ``stones`` only with the ``.vtu``
            series, ``video`` only when rendered; it may be the GIF fallback).
        """
        assert self.series is not None and self.staging is not None, "StormOutput.open() first"
        series, staging = self.series, self.staging
        if len(series) == 0:  # the result's frames were kept in memory instead of streamed
            for f in result.frames:
                series.add(f)
        series.close()
        result.stats.frames = len(series)  # the summary counts the files it describes
        write_summary(result, staging / "summary.json", self.gf)
        write_impacts(result.stats, staging / "impacts.csv")
        files = [*series.files(), "summary.json", "impacts.csv"]
        video = None
        if self.video:
            frames = series.frames()
            try:
                video = write_animation(frames, self.gf, staging / "storm.mp4",
                                        history=getattr(result, "history", None), progress=self.progress,
                                        impacts=read_impacts(staging / "impacts.csv"), **self.video_options)
            finally:
                getattr(frames, "close", lambda: None)()  # (the .vtkhdf reader holds its file open)
            files.append(video.name)
        manifest = {"format": _MANIFEST_FORMAT, "version": 1, "files": sorted(files)}
        (staging / STORM_MANIFEST).write_text(json.dumps(manifest, indent=1) + "\n")
        self._commit()
        paths = {"summary": self.out / "summary.json", "impacts": self.out / "impacts.csv",
                 "paraview": self.out / series.files()[0]}
        if isinstance(series, ParaviewSeries):
            paths["stones"] = self.out / f"{series.name}_stones.pvd"
        if video is not None:
            paths["video"] = self.out / video.name
        return paths

    def _commit(self) -> None:
        staging, out = self.staging, self.out
        assert staging is not None
        if _state(out) != self._before:  # another storm (or the user) wrote --out during the run
            self._keep()  # kept, and named: never silently replaced, never lost
            raise OutputError(f"--out {out} was written by another run while this storm ran; not replacing it: "
                              f"this storm's results are in {staging}")
        for where, what in ((staging.parent, "its folder"), (out, "--out")):
            if where.exists() and not _writable(where):  # made read-only during the run: nothing is replaced
                self._keep()
                raise OutputError(f"cannot put the results in place: {what} {where} became read-only during the "
                                  f"run; --out is as it was, and this storm's results are in {staging}")
        (staging / _PARTIAL_LOCK).unlink(missing_ok=True)  # the flock stays on the open descriptor
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(staging, 0o777 & ~umask)  # mkdtemp's directory is private; a plain mkdir's is not
        if out.is_dir() and any(out.iterdir()):
            if _foreign(out):  # someone wrote into it during the run: keep both
                self._keep()
                raise OutputError(f"--out {out} changed during the run and now holds other files; "
                                  f"the results are in {staging}")
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}{_OLD}", dir=staging.parent))
            old.rmdir()
            os.replace(out, old)
            os.replace(staging, out)
            self.committed = True
            try:
                _remove_storm_output(old)
            except OSError as exc:  # the new output is in place: the old one's removal is the next run's
                _log.warning("the storm's outputs are in %s; the output it replaced could not be removed from %s "
                             "(%s): the next storm beside it removes it", out, old, exc.strerror or exc)
        else:
            os.replace(staging, out)  # a new name, or over an empty directory
            self.committed = True
        self.staging = None
        self._release()

    def _keep(self) -> None:
        """The results stay in the temporary directory, which the error names: not removed by
        :meth:`abort`, and without its lock file, so that the next storm's sweep
        (:func:`clean_stale_partials`) leaves them to the user instead of taking them for a
        killed storm's."""
        assert self.staging is not None
        try:
            (self.staging / _PARTIAL_LOCK).unlink(missing_ok=True)  # the flock stays on the open descriptor
        except OSError as exc:  # pragma: no cover - the directory itself made read-only
            _log.warning("could not mark %s as kept (%s): the next storm beside it may remove it",
                         self.staging, exc.strerror or exc)
        self.staging = None
        self._release()

    def _release(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def abort(self) -> None:
        """Remove the temporary directory (everything in it was written here)."""
        try:
            if self.series is not None and not isinstance(self.series, ParaviewSeries):
                self.series.close()  # the .vtkhdf file still open in it
        except Exception as exc:  # a write cut short by a signal can leave the file unclosable: removed anyway
            _log.debug("closing the series of an aborted storm failed (%s)", exc)
        finally:
            if self.staging is not None:
                shutil.rmtree(self.staging, ignore_errors=True)
                self.staging = None
            self._release()


#: the infix of a storm's temporary output directory, ``.OUT.partial-XXXX``
_PARTIAL = ".partial-"
#: the infix of a replaced storm output on its way out, ``.OUT.old-XXXX``
_OLD = ".old-"


def _writable(path: Path) -> bool:
    """Whether this process may create and remove entries in the directory ``path``."""
    return os.access(path, os.W_OK | os.X_OK)
#: a file in that directory that its writer holds an flock on for as long as it runs
_PARTIAL_LOCK = ".hailstorm-writing"


def _hold_lock(path: Path) -> int:
    """Create ``path`` and hold an exclusive flock on it; returns the descriptor."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # a new file: never contended
    return fd


def _state(out: Path) -> tuple:
    """What identifies ``out``'s content for a writer that replaces it: absent, or its
    manifest's bytes (a storm output), or its listing's first entries (anything else)."""
    if not out.exists():
        return ("absent",)
    try:
        return ("manifest", (out / STORM_MANIFEST).read_bytes())
    except OSError:
        pass
    try:
        with os.scandir(out) as it:
            return ("listing", tuple(sorted(e.name for _, e in zip(range(64), it))))
    except OSError:
        return ("unreadable",)


def _running_partials(out: Path) -> list[Path]:
    """The temporary directories of storms writing ``out`` now (their lock is held)."""
    running = []
    for d in sorted(out.absolute().parent.glob(f".{out.name}{_PARTIAL}*")):
        lock = d / _PARTIAL_LOCK
        try:
            fd = os.open(lock, os.O_RDWR)
        except OSError:
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            fcntl.flock(fd, fcntl.LOCK_UN)
        except BlockingIOError:
            running.append(d)
        finally:
            os.close(fd)
    return running


def clean_stale_partials(out: str | os.PathLike) -> list[Path]:
    """Remove the temporary directories (``.NAME.partial-*``) that killed storms
    (SIGKILL, a power cut) left beside ``out``, whatever ``--out`` they were writing
    (as bundle writers clean their whole folder), and the replaced outputs
    (``.NAME.old-*``) a storm could not remove; returns the removed paths.

    Only a directory whose writer's lock file is present and not locked is removed
    (its writer is gone); a running storm's, or one without the lock file (not
    certainly ours), is left alone. Of a replaced output only the files its storm
    manifest lists go (as when it was replaced).
    """
    out = Path(out)
    parent = out.absolute().parent
    removed: list[Path] = []
    try:
        candidates = sorted(parent.glob(f".*{_PARTIAL}*"))
        replaced = sorted(parent.glob(f".*{_OLD}*"))
    except OSError:
        return removed
    for d in replaced:
        if d.is_symlink() or not d.is_dir() or not (d / STORM_MANIFEST).is_file():
            continue
        try:
            _remove_storm_output(d)
        except OSError as exc:
            _log.warning("could not remove a replaced storm output %s (%s)", d, exc.strerror or exc)
            continue
        if not d.exists():
            _log.info("removed a replaced storm output %s", d)
            removed.append(d)
    for d in candidates:
        lock = d / _PARTIAL_LOCK
        if d.is_symlink() or not d.is_dir() or not lock.is_file():
            continue
        try:
            fd = os.open(lock, os.O_RDWR)
        except OSError:
            continue
        try:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                continue  # a storm is writing it
            shutil.rmtree(d, ignore_errors=True)
            if d.exists():
                _log.warning("could not remove a killed storm's temporary output %s", d)
            else:
                _log.info("removed a killed storm's temporary output %s", d)
                removed.append(d)
        finally:
            os.close(fd)
    return removed


def _remove_storm_output(path: Path) -> None:
    """Delete a replaced storm output: the files its manifest lists, then the emptied
    directories; anything else is left in place (and reported)."""
    ours = _our_files(path) or set()
    for f in ours:
        (path / f).unlink(missing_ok=True)
    _, dirs = _listing(path)
    for d in sorted(dirs, key=lambda d: -d.count("/")) + ["."]:
        try:
            (path / d).rmdir()
        except OSError:
            pass
    if path.exists():
        _log.warning("the replaced storm output kept files it did not list: %s", path)

