"""Flight-controller log imports against pyulog and pymavlink (issue 34).

    python -m benchmarks.bench_fclogs [--hours 1,4] [--baseline-hours 1] [--dir DIR]

Writes (once, kept in ``--dir``, default ``$TMPDIR/calib-bench-fclogs``) a PX4
ULog and an ArduPilot DataFlash log of ``--hours`` hours at 1 kHz (static
positions of 20 s with 5 s turns between them; ULog: sensor_combined,
sensor_accel, sensor_gyro, sensor_selection; DataFlash: IMU, ACC, GYR, PARM),
then measures each command in its own process (wall and CPU time, peak RSS of
that process alone, as benchmarks/bench_import.py does):

- ``calib import ulog LOG --plan PLAN --out RAW.h5`` (sensor_combined) beside
  pyulog's read of the same topic (``pyulog.ULog(LOG, ["sensor_combined"])``
  and its arrays);
- ``calib import dataflash LOG --plan PLAN --out RAW.h5`` (IMU) beside
  pymavlink's read of the IMU messages (``DFReader_binary`` and
  ``recv_match(type="IMU")``, the values collected as the importer needs them).

The baselines run for the logs of at most ``--baseline-hours`` (pymavlink
needs about 4 min of CPU an hour of log); calib's imports for every length.
Targets (issue 34): ULog <= 1.2x pyulog's time, DataFlash <= 0.2x pymavlink's
time, peak <= 300 MB at every length; the last lines say which hold.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from benchmarks.bench_import import measure

PLAN = 'name = "bench"\nkind = "static"\n[[segment]]\nlabel = "pos"\nrepeat = "auto"\n'
RATE = 1000.0
PEAK_MB = 300.0

PYULOG = r"""
import sys, numpy as np, pyulog
u = pyulog.ULog(sys.argv[1], ["sensor_combined"])
d = u.data_list[0].data
a = np.column_stack([d[f"accelerometer_m_s2[{i}]"] for i in range(3)])
g = np.column_stack([d[f"gyro_rad[{i}]"] for i in range(3)])
print(len(a), float(a.sum() + g.sum()))
"""

PYMAVLINK = r"""
import sys, numpy as np
from pymavlink import DFReader
log = DFReader.DFReader_binary(sys.argv[1], zero_time_base=True)
t, a, g = [], [], []
while True:
    m = log.recv_match(type=["IMU"])
    if m is None:
        break
    if getattr(m, "I", 0) != 0:
        continue
    t.append(m.TimeUS); a.append((m.AccX, m.AccY, m.AccZ)); g.append((m.GyrX, m.GyrY, m.GyrZ))
