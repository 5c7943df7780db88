"""``calib diagnose --method turntable`` and ``calib fit turntable --with``: the discrepancy
workflow on the turntable filter's own likelihood (the rows of rows.py, with or without the
table's channels), not on bin means of a motion the filter does not share.

Base model: accelerometer bias and lower-triangular K, gyro bias and full G, each cycle's
mounting and trajectory (the filter's nuisance states). Each round refits, from the
current solution, the model with every candidate the record excites: the lever arms, the
proof-mass offsets (once the lever arms are in), the gyros' g-sensitivity, the time offset
between the IMU and the table (where an angle or rate channel times the table), and the
catalogue's sensor effects (scale asymmetry, the accelerometers' nonlinearity, temperature
drift). The candidates of a round are scored at the current model's noise levels (the
table axis's, the channels'; the sensors' white noise from the data's high frequencies,
never widened: the misfit is the signal) by the likelihood ratio Delta chi^2, chi^2 with k
degrees of freedom (k: the candidate's entries the data determine) when the effect is
absent; threshold the chi^2_k quantile at alpha / m (Bonferroni over the m candidates of the
round), as methods/diagnose.py. The best passing candidate is added and the noise levels
settled again; stop when none passes. The final model is judged against white noise by
the accelerometers' chi^2 over its degrees of freedom (n minus the hat matrix's trace).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from scipy import stats

from calib_cli.data import CalibrationResult, Recording
from calib_cli.errors import EstimationError
from calib_cli.methods.turntable.options import TurntableOptions

DIAGNOSE_PASSES = 12  # the most passes of each model's fit
# the effects the filter holds in its own options (the rest go to TurntableOptions.effects)
STRUCTURAL = ("lever_arm", "proof_mass_offsets", "g_sensitivity")
BASE_NAMES = ["accel_bias", "accel_K (lower)", "gyro_bias", "gyro_K (full)",
              "mounting and trajectory of each cycle (nuisance)"]
WANDER_WHY = ("a wandering bias is not a state of the turntable filter: diagnose it on a "
              "static record (calib diagnose --method accel / gyro, calib allan)")
NO_CLOCK = ("not observable: without a table angle or rate channel nothing times the table's "
            "motion against the IMU (a delay of every IMU sample alike changes nothing)")


def options_with(opt: TurntableOptions, effects) -> TurntableOptions:
    """The fit of the diagnosis's base model plus ``effects`` [(name, sensor)]: the base
    (no lever arms, no proof masses, no g-sensitivity) with the effects switched on."""
    names = {n for n, _ in effects}
    rest = tuple((n, s) for n, s in effects if n not in STRUCTURAL)
    lever = "lever_arm" in names or "proof_mass_offsets" in names
    return replace(opt, lever_arm="estimate" if lever else "off",
                   proof_mass="estimate" if "proof_mass_offsets" in names else "off",
                   g_sensitivity="g_sensitivity" in names, effects=rest)


def fit_with(rec: Recording, o, effects, base: str = "full") -> CalibrationResult:
    """``calib fit turntable --with EFFECTS`` (methods/registry.py): the base model (its
    scale factors full or diagonal) plus the effects, fitted as the plain fit is (its
    options; noise levels estimated)."""
    from calib_cli.methods.turntable.fit import fit_turntable

    opt = o.to_method() if hasattr(o, "to_method") else o
    opt = options_with(replace(opt, base_structure=base), effects)
    res = fit_turntable(rec, opt)
    res.stats["with"] = [with_arg(n, s) for n, s in effects]
    res.stats["base_model"] = list(BASE_NAMES)
    res.stats["base"] = base
    return res


def with_arg(name: str, sensor: str) -> str:
    from calib_cli.methods.with_effects import with_arg as arg

    return arg(name, sensor)


def effect_lines(rec: Recording | None, base: str = "full") -> list[dict]:
    """``calib fit turntable --list-effects [RAW]``: one entry per effect ``--with`` takes,
    {"with", "excites", "record", "excited" (None without a record), "why"}."""
    from calib_cli.methods.diagnose_candidates import effect_key
    from calib_cli.model.effects import make_effect

    names = [("lever_arm", ""), ("proof_mass_offsets", ""), ("g_sensitivity", "gyro"),
             ("time_offset", ""), ("scale_asymmetry", "gyro"), ("scale_asymmetry", "accel"),
             ("accel_nonlinearity", "accel"), ("temperature_drift", "accel"),
             ("temperature_drift", "gyro"), ("misalignment", "accel"), ("misalignment", "gyro")]
    why = {}
    if rec is not None:
        from calib_cli.methods.turntable.fit import problem

        pb = problem(rec, options_with(TurntableOptions(base_structure=base), ()))
        why = _candidates(rec, pb, {"lever_arm"}, base)[1]
        if base != "diagonal":
            for s in ("accel", "gyro"):
                why[effect_key("misalignment", s)] = ("the full base model's K and G hold every "
                                                      "misalignment (--base diagonal)")
    out = []
    for name, sensor in names:
        e = make_effect(name, sensor or "accel")
        key = effect_key(name, sensor)
        reason = why.get(key)
        out.append({"with": with_arg(name, sensor), "excites": e.excites, "record": e.record,
                    "excited": None if rec is None else reason is None, "why": reason})
    return out


@dataclass
class Fitted:
    """A converged fit: its problem, state, last pass, iteration info and result."""

    pb: object
    st: object
    pr: object
    info: dict
    effects: tuple
    result: CalibrationResult | None = None
    rows: list | None = None  # per cycle (nb, 7) the measurement rows' residuals
    weights: list | None = None  # ... and their weights (accelerometers at white noise)


def _solve(rec, opt, effects, start: Fitted | None = None, fixed: bool = False) -> Fitted:
    """The model base + effects fitted; from ``start``'s solution where given (its
    trajectory, its parameters by name, its noise levels: held there where ``fixed``)."""
    from calib_cli.methods.turntable.fit import iterate, prepared
    from calib_cli.methods.turntable.result import theta_labels

    pb, st = prepared(rec, replace(options_with(opt, effects), passes=DIAGNOSE_PASSES))
    if start is not None:
        old = {lab: i for i, lab in enumerate(theta_labels(start.pb))}
        for i, lab in enumerate(theta_labels(pb)):
            if lab in old:
                st.theta[i] = start.st.theta[old[lab]]
        st.C = [C.copy() for C in start.st.C]
        st.rho = [None if r is None else r.copy() for r in start.st.rho]
        st.C_start = list(start.st.C_start)
        st.angle_ref = None if start.st.angle_ref is None else list(start.st.angle_ref)
        st.axis_var = start.st.axis_var
        st.lever2 = None if start.st.lever2 is None else list(start.st.lever2)
        st.inflation = start.st.inflation
        if pb.enc is not None and start.pb.enc is not None:
            pb.sig_enc, pb.sig_enc_floor = start.pb.sig_enc, start.pb.sig_enc_floor
        if pb.rate is not None and start.pb.rate is not None:
            pb.sig_rate_row = start.pb.sig_rate_row
        pb.fixed_levels = fixed
    # (a model without the effect the data hold converges slowly, by Gauss-Newton's
    # neglect of the curvature its large residuals carry: its last pass is taken, a
    # likelihood short of its optimum by less than the thresholds' scale)
    st, pr, info = iterate(pb, st, windows=start is None, strict=False)
    return Fitted(pb, st, pr, info, tuple(effects))


def _neg2ll(f: Fitted) -> float:
    """-2 log L of a fit at its solution, its noise levels at their most likely values:
    the accelerometers' white level a (in units of the high-frequency estimate) at
    max(1, chi^2 / n) (never below the white noise the data show), the table axis's and
    the channels' as estimated, the propagation rows and the priors as they are."""
    from calib_cli.methods.turntable.estimator import row_groups

    chi_hf, n, _ = _accel_fit(f, dof=False, after=False)
    a = max(1.0, chi_hf / max(n, 1))
    total = n * np.log(a) + chi_hf / a
    # the rest of the cost at the last pass's point (evaluated, not predicted): every row
    # but the accelerometers' (at the weights the fit used)
    total += float(f.pr.step.cost) - chi_hf / f.st.inflation ** 2
    levels = {"axis": 0.5 * np.log(f.st.axis_var), "angle": np.log(max(f.pb.sig_enc, 1e-300)),
              "rate": np.log(max(f.pb.sig_rate_row, 1e-300))}
    for name, slot in row_groups(f.pb).items():
        if name == "accel":
            continue
        used = sum(int((cs.weight[:, slot] > 0).sum()) for cs in f.pr.systems)
        total += 2.0 * used * levels[name]
    return float(total)


