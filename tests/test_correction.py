"""apply inverts the same forward model that simulates and fits (property tests)."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from calib_cli.model.correction import correct
from calib_cli.model.effects import (
    Bias,
    GSensitivity,
    Layout,
    Nonlinearity,
    ScaleAsymmetry,
    ScaleMisalignment,
)
from calib_cli.model.imu_model import ImuModel
from calib_cli.model.kinematics import Kinematics


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**31 - 1), st.booleans())
def test_correct_inverts_predict(seed, nonlinear):
    rng = np.random.default_rng(seed)
    effects = [Bias("accel"), ScaleMisalignment("accel"), Bias("gyro"), ScaleMisalignment("gyro"),
               GSensitivity()]
    if nonlinear:
        effects += [Nonlinearity("accel"), ScaleAsymmetry("accel")]
    model = ImuModel(tuple(effects), Layout())
    p = {"accel_bias": rng.normal(0, 0.1, 3), "accel_K": np.eye(3) + rng.normal(0, 0.01, (3, 3)),
         "gyro_bias": rng.normal(0, 0.01, 3), "gyro_K": np.eye(3) + rng.normal(0, 0.01, (3, 3)),
         "gyro_D": rng.normal(0, 1e-3, (3, 3)),
         "accel_nonlinearity": rng.normal(0, 1e-4, 3),
         "accel_scale_asymmetry": rng.normal(0, 1e-3, 3)}
    n = 50
    f = rng.normal(0, 10, (n, 3))
    w = rng.normal(0, 2, (n, 3))
    kin = Kinematics(np.arange(n) * 0.01, f, w, np.zeros((n, 3)))
    y = model.predict(p, kin)
    f_back = correct(model, p, "accel", y["accel"])
    assert np.allclose(f_back, f, atol=1e-9 * 10)
    w_back = correct(model, p, "gyro", y["gyro"], other=f_back)
    assert np.allclose(w_back, w, atol=1e-9)
