"""Benchmark `calib fit turntable`: CPU seconds of fit per hour of data at 100 Hz.

    python -m benchmarks.bench_turntable [--seconds 600]

The issue-32 record: three standard cycles of ``--seconds`` (600 s) at 100 Hz with 10 s
remounts between them, lever arms and proof masses estimated, the log's table channels a
rate channel (2e-3 scale error) and a coarse encoder (2^16 counts, 0.05 deg
once-per-revolution error, 0.05 deg of white noise per sample), default options
(`--table-encoder auto`: both used). Printed: CPU s per hour of data and the passes, with
the channels and IMU only (`--table-encoder off`), beside the baselines measured in the
same run: a plain read of the record's HDF5 file and one integration of the gyros over
the same samples with SciPy's Rotation (the least any attitude-propagating method must
do), so the ratios stay comparable on a slower or busier machine. The target (issue 32):
<= 12 CPU s per hour with the channels, <= 5 passes. Also a 1 kHz record (a quarter of
the length).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

_MODE = {"off": "IMU only", "auto": "rate + coarse encoder, auto"}
ENCODER = ("sim_table_encoder_counts = 65536\nsim_table_encoder_opr_deg = 0.05\n"
           "sim_table_angle_noise_deg = 0.05\nsim_table_rate_scale_error = 2e-3\n")


def _case(seconds: float, rate: float, seed: int = 0):
    from calib_cli.io.plan import parse_plan
    from calib_cli.sim.simulate import simulate
    from calib_cli.sim.turntable_plans import turntable_plan_text

    text = ENCODER + turntable_plan_text(seed, duration_s=seconds, sample_rate_hz=rate,
                                         transition_s=10.0)
    return simulate(parse_plan(text), None, seed)


def _time_fit(rec, encoder: str = "off") -> tuple[float, float, int]:
    """(wall, CPU seconds, passes) of one fit: CPU stays meaningful on a busy machine."""
    from calib_cli.methods.turntable import TurntableOptions, fit_turntable

    t0, c0 = time.perf_counter(), time.process_time()
    res = fit_turntable(rec, TurntableOptions(table_encoder=encoder))
    return time.perf_counter() - t0, time.process_time() - c0, res.stats["filter_passes"]


def _time_gyro_integration(rec) -> float:
    from scipy.spatial.transform import Rotation

    dt = np.diff(rec.time, append=rec.time[-1])
    c0 = time.process_time()
    Rotation.from_rotvec(rec.gyro * dt[:, None]).as_matrix()
    return time.process_time() - c0


def _time_read(rec) -> float:
    """CPU seconds of reading the record back from its raw.h5 (calib's reader)."""
    from calib_cli.io.h5 import read_raw, write_raw

    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "raw.h5"
        write_raw(path, rec)
        c0 = time.process_time()
        read_raw(path)
        return time.process_time() - c0


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=600.0, help="length of each cycle (s)")
    args = ap.parse_args(argv)
    print(f"{'benchmark':64s} {'value':>10s} {'baseline':>10s} {'ratio':>8s}")
    for rate, secs in ((100.0, args.seconds), (1000.0, args.seconds / 4)):
        rec = _case(secs, rate)
        hours = (rec.time[-1] - rec.time[0]) / 3600.0
        read = _time_read(rec) / hours
        integ = _time_gyro_integration(rec) / hours
        print(f"{f'plain read of raw.h5, CPU s per hour at {rate:g} Hz':64s} {read:10.4g}")
        print(f"{f'gyro integration (SciPy), CPU s per hour at {rate:g} Hz':64s} {integ:10.4g}")
        for enc in ("auto", "off"):
            wall, cpu, passes = _time_fit(rec, enc)
            name = f"fit turntable ({_MODE[enc]}), CPU s per hour at {rate:g} Hz"
            print(f"{name:64s} {cpu / hours:10.4g} {read:10.4g} {cpu / hours / read:8.3g}")
            print(f"{'  vs the gyro integration':64s} {'':10s} {integ:10.4g} "
                  f"{cpu / hours / integ:8.3g}")
            print(f"{'  passes (target <= 5), wall s':64s} {passes:10d} {wall:10.4g}")


if __name__ == "__main__":
    main()
