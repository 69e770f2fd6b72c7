"""The decorator every kernel of :mod:`hailstorm.runtime.compiled` uses (numba is a core dependency).

Debugging: numba's own switch ``NUMBA_DISABLE_JIT=1`` runs every kernel as plain
Python (slow: minutes for a storm that takes seconds), so that a debugger or a
print reaches inside them.
"""

from __future__ import annotations

from typing import Any, Callable

import numba

#: what the kernels run as: ``"numba"``, or ``"python"`` under ``NUMBA_DISABLE_JIT=1``
#: (the storm's statistics record it as ``backend``)
KERNELS = "python" if numba.config.DISABLE_JIT else "numba"


def kernel(f: Callable) -> Any:
    """``numba.njit(cache=True, nogil=True)``: compiled on first call, cached on disk."""
    return numba.njit(cache=True, nogil=True)(f)
