"""Apply a calibration to sensor outputs (pure; the CLI feeds it chunks)."""

from __future__ import annotations

import numpy as np

from calib_cli.data import CalibrationResult
from calib_cli.errors import InputError
from calib_cli.model.correction import correct
from calib_cli.model.imu_model import ImuModel
from calib_cli.model.truth import effect_from_description


def model_of(cal: CalibrationResult) -> ImuModel:
    return ImuModel(tuple(effect_from_description(d) for d in cal.model), cal.layout)


def check_units(cal: CalibrationResult, rec_units: dict, path: str) -> None:
    """Refuse data in other units than the calibration was fitted on."""
    for sensor in ("accel", "gyro"):
        if f"{sensor}_bias" in cal.params or f"{sensor}_K" in cal.params:
            want, got = cal.raw_units.get(sensor), rec_units.get(sensor)
            if want and got and want != got:
                raise InputError(f"{sensor} data is in {got!r} but the calibration was fitted "
                                 f"on {want!r}", path)


def corrected_channels(cal: CalibrationResult) -> list[str]:
    return [s for s in ("accel", "gyro") if f"{s}_K" in cal.params or f"{s}_bias" in cal.params]


TEMP_MARGIN_C = 5.0  # degC beyond the calibrated range that apply accepts (docs/thermal.md)


def is_thermal(cal: CalibrationResult) -> bool:
    return any(d.get("name") == "temperature_drift" for d in cal.model)


def effective_temperature(cal: CalibrationResult, time: np.ndarray, temp: np.ndarray) -> np.ndarray:
    """The temperature the calibration's temperature terms take: the recorded
    one, lagged by the calibration's thermal_lag where it has one."""
    from calib_cli.model.effects import lag_temperature

    temp = np.asarray(temp, dtype=float)
    if any(d.get("name") == "thermal_lag" for d in cal.model):
        return lag_temperature(np.asarray(time, float), temp,
                               float(cal.params.get("thermal_lag_tau", 0.0)))
    return temp


def check_temperature(cal: CalibrationResult, temp: np.ndarray, path: str,
                      extrapolate: bool = False) -> None:
    """Refuse data outside the calibrated range by more than TEMP_MARGIN_C."""
    rng = cal.stats.get("temp_range_degC")
    if extrapolate or not rng or not len(temp):
        return
    lo, hi = float(np.nanmin(temp)), float(np.nanmax(temp))
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise InputError("the temperature column holds no finite value", path)
    if lo < rng[0] - TEMP_MARGIN_C or hi > rng[1] + TEMP_MARGIN_C:
        raise InputError(f"temperature {lo:.1f}..{hi:.1f} degC is outside the calibrated range "
                         f"{rng[0]:.1f}..{rng[1]:.1f} degC by more than {TEMP_MARGIN_C:g} degC "
                         "(--extrapolate to correct anyway)", path)


def proof_mass_offsets(cal: CalibrationResult) -> np.ndarray | None:
    """The calibration's proof-mass offsets p (3, 3), m, entries without a sigma (not
    determined) taken as 0; None when it has none."""
    p = cal.params.get("proof_mass_offsets")
    if p is None:
        return None
    p = np.asarray(p, dtype=float)
    s = np.asarray(cal.sigma.get("proof_mass_offsets", np.zeros((3, 3))), dtype=float)
    p = np.where(np.isfinite(s) & (s > 0), p, 0.0)
    return p if np.any(p) else None


def size_effect(p: np.ndarray, w: np.ndarray, dw: np.ndarray) -> np.ndarray:
    """(N, 3): component i of w x (w x p_i) + dw/dt x p_i, what accelerometer i reads more
    than the specific force at the triad's reference point (CONTRACT.md section 2; the
    rough-stand paper's size effect). w rad/s, dw rad/s^2 (N, 3), p (3, 3) m."""
    from calib_cli.model.kinematics import rigid_body_accel

    return np.column_stack([rigid_body_accel(w, dw, p[i])[:, i] for i in range(3)])


def rate_derivative(w: np.ndarray, time: np.ndarray) -> np.ndarray:
    """dw/dt (N, 3), rad/s^2, of the corrected rates: central differences (one-sided at
    the ends), what the size-effect compensation uses (and a firmware port must feed
    the exported ``*_size_effect`` function, docs/export.md)."""
    return np.gradient(w, time, axis=0)


