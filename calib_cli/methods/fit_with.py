"""``calib fit METHOD RAW --with EFFECT[,EFFECT...]``: a method's base model plus
catalogue effects, fitted by the refit engine of ``calib diagnose``
(``diagnose_fit.fit_model``: the catalogue's forward model on 0.5 s bin means,
the same likelihood), so a fit with the effects a diagnosis named and the
diagnosis's final model are one computation (docs/diagnose.md, "From a
diagnosis to a calibration").

The effects are added one at a time in the order given, each refitted as a
diagnose step is (a Gauss-Newton fit from the previous model, then a final
fit with a fresh Jacobian). The wandering biases (``bias_random_walk``,
``bias_instability``) are noise-model terms: their figure is fitted on the
residuals (``diagnose_stoch``), the deterministic parameters are refitted
under that whitening (their sigma widens), and the figure is reported in
``stats.noise_model``; it is never applied or exported.

``calibration_of`` turns a fit of the engine into an ordinary
``CalibrationResult`` (the whole model: params, sigma, covariance in the
contract's order, the effects' descriptions): ``fit --with`` and
``diagnose --calibration`` both write it.
"""

from __future__ import annotations

import numpy as np

from calib_cli.data import CalibrationResult, Recording
from calib_cli.errors import EstimationError
from calib_cli.methods import diagnose_candidates as dc
from calib_cli.methods import result as _result
from calib_cli.methods.blas_threads import one_blas_thread
from calib_cli.methods.diagnose_fit import MOUNT_KEY, Fit, ModelSpec, columns, fit_model, settle_noise
from calib_cli.methods.diagnose_problem import Problem, build_problem
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
ENGINE_METHODS = ("accel", "align", "turntable", "rimu")
WANDERS = ("bias_random_walk", "bias_instability")


GYRO_EFFECTS = ("misalignment", "scale_asymmetry", "temperature_drift", "g_sensitivity")
# what ``fit gyro --with`` takes: the deterministic effects and the wandering biases (noise-
# model terms on the gyro equations' generalised likelihood, methods/diagnose_gyro_wander.py)
GYRO_WITH = GYRO_EFFECTS + WANDERS


def method_sensors(method: str) -> tuple:
    return {"accel": ("accel",), "gyro": ("gyro",)}.get(method, ("accel", "gyro"))


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


def _candidate(pb: Problem, base: str, name: str, sensor: str) -> dc.Candidate:
    for c in dc.catalogue_order(pb, base):
        if c.name == name and c.sensor == sensor:
            return c
    raise EstimationError(f"{with_arg(name, sensor)}: not an effect the {pb.method} method "
                          "can take")


def effect_lines(pb: Problem | None, method: str, base: str = "full") -> list[dict]:
    """One entry per effect the method accepts: {"with", "excites", "record",
    "excited" (None without a record), "why"}."""
    if pb is None:
        out = []
        for name, fixed in EFFECTS.items():
            if method == "accel" and fixed in ("gyro", ""):
                continue
            if method == "rimu" and name in ("misalignment", "proof_mass_offsets"):
                continue
            if method == "align" and name in ("misalignment", "lever_arm", "proof_mass_offsets",
                                              "time_offset"):
                continue
            if method == "gyro" and name not in GYRO_WITH:
                continue
            sens = [fixed] if fixed is not None else list(method_sensors(method))
            for s in sens:
                e = make_effect(name, s or "accel")
                out.append({"with": with_arg(name, s), "excites": e.excites,
                            "record": e.record, "excited": None, "why": None})
        return out
    ex = dc.excitation(pb, base)
    out = []
    for c in dc.catalogue_order(pb, base):
        why = c.effect.not_excited(ex)
        out.append({"with": with_arg(c.name, c.sensor), "excites": c.effect.excites,
                    "record": c.effect.record, "excited": why is None, "why": why})
    return out


def check_excited(pb: Problem, base: str, effects) -> None:
    """Exit 4 (EstimationError) naming what to record, for an effect this record
    cannot excite."""
    ex = dc.excitation(pb, base)
    for name, sensor in effects:
        c = _candidate(pb, base, name, sensor)
        why = c.effect.not_excited(ex)
        if why:
            raise EstimationError(f"--with {with_arg(name, sensor)}: this record cannot "
                                  f"determine it ({why}); record {c.effect.record}")


def gyro_lines(rec: Recording, accel=None, base: str = "full") -> list[dict]:
    """``effect_lines`` of the gyro method on a record."""
    from calib_cli.methods.gyro import excitation

    ex = excitation(rec, accel if accel is not None else _accel_of(rec), base)
    out = []
    for name in GYRO_WITH:
        e = gyro_effect(name)
        why = e.not_excited(ex)
        out.append({"with": with_arg(name, "gyro"), "excites": e.excites, "record": e.record,
                    "excited": why is None, "why": why})
    return out


def _accel_of(rec: Recording):
    from calib_cli.methods.accel_lsq import fit_accel

    return fit_accel(rec)


