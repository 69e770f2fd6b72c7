"""Dense linear algebra inside compiled code: SciPy's LAPACK and BLAS called directly.

numba's ``np.linalg.solve`` copies its right-hand side in with a slice assignment,
which compiles numba's shape-error formatting (string conversions, concatenation:
~3.5 s of a first run's compile, for a message that this copy can never raise).
:func:`solve` makes the same LAPACK call (``dgesv``, the routine numba's own
``np.linalg.solve`` reaches) on the same column-major copies, filled by loops, so
its errors are the same (``LinAlgError`` for a non-finite input or a singular
matrix) and its result is that routine's on that data.

:func:`cholesky`, :func:`inverse` and :func:`eigh` do the same for
``np.linalg.cholesky``, ``np.linalg.inv`` and ``np.linalg.eigh`` (``dpotrf``,
``dgetrf`` / ``dgetri`` and ``dsyevd`` with LAPACK's own workspace query, on the
copies numba's own versions make), without their input checks' compile cost (the
storm's SPD inverse, :func:`hailstorm.runtime.compiled.contacts.inv_spd`, checks
its input once); :func:`gram` and :func:`gemm` call BLAS ``dgemm``.

The interface is a documented one: SciPy publishes its LAPACK and BLAS as
``scipy.linalg.cython_lapack`` / ``cython_blas``; each routine's address comes from
``numba.extending.get_cython_function_address`` and is registered for numba's
linker under a ``hailstorm_`` name with ``llvmlite.binding.add_symbol``; the kernels
call it as an external function of that name (``numba.types.ExternalFunction``),
with the Fortran calling convention (every argument by pointer, ``int`` integers,
one-byte characters). Not ``ctypes.CFUNCTYPE``: numba bakes a ctypes function's
address into the machine code, and a kernel holding a process's address cannot be
cached on disk ("uses dynamic globals"): every caller would compile again in every
process. A symbol is resolved when the cached code is loaded (this module, imported
by every caller, registers them first).
"""

from __future__ import annotations

import llvmlite.binding as llvm
import numpy as np
from numba import types
from numba.extending import get_cython_function_address

from hailstorm.runtime.compiled.jit import kernel

__all__ = ["cholesky", "eigh", "gemm", "gram", "inverse", "solve"]

_I = types.CPointer(types.int32)  # Fortran INTEGER (SciPy's cython_lapack: C int)
_D = types.CPointer(types.float64)
_C = types.CPointer(types.uint8)  # Fortran CHARACTER*1


def _external(module: str, name: str, *args: types.Type) -> types.ExternalFunction:
    """SciPy's ``module.name`` as a numba external function ``hailstorm_<name>`` (void, ``args``)."""
    symbol = "hailstorm_" + name
    llvm.add_symbol(symbol, get_cython_function_address(module, name))
    return types.ExternalFunction(symbol, types.void(*args))


_LAPACK, _BLAS = "scipy.linalg.cython_lapack", "scipy.linalg.cython_blas"
#: ``dgesv(n, nrhs, a, lda, ipiv, b, ldb, info)``
_dgesv = _external(_LAPACK, "dgesv", _I, _I, _D, _I, _I, _D, _I, _I)
#: ``dpotrf(uplo, n, a, lda, info)`` (Cholesky)
_dpotrf = _external(_LAPACK, "dpotrf", _C, _I, _D, _I, _I)
#: ``dgetrf(m, n, a, lda, ipiv, info)`` (LU)
_dgetrf = _external(_LAPACK, "dgetrf", _I, _I, _D, _I, _I, _I)
#: ``dgetri(n, a, lda, ipiv, work, lwork, info)`` (inverse from the LU)
_dgetri = _external(_LAPACK, "dgetri", _I, _D, _I, _I, _D, _I, _I)
#: ``dsyevd(jobz, uplo, n, a, lda, w, work, lwork, iwork, liwork, info)`` (symmetric eigendecomposition)
_dsyevd = _external(_LAPACK, "dsyevd", _C, _C, _I, _D, _I, _D, _D, _I, _I, _I, _I)
#: ``dgemm(transa, transb, m, n, k, alpha, a, lda, b, ldb, beta, c, ldc)``
_dgemm = _external(_BLAS, "dgemm", _C, _C, _I, _I, _I, _D, _D, _I, _D, _I, _D, _D, _I)
_UP, _LO, _VECTORS = ord("U"), ord("L"), ord("V")
_TRANS, _NOTRANS = ord("t"), ord("n")


