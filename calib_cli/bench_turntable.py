"""Benchmark `calib fit turntable`: seconds of fit per hour of data at 100 Hz and 1 kHz.

    python -m calib_cli.bench_turntable [--seconds 200]

Simulates three standard cycles (each ``--seconds`` long, lever arms
estimated, proof masses off, the default two passes) and times the fit. The
baseline, measured in the same run, is one integration of the gyros over the
same samples with SciPy's Rotation (the least any attitude-propagating method
must do), so the ratio stays comparable on a slower or busier machine. Also
times the issue's reference case, 3 x 600 s at 100 Hz.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def _case(seconds: float, rate: float, seed: int = 0):
    from calib_cli.io.plan import parse_plan
    from calib_cli.sim.simulate import simulate
    from calib_cli.sim.turntable_plans import turntable_plan_text

    plan = parse_plan(turntable_plan_text(seed, duration_s=seconds, sample_rate_hz=rate))
    return simulate(plan, None, seed)


def _time_fit(rec) -> float:
    from calib_cli.methods.turntable import TurntableOptions, fit_turntable

    t0 = time.perf_counter()
    fit_turntable(rec, TurntableOptions())
    return time.perf_counter() - t0


def _time_baseline(rec) -> float:
    from scipy.spatial.transform import Rotation

    dt = np.diff(rec.time, append=rec.time[-1])
    t0 = time.perf_counter()
    Rotation.from_rotvec(rec.gyro * dt[:, None]).as_matrix()
    return time.perf_counter() - t0


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=200.0, help="length of each cycle (s)")
    args = ap.parse_args(argv)
    print(f"{'benchmark':60s} {'value':>12s} {'baseline':>12s} {'ratio':>8s}")
    for rate in (100.0, 1000.0):
        secs = args.seconds if rate == 100.0 else args.seconds / 4
        rec = _case(secs, rate)
        hours = 3 * secs / 3600.0
        fit = _time_fit(rec) / hours
        base = _time_baseline(rec) / hours
        print(f"{f'fit turntable, s per hour of {rate:g} Hz data':60s} {fit:12.4g} {base:12.4g} "
              f"{fit / base:8.3g}")
    rec = _case(600.0, 100.0)
    t = _time_fit(rec)
    base = _time_baseline(rec)
    print(f"{'fit turntable, 3 x 600 s at 100 Hz (s)':60s} {t:12.4g} {base:12.4g} {t / base:8.3g}")


if __name__ == "__main__":
    main()
