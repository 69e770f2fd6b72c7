"""``python -m hailstorm``: the command line (:func:`hailstorm.runtime.cli.main`)."""

import sys

from hailstorm.runtime.cli import main

sys.exit(main())
