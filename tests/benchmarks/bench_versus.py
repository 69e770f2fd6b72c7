"""Benchmark: the storm loop of this tree against a baseline tree, paired rounds in one run.

Usage::

    git worktree add /tmp/base 3836154                        # the baseline, once
    python tests/benchmarks/bench_versus.py --baseline /tmp/base                  # default scene, 0.4 s, 5 rounds
    python tests/benchmarks/bench_versus.py --baseline /tmp/base --rate 1000 --duration 2 --dt 5e-4
    python tests/benchmarks/bench_versus.py --baseline /tmp/base --out docs/_generated/versus.txt

Each round runs the same storm (the default scene on the default seat, inertia pass off,
optionally another rate, duration or step) once in this tree and once in the baseline, each
in a fresh process whose ``import hailstorm`` is that tree (a temporary directory on
``PYTHONPATH`` with a ``hailstorm`` link to it), in alternating order. Each process first
runs a short storm (loading, the first time compiling, its kernels), then the measured one,
and reports its loop's real-time factor (``StormStats.real_time_factor``: simulated time over
the loop's wall time, frames included, set-up and compile excluded) and its impacts (the same
storm in both: a check that the two trees ran the same physics). Printed: min / median / max
of each side's factor and of the paired ratio (this / baseline, per round: the machine is
shared, and a round's two runs see about the same load).
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "notebooks"))

import argparse
import json
import os
import statistics
import subprocess
import tempfile

ROOT = Path(__file__).resolve().parents[2]

#: what each process runs: argv[1] the scene overrides (JSON); prints one JSON line
CHILD = """
import json, sys
import hailstorm
from hailstorm.runtime import Scene, run_storm
from hailstorm.runtime.storm.scene import SeatSettings
over = json.loads(sys.argv[1])
gf = hailstorm.runtime.load(over.pop("gf")) if over.get("gf") else None
if gf is None:
    from studies.resolution_study import seat_bundle
    gf = seat_bundle(SeatSettings.default().mesh_size)
d = Scene.default().to_dict()
d["validity"]["inertia"] = False
for section, key, value in over["set"]:
    d[section][key] = value
warm = json.loads(json.dumps(d))
warm["storm"]["duration"] = min(0.02, d["storm"]["duration"])
run_storm(gf, Scene.from_dict(warm), progress=False, on_frame=lambda f: None)
st = run_storm(gf, Scene.from_dict(d), progress=False, on_frame=lambda f: None).stats
print(json.dumps({"rtf": st.real_time_factor, "impacts": st.impacts, "hailstones": st.hailstones,
                  "file": hailstorm.__file__}))
"""


def one(tree: Path, over: dict, env: dict) -> dict:
    """One measured run in a fresh process importing ``tree`` as ``hailstorm``."""
    with tempfile.TemporaryDirectory() as tmp:
        (Path(tmp) / "hailstorm").symlink_to(tree.resolve(), target_is_directory=True)
        path = os.pathsep.join([tmp, str(ROOT / "notebooks")])
        out = subprocess.run([sys.executable, "-c", CHILD, json.dumps(over)], capture_output=True, text=True,
                             env=dict(env, PYTHONPATH=path), check=True).stdout
    res = json.loads(out.strip().splitlines()[-1])
    if not res["file"].startswith(tmp):
        raise RuntimeError(f"the run imported {res['file']}, not {tree}")
    return res


def mmm(values: list[float], fmt: str = ".3f") -> str:
    return " / ".join(format(v, fmt) for v in (min(values), statistics.median(values), max(values)))


def run(args: argparse.Namespace) -> None:
    sets = [("storm", "duration", float(args.duration))]
    if args.rate is not None:
        sets.append(("storm", "rate", float(args.rate)))
    if args.dt is not None:
        sets.append(("time", "dt", float(args.dt)))
    over = {"gf": args.gf, "set": sets}
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    trees = {"this": ROOT, "baseline": Path(args.baseline)}
    rtf: dict[str, list[float]] = {"this": [], "baseline": []}
    impacts: dict[str, set[int]] = {"this": set(), "baseline": set()}
    for r in range(args.rounds):
        order = ("this", "baseline") if r % 2 == 0 else ("baseline", "this")
        for side in order:
            res = one(trees[side], over, env)
            rtf[side].append(res["rtf"])
            impacts[side].add(int(res["impacts"]))
    ratio = [a / b for a, b in zip(rtf["this"], rtf["baseline"])]
    print(f"default scene, {', '.join(f'[{s}] {k} = {v:g}' for s, k, v in sets)}; inertia pass off; "
          f"{args.rounds} paired rounds, fresh processes, one BLAS thread")
    print(f"baseline tree: {args.baseline}")
    print(f"{'':10s} {'real-time factor (min / median / max)':>40s}   impacts")
    for side in ("this", "baseline"):
        print(f"{side:10s} {mmm(rtf[side]):>40s}   {', '.join(map(str, sorted(impacts[side])))}")
    print(f"{'this / baseline, paired':24s} {mmm(ratio, '.2f'):>26s}")


def main(argv: list[str] | None = None) -> None:
    from studies import record

    argv = sys.argv[1:] if argv is None else list(argv)
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", required=True, help="the baseline tree (a git worktree of the commit to compare)")
    ap.add_argument("--gf", help="bundle directory (default: the default seat, built or reused from the cache)")
    ap.add_argument("--duration", type=float, default=0.4)
    ap.add_argument("--rate", type=float, default=None, help="stones per second (default: the scene's)")
    ap.add_argument("--dt", type=float, default=None, help="the step [s] (default: the scene's)")
    ap.add_argument("--rounds", type=int, default=5)
    record.add_out_option(ap)
    args = ap.parse_args(argv)
    if not (Path(args.baseline) / "__init__.py").is_file():
        ap.error(f"--baseline {args.baseline} is not a hailstorm tree (no __init__.py)")
    record.run_or_record(args.out, "python tests/benchmarks/bench_versus.py", argv, lambda: run(args))


if __name__ == "__main__":
    main()
