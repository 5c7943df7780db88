"""Moved to calib_cli/io/history.py (below batch and report, issue 33); this alias is
left for the branches open at the move: import the new path."""

from calib_cli.io.history import CalEntry, element_names, previous, scan  # noqa: F401
