"""numba, if installed: the decorator every kernel of :mod:`hailstorm.runtime.compiled` uses."""

from __future__ import annotations

from typing import Any, Callable

try:  # pragma: no cover - exercised by whichever of the two environments runs the tests
    import numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover
    HAVE_NUMBA = False


def _njit(f: Callable) -> Any:
    """``numba.njit(cache=True)`` when numba is installed, else the plain function
    (never called then: the storm takes the numpy path)."""
    return numba.njit(cache=True, nogil=True)(f) if HAVE_NUMBA else f
