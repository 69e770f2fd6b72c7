"""Access to the compliance D of a bundle: the :class:`ComplianceSource` protocol, dof indices, blocks of D.

Everything here is about reading blocks of the (possibly memory-mapped)
compliance ``D`` fast; nothing knows about contacts. How a source is read is
decided once (:func:`reader`): a dense D by :class:`DenseReader`, whose products
with whole columns of D and ``D_VV`` block are the compiled kernels of
:mod:`hailstorm.runtime.compiled.blocks` (they read ``D.T`` as a C-contiguous
array, :func:`kernel_columns`, which is free for the column-major D that bundles
hold); a compressed bundle loaded not to expand its D by
:class:`~hailstorm.runtime.bundle.hreader.HMatrixReader`, from the H-matrix's blocks.

* :class:`ComplianceSource` -- what the contact core reads of a bundle;
* :class:`ElasticSource` -- that and the contact surface's material (Hertz-sized patches, the storm);
* :func:`dof3` -- vertex-major x, y, z dof indices of vertices;
* :func:`column_dofs` -- column dofs of D for surface vertices (-1 at clamped ones);
* :func:`unique_inverse` -- ``np.unique(..., return_inverse=True)`` for short index lists
  (these three from :mod:`hailstorm.runtime.bundle.dofs`);
* :func:`reader` -- the source's reader (:class:`DenseReader` or ``HMatrixReader``);
* :func:`gather` -- ``D[rows, cols]`` with zero clamped columns;
* :func:`vertex_block` -- ``D_VV``, the block of the vertices V;
* :func:`apply_columns` -- ``D[rows, cols] @ g``;
* :func:`constraint_rows` -- ``(D_VV G)^T``, the vertices' response per contact multiplier;
* :func:`response_columns` -- ``D[:, U] B``, the full-surface response of contacts;
* :func:`pair_blocks` -- 3 x 3 blocks ``D[rows[k], cols[k]]``.
"""

from __future__ import annotations

import weakref
from typing import Protocol

import numpy as np

from hailstorm.runtime.bundle.dofs import column_dofs, dof3, unique_inverse
from hailstorm.runtime.bundle.hreader import HMatrixReader
from hailstorm.runtime.compiled import blocks as kernels

__all__ = [
    "GATHER_BLOCK",
    "ComplianceSource",
    "DenseReader",
    "ElasticSource",
    "apply_columns",
    "column_dofs",
    "constraint_rows",
    "dof3",
    "gather",
    "kernel_columns",
    "pair_blocks",
    "reader",
    "response_columns",
    "unique_inverse",
    "vertex_block",
]


class ComplianceSource(Protocol):
    """What the contact core reads of a Green's-function bundle.

    :class:`hailstorm.runtime.bundle.read.GreensFunctions` is one; any object with
    these attributes is another (a test's analytic plate, a study's half-space).

    Attributes
    ----------
    D : (3n, 3c) float64 or float32 ndarray
        The compliance: column ``(j, e)`` is the displacement of every surface
        vertex (vertex-major rows) under a unit force at contactable vertex j
        in direction e [m/N]. Column-major (as bundles are written) is the fast
        layout; any other is copied once for the compiled kernels (in D's own
        type). Read in its storage type, computed with in float64: blocks
        gathered from a float32 D are float64, and the kernels accumulate in
        float64.
    column_of : (n,) int ndarray
        D's column block of each surface vertex, -1 where not contactable.
    contactable, fixed : (n,) bool ndarrays
        Vertices that own a column block of D; vertices on the clamp.
    vertices : (n, 3) float ndarray
        Surface vertices [m].
    triangles : (m, 3) int ndarray
        Surface triangles, counter-clockwise seen from outside.
    """

    @property
    def D(self) -> np.ndarray: ...

    @property
    def column_of(self) -> np.ndarray: ...

    @property
    def contactable(self) -> np.ndarray: ...

    @property
    def fixed(self) -> np.ndarray: ...

    @property
    def vertices(self) -> np.ndarray: ...

    @property
    def triangles(self) -> np.ndarray: ...


