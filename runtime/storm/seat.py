"""The seat's state in a storm: the contact forces at the loaded vertices, the
displacement they cause (evaluated only where it is needed) and its peaks.

The state is the vertex-force vector ``B f`` on the loaded columns of D
(:meth:`SeatState.set_forces`); the displacement of a few vertices
(:meth:`SeatState.u_at`), of the whole surface (:attr:`SeatState.u`, for frames)
and a bound of its size (:attr:`SeatState.umax`, for the broad phase) follow from
it. :meth:`SeatState.peak_field` gives, per vertex, the largest displacement since
the previous frame (an impact lasts about a millisecond, much less than a frame).
"""

from __future__ import annotations

from typing import Protocol, TYPE_CHECKING

import numpy as np

from hailstorm.runtime.bundle.compliance import reader

if TYPE_CHECKING:  # annotations only
    from hailstorm.runtime.bundle.compliance import ComplianceSource

__all__ = ["LoadedSet", "SeatState"]


class LoadedSet(Protocol):
    """What the seat needs of a contact set (:class:`hailstorm.runtime.storm.contact_set.ContactSet`)."""

    stones: np.ndarray  # (s,) stone ids
    G: np.ndarray  # (c, m) vertex forces on the loaded columns per unit multiplier
    cols: np.ndarray  # (c,) those columns of D
    DVV: np.ndarray  # (3|V|, m) displacement of the loaded vertices per unit multiplier


