"""Rotating-table calibration on a low-grade single-axis table (docs/turntable.md).

Model (CONTRACT.md section 2), from the effect catalogue: accelerometer bias b and
lower-triangular K (the instrument frame fixed by the accelerometers); gyro bias d, full
G and g-sensitivity D; per rotating cycle the lever arm s (two components perpendicular
to the table axis) and the six proof-mass offsets p_ij; any further catalogue effect
(``--with``). The pieces:

- ``setup``: the cycles, the model and its parameter vector with the priors, the noise,
  the table's channels and their checks, the start;
- ``blocks``: a cycle's accelerometer block rows from the model's Jacobian
  (model/jacobian.py) and the one integrator (model/strapdown.py);
- ``rows``: the table axis, the channels and the attitude's propagation, whitened;
- ``solve``: one Gauss-Newton step (banded elimination of the local states);
- ``estimator``: the passes, the start windows, the noise levels between passes;
- ``fit``: ``fit_turntable``; ``design``: the same rows at a known unit (plan check);
- ``result`` and ``history``: the calibration, its statistics and the sigma history.
"""

from calib_cli.methods.turntable.fit import fit_turntable
from calib_cli.methods.turntable.options import ENCODER_MODES, GRADES, PRIOR_KEYS, TurntableOptions
from calib_cli.methods.turntable.setup import IMU_KEYS, turntable_model

__all__ = ["ENCODER_MODES", "GRADES", "IMU_KEYS", "PRIOR_KEYS", "TurntableOptions",
           "fit_turntable", "turntable_model"]