def apply_triad(cal: CalibrationResult, accel: np.ndarray, gyro: np.ndarray | None,
                accel_si: bool = True, temp: np.ndarray | None = None,
                time: np.ndarray | None = None):
    """Corrected (accel, gyro) for a chunk: f = K^-1 (A - b), w = G^-1 (W - d - D f).
    With proof-mass offsets and ``time`` (s), each accelerometer is brought to the
    triad's reference point: f_i -= (w x (w x p_i) + dw/dt x p_i)_i, dw/dt from the
    corrected rates (central differences; give the chunk one sample of context on
    each side). Channels the calibration does not cover pass through unchanged. For a
    gyro-only calibration with g-sensitivity, f is the raw accelerometer
    output when that is in SI (``accel_si``), else zero. ``temp``: the
    effective temperature per sample (``effective_temperature``) for a
    thermal calibration."""
    model = model_of(cal)
    params = {k: np.asarray(v, dtype=float) for k, v in cal.params.items()}
    chans = corrected_channels(cal)
    f = correct(model, params, "accel", accel, temp=temp) if "accel" in chans else accel
    w = gyro
    if gyro is not None and "gyro" in chans:
        other = f if "accel" in chans else (accel if accel_si else None)
        w = correct(model, params, "gyro", gyro, other=other, temp=temp)
        p = proof_mass_offsets(cal) if "accel" in chans else None
        if p is not None and time is not None and len(time) > 2:
            # the size effect: each accelerometer to the triad's reference point, with the
            # corrected rates and their derivative; the gyros' D then sees that point's force
            f = f - size_effect(p, w, rate_derivative(w, time))
            w = correct(model, params, "gyro", gyro, other=f, temp=temp)
    return f, w


def redundant_extra(cal: CalibrationResult) -> bool:
    return bool({d.get("name") for d in cal.model} - {"bias", "installation", "lever_arm"})


def correct_redundant(model: ImuModel, params: dict, layout, sensor: str, m: np.ndarray,
                      other: np.ndarray | None = None, temp: np.ndarray | None = None,
                      iterations: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """(single-axis inputs (N, n), body vector (N, 3)) of a redundant unit's outputs m
    (N, n), through the one forward model (``ImuModel.predict``) as ``correct`` does for
    a triad: Gauss-Newton on the body vector x, x <- x + H^+ diag(1 + ks)^-1 (m -
    predict(x)) (exact in one step for bias + installation, where it is the
    least-squares body estimate of ``methods.rimu.body_estimate``), then each
    sensor's own input S_i . x + (m_i - predict_i(x)) / (1 + ks_i), which keeps each
    sensor's own noise and faults (for the fault detection) and is (m_i - b_i) /
    (1 + ks_i) for the base model. ``other``: the corrected body specific force for
    the gyros' g-sensitivity (zero if None); rate-dependent terms (lever arms) are
    not inverted (the contract's correction point), as for a triad."""
    from calib_cli.methods.rimu import measurement_matrix
    from calib_cli.model.kinematics import Kinematics

    m = np.asarray(m, dtype=float)
    n = len(m)
    H = measurement_matrix(params, layout, sensor)
    gain = 1.0 + np.asarray(params[f"{sensor}_scale_error"], float)
    Hp = np.linalg.pinv(H)  # (3, n)
    zeros = np.zeros((n, 3))
    f_other = zeros if other is None else np.asarray(other, float)

    def pred(x):
        kin = (Kinematics(np.zeros(n), x, zeros, zeros, temp=temp) if sensor == "accel"
               else Kinematics(np.zeros(n), f_other, x, zeros, temp=temp))
        return model.predict(params, kin, sensors=(sensor,))[sensor]

    x = zeros.copy()
    for _ in range(iterations + (4 if temp is not None else 0)):
        step = ((m - pred(x)) / gain) @ Hp.T
        x = x + step
        if np.max(np.abs(step)) <= 1e-13 * (np.max(np.abs(x)) + 1e-300):
            break
    single = x @ H.T + (m - pred(x)) / gain
    return single, x


def apply_redundant(cal: CalibrationResult, accel: np.ndarray, gyro: np.ndarray | None,
                    temp: np.ndarray | None = None) -> dict:
    """A redundant unit's corrected chunk, {"accel": (N, n), "accel_body": (N, 3),
    "gyro": ..., "gyro_body": ...}, with any catalogue model (``correct_redundant``;
    the bias + installation model is ``methods.rimu.apply_rimu``'s closed form, which
    this reproduces). Channels the calibration does not cover pass through."""
    model = model_of(cal)
    params = {k: np.asarray(v, dtype=float) for k, v in cal.params.items()}
    out = {"accel": accel, "gyro": gyro}
    f_body = None
    for sensor, m in (("accel", accel), ("gyro", gyro)):
        if m is None or f"{sensor}_bias" not in params:
            continue
        c, x = correct_redundant(model, params, cal.layout, sensor, m,
                                 other=f_body if sensor == "gyro" else None, temp=temp)
        out[sensor], out[f"{sensor}_body"] = c, x
        if sensor == "accel":
            f_body = x
    return out
