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

from calib_cli.data import CalibrationResult, Recording
from calib_cli.errors import EstimationError, InputError
from calib_cli.methods import diagnose_candidates as dc
from calib_cli.methods.blas_threads import one_blas_thread
from calib_cli.methods.diagnose_fit import Fit, ModelSpec, columns, fit_model, settle_noise
from calib_cli.methods.diagnose_problem import Problem, build_problem
from calib_cli.methods.method import Method, method_named
from calib_cli.methods.with_effects import (
    EFFECTS,
    GYRO_EFFECTS,
    GYRO_WITH,
    WANDERS,
    calibration_of,
    fit_command,
    g_error_per_position,
    gyro_effect,
    method_sensors,
    parse_with,
    with_arg,
)
from calib_cli.model.effects import make_effect


def _candidate(pb: Problem, base: str, name: str, sensor: str) -> dc.Candidate:
    for c in dc.catalogue_order(pb, base):
        if c.name == name and c.sensor == sensor:
            return c
    raise EstimationError(f"{with_arg(name, sensor)}: not an effect the {pb.method} method "
                          "can take")


def effect_lines(pb: Problem | None, method, base: str = "full") -> list[dict]:
    """One entry per effect the method (its name or ``Method``) accepts: {"with",
    "excites", "record", "excited" (None without a record), "why"}. Without a record:
    the catalogue's effects on the sensors of the method's ``Diagnose`` description
    (an effect of the whole unit only where it fits both), less its ``without``."""
    if pb is None:
        m = method if isinstance(method, Method) else method_named(method)
        if m.diagnose is None:
            raise InputError(f"the {m.name} method takes no catalogue effects (--with)")
        sensors = m.diagnose.with_sensors
        out = []
        for name, fixed in EFFECTS.items():
            if name in m.diagnose.without or (fixed and fixed not in sensors) \
                    or (fixed == "" and not {"accel", "gyro"} <= set(sensors)):
                continue
            sens = [fixed] if fixed is not None else list(sensors)
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

    ex = excitation(rec, accel if accel is not None else accel_of(rec), base)
    out = []
    for name in GYRO_WITH:
        e = gyro_effect(name)
        why = e.not_excited(ex)
        out.append({"with": with_arg(name, "gyro"), "excites": e.excites, "record": e.record,
                    "excited": why is None, "why": why})
    return out


def accel_of(rec: Recording):
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
    acc = accel if accel is not None else accel_of(rec)
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
                from calib_cli.methods.diagnose import try_wander

                got = try_wander(pb, cur, c)
                if got is None:
                    raise EstimationError(f"--with {with_arg(name, sensor)}: one wandering "
                                          f"bias per sensor (the {sensor} already has one)")
                cur = got[1]
                wander[c.key] = (got[2], got[3])
                continue
            cur = add_effect(pb, cur, c)
        pb, cur, r0 = settle_noise(pb, cur, r0)
        res = calibration_of(pb, cur, pb.method, rec, names, wander,
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


__all__ = ["EFFECTS", "GYRO_EFFECTS", "GYRO_WITH", "WANDERS", "accel_of", "calibration_of",
           "check_excited", "effect_lines", "fit_command", "fit_with", "fit_with_gyro",
           "g_error_per_position", "gyro_effect", "gyro_lines", "method_sensors", "parse_with",
           "with_arg"]
