"""Benchmark `calib batch`: files per minute with 1 and 2 local workers.

    python -m benchmarks.bench_batch [--files 24] [--workers 1 2] [--json]

Simulates an archive of good recordings (calib_cli.validation.archive: several
units, six-position and hand-placed plans, CSV and raw.h5, 50 Hz, ~20-30 s
each) and runs the archive pipeline (import, fit accel, apply, export) into a
fresh output directory per worker count, timing the whole command (pool
start-up included). Numbers depend on the machine's load: the load average and the CPU seconds
per file are printed with them (on a busy machine 2 workers cannot beat 1).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import tempfile
import time
from pathlib import Path


def run_once(pipeline: str, archive: str, out: str, workers: int) -> tuple[float, dict]:
    from calib_cli.cli.main import main

    buf = io.StringIO()
    c0 = _cpu()
    t0 = time.perf_counter()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(io.StringIO()):
        try:
            main(["batch", pipeline, archive, "--out", out, "--workers", str(workers), "--json"])
        except SystemExit:
            pass
    dt = time.perf_counter() - t0
    obj = json.loads(buf.getvalue())
    obj["cpu_seconds"] = _cpu() - c0
    return dt, obj


def _cpu() -> float:
    """CPU seconds of this process and its finished children (pool workers)."""
    import resource

    s, c = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return s.ru_utime + s.ru_stime + c.ru_utime + c.ru_stime


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", type=int, default=24)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--json", action="store_true")
    a = ap.parse_args(argv)
    from calib_cli.validation.archive import make_archive

    rows = []
    with tempfile.TemporaryDirectory(prefix="calib-bench-batch-") as tmp:
        arch = make_archive(tmp, n=a.files, n_broken=0)
        for w in a.workers:
            out = str(Path(tmp, f"out-{w}"))
            dt, obj = run_once(arch["pipeline"], arch["archive"], out, w)
            ok = obj["summary"]["ok"]
            rows.append({"workers": w, "files": ok, "seconds": round(dt, 3),
                         "files_per_minute": round(60.0 * ok / dt, 1),
                         "cpu_seconds_per_file": round(obj["cpu_seconds"] / max(ok, 1), 3),
                         "steps": obj["summary"]["steps_run"]})
        # the make-like re-run: nothing to do
        dt, obj = run_once(arch["pipeline"], arch["archive"], str(Path(tmp, "out-1")), 1)
        ok = obj["summary"]["ok"]
        rows.append({"workers": 1, "files": obj["summary"]["ok"], "seconds": round(dt, 3),
                     "files_per_minute": round(60.0 * obj["summary"]["ok"] / dt, 1),
                     "cpu_seconds_per_file": round(obj["cpu_seconds"] / max(ok, 1), 3),
                     "steps": obj["summary"]["steps_run"], "note": "re-run, all up to date"})
    load = round(os.getloadavg()[0], 2)  # the machine's other work skews the figures
    if a.json:
        print(json.dumps({"cpus": os.cpu_count(), "load_average_1min": load, "runs": rows},
                         indent=2))
        return
    print(f"calib batch benchmark ({os.cpu_count()} CPUs, load average {load}, {a.files} "
          "recordings, import + fit accel + apply + export)")
    for r in rows:
        print(f"  workers {r['workers']}: {r['files']} files in {r['seconds']:.2f} s = "
              f"{r['files_per_minute']:.0f} files/min, {r['cpu_seconds_per_file']:.3f} CPU s/file "
              f"({r['steps']} steps)"
              + (f"  [{r['note']}]" if "note" in r else ""))


if __name__ == "__main__":
    main()
