"""Deprecated: the scene moved to :mod:`hailstorm.runtime.storm.scene` (the storm's settings).

``hailstorm.runtime.Scene`` and its sections are unchanged; this module only
keeps old imports of ``hailstorm.runtime.scene`` working, with a warning.
"""

from __future__ import annotations

import warnings

from hailstorm.runtime.storm.scene import (  # noqa: F401 (re-exported)
    ContactSettings,
    HailSettings,
    OutputSettings,
    Scene,
    SceneError,
    SeatSettings,
    StormSettings,
    StormTooLarge,
    TimeSettings,
    available_memory,
)

warnings.warn("hailstorm.runtime.scene moved to hailstorm.runtime.storm.scene; import Scene and its sections "
              "from hailstorm.runtime", DeprecationWarning, stacklevel=2)
