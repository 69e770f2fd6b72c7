"""``{command-help}`` directive: the ``hailstorm`` command's own ``--help`` text.

    ```{command-help} precompute
    ```

runs ``python -m hailstorm precompute --help`` at build time and inserts its
output as a literal block, so the command-line reference cannot drift from the
parser. A command that fails is a build error.
"""

from __future__ import annotations

import os
import subprocess
import sys

from docutils import nodes
from docutils.parsers.rst import Directive
from sphinx.errors import ExtensionError


class CommandHelp(Directive):
    optional_arguments = 1
    has_content = False

    def run(self) -> list[nodes.Node]:
        sub = list(self.arguments)
        env = dict(os.environ, COLUMNS="80")
        proc = subprocess.run([sys.executable, "-m", "hailstorm", *sub, "--help"], capture_output=True,
                              text=True, env=env, timeout=300, check=False)
        if proc.returncode != 0:
            raise ExtensionError(f"hailstorm {' '.join(sub)} --help failed ({proc.returncode}): {proc.stderr.strip()}")
        text = f"$ hailstorm {' '.join(sub + ['--help'])}\n{proc.stdout.rstrip()}"
        block = nodes.literal_block(text, text)
        block["language"] = "text"
        return [block]


def setup(app):
    app.add_directive("command-help", CommandHelp)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
