"""``python -m hailstorm``: the command line (:func:`hailstorm.cli.main`)."""

import sys

from hailstorm.cli import main

sys.exit(main())
