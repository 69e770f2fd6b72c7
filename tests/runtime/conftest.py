"""Fixtures of the runtime's tests."""

import pytest
from helpers import plate_gf


@pytest.fixture(scope="module")
def gf():
    """The small clamped plate of :func:`helpers.plate_gf` (a module overrides it with its own)."""
    return plate_gf()