def _accel_fit(f: Fitted, dof: bool = True, after: bool = True) -> tuple[float, int, float]:
    """(chi^2 of the accelerometer rows at the data's white noise (not widened), their
    number, their degrees of freedom n - trace of the hat matrix); after the last pass's
    step, or at its point (``after`` False)."""
    from calib_cli.methods.turntable.solve import leverage, residuals_after

    ss, n = 0.0, 0
    for cs, dl in zip(f.pr.systems, f.pr.step.dlocal):
        r = (residuals_after(cs, dl, f.pr.step.dtheta) if after else cs.r)[:, :3]
        w = cs.weight[:, :3] * f.st.inflation
        used = w > 0
        ss += float(np.sum((r * w)[used] ** 2))
        n += int(used.sum())
    if not dof:
        return ss, n, float(n)
    tr = leverage(f.pr.step, f.pr.systems, {"accel": slice(0, 3)})["accel"]
    return ss, n, max(n - tr, 1.0)


def _result(rec, f: Fitted, light: bool = False) -> CalibrationResult:
    """The fit's result (``light``: only what scoring a candidate needs, result.build)."""
    from calib_cli.methods.turntable.result import build
    from calib_cli.methods.turntable.solve import residuals_after

    if f.result is None:
        f.result = build(f.pb, f.st, f.pr, f.info, light=light)
        chi2, n, dof = _accel_fit(f)
        f.result.stats.update({"accel_chi2": chi2, "accel_n": n, "accel_dof": dof})
        f.result.residuals.clear()
        f.result.residuals["accel"], f.result.residuals["time"] = _accel_residuals(f)
        # every measurement row's residual after the last step and its weight (the
        # accelerometers' at their white noise): the steps are compared at the final
        # model's weights (_common_scale)
        f.rows = [residuals_after(cs, dl, f.pr.step.dtheta)
                  for cs, dl in zip(f.pr.systems, f.pr.step.dlocal)]
        f.weights = []
        for cs in f.pr.systems:
            w = cs.weight.copy()
            w[:, :3] *= f.st.inflation
            f.weights.append(w)
    return f.result