print(len(t), float(np.sum(a) + np.sum(g)))
"""


def _samples(n: int, directory: Path):
    """Time (us, int64) and float32 accelerometer/gyro memory-mapped arrays of n
    samples: 20 s static positions, 5 s turns, white noise."""
    t = np.lib.format.open_memmap(directory / "t.npy", "w+", np.int64, (n,))
    a = np.lib.format.open_memmap(directory / "a.npy", "w+", np.float32, (n, 3))
    g = np.lib.format.open_memmap(directory / "g.npy", "w+", np.float32, (n, 3))
    rng = np.random.default_rng(0)
    for i0 in range(0, n, 1_000_000):
        i = np.arange(i0, min(n, i0 + 1_000_000))
        s = i / RATE
        phase = s % 25.0
        k = np.floor(s / 25.0)
        turning = phase >= 20.0
        ang = k * 0.7 + np.where(turning, (phase - 20.0) / 5.0 * 0.7, 0.0)
        m = len(i)
        t[i] = 20_000_000 + i * 1000
        a[i] = np.column_stack([9.81 * np.sin(ang), 0.3 * np.cos(ang), 9.81 * np.cos(ang)]) \
            + 0.01 * rng.standard_normal((m, 3))
        w = np.where(turning, 0.7 / 5.0, 0.0)
        g[i] = np.column_stack([np.zeros(m), w, np.zeros(m)]) + 1e-4 * rng.standard_normal((m, 3))
    return t, a, g


def cached_logs(directory: Path, hours: float) -> tuple[Path, Path, int]:
    """(ULog, DataFlash, samples) of ``hours`` hours, written on the first run only."""
    from calib_cli.io.log_writers import default_params, write_dataflash, write_ulog

    n = int(round(hours * 3600 * RATE))
    ulg = directory / f"imu_{hours:g}h.ulg"
    binf = directory / f"imu_{hours:g}h.bin"
    if ulg.exists() and binf.exists():
        return ulg, binf, n
    print(f"writing the {hours:g} h logs to {directory} (once; later runs reuse them)", flush=True)
    work = Path(tempfile.mkdtemp(dir=directory))
    try:
        t, a, g = _samples(n, work)
        temp = np.full(n, 25.0, np.float32)
        write_ulog(work / "x.ulg", t, a, g, temp, params=default_params("px4"),
                   device_ids=(2490378, 2490634))
        write_dataflash(work / "x.bin", t, a, g, temp, params=default_params("ardupilot"),
                        extra_instance=False)
        (work / "x.ulg").replace(ulg)
        (work / "x.bin").replace(binf)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return ulg, binf, n


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", default="1,4", help="log lengths, hours, comma separated")
    ap.add_argument("--baseline-hours", type=float, default=1.0,
                    help="run pyulog and pymavlink on logs of at most this length")
    ap.add_argument("--dir", help="where the logs are written once and kept "
                                  "(default: $TMPDIR/calib-bench-fclogs)")
    a = ap.parse_args(argv)
    tmp = Path(a.dir or Path(tempfile.gettempdir()) / "calib-bench-fclogs")
    tmp.mkdir(parents=True, exist_ok=True)
    py = sys.executable
    import compileall

    import calib_cli

    compileall.compile_dir(str(Path(calib_cli.__file__).parent), quiet=1)
    work = Path(tempfile.mkdtemp(prefix="run-", dir=tmp))
    verdict = []
    try:
        plan = work / "plan.toml"
        plan.write_text(PLAN)
        (work / "pyulog_read.py").write_text(PYULOG)
        (work / "pymavlink_read.py").write_text(PYMAVLINK)
        out = work / "raw.h5"
        print(f"{'log':>10s} {'samples':>10s} {'reader':34s} {'time s':>8s} {'cpu s':>7s} "
              f"{'peak MB':>8s} {'x time':>7s} {'x cpu':>6s}", flush=True)
        for hours in [float(s) for s in a.hours.split(",") if s]:
            ulg, binf, n = cached_logs(tmp, hours)
            for fmt, log, base_name, base in (
                    ("ulog", ulg, "pyulog ULog(sensor_combined)", work / "pyulog_read.py"),
                    ("dataflash", binf, "pymavlink recv_match(IMU)", work / "pymavlink_read.py")):
                runs = {}
                if hours <= a.baseline_hours:
                    runs[base_name] = [py, str(base), str(log)]
                runs[f"calib import {fmt}"] = [py, "-m", "calib_cli", "-q", "import", fmt,
                                               str(log), "--plan", str(plan), "--out", str(out)]
                with open(log, "rb") as fh:  # warm-up: the log in the page cache for all
                    while fh.read(1 << 24):
                        pass
                res = {name: measure(cmd) for name, cmd in runs.items()}
                bt = bc = None
                if base_name in res:
                    bt, _, bc = res[base_name]
                size = os.path.getsize(log) / 1e6
                for name, (t, m, c) in res.items():
                    rt = f"{t / bt:7.2f} {c / bc:6.2f}" if bt else f"{'':7s} {'':6s}"
                    print(f"{size:9.0f}M {n:10d} {name:34s} {t:8.1f} {c:7.1f} {m:8.0f} {rt}",
                          flush=True)
                t, m, c = res[f"calib import {fmt}"]
                verdict.append((f"{fmt} {hours:g} h peak {m:.0f} MB <= {PEAK_MB:g} MB",
                                m <= PEAK_MB))
                if bt:
                    limit = 1.2 if fmt == "ulog" else 0.2
                    verdict.append((f"{fmt} {hours:g} h time {t / bt:.2f}x (cpu {c / bc:.2f}x) "
                                    f"of {base_name.split()[0]} <= {limit}x", t / bt <= limit))
            print(f"{'':10s} load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs",
                  flush=True)
        for what, ok in verdict:
            print(f"{'ok  ' if ok else 'MISS'} {what}")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
