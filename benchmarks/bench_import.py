"""Import speed and memory against pyarrow's streaming CSV reader (issue 19).

    python -m benchmarks.bench_import [--sizes 100,1000] [--repeat 3] [--dir DIR]

Writes contract CSVs of the given sizes (MB; time, ax ay az, gx gy gz, temp;
one comment line; static positions with turns between them, at 1 kHz) once
into ``--dir`` (default ``$TMPDIR/calib-bench-import``; kept there and reused
by the next run, so the 1 GB log is written once), then measures, each in
its own subprocess (whole process: interpreter start, imports, reading,
writing), the wall time and peak RSS of

- ``calib import csv LOG --plan PLAN --out RAW.h5`` (static detection on, a
  ``repeat = "auto"`` plan so every detected position is kept),
- ``calib import text`` of the same file,
- the baseline: ``pyarrow.csv.open_csv`` streaming the same file to float64
  numpy arrays in one pass,

after one untimed run of each (the log in the page cache for all three;
calib's modules compiled to bytecode first, as an installed wheel has them:
with ``PYTHONDONTWRITEBYTECODE`` set, as on some CI machines, every run of an
editable install would otherwise compile its ~30 modules again, about 0.1 s
that no user pays), and prints the median over ``--repeat`` runs (``--repeat-large`` for logs
over 200 MB; wall time and CPU time, user + system, which is steadier on a
shared machine) with the ratios to the baseline measured in the same run.
The runs of the three commands are interleaved (baseline, csv, text,
baseline, ...) so that a change in the machine's load hits them alike, and
the load average is printed with the figures. The peak RSS is that of the
measured process alone (``getrusage(RUSAGE_CHILDREN)`` in a wrapper process
that runs only it).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

PLAN = 'name = "bench"\nkind = "static"\n[[segment]]\nlabel = "pos"\nrepeat = "auto"\n'

BASELINE = r"""
import sys, numpy as np, pyarrow as pa, pyarrow.csv as pc
names = "time,ax,ay,az,gx,gy,gz,temp".split(",")
r = pc.open_csv(sys.argv[1], read_options=pc.ReadOptions(skip_rows=1),
                convert_options=pc.ConvertOptions(column_types={n: pa.float64() for n in names}))
n = 0
for b in r:
    cols = [b.column(i).to_numpy() for i in range(b.num_columns)]
    n += len(cols[0])
