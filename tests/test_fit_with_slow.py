"""calib fit --with, many cases (`make validate K=fit_with`, or one part:
K=fit_with_static, fit_with_turntable, fit_with_rimu, fit_with_align, fit_with_gyro;
issue 18): for every hidden-effect case of calib_cli/validation/diagnose_cases.py,
`fit METHOD --with` the hidden effect gives estimates within sigma of the truth
(pooled over the seeds: RMS of (est - truth) / sigma in [0.8, 1.25], 99 % of |z|
below 3.3) and leaves a residual within 1.05x the noise floor in every seed. The
wandering biases are noise-model terms: their fitted figure against the truth is
reported (its sigma is rough, docs/diagnose.md), not judged by the pooled rule.

40 seeds per case and method (CALIB_WITH_N sets another number), the (case, seed)
fits on CALIB_DIAG_WORKERS processes (default 2). Each part writes its own
section of docs/diagnose-validation.md.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from calib_cli.validation import diagnose_cases as C
from calib_cli.validation import diagnose_validate as V

pytestmark = pytest.mark.slow
N = int(os.environ.get("CALIB_WITH_N", "40"))
WORKERS = int(os.environ.get("CALIB_DIAG_WORKERS", "2"))
DOC = Path(__file__).resolve().parent.parent / "docs" / "diagnose-validation.md"
PARTS = {"static": ("accel",), "turntable": ("turntable",), "rimu": ("rimu",),
         "align": ("align",), "gyro": ("gyro",)}
# measured and reported, not asserted: {case: why}
REPORTED_ONLY: dict = {}
_ROWS: dict = {}


def part_cases(part: str) -> list:
    return [c for c, v in C.CASES.items() if v[0] in PARTS[part]
            and not (v[0] == "gyro" and v[1] in V.WANDER)]  # fit gyro --with: no wanders


def rows_of(part: str) -> dict:
    if part not in _ROWS:
        _ROWS[part] = V.fit_with_rows(part_cases(part), lambda c: N, workers=WORKERS)
    return _ROWS[part]


def check(part: str, case: str) -> None:
    r = rows_of(part)[case]
    assert r["gap_ok"] == 1.0, r
    if "rms_z" in r and case in REPORTED_ONLY:
        assert r["frac_33"] >= 0.99 and r["rms_z"] <= 1.25, r  # conservative sigma only
    elif "rms_z" in r:
        assert 0.8 <= r["rms_z"] <= 1.25 and r["frac_33"] >= 0.99, r


def write(part: str) -> None:
    rows = list(rows_of(part).values())
    lines = [f"### fit --with: {part} ({', '.join(PARTS[part])} method)", "",
             f"`make validate K=fit_with_{part}`.", "", V.fit_with_table(rows), ""]
    lines += [f"- {k}: {v}." for k, v in REPORTED_ONLY.items() if k in rows_of(part)]
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