def _common_scale(fits: list) -> None:
    """Each fit's chi^2 over every measurement row (accelerometers, table axis, channels)
    at the last fit's weights, the number of rows and the last fit's degrees of freedom
    (rows less the hat matrix's trace): the residual RMS of each step on one scale (a time
    offset shows in the channels' rows, whose levels the fits estimate)."""
    from calib_cli.methods.turntable.estimator import row_groups
    from calib_cli.methods.turntable.solve import leverage

    last = fits[-1]
    tr = sum(leverage(last.pr.step, last.pr.systems, row_groups(last.pb)).values())
    n = int(sum((w > 0).sum() for w in last.weights))
    for f in fits:
        chi2 = float(sum(np.sum((r * w) ** 2) for r, w in zip(f.rows, last.weights)))
        f.result.stats.update({"chi2": chi2, "n_equations": n, "dof": max(n - tr, 1.0)})


def _accel_residuals(f: Fitted) -> tuple[np.ndarray, np.ndarray]:
    """The accelerometer block rows' residuals in units of their white noise (n, 3) and
    the blocks' start times (n,), s."""
    from calib_cli.methods.turntable.solve import residuals_after

    out, t = [], []
    for cs, dl, gp in zip(f.pr.systems, f.pr.step.dlocal, f.pr.gps):
        r = residuals_after(cs, dl, f.pr.step.dtheta)[:, :3] * cs.weight[:, :3] * f.st.inflation
        used = cs.weight[:, 0] > 0
        out.append(r[used])
        t.append(gp.t0[used])
    if not out:
        return np.zeros((0, 3)), np.zeros(0)
    t = np.concatenate(t)
    order = np.argsort(t, kind="stable")
    return np.concatenate(out)[order], t[order]


