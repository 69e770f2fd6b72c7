"""How a compile helper process rebuilds a storm: the bundle's arrays' kinds and the helper's spec.

The storm's warm-up (:meth:`hailstorm.runtime.storm.driver.Storm.warm_up`) hands part of a
first run's compile to a helper process (:mod:`hailstorm.runtime.storm.warmup`); the helper
loads the bundle from its directory and rebuilds the storm
(:func:`hailstorm.runtime.storm.run.warm_up_worker`), whose kernels must see the same argument
types as the caller's: :func:`array_kinds` is what those types depend on.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from hailstorm.runtime.bundle.compliance import reader
from hailstorm.runtime.storm.scene import Scene
from hailstorm.runtime.storm.warmup import HelperSpec

__all__ = ["array_kinds", "helper_spec"]


def array_kinds(gf: Any) -> list[tuple]:
    """What the kernels' argument types depend on in a bundle's arrays (dtype, layout, writeable, class):
    D's (or, read from its H-matrix, the H-matrix's kernel arrays') and the surface's."""
    how = reader(gf)
    arrays = [("D", a) for a in how.kernel_entries] if how.compressed else [("D", gf.D)]
    arrays += [(name, getattr(gf, name)) for name in ("vertices", "triangles", "fixed", "contactable", "areas",
                                                      "column_of")]
    return [(name, a.dtype.str, a.ndim, bool(a.flags.c_contiguous), bool(a.flags.f_contiguous),
             bool(a.flags.writeable), type(a).__name__) for name, a in arrays]


def helper_spec(gf: Any, scene: Scene) -> HelperSpec | None:
    """How a compile helper rebuilds this storm: from the bundle's directory (None if ``gf`` is
    not a bundle on disk, e.g. built in memory)."""
    from hailstorm.runtime.bundle.format import is_bundle

    path = getattr(gf, "path", None)
    if path is None or not is_bundle(path):
        return None
    try:
        kinds = array_kinds(gf)
    except AttributeError:
        return None
    native = reader(gf).compressed
    return HelperSpec("hailstorm.runtime.storm.run:warm_up_worker",
                      {"bundle": str(path), "mmap": native or isinstance(gf.D, np.memmap), "kinds": kinds,
                       "expand": None if getattr(gf, "hmatrix", None) is None else not native,
                       "scene": scene.to_dict()})