class ElasticSource(ComplianceSource, Protocol):
    """A :class:`ComplianceSource` that also knows the material under its contact surface.

    What Hertz-sized patches (:func:`hailstorm.runtime.contact.hertz.press_spheres`) and the
    storm's parts read; :class:`hailstorm.runtime.bundle.read.GreensFunctions` is one.

    Attributes
    ----------
    young, poisson : float
        Young's modulus [Pa] and Poisson's ratio of the material under the
        contactable surface (the stones' contact stiffness follows from them).
    """

    @property
    def young(self) -> float: ...

    @property
    def poisson(self) -> float: ...


_COLUMNS: "weakref.WeakKeyDictionary[object, np.ndarray]" = weakref.WeakKeyDictionary()


def kernel_columns(gf: ComplianceSource) -> np.ndarray:
    """``D.T`` as the C-contiguous (3c, 3n) array the compiled kernels read (row = a column of D).

    A view for a column-major D (every bundle); otherwise a copy, made once per
    source (kept while the source lives) or per call if the source cannot be
    weakly referenced.
    """
    Dt = np.asarray(gf.D).T
    if Dt.flags.c_contiguous:
        return Dt
    try:
        cached = _COLUMNS.get(gf)
    except TypeError:
        return np.ascontiguousarray(Dt)
    if cached is None or cached.shape != Dt.shape:
        cached = np.ascontiguousarray(Dt)
        try:
            _COLUMNS[gf] = cached
        except TypeError:  # pragma: no cover
            pass
    return cached


#: Vertex chunks gathered per block in :func:`gather` (bounds its index temporaries).
GATHER_BLOCK = 16384


def _vertex_triples(rows: np.ndarray) -> np.ndarray | None:
    """Vertices ``v`` if ``rows`` is exactly ``dof3(v)`` (whole x, y, z triples), else None."""
    if rows.size % 3:
        return None
    v = rows[::3] // 3
    return v if np.array_equal(rows, dof3(v)) else None