def _candidates(rec: Recording, pb, added: set, base: str = "full") -> tuple[list, dict]:
    """[(name, sensor)] to try this round, and {key: why not} for the others."""
    from calib_cli.methods.diagnose_candidates import effect_key
    from calib_cli.model.effects import Excitation, make_effect

    w = rec.gyro[np.concatenate([np.arange(cy.sl.start, cy.sl.stop) for cy in pb.cycles])]
    both = bool(np.any((w > 0.05).any(axis=0) & (w < -0.05).any(axis=0)))
    span = None
    if rec.temp is not None and np.all(np.isfinite(rec.temp)):
        span = float(np.ptp(rec.temp))
    ex = Excitation("turntable", ("accel", "gyro"), base, 9, both, span,
                    int(rec.time[-1] - rec.time[0]) * 2, True, False)
    names = [("lever_arm", ""), ("proof_mass_offsets", ""), ("g_sensitivity", "gyro"),
             ("time_offset", ""), ("scale_asymmetry", "gyro"), ("scale_asymmetry", "accel"),
             ("accel_nonlinearity", "accel"), ("temperature_drift", "accel"),
             ("temperature_drift", "gyro")]
    if base == "diagonal":
        names = [("misalignment", "accel"), ("misalignment", "gyro")] + names
    out, why = [], {}
    for name, sensor in names:
        key = effect_key(name, sensor)
        if key in added:
            continue
        if name == "time_offset" and pb.enc is None and pb.rate is None:
            why[key] = NO_CLOCK
            continue
        if name == "proof_mass_offsets" and "lever_arm" not in added:
            why[key] = "tried once the lever arms are in the model (they share its terms)"
            continue
        opts = {"structure": "lower" if sensor == "accel" else "full"} \
            if name == "misalignment" else {}
        reason = make_effect(name, sensor or "accel", **opts).not_excited(ex)
        if reason:
            why[key] = reason
            continue
        out.append((name, sensor))
    for s in ("accel", "gyro"):
        why[effect_key("bias_random_walk", s)] = WANDER_WHY
        why[effect_key("bias_instability", s)] = WANDER_WHY
    return out, why


def _new_entries(f: Fitted, name: str, sensor: str) -> tuple[dict, dict, int]:
    """The candidate's own entries (values, sigma) and how many the data determine."""
    from calib_cli.model.effects import make_effect

    res = f.result
    keys = [s.key for s in make_effect(name, sensor or "accel").specs(res.layout)]
    params = {k: np.asarray(res.params[k], float) for k in keys if k in res.params}
    sigma = {k: np.asarray(res.sigma[k], float) for k in keys if k in res.sigma}
    k = int(sum(int(np.sum(np.isfinite(s) & (s > 0))) for s in sigma.values()))
    return params, sigma, k


