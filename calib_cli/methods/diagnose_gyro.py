"""``calib diagnose --method gyro``: the discrepancy workflow on the gyro
method's own equations (turns between static positions, turns of known angle,
static means; methods/gyro.py), where the table-free record has no per-sample
truth for the rates, so the bin engine of the other methods does not apply.

Base model: gyro bias + G (full, or diagonal with ``--base diagonal``), the
accelerometers fitted from the same record (``fit accel --method auto``) for
the gravity directions. Each round refits the model with every candidate the
record excites (gyro scale asymmetry: turns both ways; temperature drift: a
recorded temperature spanning >= 1 degC; g-sensitivity: gravity along all
three axes; misalignment from a diagonal base) and scores it by the
likelihood ratio Delta chi^2 of the whitened equations, chi^2 with k degrees
of freedom (k = the effect's observable entries) when the effect is absent;
threshold the chi^2_k quantile at alpha / m (Bonferroni over the m
candidates of the round), as ``methods.diagnose``. The wandering gyro biases
(random walk, flicker) are candidates too, scored on the same equations'
generalised likelihood (``methods.diagnose_gyro_wander``; a noise-model term:
it widens sigma, never applied; ``fit gyro --with gyro.bias_instability`` gives the
same model). When the two wanders' likelihood ratios differ by less than
``WANDER_MARGIN``, the note says they are not separable on this plan. The best passing
candidate is added; stop when none passes. The user's quantity: the angle each turn
integrates to against the plan's, and the transition residual, base model
against final model.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from calib_cli.data import CalibrationResult, Recording
from calib_cli.errors import EstimationError
from calib_cli.methods.diagnose import ALPHA, MAX_STEPS, Step, zscore
from calib_cli.methods.diagnose_candidates import Candidate, describe, effect_key
from calib_cli.methods.diagnose_gyro_wander import KEYS, WanderLikelihood, unit_of, with_wander
from calib_cli.methods.with_effects import GYRO_EFFECTS, fit_command, gyro_effect

R2D = 180.0 / np.pi
# below this margin of likelihood ratio the two wanders are reported as not separable:
# on the linearised gyro equations and within-static contrasts of the validation plan
# (212 s; benchmarks/gyro_wander_separation.py, 120 draws a row) a hidden flicker at
# 5-10x its sigma is named first in 100 % and within 12 of the walk in 2.5 %; at half
# that size named first in 88 %, named first or within 12 in 100 %; a hidden random walk
# is within 12 of flicker in 0-0.8 % (docs/diagnose.md, "The gyro method")
WANDER_MARGIN = 12.0


@dataclass
class GyroDiagnosis:
    base_model: list
    steps: list
    results: list  # CalibrationResult of the base model and after each step
    untested: dict
    rounds: list
    base: str = "full"
    notes: list = field(default_factory=list)
    method: str = "gyro"

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
        return float(np.sqrt(max(st["dof"], 1) / st["n_equations"]))

    @property
    def final_p_value(self) -> float:
        st = self.results[-1].stats
        return float(stats.chi2.sf(st["chi2"], max(st["dof"], 1)))

    @property
    def with_list(self) -> list:
        return [s.with_arg for s in self.steps]

    def fit_command(self, raw: str = "RAW.h5", out: str = "CAL.h5") -> str | None:
        return fit_command("gyro", self.with_list, self.base, "auto", raw, out)

    def calibration(self, rec=None) -> CalibrationResult:
        res = self.results[-1]
        res.stats["with"] = self.with_list
        res.stats["base"] = self.base
        res.stats["base_model"] = list(self.base_model)
        return res

    def turn_errors(self) -> list[dict]:
        """Angle each turn integrates to minus the plan's, deg: base and final model."""
        a, b = self.results[0], self.results[-1]
        out = []
        plan = a.stats.get("turn_plan_deg", {})
        for label, ang in a.stats.get("turn_angles_deg", {}).items():
            want = plan.get(label)
            if want is None:
                continue
            out.append({"turn": label, "error_initial_deg": ang - want,
                        "error_final_deg": b.stats["turn_angles_deg"][label] - want})
        return out

    def to_json(self) -> dict:
        a, b = self.results[0].stats, self.results[-1].stats
        tr = [a.get("transition_residual_rms_rad"), b.get("transition_residual_rms_rad")]
        return {
            "method": "gyro", "base_model": self.base_model,
            "steps": [s.to_json() for s in self.steps],
            "residual_rms_initial": self.residual_rms_initial,
            "residual_rms_final": self.residual_rms_final, "noise_rms": self.noise_rms,
            "gap_left": self.residual_rms_final / self.noise_rms,
            "final_fit_p_value": self.final_p_value, "untested": self.untested,
            "rounds": self.rounds, "notes": self.notes,
            "turn_angle_error_deg": self.turn_errors(),
            "transition_residual_rms_deg": [None if x is None else x * R2D for x in tr],
            "fit_command": self.fit_command(),
        }


