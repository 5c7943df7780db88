"""Benchmark `calib plan check` against the fit of the same plan (docs/plan.md).

    python -m benchmarks.bench_plan

For each generated plan (static 12 vector and scalar, Ferraris, two-position
alignment, RIMU six-position, turntable 3 and 9 cycles): the CPU time
(time.process_time) of `plan check` without suggestions (the prediction: the plan
simulated without noise, then the fit's own code at the truth with the stated noise;
for the turntable the fit's final linearised filter pass, started from a cheap pass over
the first tenth of each cycle, instead of the fit's passes) and of the fit on a simulated
record of the same plan, measured in the same run. docs/plan.md (Speed) has the figures.
"""

from __future__ import annotations

import time


def _plans():
    from calib_cli.io.plan import parse_plan
    from calib_cli.sim import plan_make as pm

    out = [("static 12 vector", pm.static_plan(12, "vector")),
           ("static 12 scalar", pm.static_plan(12, "scalar")),
           ("ferraris", pm.ferraris_plan()), ("align 120 deg z", pm.align_plan()[0]),
           ("rimu six-position", pm.rimu_plan()),
           ("turntable 3 cycles", pm.turntable_plan()),
           ("turntable 9 cycles", pm.turntable_plan(tilted=True))]
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
    if method == "turntable":
        from calib_cli.methods.turntable import fit_turntable

        return fit_turntable(rec)
    from calib_cli.methods.rimu import fit_rimu

    return fit_rimu(rec)


def main(only: str = "") -> None:
    from calib_cli import design
    from calib_cli.sim.simulate import simulate

    print("CPU time (time.process_time), s")
    print(f"{'plan':20s} {'check s':>8s} {'sim s':>7s} {'fit s':>7s} {'check/fit':>9s}")
    for name, plan in _plans():
        if only and not name.startswith(only):
            continue
        if name.startswith("turntable"):
            import calib_cli.methods.turntable  # noqa: F401 - warm the imports
        else:
            design.check(plan, suggestions=False)  # warm the imports
        t0 = time.process_time()
        pr = design.check(plan, suggestions=False)
        t_check = time.process_time() - t0
        t0 = time.process_time()
        rec = simulate(plan, None, 1)
        t_sim = time.process_time() - t0
        t0 = time.process_time()
        _real_fit(pr.method, rec)
        t_fit = time.process_time() - t0
        print(f"{name:20s} {t_check:8.3f} {t_sim:7.3f} {t_fit:7.3f} {t_check / t_fit:9.2f}",
              flush=True)


if __name__ == "__main__":
    import sys

    main(sys.argv[1] if len(sys.argv) > 1 else "")
