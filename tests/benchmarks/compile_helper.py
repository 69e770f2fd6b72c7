"""What the first run's compile helper buys: a cold storm with it against one without.

Usage::

    python tests/benchmarks/compile_helper.py [--gf DIR] [--pairs 3] [--out FILE]

Runs ``hailstorm storm`` (a short storm without video on the bundle ``--gf``, by
default the default seat, built or reused from the cache by a first, uncounted run) in an empty numba cache
(``NUMBA_CACHE_DIR`` a new temporary directory each run), alternately with the
compile helper (the default) and with ``HAILSTORM_COMPILE_WORKERS=1`` (one process),
``--pairs`` times, and prints each one's wall and CPU seconds (the CPU of the command
and of the helper processes it started) as min / median / max, and the ratio
with / without pair by pair (so that a drift of the machine's speed cancels).
``--out FILE`` also writes what it prints, with the command, the date, the commit and
the load, for the documentation.
"""

from __future__ import annotations

import sys
from pathlib import Path

# the studies (notebooks/studies) are in the repository, not in the package
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "notebooks"))

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def cold_storm(where: list[str], one_process: bool, out: Path) -> tuple[float, float]:
    """(wall, CPU) seconds of one ``hailstorm storm`` in an empty numba cache."""
    env = dict(os.environ)
    env["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="hailstorm-cold-")
    if one_process:
        env["HAILSTORM_COMPILE_WORKERS"] = "1"
    else:
        env.pop("HAILSTORM_COMPILE_WORKERS", None)
    cmd = [sys.executable, "-m", "hailstorm", "storm", *where, "--duration", "0.05", "--no-video", "-q",
           "--out", str(out)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, env=env, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu


def _row(name: str, x: np.ndarray, fmt: str = "{:7.1f}") -> str:
    return f"  {name:28s} " + " / ".join(fmt.format(v) for v in (x.min(), np.median(x), x.max()))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gf", help="bundle directory (default: the default seat's, built or reused from the cache)")
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument("--out", type=Path, help="also write the output (with command, date, commit, load) here")
    args = ap.parse_args(argv)
    if args.pairs < 1:
        ap.error("--pairs must be at least 1")
    where = [] if args.gf is None else ["--gf", args.gf]
    with tempfile.TemporaryDirectory() as tmp:  # the default seat built (or reused) outside the timings
        subprocess.run([sys.executable, "-m", "hailstorm", "storm", *where, "--duration", "0.01", "--no-video", "-q",
                        "--out", str(Path(tmp) / "warm")], check=True, stdout=subprocess.DEVNULL)
    lines: list[str] = []

    def say(s: str = "") -> None:
        print(s, flush=True)
        lines.append(s)

    from studies import record

    stamp = record.stamp()  # date, commit, load before the runs
    rows = {True: [], False: []}
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.pairs):
            for one in (False, True):  # in turn: with the helper, then in one process
                wall, cpu = cold_storm(where, one, Path(tmp) / f"out-{i}-{int(one)}")
                rows[one].append((wall, cpu))
                say(f"pair {i + 1}: {'one process' if one else 'with the helper'}: wall {wall:.1f} s, CPU {cpu:.1f} s")
    w = {k: np.array([r[0] for r in v]) for k, v in rows.items()}
    c = {k: np.array([r[1] for r in v]) for k, v in rows.items()}
    say()
    say(f"cold first storm, {args.pairs} pairs, min / median / max [s]:")
    say(_row("wall, with the helper", w[False]))
    say(_row("wall, one process", w[True]))
    say(_row("CPU, with the helper", c[False]))
    say(_row("CPU, one process", c[True]))
    say(_row("wall ratio, pair by pair", w[False] / w[True], "{:7.2f}"))
    say(_row("CPU ratio, pair by pair", c[False] / c[True], "{:7.2f}"))
    if args.out is not None:
        cmd = "python tests/benchmarks/compile_helper.py" + (f" --pairs {args.pairs}" if args.pairs != 3 else "")
        record.write_run(args.out, cmd, stamp, lines)


if __name__ == "__main__":
    main()