def _gather_vertex_rows(D: np.ndarray, V: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``D[dof3(V), cols]`` for a column-major D, as an F-ordered (3|V|, c) array.

    In a Fortran-ordered D with a multiple of 3 rows, a vertex's x, y, z rows
    of one column are three adjacent doubles, so the gather takes 24-byte
    chunks (one index per vertex and column instead of three; measured 1.7x
    faster than the element-wise gather at s = 100). ``cols`` must be valid
    column indices.
    """
    nv = D.shape[0] // 3
    chunks = D.T.reshape(-1, 3)  # row c * nv + v: D[3v:3v+3, c]
    Mt = np.empty((cols.size, V.size, 3), dtype=D.dtype)  # np.take's out= does not cast
    # in column blocks: the index array stays small (a large temporary costs page faults)
    step = max(1, GATHER_BLOCK // max(V.size, 1))
    for i in range(0, cols.size, step):
        np.take(chunks, cols[i:i + step, None] * nv + V[None, :], axis=0, out=Mt[i:i + step])
    return Mt.reshape(cols.size, 3 * V.size).T


def reader(gf: ComplianceSource) -> "DenseReader | HMatrixReader":
    """How the runtime (the contact core, the storm) reads blocks of ``gf``'s D, decided once per source.

    An :class:`~hailstorm.runtime.bundle.hreader.HMatrixReader` for a compressed bundle loaded
    not to expand its D (``reads_hmatrix``: :func:`hailstorm.runtime.bundle.read.load`'s
    ``expand``), kept while the source lives; else a :class:`DenseReader` of ``gf.D``.
    """
    if not getattr(gf, "reads_hmatrix", False):
        return DenseReader(gf)
    try:
        cached = _READERS.get(gf)
    except TypeError:  # pragma: no cover - a source that cannot be weakly referenced
        cached = None
    if cached is None:
        cached = HMatrixReader(gf.hmatrix, gf.column_of)  # type: ignore[attr-defined]
        try:
            _READERS[gf] = cached
        except TypeError:  # pragma: no cover
            pass
    return cached


_READERS: "weakref.WeakKeyDictionary[object, HMatrixReader]" = weakref.WeakKeyDictionary()


class DenseReader:
    """Blocks of a dense D (``gf.D``, any layout; column-major is the fast one), the compiled
    kernels' way. :class:`~hailstorm.runtime.bundle.hreader.HMatrixReader` has the same methods.

    Parameters
    ----------
    gf : ComplianceSource
    """

    #: D is dense (:attr:`hailstorm.runtime.bundle.hreader.HMatrixReader.compressed` is True)
    compressed = False

    def __init__(self, gf: ComplianceSource) -> None:
        self.gf = gf

    @property
    def kernel_D(self) -> np.ndarray:
        """``D.T`` as the fused compiled paths read it (:func:`kernel_columns`)."""
        return kernel_columns(self.gf)

    @property
    def kernel_entries(self) -> np.ndarray:
        """D itself, as the storm's kernels index it (:func:`hailstorm.runtime.compiled.hblocks.d_entry`):
        a plain ndarray view of a memmap (no copy: numpy.memmap's per-index overhead dominates the
        storm loop's small gathers), column-major (a row-major memmap of at most 1 GiB is copied:
        column gathers from a row-major file read all of it)."""
        D = self.gf.D
        if isinstance(D, np.memmap) and not D.flags.f_contiguous and D.nbytes <= (1 << 30):
            D = np.asfortranarray(D)
        return np.asarray(D)

    def entries_at(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """``D[rows, cols]`` elementwise for index arrays of one (broadcast) shape (in D's type)."""
        return np.asarray(self.gf.D[rows, cols])

    def gather(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """``D[rows, cols]`` with zero columns where ``cols == -1``: see :func:`gather`."""
        return _dense_gather(self.gf.D, rows, cols)

    def vertex_block(self, V: np.ndarray) -> np.ndarray:
        """``D_VV``: see :func:`vertex_block`."""
        return kernels.vertex_block(np.asarray(V, dtype=np.intp), kernel_columns(self.gf), self.gf.column_of).T

    def apply_all(self, cols: np.ndarray, g: np.ndarray) -> np.ndarray:
        """``D[:, cols] @ g`` as (n, 3), clamped columns skipped: one pass over the columns in the
        compiled :func:`hailstorm.runtime.compiled.blocks.columns_times`."""
        return kernels.columns_times(kernel_columns(self.gf), np.asarray(cols, dtype=np.intp),
                                     np.ascontiguousarray(g, dtype=np.float64)).reshape(-1, 3)

    def constraint_rows(self, V: np.ndarray, loc: np.ndarray, w: np.ndarray, normals: np.ndarray,
                        sticky: bool) -> np.ndarray:
        """``Y = (D_VV G)^T`` from the columns of D (a fresh solve never forms ``D_VV`` itself)."""
        return kernels.constraint_rows(kernel_columns(self.gf), self.gf.column_of, V, loc, w, normals, sticky)

    def response_columns(self, cols: np.ndarray, loc: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """Full-surface response ``D[:, U] B``: see :func:`response_columns`."""
        blocks = np.where(cols[::3] >= 0, cols[::3] // 3, -1)
        zeros = np.zeros((loc.shape[0], 3))
        return kernels.weighted_rows(kernel_columns(self.gf), blocks, np.ascontiguousarray(loc, dtype=np.intp),
                                     np.ascontiguousarray(weights, dtype=np.float64), zeros, True).T

    def pair_blocks(self, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """The 3 x 3 blocks ``D[rows[k], cols[k]]``: see :func:`pair_blocks`."""
        r = 3 * np.asarray(rows)[:, None, None] + np.arange(3)[None, :, None]
        c = 3 * np.asarray(self.gf.column_of)[cols][:, None, None] + np.arange(3)[None, None, :]
        return self.entries_at(r, c).astype(np.float64, copy=False)


def _dense_gather(D: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """:func:`gather` from a dense ``D`` (a float32 D's block gathered in float32, then cast)."""
    dead = cols < 0
    cc = np.where(dead, 0, cols)
    if rows.size == 0 or cols.size == 0:
        return np.zeros((rows.size, cols.size))
    if D.flags.c_contiguous:
        out = np.take(D.reshape(-1), (rows[:, None] * D.shape[1] + cc[None, :]).ravel()).reshape(rows.size, cols.size)
        out = np.asarray(out)
    elif D.flags.f_contiguous and D.shape[0] % 3 == 0 and (V := _vertex_triples(rows)) is not None:
        out = _gather_vertex_rows(D, V, cc)
    else:  # any other layout: contiguous column take first, then the rows
        out = np.asarray(D.T[np.ix_(cc, rows)]).T
    out = out.astype(np.float64, copy=False)  # keeps the F order
    if dead.any():
        out[:, dead] = 0.0
    return out


def gather(gf: ComplianceSource, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``D[rows, cols]`` with zero columns where ``cols == -1`` (clamped vertices).

    Parameters
    ----------
    gf : ComplianceSource
    rows : (r,) int ndarray
        Row dofs of D (surface dofs, vertex-major).
    cols : (c,) int ndarray
        Column dofs of D (:func:`column_dofs`), -1 for a zero column.

    Returns
    -------
    (r, c) float64 ndarray
        F-ordered (its transpose is C-contiguous) for a column-major or compressed D; a
        float32 D's block is gathered in float32 and cast (the block, never D).
    """
    return reader(gf).gather(np.asarray(rows, dtype=np.intp), np.asarray(cols, dtype=np.intp))


def vertex_block(gf: ComplianceSource, V: np.ndarray) -> np.ndarray:
    """The compliance block ``D_VV = D[dof3(V), column_dofs(V)]`` (zero columns at clamped vertices).

    A dense D through the compiled :func:`hailstorm.runtime.compiled.blocks.vertex_block`.

    Returns
    -------
    (3|V|, 3|V|) float ndarray
        F-ordered (its transpose, the kernel's output, is C-contiguous).
    """
    return reader(gf).vertex_block(V)


def apply_columns(gf: ComplianceSource, cols: np.ndarray, g: np.ndarray, rows: np.ndarray | None) -> np.ndarray:
    """``D[rows, cols] @ g`` as (r, 3) (all rows if ``rows`` is None), skipping clamped columns.

    All rows: the reader's ``apply_all`` (a dense D: one pass over the columns in the
    compiled :func:`hailstorm.runtime.compiled.blocks.columns_times`); some rows: a
    gather of ``D[rows, cols]`` and a product.

    Raises
    ------
    ValueError, IndexError
        ``rows`` not a 1-D integer array of surface vertices.
    """
    n = gf.vertices.shape[0]
    cols = np.asarray(cols, dtype=np.intp)
    if rows is None:
        return reader(gf).apply_all(cols, g)
    rows = np.asarray(rows)
    if rows.ndim != 1 or (rows.size and not np.issubdtype(rows.dtype, np.integer)):
        raise ValueError(f"rows must be a 1-D array of vertex indices, got shape {rows.shape} dtype {rows.dtype}")
    if rows.size and (rows.min() < 0 or rows.max() >= n):
        raise IndexError(f"rows hold vertex indices outside 0..{n - 1}")
    live = cols >= 0
    c, gl = cols[live], np.asarray(g)[live]
    if c.size == 0 or rows.size == 0:
        return np.zeros((rows.size, 3))
    return (reader(gf).gather(dof3(rows), c) @ gl).reshape(-1, 3)


def constraint_rows(gf: ComplianceSource, V: np.ndarray, loc: np.ndarray, w: np.ndarray, normals: np.ndarray,
                    sticky: bool) -> np.ndarray:
    """``Y = (D_VV G)^T``: the displacement of the vertices V per unit contact multiplier, (m, 3|V|).

    ``G`` is the constraint matrix of :mod:`hailstorm.runtime.contact` (``B`` for sticky
    contacts, ``m = 3s``; ``B N`` for frictionless ones, ``m = s``); ``loc``, ``w`` (s, P) the
    position in V and the weight of each contact's vertices, ``normals`` (s, 3).
    """
    return reader(gf).constraint_rows(np.asarray(V, dtype=np.intp), loc, w, normals, sticky)


def response_columns(gf: ComplianceSource, cols: np.ndarray, loc: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Full-surface response ``D[:, U] B`` of contacts on the vertex list U, (3n, 3k), F-ordered.

    ``cols``: column dofs of U (``-1`` at clamped vertices); ``loc`` (k, P):
    positions in U of each contact's vertices, ``weights`` (k, P) theirs.
    """
    return reader(gf).response_columns(np.asarray(cols, dtype=np.intp), loc, weights)


def pair_blocks(gf: ComplianceSource, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """The 3 x 3 blocks ``D[rows[k], cols[k]]`` (surface vertex rows, contactable vertex columns), (k, 3, 3)."""
    return reader(gf).pair_blocks(rows, cols)
