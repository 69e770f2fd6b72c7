"""Build the tiny bundle shipped in ``tests/data/tiny-box`` (needs the precompute extra).

A 0.1 x 0.1 x 0.03 m box at 0.02 m (P1, 108 nodes), clamped at z = 0, of the
default seat's foam; small enough to commit (< 1 MB), so that a core install (no
gmsh, no scikit-fem) has a bundle to load and run a storm on
(``tests/contract/test_core_install.py``). Re-run after a bundle format change::

    python tests/data/make_tiny_bundle.py            # writes tests/data/tiny-box
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

HERE = Path(__file__).resolve().parent
#: the shipped bundle's directory
TINY_BUNDLE = HERE / "tiny-box"
SIZE = (0.1, 0.1, 0.03)
MESH_SIZE = 0.02


def build(out: Path = TINY_BUNDLE) -> Path:
    """Write the tiny bundle to ``out`` (replaced) and return its path."""
    from hailstorm.precompute import box_mesh, build_bundle
    from hailstorm.precompute.fem import DEFAULT_POISSON, DEFAULT_YOUNG

    if out.exists():
        shutil.rmtree(out)
    return build_bundle(out, mesh=box_mesh(SIZE, MESH_SIZE), order=1, young=DEFAULT_YOUNG,
                        poisson=DEFAULT_POISSON, progress=False)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, default=TINY_BUNDLE)
    args = p.parse_args(argv)
    path = build(args.out)
    size = sum(f.stat().st_size for f in path.rglob("*") if f.is_file())
    print(f"{path}: {size / 1024:.0f} KiB")


if __name__ == "__main__":
    main()
