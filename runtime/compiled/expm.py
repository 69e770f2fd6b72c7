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

from hailstorm.runtime.compiled.jit import kernel

__all__ = ["expm"]

#: the 1-norm bound up to which the degree-13 Padé approximant is accurate to double precision
#: (Higham 2005, Table 2.3)
_THETA13 = 5.371920351148152e0
#: the coefficients b_0..b_13 of the [13/13] Padé approximant of exp
_B13 = np.array([64764752532480000.0, 32382376266240000.0, 7771770303897600.0, 1187353796428800.0,
                 129060195264000.0, 10559470521600.0, 670442572800.0, 33522128640.0, 1323241920.0, 40840800.0,
                 960960.0, 16380.0, 182.0, 1.0])


@kernel
def expm(A):  # pragma: no cover (compiled)
    """``exp(A)`` of a real square matrix ``A`` (an (n, n) float ndarray; returns a new one).

    The degree-13 Padé approximant of ``exp(A / 2^s)``, ``s`` the least with
    ``||A||_1 / 2^s <= theta_13``, squared ``s`` times. (The lower degrees Higham takes
    for small norms only save products; at small norms degree 13 is as accurate. The
    Padé denominator is well conditioned under the bound, so its inverse is taken, the
    specialisation of ``np.linalg.inv`` the contact kernels compile anyway.)
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
    s = 0
    if nrm > _THETA13:
        s = int(math.ceil(math.log2(nrm / _THETA13)))
    As = A * (2.0 ** (-s))
    A2 = As @ As
    A4 = A2 @ A2
    A6 = A4 @ A2
    b = _B13
    U = As @ (A6 @ (b[13] * A6 + b[11] * A4 + b[9] * A2) + b[7] * A6 + b[5] * A4 + b[3] * A2 + b[1] * ident)
    V = A6 @ (b[12] * A6 + b[10] * A4 + b[8] * A2) + b[6] * A6 + b[4] * A4 + b[2] * A2 + b[0] * ident
    R = np.linalg.inv(V - U) @ (V + U)
    for _ in range(s):
        R = R @ R
    return R
