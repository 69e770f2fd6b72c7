"""The storm's import path for the patch weights: :mod:`hailstorm.runtime.contact.weights` under its old name.

The storm (``storm.py``, ``patches.py``, ``soft_contacts.py``) imports these
names from here; new code imports them from the contact core. Remove this module
once the storm does too.
"""

from hailstorm.runtime.contact.weights import (
    PATCH_DROP,
    PATCH_FACING,
    PATCH_PROFILES,
    dense_B,
    dense_Bs,
    disc_table,
    hertz_radius,
    locate,
    triangle_index,
)
from hailstorm.runtime.contact.weights import patch_weights as _patch_weights


def patch_weights(gf, tri_idx, bary, radius, normals=None, *, profile="hertz", resolution=3.0, backend=None):
    """:func:`hailstorm.runtime.contact.weights.patch_weights` (the one, compiled implementation);
    ``backend`` is accepted for the storm's numpy path and ignored."""
    return _patch_weights(gf, tri_idx, bary, radius, normals, profile=profile, resolution=resolution)


# the storm's names for them
_dense_B = dense_B
_dense_Bs = dense_Bs
_disc_table = disc_table
_locate_lists = locate
_triangle_index = triangle_index

__all__ = ["PATCH_DROP", "PATCH_FACING", "PATCH_PROFILES", "hertz_radius", "patch_weights"]
