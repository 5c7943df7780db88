"""Issue 18, the gyro method: can its equations tell a flicker from a random walk?
(docs/diagnose.md, "The gyro method", the Monte Carlo table; WANDER_MARGIN of
methods/diagnose_gyro.py.)  An analysis script, not a benchmark.

On one record of the validation's gyro plan (seed SEED of the case, base model fitted)
the equations are linearised (``WanderLikelihood.linear``: the fit's equations and the
within-static piece-mean contrasts), and draws r = L z, L L^T = I + sum x^2 M_kind, are
made with the hidden wander's figures x drawn as the validation cases draw them
(``diagnose_cases.hidden_effect_truth``) times FACTOR. Both wanders are profiled and
ranked by their likelihood ratio over the white model, as the diagnosis does. Printed
per row: named first, the margin (true kind's LR minus the other's) median and 10-90 %,
the share within WANDER_MARGIN (the pair reported not separable) and named first or
not separable.

One process.  python benchmarks/gyro_wander_separation.py N_DRAWS [SEED]
"""

from __future__ import annotations

import sys
import time

import numpy as np

from calib_cli.methods.blas_threads import one_blas_thread
from calib_cli.methods.diagnose_gyro import WANDER_MARGIN
from calib_cli.methods.diagnose_gyro_wander import KEYS, WanderLikelihood, unit_of
from calib_cli.methods.fit_with import accel_of
from calib_cli.methods.gyro import fit_gyro
from calib_cli.sim.simulate import simulate
from calib_cli.validation import diagnose_cases as C

ROWS = [("bias_instability", 0.5), ("bias_instability", 1.0), ("bias_instability", 3.0),
        ("bias_random_walk", 0.5), ("bias_random_walk", 1.0)]


def main() -> None:
    n = int(sys.argv[1])
    seed = int(sys.argv[2]) if len(sys.argv) > 2 else 3000
    case = "gyro: gyro bias_instability"
    rec = simulate(C.plan_of("gyro"), C.hidden_effect_truth(case, np.random.default_rng(seed)),
                   seed=seed + 1)
    with one_blas_thread():
        acc = accel_of(rec)
        res = fit_gyro(rec, acc, "off", False, extra=[], structure="full")
        W = WanderLikelihood(rec, acc, "full")
        _, A, _ = W.linear([], res)
        u = unit_of(res)
        print(f"{W.n0} equations + {W.sub.n_rows} within-static contrasts, "
              f"{A.shape[1]} parameters; WANDER_MARGIN {WANDER_MARGIN}")
        print("| hidden | figure (x the case's) | named first | LR margin: median (10 %-90 %) "
              "| within the margin | named first or not separable |")
        print("|---|---|---|---|---|---|")
        rng = np.random.default_rng(12345)
        for kind, factor in ROWS:
            other = next(k for k in KEYS if k != kind)
            t0 = time.process_time()
            margins = []
            for _ in range(n):
                truth = C.hidden_effect_truth(f"gyro: gyro {kind}", rng)
                x = factor * u * np.asarray(truth.params[KEYS[kind]], float)
                V = np.eye(len(A)) + np.tensordot(x ** 2, W.M[kind], axes=1)
                r = np.linalg.cholesky(V) @ rng.standard_normal(len(A))
                white = W.m2ll(r, A)[0]
                lr = {k: white - W.profile(r, A, k, reml=False)[2] for k in KEYS}
                margins.append(lr[kind] - lr[other])
            m = np.array(margins)
            q10, q50, q90 = np.percentile(m, [10, 50, 90])
            print(f"| {kind} | {factor:g} | {100 * np.mean(m > 0):.1f} % | {q50:.1f} "
                  f"({q10:.1f} to {q90:.1f}) | {100 * np.mean(np.abs(m) < WANDER_MARGIN):.1f} % "
                  f"| {100 * np.mean(m > -WANDER_MARGIN):.1f} % |  "
                  f"({n} draws, {(time.process_time() - t0) / n:.2f} s CPU each)", flush=True)


if __name__ == "__main__":
    main()