@dataclass
class TurntableDiagnosis:
    base_model: list
    steps: list
    results: list  # CalibrationResult of the base model and after each step
    untested: dict
    rounds: list
    base: str = "full"
    notes: list = field(default_factory=list)
    method: str = "turntable"

    @staticmethod
    def _rms(res: CalibrationResult) -> float:
        return float(np.sqrt(res.stats["chi2"] / res.stats["n_equations"]))

    @property
    def residual_rms_initial(self) -> float:
        return self._rms(self.results[0])

    @property
    def residual_rms_final(self) -> float:
        return self._rms(self.results[-1])

    @property
    def noise_rms(self) -> float:
        st = self.results[-1].stats
        return float(np.sqrt(st["dof"] / st["n_equations"]))

    @property
    def final_chi2(self) -> tuple[float, float, float]:
        """(chi^2 of the final model's measurement rows, its dof, the chi^2 99 % point)."""
        st = self.results[-1].stats
        return st["chi2"], st["dof"], float(stats.chi2.ppf(0.99, st["dof"]))

    @property
    def final_p_value(self) -> float:
        st = self.results[-1].stats
        return float(stats.chi2.sf(st["chi2"], st["dof"]))

    @property
    def with_list(self) -> list:
        return [s.with_arg for s in self.steps]

    def fit_command(self, raw: str = "RAW.h5", out: str = "CAL.h5") -> str | None:
        from calib_cli.methods.with_effects import fit_command

        return fit_command("turntable", self.with_list, self.base, "auto", raw, out)

    def calibration(self, rec=None) -> CalibrationResult:
        """The final model as ``calib fit turntable --with`` the steps writes it (one
        computation: the fit from its start, on the record where given)."""
        res = self.results[-1]
        if rec is not None and self.steps:
            res = fit_with(rec, TurntableOptions(), [(s.effect, s.sensor) for s in self.steps],
                           self.base)
        res.stats["with"] = self.with_list
        res.stats["base"] = self.base
        res.stats["base_model"] = list(self.base_model)
        return res

    def residual_series(self, before: int = 0, after: int = -1) -> tuple:
        """(block times (n,) s, the accelerometer residuals (n, 3) in units of their white
        noise of two models: the base model's and the final model's, or ``before`` and
        ``after`` (indices into results)): the disagreement plots."""
        a, b = self.results[before].residuals, self.results[after].residuals
        return a["time"], a["accel"], b["accel"]

    def to_json(self) -> dict:
        chi2, dof, p99 = self.final_chi2
        return {
            "method": "turntable", "base_model": self.base_model,
            "steps": [s.to_json() for s in self.steps],
            "residual_rms_initial": self.residual_rms_initial,
            "residual_rms_final": self.residual_rms_final, "noise_rms": self.noise_rms,
            "gap_left": self.residual_rms_final / self.noise_rms,
            "final_fit_p_value": self.final_p_value,
            "final_chi2": chi2, "final_dof": dof, "final_chi2_99": p99,
            "untested": self.untested, "rounds": self.rounds, "notes": self.notes,
            "table_channels": self.results[-1].stats.get("table_encoder", {}).get("mode"),
            "fit_command": self.fit_command(),
        }


def diagnose_turntable(rec: Recording, base: str = "full", alpha: float | None = None,
                       max_steps: int | None = None,
                       options: TurntableOptions | None = None) -> TurntableDiagnosis:
    """The workflow on a turntable record (module docstring)."""
    from calib_cli.methods.blas_threads import one_blas_thread
    from calib_cli.methods.diagnose import ALPHA, MAX_STEPS

    if base not in ("full", "diagonal"):
        raise EstimationError(f"base is full or diagonal, got {base!r}")
    opt = replace(options or TurntableOptions(), base_structure=base)
    with one_blas_thread():
        return _diagnose(rec, opt, ALPHA if alpha is None else alpha,
                         MAX_STEPS if max_steps is None else max_steps)


