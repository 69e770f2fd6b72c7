"""The contract between the two stages: the Green's-function bundle.

One folder for everything both stages agree on, each module one seam:

* :mod:`~hailstorm.runtime.bundle.format` -- the format itself: file names,
  array specifications, the manifest and its checks, content hashes, D's
  storage types (:class:`BundleError`);
* :mod:`~hailstorm.runtime.bundle.read` -- :func:`load` ->
  :class:`GreensFunctions` (reads; writes nothing but its verification stamps);
* :mod:`~hailstorm.runtime.bundle.write` -- :func:`~hailstorm.runtime.bundle.write.write_bundle`
  (atomic, locked, hashed), the cleanup of killed writers' temporaries and
  :func:`~hailstorm.runtime.bundle.write.convert_bundle` (D's storage type);
* :mod:`~hailstorm.runtime.bundle.compliance` -- the compliance source:
  ``compliance(rows, cols)`` as the runtime reads it (dof indices, blocks of D,
  products with its columns);
* :mod:`~hailstorm.runtime.bundle.hmatrix` -- a compressed D as stored
  (format 3): dense near blocks, low-rank far blocks, its columns and products
  (built by :mod:`hailstorm.precompute.hmatrix`);
* :mod:`~hailstorm.runtime.bundle.stamps` -- "verified and unchanged since"
  stamps and the cache directory;
* :mod:`~hailstorm.runtime.bundle.atomic` -- atomic file replacement.

The offline stage (:mod:`hailstorm.precompute`) writes through this package and
the runtime reads through it; neither imports the other's internals.
"""

from hailstorm.runtime.bundle.compliance import ComplianceSource
from hailstorm.runtime.bundle.format import BundleError
from hailstorm.runtime.bundle.read import GreensFunctions, load

__all__ = ["BundleError", "ComplianceSource", "GreensFunctions", "load"]
