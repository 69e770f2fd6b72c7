"""A storm in the browser: ``hailstorm view OUT`` writes one self-contained HTML page
(:func:`write_page`) and with ``--serve`` serves it on localhost (:func:`serve`).

The page shows the seat's deformed surface and the stones frame by frame (orbit, zoom, play,
pause, scrub, the displacement's scale) and, for a click on a dent or a stone, its impact's
numbers from ``impacts.csv``. Its JavaScript is three.js, vendored unmodified from its npm
package in ``vendor/three/`` (its version, licence and hashes: ``vendor/three/VENDOR.md``)
and carried inside the page: nothing is fetched when it is viewed.
"""

from hailstorm.runtime.output.viewer.page import FRAME_BYTES, PAGE_NAME, PageInfo, build_page, serve, write_page
from hailstorm.runtime.output.viewer.source import StormOut, ViewerInputError, open_storm_out

__all__ = ["FRAME_BYTES", "PAGE_NAME", "PageInfo", "StormOut", "ViewerInputError", "build_page", "open_storm_out",
           "serve", "write_page"]
