"""hailstorm: fast, verified contact on linear elastic solids through precomputed Green's functions.

Two stages, one package:

* :mod:`hailstorm.precompute` (offline; gmsh, scikit-fem: ``pip install "hailstorm[precompute]"``):
  mesh a solid, assemble linear elasticity and write a Green's-function bundle
  (:func:`hailstorm.precompute.build_bundle`);
* :mod:`hailstorm.runtime` (numpy, scipy, numba: the core install; nothing of the offline stage):
  load a bundle (:func:`hailstorm.runtime.load`), resolve contacts with the
  capacitance K = (Bᵀ D B)⁻¹ (:func:`hailstorm.runtime.solve_contacts`) and run a
  hail storm (:func:`hailstorm.runtime.run_storm`).

Importing :mod:`hailstorm` itself loads neither stage. The command line is
``hailstorm`` (or ``python -m hailstorm``). The package's folders are the
repository's top-level ``precompute/``, ``runtime/`` and ``meshes/`` (mapped by
``pyproject.toml``); this file and ``__main__.py`` are the package face.
"""

__version__ = "0.1.0"
__all__ = ["__version__"]
