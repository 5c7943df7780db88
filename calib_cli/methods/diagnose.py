"""``calib diagnose``: find the effect a model lacks, name it, add it, refit,
and show the gap shrink, until the residuals reach the noise.

1. Fit the method's base model (CONTRACT.md section 5) to the bin means of
   the recording (``diagnose_problem``) through the effect catalogue's forward
   model with the plan's attitudes and table motion (``diagnose_fit``).
2. Residuals in units of each channel's noise; the noise floor from the
   data's own high-frequency content.
3. Each round, refit with every candidate effect the experiment can excite
   (``diagnose_candidates``) and score it by the likelihood ratio
   Delta chi^2 = chi^2(model) - chi^2(model + effect), which is chi^2 with
   k degrees of freedom (k = the effect's observable parameters) when the
   effect is absent. Threshold: the chi^2_k quantile at ALPHA / m, with m the
   number of candidates tried in the round (Bonferroni), so a round adds a
   false effect with probability <= ALPHA. The best candidate (smallest
   p-value) is added if it passes.
4. Stop when no candidate passes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from calib_cli.data import Recording
from calib_cli.errors import EstimationError
from calib_cli.methods import diagnose_candidates as dc
from calib_cli.methods import diagnose_stoch as ds
from calib_cli.methods.blas_threads import one_blas_thread
from calib_cli.methods.diagnose_fit import MOUNT_KEY, Fit, ModelSpec, columns, fit_model
from calib_cli.methods.diagnose_problem import BIN_S, Problem, build_problem
from calib_cli.methods.method import resolve
from calib_cli.model.imu_model import ImuModel

ALPHA = 0.01  # false-alarm probability per round, shared over its candidates
MAX_STEPS = 6


@dataclass
class Step:
    effect: str
    sensor: str
    params: dict
    sigma: dict
    score: float
    threshold: float
    k: int
    p_value: float
    correlation: float
    residual_rms_before: float
    residual_rms_after: float
    evidence: str
    runner_up: str | None = None

    @property
    def with_arg(self) -> str:
        """The step's effect as ``calib fit --with`` spells it."""
        from calib_cli.methods.with_effects import with_arg

        return with_arg(self.effect, self.sensor)

    def to_json(self) -> dict:
        return {"effect": self.effect, "sensor": self.sensor, "with": self.with_arg,
                "params": self.params,
                "sigma": self.sigma, "score": self.score, "threshold": self.threshold,
                "dof": self.k, "p_value": self.p_value,
                "signature_correlation": self.correlation,
                "residual_rms_before": self.residual_rms_before,
                "residual_rms_after": self.residual_rms_after,
                "evidence": self.evidence, "runner_up": self.runner_up}