def _diagnose(rec, opt, alpha, max_steps) -> TurntableDiagnosis:
    from calib_cli.methods.diagnose import Step, zscore
    from calib_cli.methods.diagnose_candidates import Candidate, describe, effect_key

    cur = _solve(rec, opt, ())
    results = [_result(rec, cur)]
    fits = [cur]
    steps, rounds, notes = [], [], []
    untested: dict = {}
    added: set = set()
    for _ in range(max_steps):
        cands, why = _candidates(rec, cur.pb, added, opt.base_structure)
        for k, v in why.items():
            untested.setdefault(k, v)
        # the current model refitted as each candidate is (from its solution, at its levels):
        # a model short of its optimum (a slow valley) would otherwise credit every
        # candidate with the rest of its own descent
        ref = _solve(rec, opt, cur.effects, start=cur, fixed=True)
        c0 = min(_neg2ll(cur), _neg2ll(ref))
        tried = []
        for name, sensor in cands:
            key = effect_key(name, sensor)
            try:
                f = _solve(rec, opt, cur.effects + ((name, sensor),), start=cur, fixed=True)
            except EstimationError as exc:
                untested.setdefault(key, f"the refit failed ({exc.message})")
                continue
            _result(rec, f, light=True)
            k = _new_entries(f, name, sensor)[2]
            if k == 0:
                untested.setdefault(key, "not observable from this record")
                continue
            tried.append((name, sensor, f, k, c0 - _neg2ll(f)))
        if not tried:
            break
        m = len(tried)
        table, best = [], None
        for name, sensor, f, k, d in tried:
            thr = float(stats.chi2.isf(alpha / m, k))
            p = float(stats.chi2.sf(max(d, 0.0), k))
            table.append({"candidate": effect_key(name, sensor), "score": d, "threshold": thr,
                          "dof": k, "p_value": p})
            if d > thr and (best is None or -zscore(d, k) < best[0]):
                best = (-zscore(d, k), name, sensor, f, k, d, thr, p)
        table.sort(key=lambda r: -zscore(r["score"], r["dof"]))
        rounds.append(table)
        if best is None:
            break
        _, name, sensor, f, k, d, thr, p = best
        # the model with the effect, its noise levels settled again
        new = _solve(rec, opt, f.effects, start=f)
        res = _result(rec, new)
        params, sigma, k_new = _new_entries(new, name, sensor)
        before = float(np.sqrt(results[-1].stats["accel_chi2"] / results[-1].stats["accel_n"]))
        after = float(np.sqrt(res.stats["accel_chi2"] / res.stats["accel_n"]))
        runner = next((r["candidate"] for r in table if r["candidate"] != effect_key(name, sensor)
                       and r["score"] > r["threshold"]), None)
        words = describe(Candidate(name, sensor, None), params, sigma)
        ev = (f"{words}. Likelihood ratio {d:.1f} against threshold {thr:.1f} ({k} parameters, "
              f"{m} candidates tried); accelerometer residual RMS {before:.3f} -> {after:.3f} "
              "of their white noise")
        if runner:
            ev += f"; also above threshold but weaker: {runner}"
        steps.append(Step(name, sensor, params, sigma, d, thr, k, p, None, before, after, ev,
                          runner))
        added.add(effect_key(name, sensor))
        cur = new
        results.append(res)
        fits.append(new)
    _common_scale(fits)
    for i, step in enumerate(steps):  # before and after on the final model's weights
        step.residual_rms_before = TurntableDiagnosis._rms(results[i])
        step.residual_rms_after = TurntableDiagnosis._rms(results[i + 1])
    names = list(BASE_NAMES)
    if opt.base_structure == "diagonal":
        names[1], names[3] = "accel_K (diagonal)", "gyro_K (diagonal)"
    out = TurntableDiagnosis(names, steps, results, untested, rounds, opt.base_structure,
                             notes)
    chi2, dof, p99 = out.final_chi2
    if chi2 > p99:
        notes.append(f"the final model leaves {out.residual_rms_final / out.noise_rms:.3f}x the "
                     f"noise floor (chi^2 {chi2:.0f} for {dof:.0f} degrees "
                     f"of freedom, above its 99 % point {p99:.0f}): part of the gap is not "
                     "explained by any candidate")
    return out
