"""Benchmark `calib fit turntable`: seconds of fit per hour of data at 100 Hz and 1 kHz.

    python -m benchmarks.bench_turntable [--seconds 200]

Simulates three standard cycles (each ``--seconds`` long, lever arms and proof
masses estimated, passes to convergence) and times the fit, IMU only and with
the default `--table-encoder auto` on a log with the table's channels (a 2^16-count
encoder and a rate channel with a 2e-3 scale error: both used). The
baseline, measured in the same run, is one integration of the gyros over the
same samples with SciPy's Rotation (the least any attitude-propagating method
must do), so the ratio stays comparable on a slower or busier machine. Also
times the issue's reference case, 3 x 600 s at 100 Hz.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

_MODE = {"off": "IMU only", "auto": "table channels, auto"}


def _case(seconds: float, rate: float, seed: int = 0):
    from calib_cli.io.plan import parse_plan
    from calib_cli.sim.simulate import simulate
    from calib_cli.sim.turntable_plans import turntable_plan_text

    text = ("sim_table_encoder_counts = 65536\nsim_table_encoder_opr_deg = 0.05\n"
            "sim_table_rate_scale_error = 2e-3\n"
            + turntable_plan_text(seed, duration_s=seconds, sample_rate_hz=rate))
    return simulate(parse_plan(text), None, seed)


def _time_fit(rec, encoder: str = "off") -> tuple[float, float]:
    """(wall, CPU) seconds of one fit: the CPU time stays meaningful on a busy machine."""
    from calib_cli.methods.turntable import TurntableOptions, fit_turntable

    t0, c0 = time.perf_counter(), time.process_time()
    fit_turntable(rec, TurntableOptions(table_encoder=encoder))
    return time.perf_counter() - t0, time.process_time() - c0


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
        base = _time_baseline(rec) / hours
        for enc in ("off", "auto"):
            wall, cpu = (v / hours for v in _time_fit(rec, enc))
            name = f"fit turntable ({_MODE[enc]}), s per hour at {rate:g} Hz"
            print(f"{name:60s} {wall:12.4g} {base:12.4g} {wall / base:8.3g}")
            print(f"{'  the same, CPU s per hour':60s} {cpu:12.4g}")
    rec = _case(600.0, 100.0)
    base = _time_baseline(rec)
    for enc in ("off", "auto"):
        t, cpu = _time_fit(rec, enc)
        name = f"fit turntable ({_MODE[enc]}), 3 x 600 s at 100 Hz (s)"
        print(f"{name:60s} {t:12.4g} {base:12.4g} {t / base:8.3g}")
        print(f"{'  the same, CPU s':60s} {cpu:12.4g}")


if __name__ == "__main__":
    main()
