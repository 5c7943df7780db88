"""Random truth models of a redundant unit of ADIS16405-class MEMS sensors.

The sizes follow the published error table of the tetrahedron unit: scale
errors about 0.5 %, installation errors dEl and dAz up to 3 deg, gyro biases
up to 1 deg/s; accelerometer biases up to 50 mg. Noise densities of the
ADIS16405 data sheet: gyro 0.05 deg/s/sqrt(Hz), accelerometer 0.5 mg/sqrt(Hz).

A sensor along the body z axis (El0 = +-90 deg) gets its tilt in the
contract's convention (|El| <= 90 deg: dEl <= 0 at El0 = +90 deg).
"""

from __future__ import annotations

import numpy as np

from calib_cli.model.effects import Layout
from calib_cli.model.imu_model import base_model
from calib_cli.model.truth import Truth

D2R = np.pi / 180.0
G0 = 9.80665
GYRO_DENSITY = 0.05 * D2R  # rad/s/sqrt(Hz)
ACCEL_DENSITY = 0.5e-3 * G0  # m/s^2/sqrt(Hz)


def rimu_truth(layout: Layout, rng: np.random.Generator, angle_max_deg: float = 3.0,
               scale_sigma: float = 5e-3, gyro_bias_max_dps: float = 1.0,
               accel_bias_max_mg: float = 50.0, gyro_density: float = GYRO_DENSITY,
               accel_density: float = ACCEL_DENSITY, pole_tilt_min_deg: float = 0.0) -> Truth:
    """Bias + installation errors of both sensor kinds, uniform within the limits.

    pole_tilt_min_deg: smallest tilt of a sensor at El0 = +-90 deg (its
    polar (dEl, dAz) pair is far from Gaussian when the tilt is not much
    larger than its sigma; property tests keep clear of that)."""
    n = layout.n
    params = {}
    pole = np.abs(np.cos(layout.el0)) < 1e-6
    for s in ("accel", "gyro"):
        bmax = gyro_bias_max_dps * D2R if s == "gyro" else accel_bias_max_mg * 1e-3 * G0
        params[f"{s}_bias"] = rng.uniform(-1, 1, n) * bmax
        params[f"{s}_scale_error"] = rng.normal(0.0, scale_sigma, n)
        d_el = rng.uniform(-1, 1, n) * angle_max_deg * D2R
        tilt = np.maximum(np.abs(d_el[pole]), pole_tilt_min_deg * D2R)
        d_el[pole] = -tilt * np.sign(np.sin(layout.el0[pole]))
        params[f"{s}_dEl"] = d_el
        params[f"{s}_dAz"] = rng.uniform(-1, 1, n) * angle_max_deg * D2R
    noise = {"gyro_white_density": np.full(n, gyro_density),
             "accel_white_density": np.full(n, accel_density)}
    return Truth(base_model(layout=layout), params, noise)
