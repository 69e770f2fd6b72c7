"""The header of a measurement written for the documentation (``docs/_generated/*.txt``).

Every script that prints a table the docs include writes, with ``--out FILE``, the
command as a ``$`` line, then :func:`stamp` (UTC date, the code's commit, cores,
load average), then what it printed; :func:`write` puts it in place atomically.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import os
import shlex
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Callable

from hailstorm.runtime.bundle.atomic import replacing, write_text_atomic

__all__ = ["OUT_HELP", "Tee", "add_out_option", "command", "commit", "load_average", "min_median_max", "run_or_record",
           "stamp", "whole_output", "without_out", "write", "write_run"]

#: the help of a script's ``--out FILE`` (:func:`add_out_option`)
OUT_HELP = "also write the printed output to FILE, after a header (command, UTC date, commit, load)"

#: the repository the measurements describe
ROOT = Path(__file__).resolve().parents[2]


def load_average() -> str:
    """The 1, 5 and 15 minute load averages, or "n/a" where the platform has none."""
    try:
        return " ".join(f"{x:.2f}" for x in os.getloadavg())
    except OSError:
        return "n/a"


def commit() -> str:
    """``git rev-parse --short HEAD`` of the repository, followed by the tracked files that differ
    from it outside ``docs/`` and ``notebooks/figures/`` (what the scripts write does not change
    what they measure); "unknown" outside a git checkout (read-only git calls)."""
    try:
        sha = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                             text=True, timeout=30, check=True).stdout.strip()
        status = subprocess.run(["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True, timeout=30, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    changed = [line[3:] for line in status.splitlines()
               if line[3:] and not line[3:].startswith(("docs/", "notebooks/figures/"))]
    if not changed:
        return sha
    more = f" and {len(changed) - 5} more" if len(changed) > 5 else ""
    return f"{sha} with uncommitted changes to {', '.join(changed[:5])}{more}"


def stamp() -> str:
    """``# <UTC date>, code of main at git <commit>, <n> cores, load average before: <load>``."""
    return (f"# {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC, code of main at git {commit()}, "
            f"{os.cpu_count()} cores, load average before: {load_average()}")


def write(path: str | os.PathLike, lines: list[str]) -> Path:
    """The lines (a header and what was printed) into ``path`` (its folder created), atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(path, "\n".join(lines).rstrip("\n") + "\n")


def save_figure(fig: Any, path: str | os.PathLike, dpi: int = 150) -> Path:
    """Save a matplotlib figure to ``path`` (its folder created; PNG or what the suffix says),
    atomically, and close it; returns the path."""
    import matplotlib.pyplot as plt

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with replacing(path) as tmp:
            fig.savefig(tmp, dpi=dpi)
    finally:
        plt.close(fig)
    return path


def write_run(path: str | os.PathLike, command: str, stamp_before: str, lines: list[str]) -> Path:
    """A run's output into ``path``: ``$ command``, the :func:`stamp` taken before the run, the load
    average after it, a blank line, then ``lines`` (:func:`write`)."""
    return write(path, [f"$ {command}", stamp_before, f"# load average after: {load_average()}", "", *lines])


def command(prog: str, argv: list[str] | None) -> str:
    """The command line of a run, as its ``$`` line shows it: ``prog`` and the arguments (``sys.argv``'s
    when ``argv`` is None), shell-quoted."""
    return " ".join([prog, *map(shlex.quote, sys.argv[1:] if argv is None else argv)])


def min_median_max(x, fmt: str = ".3f") -> str:
    """``min/median/max`` of repeated measurements, each formatted with ``fmt``."""
    import numpy as np

    return "/".join(format(v, fmt) for v in (min(x), float(np.median(x)), max(x)))


class Tee(io.TextIOBase):
    """Writes to a stream and keeps a copy (``copy``): what a script prints, for its ``--out`` file."""

    def __init__(self, stream) -> None:
        self.stream, self.copy = stream, io.StringIO()

    def write(self, text: str) -> int:
        self.stream.write(text)
        return self.copy.write(text)

    def flush(self) -> None:
        self.stream.flush()


def without_out(argv: list[str]) -> list[str]:
    """A script's arguments without ``--out FILE`` / ``--out=FILE`` (it does not change what is printed)."""
    keep, skip = [], False
    for a in argv:
        if skip:
            skip = False
        elif a == "--out":
            skip = True
        elif not a.startswith("--out="):
            keep.append(a)
    return keep


def whole_output(path: str | os.PathLike, prog: str, argv: list[str], run) -> Any:
    """Call ``run()``, printing as it goes, and write what it printed to ``path``: the ``$`` line
    (``prog`` and ``argv`` without ``--out``), :func:`stamp` before the run, the output, and the
    run's wall time and the load average after it (:func:`write`: a run that fails leaves an
    earlier file as it was). Returns what ``run`` returns."""
    header = [f"$ {shlex.join([*shlex.split(prog), *without_out(argv)])}", stamp()]
    print("\n".join(header), flush=True)
    tee, t0 = Tee(sys.stdout), time.perf_counter()
    with contextlib.redirect_stdout(tee):
        result = run()
    footer = f"# wall time {time.perf_counter() - t0:.0f} s; load average after: {load_average()}"
    print(footer)
    write(path, [*header, tee.copy.getvalue().rstrip("\n"), footer])
    return result


def add_out_option(ap: argparse.ArgumentParser) -> None:
    """Give a script's parser ``--out FILE`` (default None; :data:`OUT_HELP`), which
    :func:`run_or_record` reads.

    Parameters
    ----------
    ap : argparse.ArgumentParser
        The script's parser.
    """
    ap.add_argument("--out", default=None, metavar="FILE", help=OUT_HELP)


def run_or_record(out: str | os.PathLike | None, prog: str, argv: list[str], run: Callable[[], Any]) -> Any:
    """A script's run as its ``--out`` asks: ``run()`` alone (``out`` None), or through
    :func:`whole_output` to ``out``.

    Parameters
    ----------
    out : path or None
        The ``--out`` file.
    prog : str
        The command that runs the script (the ``$`` line).
    argv : list of str
        The script's arguments.
    run : callable
        The script's work, called without arguments.

    Returns
    -------
    object
        What ``run`` returns.
    """
    if out is None:
        return run()
    return whole_output(out, prog, argv, run)
