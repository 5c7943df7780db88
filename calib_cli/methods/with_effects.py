"""The vocabulary of ``calib fit METHOD --with`` and the calibration of an engine fit,
shared by ``fit --with`` (methods/fit_with.py) and ``calib diagnose``
(methods/diagnose.py, methods/diagnose_gyro*.py), which both import it from here (so
they do not import each other): the effect names and the sensor each acts on, their
command-line spelling, and ``calibration_of``, a fit of the diagnose engine as an
ordinary CalibrationResult."""

from __future__ import annotations

import numpy as np

from calib_cli.data import CalibrationResult, Recording
from calib_cli.methods import result as _result
from calib_cli.methods.diagnose_fit import MOUNT_KEY, Fit
from calib_cli.methods.diagnose_problem import Problem
from calib_cli.methods.method import method_named
from calib_cli.model.correction import correct
from calib_cli.model.effects import TEMP_REF_C, make_effect

# effects a fit can take (CONTRACT.md section 5) and the sensor each acts on:
# None = per sensor (unqualified: every sensor the method fits), "" = the whole unit
EFFECTS = {
    "misalignment": None, "accel_nonlinearity": "accel", "scale_asymmetry": None,
    "temperature_drift": None, "g_sensitivity": "gyro", "lever_arm": "",
    "proof_mass_offsets": "", "time_offset": "", "bias_random_walk": None,
    "bias_instability": None,
}
WANDERS = ("bias_random_walk", "bias_instability")


GYRO_EFFECTS = ("misalignment", "scale_asymmetry", "temperature_drift", "g_sensitivity")
# what ``fit gyro --with`` takes: the deterministic effects and the wandering biases (noise-
# model terms on the gyro equations' generalised likelihood, methods/diagnose_gyro_wander.py)
GYRO_WITH = GYRO_EFFECTS + WANDERS


def method_sensors(method: str) -> tuple:
    """The sensors an unqualified ``--with`` effect goes to: those of the method's
    ``Diagnose`` description in the method table (both where it has none)."""
    how = method_named(method).diagnose
    return how.with_sensors if how is not None else ("accel", "gyro")


def gyro_effect(name: str):
    return make_effect(name, "gyro", **({"structure": "full"} if name == "misalignment" else {}))


def with_arg(name: str, sensor: str) -> str:
    """The --with spelling of one effect on one sensor: "gyro.temperature_drift",
    "lever_arm", "accel_nonlinearity"."""
    if EFFECTS.get(name) is None and sensor:
        return f"{sensor}.{name}"
    return name


def parse_with(text: str, method: str, sensors=None) -> list[tuple[str, str]]:
    """[(effect name, sensor)] from "A,B.c,...", in order (ValueError: unknown name)."""
    sensors = tuple(sensors or method_sensors(method))
    out: list[tuple[str, str]] = []
    for raw in (x.strip() for x in str(text).split(",")):
        if not raw:
            continue
        sensor = None
        name = raw
        if "." in raw:
            sensor, name = raw.split(".", 1)
            if sensor not in ("accel", "gyro"):
                raise ValueError(f"{raw!r}: the sensor is accel or gyro")
        if name not in EFFECTS:
            raise ValueError(f"unknown effect {name!r}; known: {', '.join(EFFECTS)}")
        fixed = EFFECTS[name]
        if fixed is not None:
            if sensor is not None and fixed and sensor != fixed:
                raise ValueError(f"{raw!r}: {name} acts on the {fixed} only")
            items = [(name, fixed)]
        elif sensor is not None:
            if sensor not in sensors:
                raise ValueError(f"{raw!r}: the {method} method does not fit the {sensor}")
            items = [(name, sensor)]
        else:
            items = [(name, s) for s in sensors]
        for it in items:
            if it not in out:
                out.append(it)
    if not out:
        raise ValueError("no effect named")
    return out


def g_error_per_position(pb: Problem, model, params: dict) -> list:
    """[(segment label, |mean f| - g raw, corrected)] over the static positions (triads;
    [] for a redundant unit), m/s^2 (raw: in the data's units)."""
    if pb.layout.redundant or "accel" not in pb.sensors:
        return []
    seg = pb.kin.segment
    out = []
    y = pb.y["accel"]
    for idx in np.unique(seg):
        if pb.seg_kinds[idx] != "static":
            continue
        on = seg == idx
        temp = None if pb.kin.temp is None else np.asarray(pb.kin.temp[on], float)
        x = correct(model, params, "accel", y[on], temp=temp)
        out.append((pb.seg_labels[idx], float(np.linalg.norm(y[on].mean(axis=0)) - pb.g),
                    float(np.linalg.norm(x.mean(axis=0)) - pb.g)))
    return out


