"""A storm's outputs: what a run writes and what a person looks at.

* :mod:`~hailstorm.runtime.output.files` -- ``summary.json``, ``impacts.csv``, the
  ``.vtu`` ParaView series; :mod:`~hailstorm.runtime.output.vtkhdf` -- the frames in one file;
* :mod:`~hailstorm.runtime.output.storm_output` -- the output folder as a unit
  (:class:`StormOutput`: staged, then moved into place);
* :mod:`~hailstorm.runtime.output.animation` -- the video, drawn in 3-D
  (:mod:`~hailstorm.runtime.output.video3d`) or 2-D (:mod:`~hailstorm.runtime.output.render`);
* :mod:`~hailstorm.runtime.output.viewer` -- the storm as one page in the browser.
"""

from hailstorm.runtime.output.animation import write_animation
from hailstorm.runtime.output.files import summary, write_paraview, write_summary
from hailstorm.runtime.output.storm_output import OutputError, StormOutput

__all__ = ["OutputError", "StormOutput", "summary", "write_animation", "write_paraview", "write_summary"]
