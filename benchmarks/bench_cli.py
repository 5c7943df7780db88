"""Benchmark the start-up of the command line: `calib --help`, the `--help` of
every subcommand (`calib show --help`, `calib fit accel --help`, ...) and shell
completion must answer in <= 0.5 s (issues 23 and 35).

    python -m benchmarks.bench_cli

Each figure is the median wall time of 7 runs of a fresh process, against
baselines measured in the same run: `python -c pass` (the interpreter alone)
and `python -c "import numpy"` (what any command touching data pays). The
help texts and completion answer from the static tree (calib_cli/cli/index.py)
without importing the commands' modules; `calib show cal.h5`-like start-up
(every command module loaded, as a real run of a command that is not complete
on its own) is shown for comparison.
"""

from __future__ import annotations

import os
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

LIMIT_S = 0.5
RUNS = 7
RUNS_EACH = 3  # per subcommand's --help


def _calib() -> list[str]:
    exe = Path(sys.executable).with_name("calib")
    if exe.exists():
        return [str(exe)]
    found = shutil.which("calib")
    return [found] if found else [sys.executable, "-m", "calib_cli"]


def _median(cmd: list[str], env: dict | None = None, runs: int = RUNS) -> float:
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        subprocess.run(cmd, env={**os.environ, **(env or {})}, stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL, check=False)
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def _complete(words: str) -> dict:
    n = len(words.split()) - (0 if words.endswith(" ") else 1)
    return {"_CALIB_COMPLETE": "bash_complete", "COMP_WORDS": words, "COMP_CWORD": str(n)}


def _subcommands() -> list[list[str]]:
    """Every command path of the static tree (`show`, `fit accel`, `plan check`, ...)."""
    from calib_cli.cli.tree import tree

    def walk(d, prefix):
        out = []
        for name, sub in sorted(d.get("commands", {}).items()):
            out.append(prefix + [name])
            out += walk(sub, prefix + [name])
        return out

    return walk(tree(), [])


def main() -> int:
    calib = _calib()
    base = _median([sys.executable, "-c", "pass"])
    numpy = _median([sys.executable, "-c", "import numpy"])
    helps = [(" ".join(p), _median(calib + p + ["--help"], runs=RUNS_EACH))
             for p in _subcommands()]
    worst = max(helps, key=lambda h: h[1])
    rows = [("python -c pass (baseline)", base, None),
            ('python -c "import numpy" (reference)', numpy, None),
            ("calib --help", _median(calib + ["--help"]), LIMIT_S),
            (f"calib X --help, median of {len(helps)} subcommands",
             statistics.median(h[1] for h in helps), LIMIT_S),
            (f"calib X --help, slowest ({worst[0]})", worst[1], LIMIT_S),
            ("complete `calib fi`", _median(calib, _complete("calib fi")), LIMIT_S),
            ("complete `calib fit turntable --gr`",
             _median(calib, _complete("calib fit turntable --gr")), LIMIT_S),
            ("complete `calib emulate --imu ` (profile names)",
             _median(calib, _complete("calib emulate --imu ")), LIMIT_S),
            ("every command module loaded (python -c, reference)",
             _median([sys.executable, "-c", "from calib_cli.cli import main; main._register()"],
                     runs=3), None)]
    ok = True
    print(f"CLI start-up, median of {RUNS} runs ({RUNS_EACH} per subcommand; load average "
          f"{os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs)")
    for name, t, limit in rows:
        verdict = ""
        if limit is not None:
            good = t <= limit
            ok &= good
            verdict = f"  {'ok' if good else 'SLOW'} (<= {limit:.1f} s; {t - base:+.3f} s over " \
                      "the baseline)"
        print(f"  {name:58s} {t:6.3f} s{verdict}")
    print(f"  every subcommand's --help <= {LIMIT_S:.1f} s: "
          f"{sum(t <= LIMIT_S for _, t in helps)} of {len(helps)}")
    if not ok:
        print("  (a SLOW figure on a loaded machine: compare its excess over the baseline)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
