"""Compiled kernels (numba) for the storm's per-step work and the contact solves.

A storm step is hundreds of small operations on arrays of a few stones; as numpy
calls their per-call overhead, not arithmetic, would be what a step costs. A
fresh contact solve with many contacts is scattered reads of D, which numpy's
fancy indexing does slowly. The kernels here do that work in compiled loops;
numba is a core dependency, and each storm phase exists once, here. The tests
hold them to plain statements of the same algorithms (``tests/reference/``) and
to independent oracles (brute-force closest points, analytic bounces).

Modules, in the order of a storm step:

* :mod:`~hailstorm.runtime.compiled.grid` — the surface's samples in a uniform grid
  (:class:`SampleGrid`), nearest samples and closest points of the deformed
  surface (:func:`closest_points`);
* :mod:`~hailstorm.runtime.compiled.flight` — free flight with drag, the broad phase
  (:func:`near_set`), retirement;
* :mod:`~hailstorm.runtime.compiled.narrow` — the free part of a sub-step
  (:func:`free_phase`: closest points, time of impact, contacts that open,
  hard walls) and the penetration statistics;
* :mod:`~hailstorm.runtime.compiled.free_steps` — many steps without soft contacts in one call
  (spawning, the phases above, retirement);
* :mod:`~hailstorm.runtime.compiled.patches` — patch weights, a patch's compliance and
  the patch sizing of the storm's contacts (with :mod:`~hailstorm.runtime.compiled.sphere`,
  the rigid sphere's contact law at any contact radius);
* :mod:`~hailstorm.runtime.compiled.blocks` — blocks of D (D_VV, D_VV G, D[:, V] g),
  :mod:`~hailstorm.runtime.compiled.wmatrix` — the contact compliance W from them, and
  :mod:`~hailstorm.runtime.compiled.point_solve` — one-call point-contact solves: the
  contact API's kernels (:func:`hailstorm.runtime.contact.solve_contacts`), also used by the storm;
* :mod:`~hailstorm.runtime.compiled.hblocks` — a compressed D's H-matrix: its product with
  a vector, its entries, and ``d_entry``, through which the storm's kernels read an entry of
  a dense D or of an H-matrix (a compressed bundle read without expanding D);
* :mod:`~hailstorm.runtime.compiled.contacts` — the SPD policy inside the compiled steps
  and the constrained coordinates around a contact step;
* :mod:`~hailstorm.runtime.compiled.exact` — the exact contact step (closed form, split at its
  events); :mod:`~hailstorm.runtime.compiled.integrators` — the implicit and symplectic
  contact steps, the sub-step sizing and the dashpot (with :mod:`~hailstorm.runtime.compiled.modal`,
  the modal algebra, :mod:`~hailstorm.runtime.compiled.expm`, the matrix exponential
  of a (nearly) defective set, and :mod:`~hailstorm.runtime.compiled.lapack`, a dense
  solve that is ``np.linalg.solve``'s LAPACK call without its costly-to-compile copy-in).

The kernels are compiled on first use and cached on disk (``cache=True``,
beside the modules' bytecode, or numba's user cache if that is read-only), so
only the first run after an install pays the compilation; later processes load
them in ~0.3 s. ``NUMBA_DISABLE_JIT=1`` (numba's own switch) runs them as Python,
for debugging.
"""

from __future__ import annotations

from hailstorm.runtime.compiled.jit import KERNELS
from hailstorm.runtime.compiled.blocks import columns_times, vertex_block, weighted_rows
from hailstorm.runtime.compiled.contacts import contact_post, contact_prep, inv_spd
from hailstorm.runtime.compiled.flight import flight, near_set, retired
from hailstorm.runtime.compiled.grid import SampleGrid, closest_points
from hailstorm.runtime.compiled.exact import exact_step
from hailstorm.runtime.compiled.integrators import (
    explicit_modes,
    modal_stiffness,
    substep_contacts,
    substep_damping,
    substep_size,
)
from hailstorm.runtime.compiled.narrow import free_phase, penetration
from hailstorm.runtime.compiled.patches import patch_compliance, patch_one, patch_radii
from hailstorm.runtime.compiled.point_solve import point_contacts
from hailstorm.runtime.compiled.wmatrix import contact_compliance

__all__ = [
    "KERNELS",
    "SampleGrid",
    "closest_points",
    "columns_times",
    "contact_compliance",
    "contact_post",
    "contact_prep",
    "exact_step",
    "explicit_modes",
    "flight",
    "free_phase",
    "inv_spd",
    "modal_stiffness",
    "near_set",
    "patch_compliance",
    "patch_one",
    "patch_radii",
    "penetration",
    "point_contacts",
    "retired",
    "substep_contacts",
    "substep_damping",
    "substep_size",
    "vertex_block",
    "weighted_rows",
]

