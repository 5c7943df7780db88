"""calib: bench calibration of inertial measurement units."""

__version__ = "0.1.0"
