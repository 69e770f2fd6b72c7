"""The storm settings' errors: a bad scene value, and a storm too large for the machine."""

from __future__ import annotations

from hailstorm.runtime.sections import SceneError  # (re-exported: the settings records' error)

__all__ = ["SceneError", "StormTooLarge"]


class StormTooLarge(SceneError):
    """A storm would exceed the machine (memory, steps, or an estimated hour of
    wall time); the message names the estimate and the override."""
