"""Fingerprint of five storm configurations: a refactor check (bit-identical or explained).

Usage::

    python tests/benchmarks/storm_fingerprint.py --write /tmp/fp/baseline.json     # record
    python tests/benchmarks/storm_fingerprint.py --compare /tmp/fp/baseline.json   # check

Runs, on the default seat bundle (the one ``hailstorm storm`` builds and caches, or
``--gf DIR``), five short storms: the default scene; ``exact`` at dt 0.1 ms; point
contacts (``patch = "none"``); ``symplectic``; a 400-stone storm. For each it hashes
(sha256) every recorded array (frames: time, stone positions, ids, radii, contact
counts, surface displacement and peak displacement; the force history) and the
statistics (minus wall-clock figures), and prints a few headline numbers. ``--write``
stores the fingerprint (JSON) and the arrays themselves (``.npz`` beside it), so that
``--compare`` can report, for any array that differs, its max abs / rel difference.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import numpy as np

#: statistics that are wall-clock or environment, not the storm's result
_VOLATILE = {"wall_time_s", "setup_time_s", "compile_time_s", "real_time_factor", "output_time_s", "inertia_time_s", "backend"}

#: the fingerprint's reference storms: the default scene as it was when the baseline was first
#: recorded (the packaged default's rate has since risen to 1000 stones/s, for the video)
BASE: dict[str, dict] = {"storm": {"rate": 200.0}}

#: name -> changes to the default scene's sections
CONFIGS: dict[str, dict[str, dict]] = {
    "default": {},
    "exact-dt1e-4": {"time": {"integrator": "exact", "dt": 1e-4}},
    "point": {"contact": {"patch": "none"}},
    "symplectic": {"time": {"integrator": "symplectic"}},
    "stones400": {"storm": {"stones": 400, "duration": 0.4}},
}


def run(gf, changes: dict[str, dict]) -> tuple[dict[str, np.ndarray], dict]:
    """Arrays and statistics of one configuration."""
    from hailstorm.runtime import Scene, run_storm

    d = Scene.default().to_dict()
    for sec, body in (*BASE.items(), *changes.items()):
        d[sec].update(body)
    res = run_storm(gf, Scene.from_dict(d), progress=False, keep_frames=True)
    fr = res.frames
    arrays = {
        "t": np.array([f.t for f in fr]),
        "contacts": np.array([f.contacts for f in fr]),
        "ids": np.concatenate([f.ids for f in fr]),
        "positions": np.concatenate([f.positions for f in fr]),
        "radii": np.concatenate([f.radii for f in fr]),
        "displacement": np.stack([f.displacement for f in fr]),
        "peak_displacement": np.stack([f.peak_displacement for f in fr]),
        "history": res.history,
    }
    stats = {k: v for k, v in res.stats.items() if k not in _VOLATILE}
    return arrays, stats


def sha(a: np.ndarray) -> str:
    a = np.ascontiguousarray(a)
    return hashlib.sha256(str(a.dtype).encode() + str(a.shape).encode() + a.tobytes()).hexdigest()


def fingerprint(gf, names: list[str]) -> tuple[dict, dict[str, np.ndarray]]:
    out: dict = {}
    raw: dict[str, np.ndarray] = {}
    for name in names:
        arrays, stats = run(gf, CONFIGS[name])
        out[name] = {
            "arrays": {k: sha(v) for k, v in arrays.items()},
            "stats_sha": hashlib.sha256(json.dumps(stats, sort_keys=True, default=str).encode()).hexdigest(),
            "stats": stats,
            "headline": {k: stats.get(k) for k in ("hailstones", "impacts", "stones_hit", "max_contact_force",
                                                   "max_indentation_m", "steps", "substeps")},
        }
        raw.update({f"{name}/{k}": v for k, v in arrays.items()})
        h = out[name]["headline"]
        print(f"{name:14s} stones {h['hailstones']:4d} impacts {h['impacts']:4d} hit {h['stones_hit']:4d} "
              f"max force {h['max_contact_force']:8.3f} N  indent {h['max_indentation_m'] * 1e3:.4f} mm  "
              f"substeps {h['substeps']}", flush=True)
    return out, raw


def compare(new: dict, new_raw: dict[str, np.ndarray], path: Path) -> bool:
    old = json.loads(path.read_text())
    old_raw = np.load(path.with_suffix(".npz"))
    same = True
    for name, fp in new.items():
        if name not in old:
            continue
        for k, h in fp["arrays"].items():
            if old[name]["arrays"].get(k) == h:
                continue
            same = False
            a, b = old_raw[f"{name}/{k}"], new_raw[f"{name}/{k}"]
            if a.shape != b.shape:
                print(f"DIFF {name}/{k}: shape {a.shape} -> {b.shape}")
                continue
            d = np.abs(a.astype(np.float64) - b.astype(np.float64))
            scale = np.abs(a.astype(np.float64)).max()
            print(f"DIFF {name}/{k}: max abs {d.max():.3e}, max abs / max |value| {d.max() / max(scale, 1e-300):.3e}")
        if old[name]["stats_sha"] != fp["stats_sha"]:
            same = False
            for k in sorted(set(old[name]["stats"]) | set(fp["stats"])):
                a, b = old[name]["stats"].get(k), fp["stats"].get(k)
                if a != b:
                    print(f"DIFF {name} stats[{k!r}]: {a!r} -> {b!r}")
    print("IDENTICAL" if same else "DIFFERENT")
    return same


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--gf", help="bundle directory (default: the default seat's, built or reused from the cache)")
    g = ap.add_mutually_exclusive_group(required=True)
    g.add_argument("--write", type=Path, help="store the fingerprint here (and the arrays beside it, .npz)")
    g.add_argument("--compare", type=Path, help="compare with a stored fingerprint")
    ap.add_argument("--configs", default=",".join(CONFIGS))
    args = ap.parse_args()

    import hailstorm.runtime
    from hailstorm.runtime.storm.scene import SeatSettings

    if args.gf:
        path = args.gf
    else:
        from hailstorm.precompute import build_bundle

        seat = SeatSettings.default()
        path = build_bundle(None, mesh_size=seat.mesh_size, order=seat.order, load=seat.load,
                            volume_size=seat.volume_size, young=seat.young, poisson=seat.poisson)
    gf = hailstorm.runtime.load(path)
    fp, raw = fingerprint(gf, args.configs.split(","))
    if args.write:
        args.write.parent.mkdir(parents=True, exist_ok=True)
        args.write.write_text(json.dumps(fp, indent=1, sort_keys=True, default=str))
        np.savez(args.write.with_suffix(".npz"), **raw)
        print(f"written {args.write}")
    else:
        sys.exit(0 if compare(fp, raw, args.compare) else 1)


if __name__ == "__main__":
    main()