def _static_g_errors(pb: Problem, model, params: dict, counts: bool) -> tuple:
    """RMS over the static positions of |mean f| - g, raw and corrected (triads)."""
    rows = g_error_per_position(pb, model, params)
    if not rows:
        return None, None
    before = [r[1] for r in rows]
    after = [r[2] for r in rows]
    rms = lambda v: float(np.sqrt(np.mean(np.square(v))))  # noqa: E731
    return (None if counts else rms(before)), rms(after)


def calibration_of(pb: Problem, fit: Fit, method: str, rec: Recording | None, base_names,
                   wander: dict | None = None, with_list=(), base: str = "full",
                   initial: Fit | None = None) -> CalibrationResult:
    """The whole model of an engine fit as a calibration (params, sigma, covariance over
    the model's free entries in the contract's order; the nuisance angles in stats)."""
    from calib_cli.methods.diagnose_fit import predict_bins

    model = fit.spec.model
    packing = fit.packing
    nm = packing.size
    labels = packing.labels()
    keys = [s.key for s in packing.specs]
    cov = np.asarray(fit.cov, float)[:nm, :nm]
    unobs = [_result.entry_name(k, model.spec(k).shape, i)
             for (k, i), u in zip(labels, fit.unobs[:nm]) if u]
    params = {k: np.asarray(fit.params[k], float) for k in keys}
    sigma = {k: np.asarray(fit.sigma[k], float) for k in keys}
    if "lever_arm" in sigma:  # the axial convention s . a = 0: reported 0 with sigma 0
        s = sigma["lever_arm"]
        bad = ~np.isfinite(s) | (s == 0)
        params["lever_arm"] = np.where(bad, 0.0, params["lever_arm"])
        sigma["lever_arm"] = np.where(bad, 0.0, s)
    units = _result.param_units(model, pb.units)
    pred = predict_bins(pb, fit.spec, fit.params, fit.mount)
    stats: dict = {"method": method, "engine": "diagnose refit (0.5 s bins)",
                   "base_model": list(base_names), "base": base, "with": list(with_list),
                   "unobservable": unobs}
    for s in pb.sensors:
        res = pb.ymean[s] - pred[s]
        stats[f"{s}_residual_rms"] = float(np.sqrt(np.mean(res ** 2)))
        stats[f"{s}_noise_sigma"] = np.asarray(pb.sigma[s], float).tolist()
    n = len(fit.r)
    stats["residual_rms_noise_units"] = float(np.sqrt(np.mean(fit.r ** 2)))
    stats["noise_rms"] = float(np.sqrt(max(n - fit.n_free, 1) / n))
    if initial is not None:
        stats["residual_rms_initial_noise_units"] = float(np.sqrt(np.mean(initial.r ** 2)))
    stats["chi2_dof"] = float(fit.chi2 / max(n - fit.n_free, 1))
    if fit.mount is not None and len(fit.mount):
        stats["nuisance"] = {"what": pb.how.nuisance, "values": np.asarray(fit.mount, float).tolist(),
                             "sigma": np.asarray(fit.sigma.get(MOUNT_KEY, []), float).tolist()}
    if wander:
        stats["noise_model"] = {
            k: {"params": {kk: np.asarray(vv, float).tolist() for kk, vv in v[0].items()},
                "sigma": {kk: np.asarray(vv, float).tolist() for kk, vv in v[1].items()},
                "note": "a noise-model term: it widens sigma; never applied or exported"}
            for k, v in wander.items()}
    temp_eff = [e for e in model.effects if e.name == "temperature_drift"]
    if temp_eff and pb.kin.temp is not None:
        stats["temp_ref_degC"] = float(getattr(temp_eff[0], "temp_ref", TEMP_REF_C))
        stats["temp_range_degC"] = [float(np.min(pb.kin.temp)), float(np.max(pb.kin.temp))]
    b, a = _static_g_errors(pb, model, params, pb.units.get("accel") == "count")
    if a is not None:
        stats["g_error_rms_before"] = b
        stats["g_error_rms_after"] = a
    return CalibrationResult(
        method=method, params=params, sigma=sigma, units={k: units[k] for k in keys},
        covariance=cov, cov_order=labels, stats=stats,
        model=[_result.describe_effect(e) for e in model.effects],
        raw_units=dict(pb.units), layout=model.layout,
        serial=None if rec is None else rec.serial)


def fit_command(method: str, with_list, base: str = "full", noise: str = "auto",
                raw: str = "RAW.h5", out: str = "CAL.h5") -> str | None:
    """The command that writes the calibration of a diagnosis's final model."""
    if not with_list:
        return None
    cmd = f"calib fit {method} {raw} --out {out} --with {','.join(with_list)}"
    if base != "full":
        cmd += f" --base {base}"
    if noise != "auto":
        cmd += f" --noise-floor {noise}"
    return cmd
