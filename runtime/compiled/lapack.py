"""A dense solve inside compiled code: LAPACK ``dgesv`` called directly.

numba's ``np.linalg.solve`` copies its right-hand side in with a slice assignment,
which compiles numba's shape-error formatting (string conversions, concatenation:
~3.5 s of a first run's compile, for a message that this copy can never raise).
:func:`solve` makes the same LAPACK call (numba's own ``numba_xgesv`` entry, which
calls SciPy's ``dgesv``) on the same column-major copies, filled by loops, so its
result is ``np.linalg.solve``'s bit for bit and its errors are the same
(``LinAlgError`` for a non-finite input or a singular matrix).
"""

from __future__ import annotations

import numpy as np
from numba import types
from numba.np.linalg import F_INT_nbtype, F_INT_nptype

from hailstorm.runtime.compiled.jit import kernel

__all__ = ["solve"]

#: numba's LAPACK shim (``numba/_lapack.c``): ``xgesv(kind, n, nrhs, a, lda, ipiv, b, ldb)`` -> info
_xgesv = types.ExternalFunction("numba_xgesv", types.intc(
    types.char, types.intp, types.intp, types.CPointer(types.float64), types.intp,
    types.CPointer(F_INT_nbtype), types.CPointer(types.float64), types.intp))

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
