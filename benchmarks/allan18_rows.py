"""Issue 18: fitted / true of a wander case over the test seeds (3000 + 11 k) and the share inside
the Allan 95 % interval.  python benchmarks/allan18_rows.py CASE N_SEEDS N_GRID[,N_GRID...]
(PYTHONPATH=<worktree> so the worktree's calib_cli is imported)."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from test_fit_with_slow import allan_interval

from calib_cli.methods import diagnose_stoch as ds
from calib_cli.validation import diagnose_validate as V

case = sys.argv[1]; n = int(sys.argv[2]); grids = [int(g) for g in sys.argv[3].split(",")]
f = ds.fit_process
res = {}
for g in grids:
    d = list(f.__defaults__); d[1] = g; f.__defaults__ = tuple(d)
    rs, ins = [], []
    for k in range(n):
        o = V.fit_with_z((case, 3000 + 11 * k))
        info = o[7]
        for r, c, w in zip(o[4], info["true"], info["white"]):
            lo, hi, _ = allan_interval(info["kind"], c, w, info["fs"], info["span"])
            rs.append(r); ins.append(lo <= r <= hi)
    rs = np.array(rs)
    print(f"n_grid {g}: median {np.median(rs):.3f} sd log {np.std(np.log(rs)):.3f} range {rs.min():.2f}-{rs.max():.2f} inside {100*np.mean(ins):.1f} %", flush=True)
