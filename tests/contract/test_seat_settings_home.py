"""The default seat's settings live outside the storm's scene module, in a module that imports
neither stage's heavy parts: the runtime (and the scene reader) still import without the mesher."""

from __future__ import annotations

import json
import subprocess
import sys

#: what the runtime must never load when it is imported
OFFLINE = ("gmsh", "skfem", "meshio", "pyamg", "cholespy", "hailstorm.precompute")

PROBE = """
import json, sys
import {module}
print(json.dumps(sorted(m for m in {offline!r} if m in sys.modules)))
"""


def _loaded_by(module: str) -> list[str]:
    out = subprocess.run([sys.executable, "-c", PROBE.format(module=module, offline=OFFLINE)], check=True,
                         capture_output=True, text=True).stdout
    return json.loads(out)


def test_the_runtime_and_the_seat_settings_import_without_the_offline_stage():
    assert _loaded_by("hailstorm.runtime") == []
    assert _loaded_by("hailstorm.runtime.seat_settings") == []


def test_the_seat_settings_are_one_class_wherever_they_are_imported_from():
    from hailstorm.runtime import SeatSettings as from_runtime
    from hailstorm.runtime.seat_settings import SeatSettings
    from hailstorm.runtime.storm.scene import SeatSettings as from_scene

    assert SeatSettings is from_scene is from_runtime
    assert SeatSettings.__module__ == "hailstorm.runtime.seat_settings"
    assert SeatSettings.default().order in (1, 2)
