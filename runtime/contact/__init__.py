"""The contact core: point and patch contacts on the seat through the precomputed compliance.

Modules, one seam each:

* :mod:`~hailstorm.runtime.bundle.compliance` -- access to D: the
  :class:`ComplianceSource` protocol (what the core reads of a bundle), dof
  indices, blocks of D and products with its columns (compiled kernels of
  :mod:`hailstorm.runtime.compiled.blocks`);
* :mod:`~hailstorm.runtime.contact.weights` -- the force-distribution weights
  B of point and patch contacts (:func:`barycentric_matrix`, :func:`patch_weights`);
* :mod:`~hailstorm.runtime.contact.normals` -- the surface's normals: a triangle's
  own (:func:`triangle_normals`) and the smooth normal across its facets;
* :mod:`~hailstorm.runtime.contact.sphere_patch` -- a sphere's contact patch, its
  radius and offset: :func:`hertz_radius`, :func:`sphere_radius`, :func:`impact_radius`;
* :mod:`~hailstorm.runtime.contact.policy` -- the numerical policy: the
  constants (condition limit, pseudo-inverse cut-off, rigid threshold,
  fast-path size), named once, and the one SPD factorisation
  :class:`SPDFactor` / :func:`spd_inverse`;
* :mod:`~hailstorm.runtime.contact.near_field` -- contacts smaller than a
  surface element: the half-space near field added to W's diagonal
  (:class:`NearField`, :func:`near_field`);
* :mod:`~hailstorm.runtime.contact.validate` -- input checks;
* :mod:`~hailstorm.runtime.contact.contact_capacitance` -- :class:`Capacitance`
  (``W``, its factorisation, ``K``, the :meth:`~Capacitance.solve`), assembled from
  :mod:`~hailstorm.runtime.contact.capacitance_update` (the low-rank
  :meth:`~Capacitance.add` / :meth:`~Capacitance.remove`),
  :mod:`~hailstorm.runtime.contact.capacitance_readout` (the displacement read-outs) and
  :mod:`~hailstorm.runtime.contact.active_set` (the unilateral solve: block pivoting, the
  convex QP, :class:`ActiveSet`); :mod:`~hailstorm.runtime.contact.capacitance_blocks`
  holds the blocks W is built from;
* :mod:`~hailstorm.runtime.contact.capacitance_build` -- :func:`capacitance` and the
  builders under it (``build``, ``from_weights``, ``resolve_near_field``);
* :mod:`~hailstorm.runtime.contact.solve` -- :func:`solve_contacts` and
  :class:`ContactSolution`.

Notation (see ``DESIGN.md`` and the course hint). Contact ``k`` sits on surface
triangle ``t_k`` with barycentric coordinates ``beta_k``. ``V`` is the sorted
union of the contacted triangles' vertices and

* ``D_VV`` is the ``3|V| x 3|V|`` block of the compliance ``D`` (columns of
  clamped vertices are zero: a force there goes into the support);
* ``B`` (the hint's symbol) is ``3|V| x 3s`` with block ``(i, k) = beta_{k,i} I3``;
  vertex forces are ``f_V = B f_s`` and contact-point displacements
  ``u_s = B^T u_V``;
* the *contact compliance* is ``W = B^T D_VV B`` and the *capacitance*
  (effective stiffness, the hint's ``K^beta``, DESIGN's ``K_s``) is ``K = W^-1``,
  so prescribed contact-point displacements ``ubar`` give ``f_s = K ubar``;
* the surface then moves by ``u = D[:, V] B f_s``.

Patch contacts (``patch_radius=a``) replace ``beta_k`` by the weights of a
pressure disc of radius ``a`` (the consistent nodal load of a Hertz profile,
:func:`hailstorm.runtime.contact.weights.patch_weights`): ``B`` keeps its shape ``3|V| x 3s``
with block ``(i, k) = w_{k,i} I3`` over the patch vertices, and everything
below (``W``, ``K``, rigid contacts, the low-rank updates, the active set)
is unchanged. A point load is singular (its stiffness vanishes as the mesh is
refined); a patch load of fixed radius converges with the mesh.

Frictionless contacts constrain only the normal component: with ``N`` the
block-diagonal ``3s x s`` matrix of the unit normals, ``W_n = N^T W N`` and the
forces are ``f_s = N W_n^-1 N^T ubar``. Internally both modes are one case:
a constraint matrix ``G = B N`` (``N = I`` for sticky contacts) with
``m = 3s`` or ``m = s`` constrained components ("dofs").

Sign conventions
----------------
* ``forces`` are the forces applied **to the seat** [N] (a stone feels ``-f``).
* Normals are **outward** unit normals of the seat surface. A stone pressing
  on the seat prescribes ``ubar . n < 0`` and produces ``f . n < 0``; a contact
  with ``f . n > 0`` would *pull* (adhesion), and unilateral contact releases it.
* Displacements are in metres, positive along the coordinate axes.

Degenerate cases (documented choices)
-------------------------------------
* **Rigid contacts.** A contact whose barycentric weight lies entirely on clamped
  vertices (e.g. any point of a triangle whose three vertices are all clamped)
  cannot move: its rows and columns of ``W`` are zero. It is excluded from the
  solve (no zero block is ever inverted), flagged in ``rigid``, its reported
  force is ``0`` and its contact displacement is ``0``. Callers (the storm)
  treat rigid contacts as a hard wall; the prescribed displacement there simply
  cannot be imposed and is ignored.
* **Singular / ill-conditioned W** (coincident or nearly coincident contacts,
  more contacts on a patch than its vertices have degrees of freedom). ``W`` is
  factorised by Cholesky when its (cheap, diagonal-of-L based) condition
  estimate is below :data:`~hailstorm.runtime.contact.policy.COND_LIMIT`.
  Otherwise ``K`` is the rank-revealing pseudo-inverse of ``W`` (symmetric
  eigendecomposition; eigenvalues below
  :data:`~hailstorm.runtime.contact.policy.PINV_RCOND` times the largest are
  dropped): :class:`~hailstorm.runtime.contact.policy.SPDFactor`. The pseudo-inverse gives
  the minimum-norm forces that best realise the prescription: coincident
  contacts share the force equally and stay finite even when they prescribe
  conflicting displacements (least-squares compromise). No Tikhonov shift is
  applied to well-conditioned systems, so the regular case is exact. (``W`` is the
  symmetric part of ``G^T D G``: ``G^T D G`` itself on a point-load bundle, whose D
  is symmetric; a hat-load D is not, docs/verification.md, "reciprocity".)
"""

