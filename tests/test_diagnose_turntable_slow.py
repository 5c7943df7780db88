"""calib diagnose --method turntable on records with hidden effects (issues 14, 32), `make
validate K=diagnose_turntable`: one hidden effect (lever arm, g-sensitivity, time offset)
and two at once (lever arm + g-sensitivity), each observable entry U(5, 10) x its own
sigma with a random sign, 20 seeds per case, for three channel cases: no table channels
(a rough stand), an exact encoder, an encoder with 0.05 deg of white noise per sample.
Per case: the seeds where diagnose names exactly the hidden effects and stops, and those
whose final residual chi^2 is within the chi^2 99 % point of its degrees of freedom.
Without a table channel a time offset is physically unobservable (nothing times the
table's motion against the IMU: a delay of every IMU sample alike changes nothing): there
the exact answer is no step, with time_offset listed as untested. Two tables: a vertical
table with six static positions (docs/validation/turntable-diagnose.md) and a rough stand,
four cycles about a horizontal axis (docs/validation/turntable-diagnose-horizontal.md).
"""

from __future__ import annotations

import os
import time
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import binom
from scipy.stats import chi2 as chi2_dist

pytestmark = pytest.mark.slow
SEEDS = int(os.environ.get("CALIB_TT_DIAG_SEEDS", "20"))
DOC = Path(__file__).resolve().parents[1] / "docs" / "validation" / "turntable-diagnose.md"
CASES = {"lever_arm": ["lever_arm"], "gyro g_sensitivity": ["gyro g_sensitivity"],
         "time_offset": ["time_offset"],
         "lever_arm + gyro g_sensitivity": ["lever_arm", "gyro g_sensitivity"]}
CHANNELS = {"none": "no table channels", "encoder": "exact encoder",
            "coarse": "encoder, 0.05 deg white noise"}
COARSE_SD = float(np.radians(0.05))


_SIGMA: dict = {}


def _sigma(name: str, channels: str, plan: str = "turntable") -> dict:
    """The effect's 1-sigma on the pilot record as the channel case logs it (a time offset
    seen through a 0.05 deg encoder is 2-3x less certain than through an exact one: sized
    by the exact encoder's sigma, it was below detection in 2 of 5 seeds)."""
    from calib_cli.errors import EstimationError
    from calib_cli.validation import diagnose_cases as C

    if (name, channels, plan) not in _SIGMA:
        try:
            _SIGMA[name, channels, plan] = C.effect_sigma(
                name, lambda r: with_channels(r, channels, np.random.default_rng(12345)), plan)
        except EstimationError:  # the pilot fit without channels does not converge: the
            # exact encoder's sigma (smaller: the effect is then the harder to find)
            _SIGMA[name, channels, plan] = C.effect_sigma(name, None, plan)
    return _SIGMA[name, channels, plan]


def _truth(case: str, rng, channels: str = "encoder", plan: str = "turntable"):
    from calib_cli.model.imu_model import ImuModel
    from calib_cli.model.truth import Truth
    from calib_cli.validation import diagnose_cases as C

    names = CASES[case]
    t = C.hidden_effect_truth(names[0], rng, sigma=_sigma(names[0], channels, plan),
                              plan_key=plan)
    for extra in names[1:]:  # a second hidden effect, drawn the same way
        method, name, sensor, _base = C.CASES[extra]
        p = {**t.params, **C.effect_draws(_sigma(extra, channels, plan), rng)}
        t = Truth(ImuModel(t.model.effects + (C.effect_of(method, name, sensor),),
                           t.model.layout), p, t.noise)
    return t


def with_channels(rec, channels: str, rng):
    """The record as each channel case logs it (the simulator's channels are exact)."""
    if channels == "none":
        return rec.with_(table_angle=None, table_rate=None)
    ang = np.asarray(rec.table_angle, float)
    if channels == "coarse":
        ang = ang + rng.normal(0.0, COARSE_SD, ang.shape)
    return rec.with_(table_angle=ang, table_rate=None)


def _one(args):
    case, channels, seed, plan = (*args, "turntable")[:4]
    from calib_cli.methods.diagnose import diagnose
    from calib_cli.methods.diagnose_candidates import effect_key
    from calib_cli.sim.simulate import simulate
    from calib_cli.validation import diagnose_cases as C

    t0 = time.perf_counter()
    truth = _truth(case, np.random.default_rng(seed), channels, plan)
    rec = simulate(C.plan_of(plan), truth, seed=seed + 1)
    rec = with_channels(rec, channels, np.random.default_rng(70_000 + seed))
    d = diagnose(rec, "turntable")
    keys = [effect_key(s.effect, s.sensor) for s in d.steps]
    chi2, dof, p99 = d.final_chi2
    return (case, channels, seed, keys, float(chi2), float(dof), float(p99),
            "time_offset" in d.untested, time.perf_counter() - t0)


def final_needed(n: int) -> int:
    """The fewest of n seeds whose final chi^2 is within its 99 % point for a case to pass:
    the largest k with P(X < k) < 5 %, X ~ Binomial(n, 0.99) the count a true model gives
    (19 of 20: P(X <= 18) = 1.7 %)."""
    for k in range(n, -1, -1):
        if binom.cdf(k - 1, n, 0.99) < 0.05:
            return k
    return 0


