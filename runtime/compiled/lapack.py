"""Dense linear algebra inside compiled code: LAPACK called directly.

numba's ``np.linalg.solve`` copies its right-hand side in with a slice assignment,
which compiles numba's shape-error formatting (string conversions, concatenation:
~3.5 s of a first run's compile, for a message that this copy can never raise).
:func:`solve` makes the same LAPACK call (numba's own ``numba_xgesv`` entry, which
calls SciPy's ``dgesv``) on the same column-major copies, filled by loops, so its
result is ``np.linalg.solve``'s bit for bit and its errors are the same
(``LinAlgError`` for a non-finite input or a singular matrix).

:func:`cholesky`, :func:`inverse` and :func:`eigh` do the same for
``np.linalg.cholesky``, ``np.linalg.inv`` and ``np.linalg.eigh`` (numba's
``numba_xxpotrf``, ``numba_xxgetrf`` / ``numba_ez_xxgetri`` and
``numba_ez_xxxevd`` entries, on the copies numba's own versions make): the same
results bit for bit, without their input checks' compile cost (the storm's SPD
inverse, :func:`hailstorm.runtime.compiled.contacts.inv_spd`, checks its input once).
"""

from __future__ import annotations

import numpy as np
from numba import types
from numba.np.linalg import F_INT_nbtype, F_INT_nptype

from hailstorm.runtime.compiled.jit import kernel

__all__ = ["cholesky", "eigh", "gemm", "gram", "inverse", "solve"]

#: numba's LAPACK shim (``numba/_lapack.c``): ``xgesv(kind, n, nrhs, a, lda, ipiv, b, ldb)`` -> info
_xgesv = types.ExternalFunction("numba_xgesv", types.intc(
    types.char, types.intp, types.intp, types.CPointer(types.float64), types.intp,
    types.CPointer(F_INT_nbtype), types.CPointer(types.float64), types.intp))

#: ``xxpotrf(kind, uplo, n, a, lda)`` -> info (Cholesky)
_xxpotrf = types.ExternalFunction("numba_xxpotrf", types.intc(
    types.char, types.char, types.intp, types.CPointer(types.float64), types.intp))
#: ``xxgetrf(kind, m, n, a, lda, ipiv)`` -> info (LU)
_xxgetrf = types.ExternalFunction("numba_xxgetrf", types.intc(
    types.char, types.intp, types.intp, types.CPointer(types.float64), types.intp, types.CPointer(F_INT_nbtype)))
#: ``ez_xxgetri(kind, n, a, lda, ipiv)`` -> info (inverse from the LU)
_xxgetri = types.ExternalFunction("numba_ez_xxgetri", types.intc(
    types.char, types.intp, types.CPointer(types.float64), types.intp, types.CPointer(F_INT_nbtype)))
#: ``ez_xxxevd(kind, jobz, uplo, n, a, lda, w)`` -> info (symmetric eigendecomposition)
_xxxevd = types.ExternalFunction("numba_ez_xxxevd", types.intc(
    types.char, types.char, types.char, types.intp, types.CPointer(types.float64), types.intp,
    types.CPointer(types.float64)))
#: BLAS ``xxgemm(kind, transa, transb, m, n, k, alpha, a, lda, b, ldb, beta, c, ldc)`` -> status
_F64P = types.CPointer(types.float64)
_xxgemm = types.ExternalFunction("numba_xxgemm", types.intc(
    types.char, types.char, types.char, types.intp, types.intp, types.intp, _F64P, _F64P, types.intp,
    _F64P, types.intp, _F64P, _F64P, types.intp))
_UP, _LO, _VECTORS = ord("U"), ord("L"), ord("V")
_TRANS, _NOTRANS = ord("t"), ord("n")

#: LAPACK's type letter for float64
_KIND = ord("d")


@kernel
def solve(A, b):  # pragma: no cover (compiled)
    """``np.linalg.solve(A, b)`` for a float64 (n, n) ``A`` and (n,) ``b`` (LU with partial
    pivoting, LAPACK ``dgesv``: the same call on the same data, the same result).

    Raises
    ------
    numpy.linalg.LinAlgError
        ``A`` or ``b`` holds an inf or NaN, or ``A`` is singular.
    """
    n = A.shape[0]
    for i in range(n):
        if not np.isfinite(b[i]):
            raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
        for j in range(n):
            if not np.isfinite(A[i, j]):
                raise np.linalg.LinAlgError("Array must not contain infs or NaNs.")
    x = np.empty(n)
    if n == 0:
        return x
    # column-major copy of A: at[j, i] (row-major) is A[i, j]
    at = np.empty((n, n))
    for j in range(n):
        for i in range(n):
            at[j, i] = A[i, j]
    for i in range(n):
        x[i] = b[i]
    ipiv = np.empty(n, F_INT_nptype)
    info = _xgesv(_KIND, n, 1, at.ctypes, n, ipiv.ctypes, x.ctypes, n)
    if info < 0:
        raise ValueError("LAPACK dgesv: an illegal argument")
    if info > 0:
        raise np.linalg.LinAlgError("Matrix is singular to machine precision.")
    return x