@kernel
def solve(A, b):  # pragma: no cover (compiled)
    """``np.linalg.solve(A, b)`` for a float64 (n, n) ``A`` and (n,) ``b`` (LU with partial
    pivoting, LAPACK ``dgesv`` on the column-major copy numba's solve makes).

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
    iv = np.empty(3, np.int32)  # n (also lda, ldb), nrhs, info
    iv[0], iv[1] = n, 1
    ipiv = np.empty(n, np.int32)
    _dgesv(iv[0:].ctypes, iv[1:].ctypes, at.ctypes, iv[0:].ctypes, ipiv.ctypes, x.ctypes, iv[0:].ctypes,
           iv[2:].ctypes)
    info = iv[2]
    if info < 0:
        raise ValueError("LAPACK dgesv: an illegal argument")
    if info > 0:
        raise np.linalg.LinAlgError("Matrix is singular to machine precision.")
    return x


@kernel
def cholesky(A):  # pragma: no cover (compiled)
    """``np.linalg.cholesky(A)`` of a finite symmetric float64 (n, n) ``A`` (LAPACK ``dpotrf``
    as numba calls it), and whether ``A`` is positive definite (``L, ok``; ``L`` is meaningless
    when not ``ok``). The caller checks finiteness."""
    n = A.shape[0]
    out = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            out[i, j] = A[i, j]
    if n == 0:
        return out, True
    # numba's cholesky: UP on the C-ordered copy (it is its own transpose in F order)
    iv = np.empty(2, np.int32)  # n (also lda), info
    iv[0] = n
    uplo = np.empty(1, np.uint8)
    uplo[0] = _UP
    _dpotrf(uplo.ctypes, iv[0:].ctypes, out.ctypes, iv[0:].ctypes, iv[1:].ctypes)
    info = iv[1]
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
    """``np.linalg.inv(A)`` of a finite float64 (n, n) ``A`` (LAPACK ``dgetrf`` and ``dgetri``
    with its workspace query, as numba's; a Fortran-ordered array, as numba's). The caller
    checks finiteness.

    Raises
    ------
    numpy.linalg.LinAlgError
        ``A`` is singular.
    """
    n = A.shape[0]
    acpy = _fortran_copy(A)  # as numba's inv copies
    if n == 0:
        return acpy
    iv = np.empty(3, np.int32)  # n (also m, lda), lwork, info
    iv[0] = n
    ipiv = np.empty(n, np.int32)
    _dgetrf(iv[0:].ctypes, iv[0:].ctypes, acpy.ctypes, iv[0:].ctypes, ipiv.ctypes, iv[2:].ctypes)
    if iv[2] < 0:
        raise ValueError("LAPACK dgetrf: an illegal argument")
    if iv[2] > 0:
        raise np.linalg.LinAlgError("Matrix is singular to machine precision.")
    query = np.empty(1)
    iv[1] = -1  # workspace query: the optimal lwork comes back in work[0]
    _dgetri(iv[0:].ctypes, acpy.ctypes, iv[0:].ctypes, ipiv.ctypes, query.ctypes, iv[1:].ctypes, iv[2:].ctypes)
    iv[1] = max(1, int(query[0]))
    work = np.empty(iv[1])
    _dgetri(iv[0:].ctypes, acpy.ctypes, iv[0:].ctypes, ipiv.ctypes, work.ctypes, iv[1:].ctypes, iv[2:].ctypes)
    if iv[2] < 0:
        raise ValueError("LAPACK dgetri: an illegal argument")
    if iv[2] > 0:
        raise np.linalg.LinAlgError("Matrix is singular to machine precision.")
    return acpy


@kernel
def eigh(A):  # pragma: no cover (compiled)
    """``np.linalg.eigh(A)`` of a finite symmetric float64 (n, n) ``A`` (LAPACK ``dsyevd``,
    lower triangle, with its workspace query, as numba's): ascending eigenvalues and the
    eigenvectors (columns, Fortran-ordered). The caller checks finiteness.

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
    iv = np.empty(4, np.int32)  # n (also lda), lwork, liwork, info
    iv[0], iv[1], iv[2] = n, -1, -1  # workspace query first
    ch = np.empty(2, np.uint8)
    ch[0], ch[1] = _VECTORS, _LO
    query = np.empty(1)
    iquery = np.empty(1, np.int32)
    _dsyevd(ch[0:].ctypes, ch[1:].ctypes, iv[0:].ctypes, acpy.ctypes, iv[0:].ctypes, w.ctypes, query.ctypes,
            iv[1:].ctypes, iquery.ctypes, iv[2:].ctypes, iv[3:].ctypes)
    if iv[3] == 0:
        iv[1], iv[2] = max(1, int(query[0])), max(1, iquery[0])
        work = np.empty(iv[1])
        iwork = np.empty(iv[2], np.int32)
        _dsyevd(ch[0:].ctypes, ch[1:].ctypes, iv[0:].ctypes, acpy.ctypes, iv[0:].ctypes, w.ctypes, work.ctypes,
                iv[1:].ctypes, iwork.ctypes, iv[2:].ctypes, iv[3:].ctypes)
    if iv[3] != 0:
        raise ValueError("Internal algorithm failed to converge.")
    return w, acpy


@kernel
def _dgemm_call(ta, tb, m, n, k, alpha, A, lda, B, ldb, beta, C, ldc):  # pragma: no cover (compiled)
    """BLAS ``dgemm`` with ``ta`` / ``tb`` the transpose letters (``_TRANS`` / ``_NOTRANS``) and the
    scalars passed by value (copied to the pointers Fortran takes)."""
    ch = np.empty(2, np.uint8)
    ch[0], ch[1] = ta, tb
    iv = np.empty(6, np.int32)  # m, n, k, lda, ldb, ldc
    iv[0], iv[1], iv[2], iv[3], iv[4], iv[5] = m, n, k, lda, ldb, ldc
    ab = np.empty(2)
    ab[0], ab[1] = alpha, beta
    _dgemm(ch[0:].ctypes, ch[1:].ctypes, iv[0:].ctypes, iv[1:].ctypes, iv[2:].ctypes, ab[0:].ctypes, A.ctypes,
           iv[3:].ctypes, B.ctypes, iv[4:].ctypes, ab[1:].ctypes, C.ctypes, iv[5:].ctypes)


@kernel
def gram(A):  # pragma: no cover (compiled)
    """``A.T @ A`` of a Fortran-ordered float64 (n, n) ``A`` (what :func:`inverse` returns): the
    ``dgemm`` call numba's matmul makes on the same buffer, a C-ordered result."""
    n = A.shape[0]
    out = np.empty((n, n))
    if n == 0:
        return out
    # numba's dot_2_mm for x = A.T (C layout) @ y = A (F layout) into C: transa 't' on y, transb 'n'
    # on x, both the same buffer with leading dimension n
    _dgemm_call(_TRANS, _NOTRANS, n, n, n, 1.0, A, n, A, n, 0.0, out, n)
    return out


@kernel
def gemm(transa, transb, m, n, k, alpha, A, lda, B, ldb, beta, C, ldc):  # pragma: no cover (compiled)
    """BLAS ``dgemm``: ``C = alpha op(A) op(B) + beta C`` on column-major data.

    ``A``, ``B`` and ``C`` are 1-D float64 arrays whose first element is the
    matrix's (0, 0) (pass a slice to start inside a larger array); ``op`` is the
    transpose where ``transa`` / ``transb`` is true. C is (m, n) with leading
    dimension ``ldc``; nothing is checked.
    """
    _dgemm_call(_TRANS if transa else _NOTRANS, _TRANS if transb else _NOTRANS, m, n, k, alpha, A, lda, B, ldb,
                beta, C, ldc)