@dataclass
class Diagnosis:
    method: str
    base_model: list
    steps: list
    residual_rms_initial: float
    residual_rms_final: float
    noise_rms: float
    untested: dict
    rounds: list  # per round: [{candidate, score, threshold, dof, p_value}]
    problem: Problem
    fits: list  # Fit after the base and after each step
    notes: list = field(default_factory=list)
    noise_sigma: dict = field(default_factory=dict)
    final_p_value: float = float("nan")  # chi^2 test of the final model against white noise
    base: str = "full"

    @property
    def with_list(self) -> list:
        return [s.with_arg for s in self.steps]

    def fit_command(self, raw: str = "RAW.h5", out: str = "CAL.h5") -> str | None:
        """The command that writes the final model's calibration (None: no step)."""
        from calib_cli.methods.with_effects import fit_command

        return fit_command(self.method, self.with_list, self.base, self.problem.noise_mode,
                           raw, out)

    def calibration(self, rec=None):
        """The final model as an ordinary calibration (``methods.fit_with``)."""
        from calib_cli.methods.diagnose_fit import settle_noise
        from calib_cli.methods.with_effects import WANDERS, calibration_of

        wander = {dc.effect_key(s.effect, s.sensor): (s.params, s.sigma) for s in self.steps
                  if s.effect in WANDERS}
        # the noise level settled for the final model, as fit --with does
        with one_blas_thread():
            pb, fit, first = settle_noise(self.problem, self.fits[-1], self.fits[0])
        return calibration_of(pb, fit, self.method, rec, self.base_model,
                              wander, self.with_list, self.base, initial=first)

    def by_segment(self) -> list:
        """Residual RMS (noise units) per segment, base model and final model."""
        pb = self.problem
        out = []
        res0 = self.fits[0].residual_blocks(pb)
        res1 = self.fits[-1].residual_blocks(pb)
        for idx in np.unique(pb.bin_seg):
            sel = pb.bin_seg == idx
            a = np.concatenate([res0[s][sel] for s in pb.sensors], axis=1)
            b = np.concatenate([res1[s][sel] for s in pb.sensors], axis=1)
            out.append({"segment": pb.seg_labels[idx], "kind": pb.seg_kinds[idx],
                        "rms_initial": float(np.sqrt(np.mean(a ** 2))),
                        "rms_final": float(np.sqrt(np.mean(b ** 2)))})
        return out

    def to_json(self) -> dict:
        return {
            "method": self.method, "base_model": self.base_model,
            "steps": [s.to_json() for s in self.steps],
            "residual_rms_initial": self.residual_rms_initial,
            "residual_rms_final": self.residual_rms_final,
            "noise_rms": self.noise_rms,
            "gap_left": self.residual_rms_final / self.noise_rms,
            "final_fit_p_value": self.final_p_value,
            "untested": self.untested,
            "rounds": self.rounds,
            "noise_sigma_per_sample": {s: v for s, v in self.noise_sigma.items()},
            "noise_sigma_high_frequency": self.problem.sigma_hf,
            "noise_estimate": self.problem.noise_mode,
            "bin_scatter_ratio": self.problem.scatter_ratio,
            "residual_by_segment": self.by_segment(),
            "notes": self.notes,
            "fit_command": self.fit_command(),
        }


def base_spec(pb: Problem, base: str = "full") -> tuple[ModelSpec, list]:
    """The method's base model: (spec, its names for the JSON), as its ``Diagnose``
    description in the method table names it (methods/diagnose_models.py)."""
    effects, names, mount = resolve(pb.how.base)(pb, base)
    return ModelSpec(ImuModel(tuple(effects), pb.layout), mount), names


def start_params(pb: Problem, base: str = "full") -> dict | None:
    """Starting values of the base fit (the scalar case's ellipsoid fit, the alignment)."""
    if not pb.start:
        return None
    start = dict(pb.start)
    if base == "diagonal" and "accel_K" in start:
        start["accel_K"] = np.diag(np.diag(start["accel_K"]))
    return start


def zscore(d: float, k: int) -> float:
    """Normal-equivalent z of a chi^2_k statistic (Wilson-Hilferty): ranks
    candidates with different k by their p-value without underflow."""
    v = 2.0 / (9.0 * k)
    return float(((max(d, 0.0) / k) ** (1 / 3) - (1 - v)) / np.sqrt(v))


def rms(fit: Fit) -> float:
    return float(np.sqrt(np.mean(fit.r ** 2)))


def white_rms(fit: Fit) -> float:
    """RMS white noise alone would leave after fitting this model."""
    n = len(fit.r)
    return float(np.sqrt(max(n - fit.n_free, 1) / n))


def _new_entries(cand_fit: Fit, cur: Fit, keys: set) -> tuple[dict, dict, int]:
    """The candidate's own parameters (values, sigma) and how many are observable."""
    params, sigma = {}, {}
    for key in keys:
        params[key] = np.asarray(cand_fit.params[key], float)
        sigma[key] = np.asarray(cand_fit.sigma[key], float)
    k = sum(1 for j, lab in enumerate(cand_fit.labels)
            if lab[0] in keys and not cand_fit.unobs[j])
    if "lever_arm" in keys:
        k -= cand_fit.lever_constraints
    return params, sigma, max(k, 0)