@kernel
def cholesky(A):  # pragma: no cover (compiled)
    """``np.linalg.cholesky(A)`` of a finite symmetric float64 (n, n) ``A``, bit for bit, and
    whether ``A`` is positive definite (``L, ok``; ``L`` is meaningless when not ``ok``).
    The caller checks finiteness."""
    n = A.shape[0]
    out = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            out[i, j] = A[i, j]
    if n == 0:
        return out, True
    # numba's cholesky: UP on the C-ordered copy (it is its own transpose in F order)
    info = _xxpotrf(_KIND, _UP, n, out.ctypes, n)
    if info < 0:
        raise ValueError("LAPACK dpotrf: an illegal argument")
    for col in range(n):
        for row in range(col):
            out[row, col] = 0.0
    return out, info == 0


@kernel
def _fortran_copy(A):  # pragma: no cover (compiled)
    """A Fortran-ordered copy of a square ``A`` (what numba's inv and eigh hand LAPACK)."""
    n = A.shape[0]
    acpy = np.empty((n, n)).T
    for j in range(n):
        for i in range(n):
            acpy[i, j] = A[i, j]
    return acpy


@kernel
def inverse(A):  # pragma: no cover (compiled)
    """``np.linalg.inv(A)`` of a finite float64 (n, n) ``A``, bit for bit (a Fortran-ordered
    array, as numba's). The caller checks finiteness.

    Raises
    ------
    numpy.linalg.LinAlgError
        ``A`` is singular.
    """
    n = A.shape[0]
    acpy = _fortran_copy(A)  # as numba's inv copies
    if n == 0:
        return acpy
    ipiv = np.empty(n, F_INT_nptype)
    info = _xxgetrf(_KIND, n, n, acpy.ctypes, n, ipiv.ctypes)
    if info < 0:
        raise ValueError("LAPACK dgetrf: an illegal argument")
    if info > 0:
        raise np.linalg.LinAlgError("Matrix is singular to machine precision.")
    info = _xxgetri(_KIND, n, acpy.ctypes, n, ipiv.ctypes)
    if info != 0:
        raise np.linalg.LinAlgError("Matrix is singular to machine precision.")
    return acpy


@kernel
def eigh(A):  # pragma: no cover (compiled)
    """``np.linalg.eigh(A)`` of a finite symmetric float64 (n, n) ``A``, bit for bit:
    ascending eigenvalues and the eigenvectors (columns, Fortran-ordered). The caller
    checks finiteness.

    Raises
    ------
    ValueError
        LAPACK's algorithm did not converge.
    """
    n = A.shape[0]
    acpy = _fortran_copy(A)
    w = np.empty(n)
    if n == 0:
        return w, acpy
    info = _xxxevd(_KIND, _VECTORS, _LO, n, acpy.ctypes, n, w.ctypes)
    if info != 0:
        raise ValueError("Internal algorithm failed to converge.")
    return w, acpy


@kernel
def gram(A):  # pragma: no cover (compiled)
    """``A.T @ A`` of a Fortran-ordered float64 (n, n) ``A`` (what :func:`inverse` returns), bit
    for bit numba's matmul: the same ``dgemm`` call on the same buffer, a C-ordered result."""
    n = A.shape[0]
    out = np.empty((n, n))
    if n == 0:
        return out
    one = np.ones(1)
    zero = np.zeros(1)
    # numba's dot_2_mm for x = A.T (C layout) @ y = A (F layout) into C: transa 't' on y, transb 'n'
    # on x, both the same buffer with leading dimension n
    if _xxgemm(_KIND, _TRANS, _NOTRANS, n, n, n, one.ctypes, A.ctypes, n, A.ctypes, n, zero.ctypes,
               out.ctypes, n) != 0:
        raise ValueError("BLAS dgemm failed")
    return out


@kernel
def gemm(transa, transb, m, n, k, alpha, A, lda, B, ldb, beta, C, ldc):  # pragma: no cover (compiled)
    """BLAS ``dgemm``: ``C = alpha op(A) op(B) + beta C`` on column-major data.

    ``A``, ``B`` and ``C`` are 1-D float64 arrays whose first element is the
    matrix's (0, 0) (pass a slice to start inside a larger array); ``op`` is the
    transpose where ``transa`` / ``transb`` is true. C is (m, n) with leading
    dimension ``ldc``; nothing is checked.
    """
    ab = np.empty(2)
    ab[0] = alpha
    ab[1] = beta
    ta = _TRANS if transa else _NOTRANS
    tb = _TRANS if transb else _NOTRANS
    if _xxgemm(_KIND, ta, tb, m, n, k, ab[0:].ctypes, A.ctypes, lda, B.ctypes, ldb, ab[1:].ctypes,
               C.ctypes, ldc) != 0:
        raise ValueError("BLAS dgemm failed")
