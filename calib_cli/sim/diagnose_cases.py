"""Moved to ``calib_cli/validation/diagnose_cases.py``. Compatibility alias for the branches
open when it moved: new code imports the new path; this file goes after their merge
(tests/test_layers.py lists it)."""

import sys

from calib_cli.validation import diagnose_cases as _moved

sys.modules[__name__] = _moved
