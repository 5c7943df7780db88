"""calib fit --with, many cases (`make validate K=fit_with`, or one part:
K=fit_with_static, fit_with_turntable, fit_with_rimu, fit_with_align, fit_with_gyro;
issue 18): for every hidden-effect case of calib_cli/validation/diagnose_cases.py,
`fit METHOD --with` the hidden effect gives estimates within sigma of the truth
(pooled over the seeds: RMS of (est - truth) / sigma in [0.8, 1.25], 99 % of |z|
below 3.3) and leaves a residual within 1.05x the noise floor in every seed. The
wandering biases are noise-model terms: their fitted figure is judged by the Allan
confidence bounds instead (``allan_interval``): per channel, fitted / true within the
95 % interval of the best single Allan-deviation reading of that figure on a record of
the same length in >= 95 % of the channels over the seeds.

40 seeds per case and method (CALIB_WITH_N sets another number), the (case, seed)
fits on CALIB_DIAG_WORKERS processes (default 2). Each part writes its own
section of docs/validation/diagnose.md.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from calib_cli.model.effects import FLICKER_SCALE, FLICKER_TAUS
from calib_cli.validation import diagnose_cases as C
from calib_cli.validation import diagnose_validate as V

pytestmark = pytest.mark.slow
N = int(os.environ.get("CALIB_WITH_N", "40"))
WORKERS = int(os.environ.get("CALIB_DIAG_WORKERS", "2"))
DOC = Path(__file__).resolve().parent.parent / "docs" / "validation" / "diagnose.md"
PARTS = {"static": ("accel",), "turntable": ("turntable",), "rimu": ("rimu",),
         "align": ("align",), "gyro": ("gyro",)}
# measured and reported, not asserted: {case: why}
REPORTED_ONLY: dict = {}
# noise terms whose fitted figure scatters more than the best single Allan reading of a
# continuous static record of the same length allows (measured: below 95 % of the
# channels within its 95 % interval); reported, and held above ALLAN_FLOOR: {case: why}
# (the engine's random walks, accel and turntable gyro, were here at 82-83 % until their
# figure was read by the restricted likelihood on a refined grid, diagnose_stoch.fit_process:
# now near the Cramer-Rao bound of the record, benchmarks/allan18_crb.py; the gyro
# method's two wanders, at 80.8-90.0 %, until its likelihood took the within-static
# piece-mean contrasts, diagnose_gyro_wander.SubMeans)
ALLAN_REPORTED: dict = {}
ALLAN_FLOOR = 0.75
_ROWS: dict = {}


def part_cases(part: str) -> list:
    return [c for c, v in C.CASES.items() if v[0] in PARTS[part]]


def process_avar(kind: str, c: float, tau):
    """Allan variance of a bias process of figure c at tau: random walk of density q,
    q^2 tau / 3; flicker of figure B, the catalogue's Gauss-Markov sum (each of variance
    s^2 = (FLICKER_SCALE B)^2: s^2 T^2 / tau^2 (2 tau/T - 3 + 4 e^(-tau/T) - e^(-2 tau/T)))."""
    tau = np.asarray(tau, float)
    if kind == "bias_random_walk":
        return c * c * tau / 3.0
    s2 = (FLICKER_SCALE * c) ** 2
    return sum(s2 * (T / tau) ** 2 * (2 * tau / T - 3 + 4 * np.exp(-tau / T)
                                      - np.exp(-2 * tau / T)) for T in FLICKER_TAUS)


def allan_interval(kind: str, c: float, white: float, fs: float, span: float,
                   level: float = 0.95):
    """The 95 % interval of fitted / true for the figure c of a wander, as the best single
    reading of an overlapping Allan deviation (IEEE 952) of a record of ``span`` s at fs
    with white noise ``white`` per sample gives it: at each octave tau the estimated Allan
    variance is (W + P) chi^2_edf / edf (edf: allantools' Greenhall algorithm for the
    process's noise type, flicker FM alpha = -1, random-walk FM alpha = -2), the figure
    read with the white part W known, c^2_est / c^2 = ((W + P) chi^2 / edf - W) / P.
    Returns (lo, hi, tau) at the tau of the narrowest interval (the averaging time that
    dominates the reading)."""
    import allantools
    from scipy import stats

    n = int(span * fs)
    alpha = -2 if kind == "bias_random_walk" else -1
    best = None
    m = 1
    while 4 * m <= n:
        tau = m / fs
        W = white * white / (fs * tau)
        P = float(process_avar(kind, c, tau))
        edf = float(allantools.edf_greenhall(alpha=alpha, d=2, m=m, N=n, overlapping=True,
                                             modified=False))
        q = (1 - level) / 2
        lo2 = ((W + P) * stats.chi2.ppf(q, edf) / edf - W) / P
        hi2 = ((W + P) * stats.chi2.isf(q, edf) / edf - W) / P
        lo, hi = np.sqrt(max(lo2, 0.0)), np.sqrt(max(hi2, 0.0))
        if best is None or hi - lo < best[1] - best[0]:
            best = (lo, hi, tau)
        m *= 2
    return best


def allan_judge(row: dict) -> None:
    """Adds to a wander row the share of channels whose fitted / true lies in its
    Allan interval, the intervals' ranges and the averaging times."""
    inside, los, his, taus = [], [], [], []
    for sd in row["wander_seeds"]:
        for ratio, c, white in zip(sd["ratio"], sd["true"], sd["white"], strict=True):
            lo, hi, tau = allan_interval(sd["kind"], c, white, sd["fs"], sd["span"])
            inside.append(lo <= ratio <= hi)
            los.append(lo)
            his.append(hi)
            taus.append(tau)
    row["allan_within"] = float(np.mean(inside))
    row["allan_n"] = len(inside)
    row["allan_ci"] = [float(min(los)), float(max(los))]
    row["allan_ci_hi"] = [float(min(his)), float(max(his))]
    row["allan_tau"] = [float(min(taus)), float(max(taus))]


def rows_of(part: str) -> dict:
    if part not in _ROWS:
        _ROWS[part] = V.fit_with_rows(part_cases(part), lambda c: N, workers=WORKERS)
        for r in _ROWS[part].values():
            if "wander_seeds" in r:
                allan_judge(r)
    return _ROWS[part]


def check(part: str, case: str) -> None:
    r = rows_of(part)[case]
    assert r["gap_ok"] == 1.0, r
    if "allan_within" in r:  # a noise term: within its Allan interval
        brief = {k: v for k, v in r.items() if k != "wander_seeds"}
        assert r["allan_within"] >= (ALLAN_FLOOR if case in ALLAN_REPORTED else 0.95), brief
    if "rms_z" in r and case in REPORTED_ONLY:
        assert r["frac_33"] >= 0.99 and r["rms_z"] <= 1.25, r  # conservative sigma only
    elif "rms_z" in r:
        assert 0.8 <= r["rms_z"] <= 1.25 and r["frac_33"] >= 0.99, r


def write(part: str) -> None:
    rows = list(rows_of(part).values())
    lines = [f"### fit --with: {part} ({', '.join(PARTS[part])} method)", "",
             f"`make validate K=fit_with_{part}`.", "", V.fit_with_table(rows), ""]
    lines += [f"- {k}: {v}." for k, v in REPORTED_ONLY.items() if k in rows_of(part)]
    lines += [f"- {k}: within the Allan interval in {100 * rows_of(part)[k]['allan_within']:.1f} "
              f"% of the channels, below 95 % (reported, held above "
              f"{100 * ALLAN_FLOOR:.0f} %): {v}." for k, v in ALLAN_REPORTED.items()
              if k in rows_of(part)]
    V.write_section(DOC, f"fit_with_{part}", "\n".join(lines))


@pytest.mark.parametrize("case", part_cases("static"))
def test_fit_with_static(case):
    check("static", case)


def test_fit_with_static_table():
    write("static")


@pytest.mark.parametrize("case", part_cases("turntable"))
def test_fit_with_turntable(case):
    check("turntable", case)


def test_fit_with_turntable_table():
    write("turntable")


@pytest.mark.parametrize("case", part_cases("rimu"))
def test_fit_with_rimu(case):
    check("rimu", case)


def test_fit_with_rimu_table():
    write("rimu")


@pytest.mark.parametrize("case", part_cases("align"))
def test_fit_with_align(case):
    check("align", case)


def test_fit_with_align_table():
    write("align")


@pytest.mark.parametrize("case", part_cases("gyro"))
def test_fit_with_gyro(case):
    check("gyro", case)


def test_fit_with_gyro_table():
    write("gyro")
