"""Moved to ``calib_cli/design.py`` (experiment design runs the simulator and the
fits, so it sits above both). Compatibility alias for the branches open when it
moved: new code imports the new path; this file goes after their merge
(tests/test_layers.py lists it)."""

import sys

from calib_cli import design as _moved

sys.modules[__name__] = _moved