print(n)
"""


def write_log(path: Path, mb: float, rate: float = 1000.0) -> int:
    """A contract CSV of about ``mb`` megabytes: 20 s static positions with
    5 s turns between them; returns the row count. Written to a temporary
    name and renamed, so an interrupted run leaves no partial log to reuse."""
    import numpy as np
    import pyarrow as pa
    import pyarrow.csv as pc

    rng = np.random.default_rng(0)
    target = mb * 1e6
    rows_per_chunk = 100_000
    n = 0
    part = path.with_name(path.name + ".part")
    with open(part, "wb") as fh:
        fh.write(b"# calib benchmark log\ntime,ax,ay,az,gx,gy,gz,temp\n")
        while fh.tell() < target:
            i = np.arange(n, n + rows_per_chunk)
            t = i / rate
            phase = (t % 25.0)
            k = np.floor(t / 25.0)
            turning = phase >= 20.0
            ang = k * 0.7 + np.where(turning, (phase - 20.0) / 5.0 * 0.7, 0.0)
            g = 9.81
            ax = g * np.sin(ang) + 0.01 * rng.standard_normal(len(i))
            ay = 0.3 * np.cos(ang) + 0.01 * rng.standard_normal(len(i))
            az = g * np.cos(ang) + 0.01 * rng.standard_normal(len(i))
            w = np.where(turning, 0.7 / 5.0, 0.0)
            gx = 1e-4 * rng.standard_normal(len(i))
            gy = w + 1e-4 * rng.standard_normal(len(i))
            gz = 1e-4 * rng.standard_normal(len(i))
            temp = 25.0 + 0.001 * t
            cols = {"time": np.round(t, 6)}
            for name, v in (("ax", ax), ("ay", ay), ("az", az), ("gx", gx), ("gy", gy),
                            ("gz", gz), ("temp", temp)):
                cols[name] = np.round(v, 9 if name[0] == "g" else 6)
            pc.write_csv(pa.table(cols), fh, write_options=pc.WriteOptions(include_header=False,
                                                                           quoting_style="none"))
            n += rows_per_chunk
    part.replace(path)
    return n


def cached_log(directory: Path, mb: float) -> tuple[Path, int]:
    """The log of ``mb`` MB in ``directory``, written on the first run only."""
    log = directory / f"log_{mb:g}MB_v2.csv"
    rows_file = log.with_suffix(".rows")
    if log.exists() and rows_file.exists():
        return log, int(rows_file.read_text())
    print(f"writing the {mb:g} MB log to {log} (once; later runs reuse it)", flush=True)
    rows = write_log(log, mb)
    rows_file.write_text(str(rows))
    return log, rows


def measure(cmd: list[str]) -> tuple[float, float, float]:
    """(wall s, peak RSS MB, CPU s) of ``cmd`` run alone in a fresh wrapper process."""
    wrapper = ("import resource, subprocess, sys, time, json\n"
               "t0 = time.perf_counter()\n"
               "p = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL)\n"
               "dt = time.perf_counter() - t0\n"
               "ru = resource.getrusage(resource.RUSAGE_CHILDREN)\n"
               "print(json.dumps([p.returncode, dt, ru.ru_maxrss, ru.ru_utime + ru.ru_stime]))\n")
    out = subprocess.run([sys.executable, "-c", wrapper] + cmd, capture_output=True, text=True,
                         check=True).stdout
    code, dt, rss_kb, cpu = json.loads(out)
    if code != 0:
        raise SystemExit(f"benchmark command failed ({code}): {' '.join(cmd)}")
    return dt, rss_kb / 1024.0, cpu


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="100,1000", help="log sizes, MB, comma separated")
    ap.add_argument("--repeat", type=int, default=3, help="runs per figure (median)")
    ap.add_argument("--repeat-large", type=int, default=1,
                    help="runs per figure for logs over 200 MB")
    ap.add_argument("--dir", help="where the logs are written once and kept "
                                  "(default: $TMPDIR/calib-bench-import)")
    ap.add_argument("--no-text", action="store_true", help="skip calib import text")
    a = ap.parse_args(argv)
    tmp = Path(a.dir or Path(tempfile.gettempdir()) / "calib-bench-import")
    tmp.mkdir(parents=True, exist_ok=True)
    py = sys.executable
    # calib's bytecode, as pip writes it at install time (the baseline's libraries have it)
    import compileall

    import calib_cli

    compileall.compile_dir(str(Path(calib_cli.__file__).parent), quiet=1)
    work = Path(tempfile.mkdtemp(prefix="calib-bench-import-", dir=tmp))
    try:
        plan = work / "plan.toml"
        plan.write_text(PLAN)
        base_py = work / "baseline.py"
        base_py.write_text(BASELINE)
        print(f"{'log':>8s} {'rows':>10s} {'reader':28s} {'time s':>8s} {'cpu s':>7s} "
              f"{'peak MB':>8s} {'x time':>7s} {'x cpu':>6s} {'x mem':>6s}")
        for mb in [float(s) for s in a.sizes.split(",") if s]:
            log, rows = cached_log(tmp, mb)
            size = os.path.getsize(log) / 1e6
            out = work / "raw.h5"
            runs = {"pyarrow open_csv -> float64": [py, str(base_py), str(log)],
                    "calib import csv": [py, "-m", "calib_cli", "-q", "import", "csv", str(log),
                                         "--plan", str(plan), "--out", str(out)]}
            if not a.no_text:
                runs["calib import text"] = [py, "-m", "calib_cli", "-q", "import", "text",
                                             str(log), "--plan", str(plan), "--out", str(out)]
            ms: dict[str, list] = {name: [] for name in runs}
            for cmd in runs.values():  # warm-up, untimed: the log in the page cache for all
                measure(cmd)
            load0 = os.getloadavg()[0]
            for _ in range(a.repeat if mb <= 200 else a.repeat_large):
                for name, cmd in runs.items():  # interleaved: the load changes alike for all
                    ms[name].append(measure(cmd))
            res = {name: (statistics.median(m[0] for m in v), max(m[1] for m in v),
                          statistics.median(m[2] for m in v)) for name, v in ms.items()}
            bt, bm, bc = res["pyarrow open_csv -> float64"]
            for name, (t, m, c) in res.items():
                print(f"{size:7.0f}M {rows:10d} {name:28s} {t:8.2f} {c:7.2f} {m:8.0f} "
                      f"{t / bt:7.2f} {c / bc:6.2f} {m / bm:6.2f}", flush=True)
            print(f"{'':8s} load average {load0:.1f} -> {os.getloadavg()[0]:.1f} on "
                  f"{os.cpu_count()} CPUs", flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
