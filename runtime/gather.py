"""The storm's import path for access to D: :mod:`hailstorm.runtime.contact.compliance` under its old names.

The storm (``patches.py``, ``soft_contacts.py``, ``collide.py``) imports these
names from here; new code imports them from the contact core. Remove this module
once the storm does too.
"""

from hailstorm.runtime.contact.compliance import column_dofs, dof3, gather, unique_inverse

# the storm's names for them
_column_dofs = column_dofs
_dof3 = dof3
_gather = gather
_unique_inverse = unique_inverse

__all__: list[str] = []