def fit_with_gyro(rec: Recording, effects, base: str = "full", accel=None,
                  accel_independent: bool = False) -> CalibrationResult:
    """``fit gyro --with``: bias + G (gyro_D only with g_sensitivity) plus the effects,
    through the gyro fit's own equations (methods/gyro.py). A wandering bias
    (``bias_random_walk`` or ``bias_instability``, one) is a noise-model term: its figure
    is fitted on the same equations' generalised likelihood, the parameters' covariance
    becomes the sandwich under it (sigma widens), and the figure goes to
    ``stats.noise_model`` (``diagnose_gyro_wander.with_wander``, as the diagnosis's
    final model)."""
    from calib_cli.methods.diagnose_gyro_wander import WanderLikelihood, with_wander
    from calib_cli.methods.gyro import excitation, fit_gyro

    bad = [with_arg(n, s) for n, s in effects if s != "gyro" or n not in GYRO_WITH]
    if bad:
        raise EstimationError(f"--with {', '.join(bad)}: the gyro method takes "
                              f"{', '.join(GYRO_WITH)} (gyro)")
    wanders = [n for n, _ in effects if n in WANDERS]
    if len(wanders) > 1:
        raise EstimationError(f"--with {', '.join('gyro.' + n for n in wanders)}: one "
                              "wandering bias per sensor")
    acc = accel if accel is not None else _accel_of(rec)
    ex = excitation(rec, acc, base)
    extra, names = [], []
    for name, _ in effects:
        e = gyro_effect(name)
        why = e.not_excited(ex)
        if why:
            raise EstimationError(f"--with {with_arg(name, 'gyro')}: this record cannot "
                                  f"determine it ({why}); record {e.record}")
        if name not in WANDERS:
            extra.append(e)
            names.append(name)
    structure = "diagonal" if base == "diagonal" else "full"
    with one_blas_thread():  # small dense systems: threads only contend (as diagnose_gyro)
        res = fit_gyro(rec, acc, "off", accel_independent, extra=extra, structure=structure)
        if wanders:
            W = WanderLikelihood(rec, acc, structure)
            if names:  # the equations' response to the wander at the base model, as diagnose
                W.linear([], fit_gyro(rec, acc, "off", accel_independent, structure=structure))
            res = with_wander(W, W.linear(names, res), res, wanders[0])[0]
    res.stats["with"] = [with_arg(n, s) for n, s in effects]
    res.stats["base"] = base
    res.stats["base_model"] = ["gyro_bias", f"gyro_K ({'diagonal' if base == 'diagonal' else 'full'})"]
    return res


def fit_with(rec: Recording, method: str, effects, base: str = "full", noise: str = "auto"
             ) -> tuple[CalibrationResult, Problem, Fit]:
    """The method's base model plus ``effects`` [(name, sensor)] (module docstring)."""
    if method not in ENGINE_METHODS:
        raise EstimationError(f"--with is not available for the {method} method yet")
    with one_blas_thread():
        pb = build_problem(rec, method, noise=noise)
        check_excited(pb, base, effects)
        from calib_cli.methods.diagnose import base_spec, start_params

        spec, names = base_spec(pb, base)
        cur = fit_model(pb, spec, start=start_params(pb, base), refresh=True)
        r0 = cur
        wander: dict = {}
        for name, sensor in effects:
            c = _candidate(pb, base, name, sensor)
            if name in WANDERS:
                from calib_cli.methods.diagnose import _try_wander

                got = _try_wander(pb, cur, c)
                if got is None:
                    raise EstimationError(f"--with {with_arg(name, sensor)}: one wandering "
                                          f"bias per sensor (the {sensor} already has one)")
                cur = got[1]
                wander[c.key] = (got[2], got[3])
                continue
            cur = add_effect(pb, cur, c)
        pb, cur, r0 = settle_noise(pb, cur, r0)
        res = calibration_of(pb, cur, method, rec, names, wander,
                             [with_arg(n, s) for n, s in effects], base, initial=r0)
    return res, pb, cur


def add_effect(pb: Problem, cur: Fit, c: dc.Candidate) -> Fit:
    """One diagnose step's refit: the candidate fit from the current model (its
    Jacobian columns reused), then a final fit with a fresh Jacobian."""
    spec = ModelSpec(cur.spec.model.with_effect(c.effect), cur.spec.mount, cur.spec.stochastic)
    f = fit_model(pb, spec, start=cur.params, start_mount=cur.mount, known_cols=columns(cur))
    return fit_model(pb, f.spec, start=f.params, start_mount=f.mount, refresh=True)


# ---------------------------------------------------------------------------
# a fit of the engine as an ordinary calibration


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
        what = {"align": "attitude correction (rotation of the navigation frame, rad)",
                "turntable": "mount angles of the unit on the table (rad)"}.get(
            method, "gravity-direction nuisance of each position (rad)")
        stats["nuisance"] = {"what": what, "values": np.asarray(fit.mount, float).tolist(),
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
