"""The storm's import path for the contact policy: :mod:`hailstorm.runtime.contact` names under their old module.

The storm (``hail.py``, ``soft_contacts.py``, ``scene.py``) imports these names
from here; new code imports them from the contact core
(:mod:`hailstorm.runtime.contact.policy`, ``.capacitance``, ``.validate``).
Remove this module once the storm does too.
"""

from hailstorm.runtime.contact.contact_set import contact_compliance
from hailstorm.runtime.contact.policy import COND_LIMIT, PINV_RCOND, RIGID_WEIGHT, is_rigid, spd_inverse
from hailstorm.runtime.contact.validate import Mode


def _rigid(gf, verts, w):  # the storm's name and signature for is_rigid
    return is_rigid(gf.fixed, verts, w)


# the storm's name for it
_contact_compliance = contact_compliance

__all__ = ["COND_LIMIT", "PINV_RCOND", "RIGID_WEIGHT", "Mode", "spd_inverse"]
