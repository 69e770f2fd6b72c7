"""Sphinx configuration of the hailstorm documentation.

Build (fails on any warning)::

    sphinx-build -W --keep-going -b html docs /tmp/hailstorm-docs
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import hailstorm

sys.path.insert(0, str(Path(__file__).parent / "_ext"))

project = "hailstorm"
author = "The hailstorm developers"
copyright = "2026, the hailstorm developers"
release = hailstorm.__version__
version = release

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.napoleon",
    "sphinx.ext.mathjax",
    "command_help",
]

source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
root_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]

# Markdown pages: ```{directive} fences, $math$, and anchors for "## headings"
myst_enable_extensions = ["colon_fence", "dollarmath"]
myst_heading_anchors = 3

# numpydoc docstrings (the project's standard), read by napoleon
napoleon_google_docstring = False
napoleon_numpy_docstring = True
napoleon_use_rtype = False
napoleon_use_ivar = True
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "show-inheritance": False}

# furo when it is installed (the `docs` extra), Sphinx's own alabaster otherwise
html_theme = "furo" if importlib.util.find_spec("furo") else "alabaster"
html_title = f"hailstorm {release}"
html_static_path: list[str] = []