def diagnose_gyro(rec: Recording, base: str = "full", alpha: float = ALPHA,
                  max_steps: int = MAX_STEPS, accel: CalibrationResult | None = None,
                  wanders: bool = True) -> GyroDiagnosis:
    """The workflow on a gyro record (module docstring)."""
    from calib_cli.methods.blas_threads import one_blas_thread

    with one_blas_thread():  # small dense systems: threads only contend
        return _diagnose_gyro(rec, base, alpha, max_steps, accel, wanders)


def _diagnose_gyro(rec: Recording, base: str, alpha: float, max_steps: int,
                   accel: CalibrationResult | None, wanders: bool) -> GyroDiagnosis:
    from calib_cli.methods.accel_lsq import fit_accel
    from calib_cli.methods.gyro import excitation, fit_gyro

    if rec.gyro is None:
        raise EstimationError("the recording has no gyro data")
    acc = accel if accel is not None else fit_accel(rec)
    ex = excitation(rec, acc, base)
    structure = "diagonal" if base == "diagonal" else "full"

    def fit(names):
        res = fit_gyro(rec, acc, "off", extra=[gyro_effect(n) for n in names],
                       structure=structure)
        turns = [s for s in rec.segments if s.kind == "turn"]
        res.stats["turn_plan_deg"] = {s.label: float(np.degrees(s.rotation_angle))
                                      for s in turns if s.rotation_angle is not None}
        return res

    cur = fit([])
    results, added, steps, rounds, notes = [cur], [], [], [], []
    untested = {}
    for n in GYRO_EFFECTS:
        why = gyro_effect(n).not_excited(ex)
        if why:
            untested[effect_key(n, "gyro")] = why
    # the wandering biases: scored by the generalised likelihood of the same equations
    # (methods/diagnose_gyro_wander.py); one wander, then the deterministic candidates
    # are scored under it: generalised chi^2 with its figures held (re-estimated after
    # each step)
    W = WanderLikelihood(rec, acc, structure) if wanders else None
    wander = None  # (kind, figures in data units, sigma)
    lin = {}

    def linear(names, res):
        key = tuple(names)
        if key not in lin:
            lin[key] = W.linear(names, res)
        return lin[key]

    for _ in range(max_steps):
        cands = [n for n in GYRO_EFFECTS if n not in added
                 and effect_key(n, "gyro") not in untested]
        tried = []
        if wander is not None:  # scored under the current wander (its figures fixed)
            r, A, _ = linear(added, cur)
            cur_m2 = W.m2ll(r, A, wander[0], wander[1])[0]
        for n in cands:
            try:
                f = fit(added + [n])
            except EstimationError as exc:
                untested.setdefault(effect_key(n, "gyro"), f"the refit failed ({exc.message})")
                continue
            keys = [sp.key for sp in gyro_effect(n).specs(rec.layout)]
            unobs = set(f.stats.get("unobservable", []))
            k = sum(1 for key, i in f.cov_order if key in keys
                    and _entry(key, f.params[key], i) not in unobs)
            if k == 0:
                untested.setdefault(effect_key(n, "gyro"), "not observable from this experiment")
                continue
            if wander is None:
                d = float(cur.stats["chi2"] - f.stats["chi2"])
            else:
                r, A, _ = linear(added + [n], f)
                d = float(cur_m2 - W.m2ll(r, A, wander[0], wander[1])[0])
            tried.append((n, f, keys, k, d))
        if W is not None and wander is None:
            r, A, _ = linear(added, cur)
            m2_white = W.m2ll(r, A)[0]
            for kind in KEYS:
                m2 = W.profile(r, A, kind, reml=False)[2]  # the likelihood ratio
                x, sig = W.profile(r, A, kind)[:2]  # the figures: restricted likelihood
                k = int((x > 0).sum())
                d = float(m2_white - m2) if k else 0.0
                tried.append((kind, (x, sig), [KEYS[kind]], max(k, 1), d))
        if not tried:
            break
        m = len(tried)
        table, best = [], None
        for n, f, keys, k, d in tried:
            thr = float(stats.chi2.isf(alpha / m, k))
            p = float(stats.chi2.sf(max(d, 0.0), k))
            table.append({"candidate": effect_key(n, "gyro"), "score": d, "threshold": thr,
                          "dof": k, "p_value": p})
            if d > thr and (best is None or -zscore(d, k) < best[0]):
                best = (-zscore(d, k), n, f, keys, k, d, thr, p)
        table.sort(key=lambda r: -zscore(r["score"], r["dof"]))
        rounds.append(table)
        if best is None:
            break
        _, n, f, keys, k, d, thr, p = best
        before = GyroDiagnosis._rms(results[-1])
        if n in KEYS:  # a wander: a noise-model term of the current model
            x, sig = f
            wander = (n, x, sig)
            unit = unit_of(cur)
            params, sigma = {KEYS[n]: x / unit}, {KEYS[n]: sig / unit}
        else:
            params = {key: np.asarray(f.params[key]) for key in keys}
            sigma = {key: np.asarray(f.sigma[key]) for key in keys}
            added.append(n)
            cur = f
        res = cur
        if wander is not None:
            res, x, sig = with_wander(W, linear(added, cur), cur, wander[0])
            wander = (wander[0], x, sig)
        after = GyroDiagnosis._rms(res)
        runner = next((r["candidate"] for r in table if r["candidate"] != effect_key(n, "gyro")
                       and r["score"] > r["threshold"]), None)
        words = describe(Candidate(n, "gyro", gyro_effect(n) if n not in KEYS else None),
                         params, sigma)
        ev = (f"{words}. Likelihood ratio {d:.1f} against threshold {thr:.1f} ({k} parameters, "
              f"{m} candidates tried); residual RMS {before:.2f} -> {after:.2f} noise units")
        if runner:
            ev += f"; also above threshold but weaker: {runner}"
        other = next((r for r in table if n in KEYS and r["candidate"] != effect_key(n, "gyro")
                      and r["candidate"] in [effect_key(w, "gyro") for w in KEYS]), None)
        if other is not None and other["score"] > other["threshold"] \
                and d - other["score"] < WANDER_MARGIN:
            ev += f"; not separable from {other['candidate']} on this plan"
            notes.append(f"gyro bias_random_walk and bias_instability are not separable on "
                         f"this plan (likelihood ratios {d:.1f} for {effect_key(n, 'gyro')} and "
                         f"{other['score']:.1f} for {other['candidate']}, within "
                         f"{WANDER_MARGIN:.0f}): the step named {effect_key(n, 'gyro')} stands "
                         "for either; to tell them apart record a static stretch of 30 min or "
                         "more and run calib allan (flicker is flat, a random walk rises as "
                         "sqrt(tau))")
        steps.append(Step(n, "gyro", params, sigma, d, thr, k, p, None, before, after, ev,
                              runner))  # no signature correlation in the gyro fit
        results.append(res)
    names = ["gyro_bias", f"gyro_K ({structure})",
             "accelerometers: fit accel --method auto on the same record (gravity directions)"]
    out = GyroDiagnosis(names, steps, results, untested, rounds, base, notes)
    if wander is not None:
        out.notes.append(f"gyro {wander[0]} is a noise-model term: it widens sigma and is "
                         "reported in the calibration's stats.noise_model, never applied or "
                         "exported")
    if out.final_p_value < alpha:
        out.notes.append(f"the final model leaves {out.residual_rms_final / out.noise_rms:.2f}x "
                         "the noise floor: part of the gap is not explained by any candidate")
    return out



def _entry(key: str, value, flat: int) -> str:
    from calib_cli.methods.result import entry_name

    return entry_name(key, np.shape(value), flat)
