"""The read-outs of a capacitance: what contact forces do to the vertices, the contact points and the surface.

:class:`Readouts` is the part of
:class:`~hailstorm.runtime.contact.contact_capacitance.Capacitance` that maps forces (or
constraint multipliers) to displacements: the responses per unit multiplier
(:meth:`~Readouts.loaded_columns`, :meth:`~Readouts.vertex_response`,
:meth:`~Readouts.surface_response`, the kept full-surface response of
:meth:`~Readouts.keep_response`) and the displacements of a solution (vertex forces,
vertex, contact-point, near-field and surface displacements). It reads the
capacitance's fields and never changes W or K; the notation is :mod:`hailstorm.runtime.contact`'s.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from hailstorm.runtime.bundle.compliance import ComplianceSource, apply_columns, dof3, gather, response_columns
from hailstorm.runtime.contact.capacitance_blocks import constrained_rows
from hailstorm.runtime.contact.validate import ContactMode
from hailstorm.runtime.contact.weights import interpolate, vertex_forces

if TYPE_CHECKING:
    from hailstorm.runtime.contact.active_set import ActiveSet

__all__ = ["Readouts"]


class Readouts:
    """The displacement read-outs of :class:`~hailstorm.runtime.contact.contact_capacitance.Capacitance`.

    A mixin: its methods read the capacitance's fields (declared below for
    reference; :class:`Capacitance` holds and documents them) and keep the
    full-surface response ``_R`` (:meth:`keep_response`).
    """

    gf: ComplianceSource
    mode: ContactMode
    normals: np.ndarray
    V: np.ndarray
    loc: np.ndarray
    weights: np.ndarray
    W: np.ndarray
    column_dofs: np.ndarray
    local: np.ndarray | None
    _R: np.ndarray | None
    _Y: np.ndarray | None
    s: int
    D_VV: np.ndarray
    G: np.ndarray

    # -- responses per unit multiplier ---------------------------------------
    def loaded_columns(self) -> tuple[np.ndarray, np.ndarray]:
        """The columns of D the contacts load and the forces on them per unit multiplier.

        Returns
        -------
        cols : (c,) int ndarray
            Column dofs of D of the non-clamped dofs of V (vertex-major).
        G : (c, m) float ndarray
            Rows ``cols`` of :attr:`G`: the surface displacement per unit
            multiplier is ``D[:, cols] @ G``.
        """
        loaded = self.column_dofs >= 0
        return self.column_dofs[loaded], np.ascontiguousarray(self.G[loaded])

    def vertex_response(self) -> np.ndarray:
        """Displacement of the vertices V per unit constraint multiplier, ``D_VV G``, (3|V|, m).

        From the build's ``(D_VV G)^T`` (no ``D_VV`` needed) until :meth:`add`
        or :meth:`remove`; then from ``D_VV``.
        """
        if self._Y is not None and self._Y.shape[0] == self.W.shape[0]:
            return np.ascontiguousarray(self._Y.T)
        return self.D_VV @ self.G

    def keep_response(self) -> np.ndarray:
        """Form (once) and keep the full-surface response ``R = D[:, V] B``.

        ``R`` maps contact forces to the displacement of every surface vertex:
        ``u = R @ forces.ravel()``. Once kept, :meth:`surface_displacement`
        with ``rows=None`` is that one product (``3n x 3s`` doubles, read in
        one contiguous pass) instead of gathering the contacted columns of
        ``D`` on every call; :meth:`add` appends the new contact's columns and
        :meth:`remove` deletes them. Worth it when one contact set is solved
        many times (measured in ``tests/benchmarks/bench_contacts.py``: on the
        default seat at s = 100, forces + full-surface displacement take
        0.24 ms against 5-8 ms for a fresh solve; building the capacitance and
        forming R cost 9 ms). Memory: ``3n x 3s`` doubles (11 MB at n = 1557, s = 100).

        Returns
        -------
        (3n, 3s) float ndarray
            Vertex-major rows, contact-major columns (the kept array itself:
            do not modify it).
        """
        if self._R is None:
            self._R = response_columns(self.gf, self.column_dofs, self.loc, self.weights)
        return self._R

    def surface_response(self, rows: np.ndarray | None = None) -> np.ndarray:
        """Surface displacement per unit constraint multiplier, ``D[rows, V] G``.

        ``u = surface_response() @ lam`` for multipliers ``lam`` (sticky: the
        flattened contact forces; frictionless: the signed normal forces).

        Parameters
        ----------
        rows : (r,) int ndarray, optional
            Surface vertices; default every surface vertex.

        Returns
        -------
        (3r, m) float ndarray
            Vertex-major rows; ``m = 3s`` (sticky) or ``s`` (frictionless).
        """
        n = self.gf.vertices.shape[0]
        r = np.arange(n) if rows is None else np.asarray(rows)
        if r.ndim != 1 or (r.size and not np.issubdtype(r.dtype, np.integer)):
            raise ValueError(f"rows must be a 1-D array of vertex indices, got shape {r.shape} dtype {r.dtype}")
        if r.size and (r.min() < 0 or r.max() >= n):
            raise IndexError(f"rows hold vertex indices outside 0..{n - 1}")
        M = gather(self.gf, dof3(r), self.column_dofs)  # D[rows, V], (3r, 3|V|)
        return constrained_rows(np.ascontiguousarray(M.T), self.loc, self.weights, self.normals, self.mode).T

    # -- displacements under contact forces ----------------------------------
    def vertex_forces(self, forces: np.ndarray) -> np.ndarray:
        """Vertex forces ``f_V = B f_s`` as a (len(V), 3) array."""
        return vertex_forces(self.V.size, self.loc, self.weights, np.asarray(forces, dtype=np.float64).reshape(-1, 3))

    def vertex_displacement(self, solution: ActiveSet) -> np.ndarray:
        """Displacement of the vertices V under a solution's forces, ``D_VV B f``, (len(V), 3).

        Right after the build this is ``Y^T lam`` with the build's
        ``Y = (D_VV G)^T`` (no ``D_VV`` needed); after :meth:`add` or
        :meth:`remove`, ``D_VV`` times the vertex forces.
        """
        if self._Y is not None and solution.multipliers.size == self._Y.shape[0]:
            return (self._Y.T @ solution.multipliers).reshape(-1, 3)
        return (self.D_VV @ self.vertex_forces(solution.forces).reshape(-1)).reshape(-1, 3)

    def contact_displacement(self, forces: np.ndarray) -> np.ndarray:
        """Contact-point displacements ``B^T D_VV B f_s`` (plus the near field's ``local f_s``)
        caused by contact forces, (s, 3)."""
        f = np.asarray(forces, dtype=np.float64).reshape(-1, 3)
        g = self.vertex_forces(f).reshape(-1)
        return interpolate((self.D_VV @ g).reshape(-1, 3), self.loc, self.weights) + self.near_displacement(f)

    def near_displacement(self, forces: np.ndarray) -> np.ndarray:
        """The near field's share of the contact-point displacements, ``local f_s``, (s, 3)
        (zero without a near field; frictionless: along the normals)."""
        f = np.asarray(forces, dtype=np.float64).reshape(-1, 3)
        if self.local is None or not self.local.any():
            return np.zeros_like(f)
        if self.mode.sticky:
            return np.einsum("kij,kj->ki", self.local, f)
        return (self.local[:, 0, 0] * np.einsum("ki,ki->k", f, self.normals))[:, None] * self.normals

    def surface_displacement(self, forces: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """Surface displacement ``u = D[:, V] B f_s``.

        Parameters
        ----------
        forces : (s, 3) float ndarray
            Contact forces on the seat [N].
        rows : (r,) int ndarray, optional
            Surface vertices where the displacement is wanted. Default: every
            surface vertex (one matrix-vector product with ``D[:, V]``, or
            with the whole ``D`` when V covers much of it).

        Returns
        -------
        (r, 3) or (n, 3) float ndarray
        """
        if rows is None and self._R is not None:
            f = np.asarray(forces, dtype=np.float64).reshape(-1)
            if f.size != self._R.shape[1]:
                raise ValueError(f"forces must have shape ({self.s}, 3), got {np.shape(forces)}")
            return (self._R @ f).reshape(-1, 3)
        g = self.vertex_forces(forces).reshape(-1)
        return apply_columns(self.gf, self.column_dofs, g, rows)
