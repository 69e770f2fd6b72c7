"""The matrix exponential, compiled: scaling and squaring with a Padé approximant
(Higham 2005, "The scaling and squaring method for the matrix exponential revisited",
SIAM J. Matrix Anal. Appl. 26(4), its Algorithm 2.3).

The exact contact step advances a contact set in closed form through its modes; where
the modal basis is (nearly) defective (critically damped modes, repeated eigenvalues)
it advances with :func:`expm` instead (:mod:`hailstorm.runtime.compiled.integrators`).
The tests hold it to :func:`scipy.linalg.expm`.
"""

from __future__ import annotations

import math

import numpy as np

from hailstorm.runtime.compiled._jit import _njit

__all__ = ["expm"]

#: the 1-norm bounds up to which the Padé degrees 3, 5, 7, 9 and 13 are accurate to double precision
#: (Higham 2005, Table 2.3)
_THETA = np.array([1.495585217958292e-2, 2.539398330063230e-1, 9.504178996162932e-1, 2.097847961257068e0])
_THETA13 = 5.371920351148152e0
#: the numerator coefficients b_0..b_m of the [m/m] Padé approximant of exp, one row per degree (zero padded)
_B = np.zeros((5, 14))
_B[0, :4] = [120.0, 60.0, 12.0, 1.0]
_B[1, :6] = [30240.0, 15120.0, 3360.0, 420.0, 30.0, 1.0]
_B[2, :8] = [17297280.0, 8648640.0, 1995840.0, 277200.0, 25200.0, 1512.0, 56.0, 1.0]
_B[3, :10] = [17643225600.0, 8821612800.0, 2075673600.0, 302702400.0, 30270240.0, 2162160.0, 110880.0, 3960.0,
              90.0, 1.0]
_B[4, :] = [64764752532480000.0, 32382376266240000.0, 7771770303897600.0, 1187353796428800.0,
            129060195264000.0, 10559470521600.0, 670442572800.0, 33522128640.0, 1323241920.0, 40840800.0,
            960960.0, 16380.0, 182.0, 1.0]


@_njit
def expm(A):  # pragma: no cover (compiled)
    """``exp(A)`` of a real square matrix ``A`` (an (n, n) float ndarray; returns a new one).

    The lowest Padé degree m in (3, 5, 7, 9) whose bound ``theta_m`` covers ``||A||_1``,
    else degree 13 on ``A / 2^s`` (``s`` the least with ``||A||_1 / 2^s <= theta_13``)
    squared ``s`` times.
    """
    n = A.shape[0]
    ident = np.eye(n)
    nrm = 0.0
    for c in range(n):
        col = 0.0
        for r in range(n):
            col += abs(A[r, c])
        nrm = max(nrm, col)
    if not np.isfinite(nrm):
        return np.full((n, n), np.nan)
    A2 = A @ A
    for d in range(_THETA.size):
        if nrm <= _THETA[d]:
            m = 3 + 2 * d
            b = _B[d]
            # U = A (b_1 I + b_3 A^2 + ...), V = b_0 I + b_2 A^2 + ...
            P = ident.copy()
            U = b[1] * ident
            V = b[0] * ident
            for k in range(1, m // 2 + 1):
                P = P @ A2
                U += b[2 * k + 1] * P
                V += b[2 * k] * P
            U = A @ U
            return np.ascontiguousarray(np.linalg.solve(V - U, V + U))
    s = 0
    if nrm > _THETA13:
        s = int(math.ceil(math.log2(nrm / _THETA13)))
    sc = 2.0 ** (-s)
    As = A * sc
    A2 = A2 * (sc * sc)
    A4 = A2 @ A2
    A6 = A4 @ A2
    b = _B[4]
    U = As @ (A6 @ (b[13] * A6 + b[11] * A4 + b[9] * A2) + b[7] * A6 + b[5] * A4 + b[3] * A2 + b[1] * ident)
    V = A6 @ (b[12] * A6 + b[10] * A4 + b[8] * A2) + b[6] * A6 + b[4] * A4 + b[2] * A2 + b[0] * ident
    R = np.ascontiguousarray(np.linalg.solve(V - U, V + U))
    for _ in range(s):
        R = R @ R
    return R

