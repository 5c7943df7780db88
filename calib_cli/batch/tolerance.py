"""Moved to calib_cli/io/tolerance.py (one evaluator below batch and report, issue 33);
this alias is left for the branches open at the move: import the new path."""

from calib_cli.io.tolerance import ParamTolerance, check, evaluate, load_tolerances  # noqa: F401