def neg2ll(fit: Fit, pb: Problem, skip_first: str | None = None) -> float:
    """-2 log L of a fit (constants and the working sigma's log-determinant dropped).

    Where the working noise sigma was raised to the bins' scatter
    (``apply_noise``), each channel's white level is taken at its most likely value
    between the high-frequency estimate and the raised one, for every model alike:
    an effect that explains the scatter within the positions (a drift) then gets
    the credit the raise would otherwise take from it. Where no raise was made this
    is chi^2. Sensors under a wander (whitened) count their chi^2 as they are.
    skip_first: a sensor whose first bin is left out (the filter's diffuse start)."""
    tot = 0.0
    for s, z in fit.residual_blocks(pb).items():
        if s == skip_first:
            z = z[1:]
        ss = (z ** 2).sum(axis=0)
        if s in fit.spec.stochastic:
            tot += float(ss.sum())
            continue
        lo = (pb.whitener(s, high_frequency=True)[0] / pb.whitener(s)[0]) ** 2
        a = np.clip(ss / len(z), np.minimum(lo, 1.0), 1.0)
        tot += float((len(z) * np.log(a) + ss / a).sum())
    return tot


WANDERS = {"bias_random_walk": ("random_walk", "bias_rw"),
           "bias_instability": ("flicker", "bias_instability")}


def try_wander(pb: Problem, cur: Fit, c: dc.Candidate):
    """(candidate, fit, params, sigma, k, score, within-segment score) of a wandering
    bias on one sensor (a random walk or flicker, diagnose_stoch). Score: the
    likelihood ratio over the whole record with the model refitted under the
    process; the within-segment score (the level restarting at every segment) must
    pass too, because offsets between positions visited in sequence are what any
    position-dependent misfit also produces."""
    s = c.sensor
    if s in cur.spec.stochastic:  # one wander per sensor
        return None
    kind, suffix = WANDERS[c.name]
    key = f"{s}_{suffix}"
    z = cur.residual_blocks(pb)[s]
    wh = pb.whitener(s)
    reset = np.concatenate([[True], pb.bin_seg[1:] != pb.bin_seg[:-1]])
    white = pb.whitener(s, high_frequency=True)
    _, _, lr_in = ds.fit_process(pb.bin_t, z, wh, kind, reset, bin_s=BIN_S, white=white)
    val, sig, _ = ds.fit_process(pb.bin_t, z, wh, kind, bin_s=BIN_S, white=white,
                                 cols=_sensor_columns(pb, cur, s))
    if not np.any(val > 0):  # tested: the likelihood is largest without a wander
        return (c, cur, {key: val}, {key: np.full_like(val, np.nan)}, len(val), 0.0, 0.0)
    q, B = (val, None) if kind == "random_walk" else (np.zeros_like(val), val)
    w = ds.ProcessWhitener(pb.bin_t, wh, q, B=B, bin_s=BIN_S, white=white)
    spec = ModelSpec(cur.spec.model, cur.spec.mount, {**cur.spec.stochastic, s: w})
    f = fit_model(pb, spec, start=cur.params, start_mount=cur.mount)
    # -2 log L of both models over the same bins (the filter's first bin is diffuse)
    white_logdet = ds.log_det_white(wh)[1:].sum()
    score = (neg2ll(cur, pb, skip_first=s) + white_logdet) - (neg2ll(f, pb) + w.logdet[1:].sum())
    k = int((val > 0).sum())
    return (c, f, {key: val}, {key: sig}, k, float(score), float(lr_in.sum()))


def _sensor_columns(pb: Problem, cur: Fit, s: str) -> np.ndarray:
    """(M, n, p) the current fit's Jacobian columns on sensor s's bin means, in data units
    (the deterministic model the wander's restricted likelihood projects out)."""
    n = pb.y[s].shape[1]
    i = sum(pb.n_bins * pb.y[x].shape[1] for x in pb.sensors[:pb.sensors.index(s)])
    J = np.asarray(cur.J, float)[i:i + pb.n_bins * n]
    return (J * pb.whitener(s).ravel()[:, None]).reshape(pb.n_bins, n, -1)


def _clean(c: dc.Candidate, params: dict, sigma: dict) -> tuple[dict, dict]:
    """Contract conventions: the lever arm's axial component (unobservable) is
    reported as 0 with sigma 0."""
    if c.name == "lever_arm":
        v, s = params["lever_arm"].copy(), sigma["lever_arm"].copy()
        bad = ~np.isfinite(s) | (s == 0)
        v[bad], s[bad] = 0.0, 0.0
        params, sigma = dict(params, lever_arm=v), dict(sigma, lever_arm=s)
    return params, sigma


