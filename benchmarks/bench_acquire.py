"""Acquisition benchmark: the highest frame rate the recorder sustains from
the emulator without loss, and the recorder's CPU use at 1 kHz; then every
shipped vendor profile at its highest documented output rate (the
configuration exchange included), lossless or not, with its CPU share and its
ratio to generic-bin6 at the same rate, measured in the same run.

    python -m benchmarks.bench_acquire [--profile generic-bin6] [--seconds 4] [--json]
                                       [--vendors-only]

The emulator runs in its own process (``calib emulate``) on a pty; the
recorder (the same Session as ``calib record``, free-running) runs here, so
its CPU time is this process's. A rate passes when the recorder got every
frame the emulator sent (no checksum error, no counter gap, no emulator
FIFO overflow while the recorder listened, which would show as gaps) and
the recorder received at least 95 % of the nominal rate (else the emulator,
not the recorder, is the limit: reported as such).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from calib_cli.acquire.profile import load_imu_profile
from calib_cli.acquire.session import Session, SettleConfig, free_run_plan
from calib_cli.acquire.transport import SerialTransport
from calib_cli.io.plan import parse_plan

ROOT = Path(__file__).resolve().parents[1]


def run_rate(profile: str, rate: float, seconds: float) -> dict:
    """One run: emulator at ``rate`` Hz, recorder for ``seconds``."""
    prof = load_imu_profile(profile).with_rate(rate)
    with tempfile.TemporaryDirectory(prefix="calib-bench-") as d:
        env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH",
                                                                                  ""))
        emu = subprocess.Popen(
            [sys.executable, "-m", "calib_cli", "--quiet", "emulate", "--imu", profile,
             "--rate", str(rate), "--duration", str(seconds + 3.0), "--link-dir", d],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
        try:
            paths = json.loads(emu.stdout.readline())
            s = Session(prof, SerialTransport(paths["imu"], prof.transport),
                        parse_plan(free_run_plan(seconds)), os.path.join(d, "bench.journal"),
                        settle=SettleConfig())
            s.start()
            time.sleep(0.5)  # let the first chunk arrive
            s.pump(0.0)  # and take it, so that the window below starts empty
            c0, w0 = time.process_time(), time.monotonic()
            n0 = s.n_rows
            s.run_free(seconds)
            cpu, wall = time.process_time() - c0, time.monotonic() - w0
            n = s.n_rows - n0
            counts = s.close()
            out, _ = emu.communicate(timeout=seconds + 20)
        finally:
            if emu.poll() is None:
                emu.kill()
        summary = json.loads(out.strip().splitlines()[-1]) if out.strip() else {}
    # frames lost inside the recorder's window show as gaps; the emulator's FIFO
    # overflows after the recorder has closed the port are not losses
    lost = counts["checksum_errors"] + counts["gaps"]
    got_rate = n / wall
    return {"rate_hz": rate, "received_hz": round(got_rate, 1), "lost": lost,
            "checksum_errors": counts["checksum_errors"], "gaps": counts["gaps"],
            "emulator_overflow": summary.get("overflow"),
            "cpu_percent": round(100.0 * cpu / wall, 1),
            "ok": lost == 0 and got_rate > 0.95 * rate,
            "limited_by": None if got_rate > 0.95 * rate else "emulator or pty throughput"}


# the highest output rate each vendor documents for its inertial data (Hz)
VENDOR_MAX_HZ = {"safran-stim300": 2000.0, "xsens-mti": 2000.0, "epson-g370": 2000.0,
                 "microstrain-gx5": 1000.0, "vectornav-vn100": 800.0,
                 "vectornav-vnimu": 200.0}


def vendors(seconds: float, as_json: bool) -> list[dict]:
    """Each vendor profile at its highest documented rate, beside generic-bin6
    at the same rate (the baseline of this run)."""
    out, base = [], {}
    for name, rate in VENDOR_MAX_HZ.items():
        if rate not in base:
            base[rate] = run_rate("generic-bin6", rate, seconds)
        res = run_rate(name, rate, seconds)
        res["profile"] = name
        b = base[rate]["cpu_percent"]
        res["cpu_ratio_to_generic_bin6"] = round(res["cpu_percent"] / b, 2) if b else None
        out.append(res)
        if not as_json:
            print(f"{name:16s} {rate:6.0f} Hz: received {res['received_hz']:7.1f} Hz, lost "
                  f"{res['lost']}, recorder CPU {res['cpu_percent']:5.1f} % of one core "
                  f"({res['cpu_ratio_to_generic_bin6']}x generic-bin6 at {rate:.0f} Hz: "
                  f"{b} %)  {'ok' if res['ok'] else 'FAIL'}", flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="generic-bin6")
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--rates", default="1000,2000,4000,8000,12000,16000,24000,32000")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--vendors-only", action="store_true",
                    help="Only the vendor profiles at their highest documented rates.")
    a = ap.parse_args(argv)
    if a.vendors_only:
        vend = vendors(a.seconds, a.json)
        if a.json:
            print(json.dumps({"vendors": vend}, indent=2))
        return 0 if all(v["ok"] for v in vend) else 1
    runs = []
    best = 0.0
    for r in (float(x) for x in a.rates.split(",")):
        res = run_rate(a.profile, r, a.seconds)
        runs.append(res)
        if not a.json:
            print(f"{r:8.0f} Hz: received {res['received_hz']:8.1f} Hz, lost {res['lost']} "
                  f"(checksum {res['checksum_errors']}, gaps {res['gaps']}, emulator overflow "
                  f"{res['emulator_overflow']}), "
                  f"recorder CPU {res['cpu_percent']:5.1f} %  {'ok' if res['ok'] else 'FAIL'}",
                  flush=True)
        if not res["ok"]:
            break
        best = r
    cpu1k = next((x["cpu_percent"] for x in runs if x["rate_hz"] == 1000.0), None)
    vend = vendors(a.seconds, a.json)
    result = {"profile": a.profile, "max_lossless_rate_hz": best,
              "cpu_percent_at_1khz": cpu1k, "runs": runs, "vendors": vend}
    if a.json:
        print(json.dumps(result, indent=2))
    else:
        print(f"highest lossless rate: {best:.0f} Hz ({a.profile}); recorder CPU at 1 kHz: "
              f"{cpu1k} % of one core")
    return 0 if best >= 4000 and all(v["ok"] for v in vend) else 1


if __name__ == "__main__":
    sys.exit(main())
