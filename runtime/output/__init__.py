"""A storm's outputs: what a run writes and what a person looks at.

* :mod:`~hailstorm.runtime.output.files` -- ``summary.json``, the ParaView
  series, the output folder as a unit (:class:`StormOutput`: staged, then
  moved into place);
* :mod:`~hailstorm.runtime.output.render` -- the video (frames drawn with
  matplotlib, encoded with imageio-ffmpeg).
"""

from hailstorm.runtime.output.files import OutputError, StormOutput, summary, write_paraview, write_summary
from hailstorm.runtime.output.animation import write_animation

__all__ = ["OutputError", "StormOutput", "summary", "write_animation", "write_paraview", "write_summary"]