from hailstorm.runtime.contact.active_set import ActiveSet
from hailstorm.runtime.contact.capacitance_build import capacitance
from hailstorm.runtime.contact.contact_capacitance import Capacitance
from hailstorm.runtime.bundle.compliance import ComplianceSource
from hailstorm.runtime.contact.policy import COND_LIMIT, PINV_RCOND, SPDFactor, spd_inverse
from hailstorm.runtime.contact.solve import ContactSolution, solve_contacts
from hailstorm.runtime.contact.near_field import NearField, near_field
from hailstorm.runtime.contact.validate import Mode
from hailstorm.runtime.contact.normals import triangle_normals
from hailstorm.runtime.contact.sphere_patch import hertz_radius, impact_radius, sphere_radius
from hailstorm.runtime.contact.weights import barycentric_matrix, contact_points, patch_matrix, patch_weights

__all__ = [
    "COND_LIMIT",
    "PINV_RCOND",
    "ActiveSet",
    "Capacitance",
    "ComplianceSource",
    "ContactSolution",
    "Mode",
    "NearField",
    "SPDFactor",
    "barycentric_matrix",
    "capacitance",
    "contact_points",
    "hertz_radius",
    "impact_radius",
    "sphere_radius",
    "near_field",
    "patch_matrix",
    "patch_weights",
    "solve_contacts",
    "spd_inverse",
    "triangle_normals",
]