class SeatState:
    """Vertex forces, displacement queries and peaks of the seat.

    Parameters
    ----------
    gf : ComplianceSource
        The bundle: ``D`` (a column-major copy is held when D is a row-major
        memmap of at most 1 GiB: column gathers from a row-major file read all of
        it; a compressed bundle read from its H-matrix is never expanded), ``column_of``,
        the vertex count.
    """

    def __init__(self, gf: ComplianceSource) -> None:
        #: how D is read (:func:`hailstorm.runtime.bundle.compliance.reader`): a dense D, or a
        #: compressed bundle's H-matrix (its displacements through the reader's products)
        self.reader = reader(gf)
        self._dense = not self.reader.compressed
        #: what the kernels read D's entries through (``d_entry``): D (column-major, a plain
        #: ndarray), or the H-matrix's kernel arrays
        self.D = self.reader.kernel_entries
        #: the column of D of each vertex (-1: clamped), as the kernels take it
        self.column_of = np.ascontiguousarray(gf.column_of, dtype=np.int64)
        self.n = int(np.asarray(gf.vertices).shape[0])
        #: the loaded columns of D and their forces (None: no load)
        self.forces: np.ndarray | None = None
        self.cols: np.ndarray | None = None
        #: a bound of |u| over the surface [m] (0: no load), the largest seen, and the
        #: largest in the current step (the broad phase's bound)
        self.umax = 0.0
        self.umax_seen = 0.0
        self.umax_step = 0.0
        self._version = 0
        self._u_cache: tuple[int, np.ndarray] = (-1, np.zeros((self.n, 3)))
        #: per stone, its deepest dent since the previous frame and the vertex forces
        #: then: stone id -> (dent [m], D columns, vertex forces)
        self._peaks: dict[int, tuple[float, np.ndarray, np.ndarray]] = {}
        self._no_cols = np.zeros(0, dtype=np.int64)
        self._no_forces = np.zeros(0)

    @property
    def loaded(self) -> bool:
        """True while contact forces load the seat."""
        return self.forces is not None

    def kernel_load(self) -> tuple[bool, np.ndarray, np.ndarray]:
        """``(loaded, cols, forces)`` as the compiled queries take them (empty when unloaded)."""
        if self.forces is None:
            return False, self._no_cols, self._no_forces
        assert self.cols is not None  # set together with forces
        return True, self.cols, self.forces

    def set_forces(self, cc: LoadedSet | None, lam: np.ndarray, peak: np.ndarray | None = None) -> None:
        """Contact multipliers ``lam`` of set ``cc`` -> vertex forces; displacement bound
        ``umax``. ``peak``: the multipliers of each contact's largest force within the
        sub-step (default ``lam``), kept for the frames' peak displacement."""
        self._version += 1
        if cc is None or lam.size == 0 or not np.any(lam):
            self.forces = None
            self.cols = None
            self.umax = 0.0
            if cc is not None and peak is not None and np.any(peak):
                self._track_peaks(cc, peak)  # released within the sub-step: its dent still counts
            return
        self.forces = cc.G @ lam
        self.cols = cc.cols
        uV = (cc.DVV @ lam).reshape(-1, 3)
        # |u| peaks under the loads; 1.5x covers superposition between nearby loads
        self.umax = 1.5 * float(np.sqrt((uV**2).sum(axis=1).max())) if uV.size else 0.0
        self.umax_seen = max(self.umax_seen, self.umax)
        self.umax_step = max(self.umax_step, self.umax)
        self._track_peaks(cc, lam if peak is None else peak)

    def _track_peaks(self, cc: LoadedSet, lam: np.ndarray) -> None:
        """Keep, per stone, the vertex forces of its deepest dent since the last frame.

        The dent is the largest displacement of the contact's own load at the loaded
        vertices (``D_VV G``): for fixed weights it grows with the force, and across
        a re-weighting (a patch resized) it still ranks the fields by what they show,
        which the force alone does not (a wider patch carries more force in a shallower dent).
        """
        s = cc.stones.size
        m = lam.size // s  # multipliers per contact (1 frictionless, 3 sticky)
        L = lam.reshape(-1, m)
        if m == 1:
            U = cc.DVV * L[:, 0]  # (3|V|, s): each contact's own displacement of V
        else:
            U = np.einsum("rkj,kj->rk", cc.DVV.reshape(-1, s, m), L)
        U = U.reshape(-1, 3, s)
        dent = np.sqrt((U * U).sum(axis=1).max(axis=0)) if U.size else np.zeros(s)
        peaks = self._peaks
        for k in np.flatnonzero(dent > 0.0).tolist():
            sid = int(cc.stones[k])
            prev = peaks.get(sid)
            if prev is None or dent[k] > prev[0]:
                fk = cc.G[:, m * k:m * k + m] @ L[k]
                nz = np.flatnonzero(fk)
                peaks[sid] = (float(dent[k]), cc.cols[nz], fk[nz])

    def end_step(self) -> None:
        """The step is over: the next step's broad phase starts from the current bound."""
        self.umax_step = self.umax

    def peak_field(self) -> np.ndarray:
        """Per vertex, the largest of the current displacement and each stone's displacement
        at its deepest dent since the previous call (each stone's field alone: impacts rarely
        overlap within a frame, and superposing peaks of different instants would overstate).
        Starts a new peak interval."""
        u = self.u
        peaks, self._peaks = self._peaks, {}
        if not peaks:
            return u
        fields = [u] + [self._field(cols, fv) for _, cols, fv in peaks.values()]
        F = np.stack(fields)  # (m + 1, n, 3)
        pick = np.argmax(np.einsum("mnd,mnd->mn", F, F), axis=0)
        return F[pick, np.arange(self.n)]

    def u_at(self, verts: np.ndarray) -> np.ndarray:
        """Displacement (k, 3) of surface vertices ``verts`` under the current contact forces."""
        if self.forces is None or verts.size == 0:
            return np.zeros((verts.size, 3))
        assert self.cols is not None
        rows = (3 * verts[:, None] + np.arange(3)).ravel()
        block = self.D[np.ix_(rows, self.cols)] if self._dense else self.reader.gather(rows, self.cols)
        return (block @ self.forces).reshape(-1, 3)

    def entries_at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """``D[rows, cols]`` elementwise (index arrays of one broadcast shape)."""
        return self.reader.entries_at(rows, cols)

    def _field(self, cols: np.ndarray, fv: np.ndarray) -> np.ndarray:
        """``D[:, cols] @ fv`` as (n, 3) (a dense D: numpy's product, as the frames always had it)."""
        if not self._dense:
            return self.reader.apply_all(cols, fv)
        return (self.D[:, cols] @ fv).reshape(self.n, 3)

    @property
    def u(self) -> np.ndarray:
        """Displacement (n, 3) of the whole surface (computed on demand, e.g. for frames)."""
        if self._u_cache[0] != self._version:
            if self.forces is None:
                u = np.zeros((self.n, 3))
            else:
                u = self._field(self.cols, self.forces)
            self._u_cache = (self._version, u)
        return self._u_cache[1]
