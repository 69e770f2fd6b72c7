"""Validation of the contact API's input: contacts, modes, patch radii (clear errors before any work)."""

from __future__ import annotations

from enum import StrEnum
from typing import Any, Literal, overload

import numpy as np

from hailstorm.runtime.bundle.compliance import ComplianceSource
from hailstorm.runtime.contact.policy import BARY_NEG_TOL, BARY_SUM_TOL
from hailstorm.runtime.contact.normals import triangle_normals
from hailstorm.runtime.contact.weights import PATCH_PROFILES

__all__ = ["ContactMode", "Mode", "check_contacts", "check_mode", "check_patch"]


class ContactMode(StrEnum):
    """A contact mode, resolved once from its name (``ContactMode("sticky")``).

    A string enum: it compares equal to, prints as and serialises to its name, so a
    mode given as ``"sticky"`` and one given as ``ContactMode.STICKY`` are the same
    thing; what the mode means is read from its members, never from string tests.
    """

    #: all three components of each contact point constrained (no slip)
    STICKY = "sticky"
    #: the normal component only (free tangential motion)
    FRICTIONLESS = "frictionless"

    @property
    def sticky(self) -> bool:
        """All three force components are unknowns (the tangential ones stuck)."""
        return self is ContactMode.STICKY

    @property
    def dofs(self) -> int:
        """Unknowns per contact in ``W`` and ``K``: 3 (sticky) or 1 (the normal force)."""
        return 3 if self is ContactMode.STICKY else 1

    @property
    def tangential(self) -> str:
        """The tangential rule: ``"stuck"`` or ``"free"``."""
        return "stuck" if self is ContactMode.STICKY else "free"


#: what a mode argument may be: a :class:`ContactMode` or its name
Mode = ContactMode | str


@overload
def check_contacts(gf: ComplianceSource, tri_idx: Any, bary: Any, normals: Any = None,
                   need_normals: Literal[True] = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]: ...


@overload
def check_contacts(gf: ComplianceSource, tri_idx: Any, bary: Any, normals: Any,
                   need_normals: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]: ...


def check_contacts(
    gf: ComplianceSource,
    tri_idx: Any,
    bary: Any,
    normals: Any = None,
    need_normals: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Validate contact triangles, barycentric coordinates and normals.

    The triangles' normals are computed (and checked) only if ``normals`` is
    None and ``need_normals``; otherwise None is returned for them.
    """
    t = np.asarray(tri_idx)
    if t.ndim != 1:
        raise ValueError(f"triangles must have shape (s,), got {t.shape}")
    s = t.size
    if s and not np.issubdtype(t.dtype, np.integer):
        raise ValueError(f"triangles must be integer triangle indices, got dtype {t.dtype}")
    t = t.astype(np.intp, copy=False)
    m = gf.triangles.shape[0]
    if s and (t.min() < 0 or t.max() >= m):
        bad = t[(t < 0) | (t >= m)]
        raise IndexError(f"triangle indices {bad[:5].tolist()} are outside 0..{m - 1}")
    b = np.asarray(bary, dtype=np.float64)
    if b.shape != (s, 3):
        raise ValueError(f"barycentric must have shape ({s}, 3) to match triangles, got {b.shape}")
    if not np.isfinite(b).all():
        raise ValueError("barycentric coordinates contain NaN or infinity")
    if s:
        err = np.abs(b.sum(axis=1) - 1.0)
        if err.max() > BARY_SUM_TOL:
            k = int(np.argmax(err))
            raise ValueError(f"barycentric coordinates of contact {k} sum to {b[k].sum()!r}, not 1 (tolerance {BARY_SUM_TOL})")
        if b.min() < -BARY_NEG_TOL:
            k = int(np.argmin(b.min(axis=1)))
            raise ValueError(f"barycentric coordinates of contact {k} are negative ({b[k].tolist()}): the point lies outside its triangle")
    verts = gf.triangles[t]
    ok = gf.contactable[verts] | gf.fixed[verts]
    if not ok.all():
        k = int(np.flatnonzero(~ok.all(axis=1))[0])
        raise ValueError(
            f"contact {k} lies on triangle {int(t[k])} whose vertices {verts[k].tolist()} are not all "
            "contactable or clamped: the bundle holds no compliance column for them"
        )
    if normals is None and not need_normals:
        n = None
    elif normals is None:
        n = triangle_normals(gf.vertices, verts)
        if s and not np.any(n, axis=1).all():
            raise ValueError("a contacted triangle is degenerate (zero area): pass normals explicitly")
    else:
        n = np.asarray(normals, dtype=np.float64)
        if n.shape != (s, 3):
            raise ValueError(f"normals must have shape ({s}, 3), got {n.shape}")
        if not np.isfinite(n).all():
            raise ValueError("normals contain NaN or infinity")
        ln = np.linalg.norm(n, axis=1, keepdims=True)
        if np.any(ln == 0):
            raise ValueError("normals contain a zero vector")
        n = n / ln
    return t, b, n


def check_mode(mode: Mode) -> ContactMode:
    """``mode`` as a :class:`ContactMode`; ValueError unless "sticky" or "frictionless"."""
    try:
        return ContactMode(mode)
    except ValueError:
        raise ValueError(f"mode must be 'sticky' or 'frictionless', got {mode!r}") from None


def check_patch(patch_radius: Any, s: int, profile: str) -> np.ndarray | None:
    """Patch radii as an (s,) array, or None for point contacts only."""
    if profile not in PATCH_PROFILES:
        raise ValueError(f"patch_profile must be one of {PATCH_PROFILES}, got {profile!r}")
    if patch_radius is None:
        return None
    a = np.asarray(patch_radius, dtype=np.float64)
    if a.ndim > 1 or (a.ndim == 1 and a.shape != (s,)):
        raise ValueError(f"patch_radius must be a scalar or have shape ({s},), got {a.shape}")
    if not np.isfinite(a).all() or np.any(a < 0):
        raise ValueError("patch_radius must be finite and non-negative")
    a = np.broadcast_to(a, (s,)).copy()
    return a if a.any() else None