def expected(case: str, channels: str) -> list:
    want = list(CASES[case])
    if channels == "none":  # physically unobservable without a table channel
        want = [k for k in want if k != "time_offset"]
    return sorted(want)


PLAN_WORDS = {"turntable": "six static positions, four rotating cycles about the vertical",
              "turntable-horizontal": "four rotating cycles about a horizontal axis (East), "
                                      "no static positions: the issue's rough stand"}


def test_turntable_diagnose_names_exactly_the_hidden_effects():
    """The vertical table of calib_cli/validation/diagnose_cases.py (with static positions)."""
    _validate("turntable", DOC)


def test_turntable_diagnose_horizontal_axis():
    """The rough stand: four cycles about a horizontal axis, no static positions."""
    _validate("turntable-horizontal", DOC.with_name("turntable-diagnose-horizontal.md"))


def _validate(plan: str, doc: Path) -> None:
    for names in CASES.values():  # the pilots' sigma, before the workers fork
        for name in names:
            for ch in CHANNELS:
                _sigma(name, ch, plan)
    jobs = [(c, ch, s, plan) for c in CASES for ch in CHANNELS for s in range(SEEDS)]
    t0 = time.perf_counter()
    with get_context("fork").Pool(2) as pool:
        res = list(pool.imap_unordered(_one, jobs))
    wall = time.perf_counter() - t0
    lines = ["# calib diagnose --method turntable: hidden effects (issues 14, 32)", "",
             "Generated by tests/test_diagnose_turntable_slow.py (`make validate "
             f"K=diagnose_turntable`): {SEEDS} seeds per case, the plan "
             f"{plan!r} of calib_cli/validation/diagnose_cases.py ({PLAN_WORDS[plan]}, "
             "50 Hz), each observable entry of each hidden effect "
             "U(5, 10) times its own 1-sigma (the refit's on a pilot record of the same "
             "channel case; without channels, where that pilot fit does not converge, the "
             "exact encoder's) with a random sign; three channel cases: no "
             "table channels, an exact encoder, an encoder with 0.05 deg of white noise per "
             "sample. Exact: the steps name exactly the hidden effects (in any order) and "
             "nothing else (without a table channel a time offset is unobservable: there "
             "exact is no step, time_offset untested). Final: the final model's chi^2 within "
             "the chi^2 99 % point of its degrees of freedom. "
             f"Wall time on 2 workers: {wall / 60:.1f} min.", "",
             "| hidden | channels | exact | final chi^2 <= 99 % point | pooled chi^2 / dof | "
             "largest chi^2 / dof | other steps (count) | s per case |",
             "|---|---|---|---|---|---|---|---|"]
    bad = []
    for case in CASES:
        for ch, words in CHANNELS.items():
            rows = [r for r in res if r[0] == case and r[1] == ch]
            want = expected(case, ch)
            exact = sum(sorted(r[3]) == want and (ch != "none" or "time_offset" not in CASES[case]
                                                  or r[7]) for r in rows)
            final = sum(r[4] <= r[6] for r in rows)
            # pooled over the seeds: sum chi^2 against the 99 % point of the summed dof
            pooled = (sum(r[4] for r in rows), sum(r[5] for r in rows))
            pooled_ok = pooled[0] <= chi2_dist.ppf(0.99, pooled[1])
            other: dict = {}
            for r in rows:
                for k in r[3]:
                    if k not in want:
                        other[k] = other.get(k, 0) + 1
            oth = ", ".join(f"{k} {n}" for k, n in sorted(other.items())) or "-"
            lines.append(f"| {case} | {words} | {exact}/{len(rows)} | {final}/{len(rows)} | "
                         f"{pooled[0] / pooled[1]:.3f} ({'within' if pooled_ok else 'above'}) | "
                         f"{max(r[4] / r[5] for r in rows):.3f} | {oth} | "
                         f"{np.mean([r[8] for r in rows]):.0f} |")
            if exact < 0.95 * len(rows) or final < final_needed(len(rows)) or not pooled_ok:
                bad.append((case, ch, exact, final,
                            [r[2] for r in rows if sorted(r[3]) != want]))
    lines += ["", "The final rule: a true model's chi^2 exceeds its 99 % point in 1 % of the "
              "seeds (in at least one of 20 seeds with probability 1 - 0.99^20 = 18 %; the "
              "four cases of one channel case share each seed's noise), so a case passes with "
              f"at least {final_needed(SEEDS)} of {SEEDS} seeds within it (fewer has a "
              "probability below 5 % under the true model: 1.7 % for 18 of 20) and the chi^2 pooled over its "
              "seeds within the 99 % point of the pooled degrees of freedom.", "",
              f"Cases outside the rule (>= 19 of 20 exact, the final rule above): {len(bad)}."]
    lines += [f"- {c} ({ch}): exact {e}, final {f}; seeds not exact: {s}"
              for c, ch, e, f, s in bad]
    doc.write_text("\n".join(lines) + "\n")
    assert not bad, bad
