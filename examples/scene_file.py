"""A scene file: every storm setting in TOML, read, changed and run.

Usage::

    python examples/scene_file.py                  # the whole scene on the default seat (built once, cached)
    python examples/scene_file.py --small          # 0.03 s of it on the small block of examples/geometries

Reads ``examples/scenes/dense_storm.toml`` into a :class:`hailstorm.runtime.Scene`,
prints what it changes from the default, writes a changed copy (``Scene.with_``,
``Scene.to_toml``) and runs the storm from the command line::

    hailstorm storm --scene examples/scenes/dense_storm.toml --out DIR/storm [--gf BUNDLE --duration 0.03]

Outputs go to ``--out`` (default ``./scene-out``).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

from hailstorm import precompute
from hailstorm.runtime import Scene, SeatSettings

HERE = Path(__file__).resolve().parent
SCENE = HERE / "scenes" / "dense_storm.toml"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--small", action="store_true", help="a short storm on a small block (seconds)")
    ap.add_argument("--out", type=Path, default=Path("scene-out"))
    args = ap.parse_args(argv)

    scene, default = Scene.from_toml(SCENE), Scene.default()
    now, before = scene.to_dict(), default.to_dict()
    for section in now:
        for key, value in now[section].items():
            if before[section].get(key) != value:
                print(f"[{section}] {key} = {value!r}   (default {before[section].get(key)!r})")
    print(f"seat (used without --gf): {SeatSettings.from_toml(SCENE)}")

    args.out.mkdir(parents=True, exist_ok=True)
    copy = scene.with_(restitution=0.6, seed=2)   # flat keys, each routed to its section
    copy.to_toml(args.out / "changed.toml", seat=SeatSettings.from_toml(SCENE))
    assert Scene.from_toml(args.out / "changed.toml") == copy   # round trip
    print(f"wrote {args.out / 'changed.toml'}: contact.restitution = {copy.contact.restitution}, "
          f"storm.seed = {copy.storm.seed}")

    cmd = ["storm", "--scene", str(SCENE), "--out", str(args.out / "storm")]
    if args.small:
        gf = precompute.build_bundle(geometry=HERE / "geometries" / "block.geo", mesh_size=0.012, order=1,
                                     young=5e5, poisson=0.4)
        cmd += ["--gf", str(gf), "--duration", "0.03", "--stones", "5", "--no-video", "-q"]
    print("$ hailstorm " + " ".join(cmd), flush=True)
    subprocess.run([sys.executable, "-m", "hailstorm", *cmd], check=True)
    s = json.loads((args.out / "storm" / "summary.json").read_text())
    print(f"ran: integrator {s['integrator']}, dt {s['dt']:g} s, {s['hailstones']} stones, {s['impacts']} impacts")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
