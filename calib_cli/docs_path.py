"""Where the documentation is: the help texts name files as ``docs/NAME.md``.

In a source tree (or an editable install) that is ``docs/`` beside the
package; a wheel or ``pip install .`` puts the same files under
``<prefix>/share/calib/docs`` (pyproject.toml, data-files), the way the
shipped profiles go to ``<prefix>/share/calib/profiles``. ``calib --help``
prints the directory. Imports nothing heavy (it runs for --help).
"""

from __future__ import annotations

import sys
from pathlib import Path


def docs_dir() -> Path:
    src = Path(__file__).resolve().parents[1] / "docs"
    if (src / "commands.md").is_file():
        return src
    return Path(sys.prefix) / "share" / "calib" / "docs"