def diagnose(rec: Recording, method: str, base: str = "full", alpha: float = ALPHA,
             max_steps: int = MAX_STEPS, noise: str = "auto") -> Diagnosis:
    """Run the workflow on a recording (module docstring) for a method (its name or
    ``Method``: its ``Diagnose`` description in the method table); a method with a
    diagnosis of its own (gyro, turntable) runs that."""
    from calib_cli.methods.method import method_named

    m = method_named(method) if isinstance(method, str) else method
    if m.diagnose is not None and m.diagnose.own:
        return resolve(m.diagnose.engine)(rec, base=base, alpha=alpha, max_steps=max_steps)
    with one_blas_thread():
        try:
            return _diagnose(rec, method, base, alpha, max_steps, noise)
        except np.linalg.LinAlgError as exc:  # degenerate data (issue 37): never exit 70
            raise EstimationError(f"diagnose: the data do not determine the base model (a "
                                  f"singular system: {exc}); check that the positions differ "
                                  "as the plan says") from None


def _diagnose(rec: Recording, method: str, base: str, alpha: float, max_steps: int,
              noise: str) -> Diagnosis:
    from calib_cli.methods.segstats import check_gravity_seen

    check_gravity_seen(rec)  # static positions that do not see gravity: exit 3 (issue 37)
    pb = build_problem(rec, method, noise=noise)
    spec, names = base_spec(pb, base)
    cur = fit_model(pb, spec, start=start_params(pb, base), refresh=True)
    fits = [cur]
    r0 = rms(cur)
    steps, rounds = [], []
    added: set = set()
    untested_all: dict = {}
    notes = []
    tn = dc.temperature_note(pb)
    if tn:
        notes.append(tn)
    for _ in range(max_steps):
        cands, why = dc.candidates(pb, cur.spec.model, base, added)
        for k, v in why.items():
            untested_all.setdefault(k, v)
        tried = []
        within: dict = {}
        known = columns(cur)
        for c in cands:
            if c.name in WANDERS:
                got = try_wander(pb, cur, c)
                if got is not None:
                    within[c.key] = got[6]
                    tried.append(got[:6])
                continue
            model = cur.spec.model.with_effect(c.effect)
            cspec = ModelSpec(model, cur.spec.mount, cur.spec.stochastic)
            keys = {s.key for s in c.effect.specs(pb.layout)}
            try:
                f = fit_model(pb, cspec, start=cur.params, start_mount=cur.mount,
                              known_cols=known)
            except Exception as exc:  # noqa: BLE001 - a candidate that cannot be fitted
                untested_all.setdefault(c.key, f"the refit failed ({exc})")
                continue
            params, sigma, k = _new_entries(f, cur, keys)
            if k == 0:
                untested_all.setdefault(c.key, "not observable from this experiment")
                continue
            d = neg2ll(cur, pb) - neg2ll(f, pb)
            tried.append((c, f, params, sigma, k, d))
        if not tried:
            break
        m = len(tried)
        table = []
        best = None
        for c, f, params, sigma, k, d in tried:
            thr = float(stats.chi2.isf(alpha / m, k))
            p = float(stats.chi2.sf(max(d, 0.0), k))
            logp = -zscore(d, k)
            table.append({"candidate": c.key, "score": d, "threshold": thr, "dof": k,
                          "p_value": p})
            if c.key in within:  # a wander must show inside the segments too
                table[-1]["within_segment_score"] = within[c.key]
                if within[c.key] <= thr:
                    continue
            if d > thr and (best is None or logp < best[0]):
                best = (logp, c, f, params, sigma, k, d, thr, p)
        table.sort(key=lambda r: -zscore(r["score"], r["dof"]))
        rounds.append(table)
        if best is None:
            break
        _, c, f, params, sigma, k, d, thr, p = best
        if c.name not in WANDERS:
            # final refit with a fresh Jacobian: honest sigma for the reported values
            f = fit_model(pb, f.spec, start=f.params, start_mount=f.mount, refresh=True)
            keys = set(params)
            params, sigma, k = _new_entries(f, cur, keys)
            params, sigma = _clean(c, params, sigma)
        diff = cur.r - f.r
        corr = float(-(cur.r @ (f.r - cur.r)) / (np.linalg.norm(cur.r) * np.linalg.norm(diff)
                                                 + 1e-300))
        runner = next((r["candidate"] for r in table if r["candidate"] != c.key
                       and r["score"] > r["threshold"]), None)
        before, after = rms(cur), rms(f)
        words = dc.describe(c, params, sigma, pb)
        # the excess over the noise before = what the step explains + what it leaves
        # (the same scale for a wander step, whose residuals are whitened innovations)
        left = f.chi2 - (len(f.r) - f.n_free)
        excess = d + max(left, 0.0)
        share = d / excess
        at_floor = c.name not in WANDERS and cur.chi2 <= len(cur.r) - cur.n_free
        ev = (f"{words}. Likelihood ratio {d:.1f} against threshold {thr:.1f} "
              f"({k} parameters, {m} candidates tried); residual RMS {before:.2f} -> "
              f"{after:.2f} noise units; the residuals correlate {corr:.2f} with its "
              "signature; " + (f"it explains {100 * min(share, 9.99):.0f} % of the excess "
                               f"over the noise, leaving "
                               f"{max(left, 0.0) / excess * 100:.0f} %" if not at_floor else
                               "the model was already at the noise floor before it (a weak "
                               "step: read it with care)"))
        if c.name in WANDERS and pb.raised:
            ev += ("; the RMS after is of the whitened innovations against the "
                   "high-frequency noise floor, the RMS before against the raised one")
        if runner:
            ev += f"; also above threshold but weaker: {runner}"
        steps.append(Step(c.name, c.sensor, params, sigma, d, thr, k, p, corr, before, after,
                          ev, runner))
        added.add(c.key)
        cur = f
        fits.append(cur)
    pair = [st for st in steps if st.effect in ("accel_nonlinearity", "scale_asymmetry")
            and st.sensor == "accel"]
    if pair and "accel scale_asymmetry" in untested_all \
            and dc.excitation(pb, base).accel_levels == 3:
        notes.append("accelerometer nonlinearity and scale asymmetry are not separable on this "
                     "plan (each axis sees only 0 and +-g, where k2 u^2 and a |u| are the same "
                     "signature): the step named nonlinearity stands for either; to tell them "
                     "apart record positions with the axes at 35-55 deg inclination")
    n_after = rms(cur)
    floor = white_rms(cur)
    dof = len(cur.r) - cur.n_free
    p_fit = float(stats.chi2.sf(cur.chi2, dof))
    if p_fit < alpha:
        notes.append(f"the final model leaves {n_after / floor:.2f}x the noise floor (chi^2 "
                     f"{cur.chi2:.0f} for {dof} degrees of freedom, p = {p_fit:.2g}): part of "
                     "the gap is not explained by any effect of the catalogue in the form it "
                     "has, or the noise is not white")
        gated = [r for r in (rounds[-1] if rounds else [])
                 if "within_segment_score" in r and r["score"] > r["threshold"]
                 and r["within_segment_score"] <= r["threshold"]]
        for r in gated:
            notes.append(f"a wandering bias ({r['candidate']}) would fit the offsets between "
                         f"positions (score {r['score']:.0f}) but shows no wander within them "
                         f"(within-segment score {r['within_segment_score']:.1f} against "
                         f"{r['threshold']:.1f}): the positions differ by more than the model "
                         "allows (check the attitudes, or an effect outside the catalogue)")
        eligible = [r for r in (rounds[-1] if rounds else []) if r not in gated]
        if eligible:
            near = eligible[0]
            excess = cur.chi2 - dof
            notes.append(f"nearest catalogue effect left: {near['candidate']} (score "
                         f"{near['score']:.1f} against threshold {near['threshold']:.1f}); it "
                         f"would explain {100 * max(near['score'], 0) / max(excess, 1e-300):.0f}"
                         " % of the remaining excess")
    out_base = names
    out = Diagnosis(pb.method, out_base, steps, r0, n_after, floor, untested_all, rounds, pb,
                    fits, notes, {s: pb.sigma[s] for s in pb.sensors})
    out.final_p_value = p_fit
    out.base = base
    return out


__all__ = ["diagnose", "Diagnosis", "Step", "MOUNT_KEY"]
