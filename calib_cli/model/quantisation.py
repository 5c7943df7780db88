"""Output quantisation of a sensor (docs/allan.md, "Quantisation noise").

Two ways a digital sensor quantises, with different noise:

- ``increments``: the sensor outputs angle (velocity) increments in whole
  quanta q and carries the remainder to the next sample, so the running sum
  of the output never strays more than q/2 from the true integral. The error
  is a white *phase* error: Allan deviation sqrt(3) Q / tau with
  Q = q / sqrt(12) (IEEE Std 952's quantisation noise, slope -1).
- ``samples``: each rate sample is rounded on its own (remainder dropped).
  The error is white *rate* noise of variance q^2 / 12 per sample: slope
  -1/2, indistinguishable from the random walk N (it adds
  q^2 tau0 / 12 to N^2).

Pure numpy; used by the simulator's callers and the tests alike.
"""

from __future__ import annotations

import numpy as np


def quantise_increments(rate: np.ndarray, tau0: float, q: float) -> np.ndarray:
    """Rates (N, ...) -> rates of increments quantised to q (unit * s), the
    remainder carried: out_k tau0 = q (round(S_k / q) - round(S_{k-1} / q)),
    S_k the running integral of rate * tau0 (S_{-1} = 0)."""
    rate = np.asarray(rate, dtype=float)
    n = np.rint(np.cumsum(rate * tau0, axis=0) / q)
    return np.diff(n, axis=0, prepend=np.zeros((1, *rate.shape[1:]))) * q / tau0


def quantise_samples(rate: np.ndarray, q: float) -> np.ndarray:
    """Each rate sample rounded to a multiple of q (unit) on its own."""
    return np.rint(np.asarray(rate, dtype=float) / q) * q
