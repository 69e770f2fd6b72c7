"""The hail storm: stones falling on the seat, contacts through the capacitance.

Siblings, each a part the driver composes (none imports the driver):

* :mod:`~hailstorm.runtime.storm.scene` -- the scene: :class:`Scene` (TOML), the
  pre-flight estimate, the default seat's ``[seat]`` settings; its settings
  sections in :mod:`~hailstorm.runtime.storm.scene_sections`;
* :mod:`~hailstorm.runtime.storm.hail` -- hailstone physics: sizes, drag,
  terminal speed, the dashpot and the contact step's integrators;
* :mod:`~hailstorm.runtime.storm.stones` -- the stones in flight and their spawning;
* :mod:`~hailstorm.runtime.storm.seat` -- the seat's deformed state;
* :mod:`~hailstorm.runtime.storm.collide` -- broad and narrow phase against the deformed surface;
* :mod:`~hailstorm.runtime.storm.patches` -- the contact patches' sizes and weights;
* :mod:`~hailstorm.runtime.storm.contact_set` -- the contacts of a step as a layer over
  the contact API's capacitance;
* :mod:`~hailstorm.runtime.storm.soft_contacts` / :mod:`~hailstorm.runtime.storm.integrators`
  -- the contact step of a sub-step;
* :mod:`~hailstorm.runtime.storm.recording` -- frames, statistics, :class:`StormResult`;
* :mod:`~hailstorm.runtime.storm.warmup` -- the first run's compile;
* :mod:`~hailstorm.runtime.storm.free_run` -- the steps without soft contacts, many per call in
  compiled code;
* :mod:`~hailstorm.runtime.storm.driver` -- :class:`Storm`, the parts composed into a step;
* :mod:`~hailstorm.runtime.storm.run` -- :func:`run_storm`, a storm from start to end.

The driver's names are imported on first use (PEP 562), so that a part (the
scene, which the command line and the offline stage's estimates read) does
not load the driver.
"""

from __future__ import annotations

from typing import Any

__all__ = ["Storm", "StormResult", "run_storm"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from hailstorm.runtime.storm import driver, run

        if name == "run_storm":
            return run.run_storm

        return getattr(driver, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
