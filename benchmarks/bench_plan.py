"""Benchmark `calib plan check` against the fit of the same plan (docs/plan.md).

    python -m benchmarks.bench_plan

For each generated plan (static 12 vector and scalar, Ferraris, two-position
alignment, RIMU six-position): the time of `plan check` without suggestions
(the prediction: the plan simulated without noise and the fit's own code run
at the truth with the stated noise) and of the fit on a simulated record of the
same plan, measured in the same run. Turntable plans: plan check is not
available yet (docs/plan.md).
"""

from __future__ import annotations

import time


def _plans():
    from calib_cli.io.plan import parse_plan
    from calib_cli.sim import plan_make as pm

    out = [("static 12 vector", pm.static_plan(12, "vector")),
           ("static 12 scalar", pm.static_plan(12, "scalar")),
           ("ferraris", pm.ferraris_plan()), ("align 120 deg z", pm.align_plan()[0]),
           ("rimu six-position", pm.rimu_plan())]
    return [(n, parse_plan(pm.to_toml(d), n)) for n, d in out]


def _real_fit(method, rec):
    if method in ("vector", "scalar"):
        from calib_cli.methods.accel_lsq import fit_accel

        return fit_accel(rec, method)
    if method == "gyro":
        from calib_cli.methods.gyro import fit_gyro

        return fit_gyro(rec)
    if method == "align":
        from calib_cli.methods.align import fit_align

        return fit_align(rec)
    from calib_cli.methods.rimu import fit_rimu

    return fit_rimu(rec)


def main() -> None:
    from calib_cli import design
    from calib_cli.sim.simulate import simulate

    print(f"{'plan':20s} {'check s':>8s} {'sim s':>7s} {'fit s':>7s} {'check/fit':>9s}")
    for name, plan in _plans():
        design.check(plan, suggestions=False)  # warm the imports
        t0 = time.perf_counter()
        pr = design.check(plan, suggestions=False)
        t_check = time.perf_counter() - t0
        t0 = time.perf_counter()
        rec = simulate(plan, None, 1)
        t_sim = time.perf_counter() - t0
        t0 = time.perf_counter()
        _real_fit(pr.method, rec)
        t_fit = time.perf_counter() - t0
        print(f"{name:20s} {t_check:8.3f} {t_sim:7.3f} {t_fit:7.3f} {t_check / t_fit:9.2f}")
    print("turntable: plan check not available yet (the estimator is being rewritten)")


if __name__ == "__main__":
    main()
