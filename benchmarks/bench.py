"""make bench: speed figures, each against a baseline measured in the same run.

Prints one line per benchmark: the figure, the baseline and their ratio, so a
slower machine changes both and the ratio stays comparable.
"""

from __future__ import annotations

import time

import numpy as np


def _best(fn, repeat=3):
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench_static():
    """fit accel (vector, GLS with covariance) vs a bare per-axis numpy lstsq on
    the same segment means; and the simulator's samples per second."""
    from calib_cli.io.plan import parse_plan
    from calib_cli.methods.accel_lsq import fit_vector
    from calib_cli.methods.segstats import static_stats
    from calib_cli.model.frames import attitude_to_rotation
    from calib_cli.sim.simulate import simulate
    from calib_cli.validation.static_cases import static_plan_text

    plan = parse_plan(static_plan_text(duration=60.0, rate=200.0))
    t_sim = _best(lambda: simulate(plan, None, 0), 2)
    rec = simulate(plan, None, 0)
    t_fit = _best(lambda: fit_vector(rec))

    def baseline():
        st = static_stats(rec)
        f = attitude_to_rotation(np.array([s.attitude for s in st.segments])).inv().apply(
            [0, 0, rec.site.gravity])
        np.linalg.lstsq(np.column_stack([np.ones(len(f)), f]), st.means, rcond=None)

    t_base = _best(baseline)
    n = len(rec)
    rng = np.random.default_rng(0)
    t_noise = _best(lambda: rng.standard_normal((n, 6)))  # the cost of the noise alone
    return [("fit accel vector, 12 x 60 s at 200 Hz (s) vs bare lstsq", t_fit, t_base, "s"),
            ("simulate: samples per second vs drawing their noise", n / t_sim, n / t_noise,
             "1/s")]


def main() -> None:
    rows = bench_static()
    print(f"{'benchmark':60s} {'value':>12s} {'baseline':>12s} {'ratio':>8s}")
    for name, value, base, _unit in rows:
        print(f"{name:60s} {value:12.4g} {base:12.4g} {value / base:8.3g}")


if __name__ == "__main__":
    main()
