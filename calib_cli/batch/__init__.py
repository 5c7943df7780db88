"""`calib batch`: the same steps over many recordings, idempotent like make.

registry.py  the step registry (import, fit METHOD, apply, export, ...)
steps.py     the built-in steps (one line each to register more)
pipeline.py  pipeline TOML -> Pipeline (steps, options, hashes)
paths.py     input discovery and safe, deterministic output paths
runner.py    one input's chain with up-to-date checks; local, process pool, Dask
tolerance.py tolerance files and the pass/fail check per unit
history.py   a unit's calibrations over time
archive.py   simulated test archives (tests, benchmark)

See docs/batch.md.
"""
