"""Figures of merit of a redundant unit's geometry (docs/rimu.md, "Comparing
layouts": `calib rimu-geometry PROFILE`). Pure: directions in, numbers out.

H (n, 3) holds the unit sensing directions (model.effects.Layout.axes, the
same S_i as the measurement model). With equal, independent sensor noise
sigma:

- accuracy gain against one orthogonal triad: the least-squares estimate of
  x has covariance sigma^2 (H^T H)^-1; a triad has sigma^2 I (trace 3). The
  gain is the ratio of the RMS errors, sqrt(3 / trace((H^T H)^-1)) (>1:
  better than a triad).
- subsets: every set of >= 3 sensors whose directions span 3-D (rank 3,
  smallest singular value above RANK_TOL of the largest) still measures x:
  the count of those is the number of usable configurations after faults.
- faults (parity space, methods/rimu_fdi.py): V (n-3, n) orthonormal with
  V H = 0; a fault f on sensor i gives the parity p = f v_i, v_i = V e_i.
  A fault set F is *tolerated* when the other sensors span 3-D, *detectable*
  when V_F (the columns of F) has full column rank, *isolable* when no
  other set G of the same size has a parity subspace within ISOLATION_COS
  of it (single faults: |cos(v_i, v_j)| < ISOLATION_COS; the test's
  generalised likelihood ratio uses |z_i|, so opposite directions are as
  ambiguous as equal ones). Collinear sensors (parallel or opposite
  directions) cannot isolate each other wherever they are the only two
  sensors that see their axis apart from the rest: a subset in which they
  are is counted as detect-only.
- detection power of the parity test for a fault of size F (in units of the
  noise sigma of the tested quantity, e.g. a window mean) on sensor i at
  false-alarm probability alpha: T = p^T p / sigma^2 is chi-square with
  n - 3 dof without fault and non-central with lambda = F^2 |v_i|^2 with it;
  power = P(T > chi2.isf(alpha, n - 3)).
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy import stats

from calib_cli.errors import InputError
from calib_cli.methods.rimu_fdi import ISOLATION_COS
from calib_cli.model.effects import Layout

RANK_TOL = 1e-6  # smallest/largest singular value below this: does not span 3-D
MAX_SENSORS = 20  # subsets are enumerated (2^n): refuse larger layouts


def axes(el0_rad, az0_rad) -> np.ndarray:
    """(n, 3) nominal sensing directions (the model's Layout.axes)."""
    el0, az0 = np.asarray(el0_rad, float), np.asarray(az0_rad, float)
    return Layout(n=len(el0), el0=el0, az0=az0).axes()


def spans(H: np.ndarray) -> bool:
    s = np.linalg.svd(H, compute_uv=False)
    return len(s) == 3 and s[0] > 0 and s[-1] > RANK_TOL * s[0]


def accuracy_gain(H: np.ndarray) -> float:
    """sqrt(3 / trace((H^T H)^-1)); NaN when H does not span 3-D."""
    if not spans(H):
        return float("nan")
    return float(np.sqrt(3.0 / np.trace(np.linalg.inv(H.T @ H))))


def parity(H: np.ndarray) -> np.ndarray:
    """V (n-3, n), orthonormal rows, V H = 0."""
    U, _, _ = np.linalg.svd(H, full_matrices=True)
    return U[:, 3:].T


def collinear_groups(H: np.ndarray, cos_tol: float = ISOLATION_COS) -> list[list[int]]:
    """Groups of sensors whose directions are parallel or opposite."""
    n = len(H)
    seen, out = set(), []
    for i in range(n):
        if i in seen:
            continue
        g = [i] + [j for j in range(i + 1, n) if abs(H[i] @ H[j]) >= cos_tol]
        if len(g) > 1:
            out.append(g)
            seen.update(g)
    return out


def _subspace_cos(A: np.ndarray, B: np.ndarray) -> float:
    """Cosine of the largest principal angle between span(A) and span(B)
    (1: one lies within the other)."""
    qa, _ = np.linalg.qr(A)
    qb, _ = np.linalg.qr(B)
    return float(np.linalg.svd(qa.T @ qb, compute_uv=False).min())


def fault_sets(H: np.ndarray, size: int) -> dict:
    """Tolerated, detectable and isolable fault sets of ``size`` sensors."""
    n = len(H)
    V = parity(H) if n > 3 else np.zeros((0, n))
    sets = list(itertools.combinations(range(n), size))
    tolerated, detectable = [], []
    for F in sets:
        rest = [i for i in range(n) if i not in F]
        if len(rest) >= 3 and spans(H[rest]):
            tolerated.append(F)
        VF = V[:, list(F)]
        if V.shape[0] >= size and np.linalg.matrix_rank(VF, tol=1e-9) == size:
            detectable.append(F)
    isolable, confused = [], []
    for F in detectable:
        others = [G for G in detectable if G != F]
        bad = [G for G in others if _subspace_cos(V[:, list(F)], V[:, list(G)]) >= ISOLATION_COS]
        if bad:
            confused += [(F, G) for G in bad if F < G]
        else:
            isolable.append(F)
    return {"total": len(sets), "tolerated": tolerated, "detectable": detectable,
            "isolable": isolable, "confused": confused}


def subsets(H: np.ndarray) -> dict:
    """Subsets of >= 3 sensors: how many span 3-D, per size, and what each
    spanning subset can do about a single fault (n_sub - 3 parity equations:
    >= 1 detects, >= 2 can isolate when no two of its sensors share a parity
    direction)."""
    n = len(H)
    total = spanning = 0
    per_size, not_spanning = [], []
    detect = isolate = 0
    for k in range(3, n + 1):
        tk = sk = dk = ik = 0
        for S in itertools.combinations(range(n), k):
            tk += 1
            Hs = H[list(S)]
            if not spans(Hs):
                not_spanning.append(list(S))
                continue
            sk += 1
            if k >= 4:
                fs = fault_sets(Hs, 1)
                if len(fs["detectable"]) == k:
                    dk += 1
                    if len(fs["isolable"]) == k:
                        ik += 1
        per_size.append({"size": k, "subsets": tk, "spanning": sk,
                         "detect_any_single_fault": dk, "isolate_any_single_fault": ik})
        total, spanning, detect, isolate = total + tk, spanning + sk, detect + dk, isolate + ik
    return {"total": total, "spanning": spanning, "not_spanning": not_spanning,
            "per_size": per_size, "detect_any_single_fault": detect,
            "isolate_any_single_fault": isolate}


def detection_power(H: np.ndarray, fault: float, alpha: float) -> dict:
    """Power of the chi-square parity test for a fault of ``fault`` noise
    sigmas on each sensor at false-alarm probability alpha."""
    n = len(H)
    dof = n - 3
    if dof < 1:
        return {"dof": dof, "threshold": None, "per_sensor": [None] * n}
    V = parity(H)
    thr = float(stats.chi2.isf(alpha, dof))
    lam = fault**2 * np.sum(V**2, axis=0)
    power = [float(stats.ncx2.sf(thr, dof, lam_i)) if lam_i > 1e-12 else float(alpha)
             for lam_i in lam]
    return {"dof": dof, "threshold": thr, "parity_norm": np.sqrt(np.sum(V**2, axis=0)).tolist(),
            "per_sensor": power}


def geometry_report(el0_rad, az0_rad, fault: float = 5.0, alpha: float = 1e-3,
                    name: str | None = None) -> dict:
    """All figures of merit of a layout (one JSON-ready dict)."""
    el0, az0 = np.asarray(el0_rad, float), np.asarray(az0_rad, float)
    n = len(el0)
    if n < 3 or len(az0) != n:
        raise InputError(f"a geometry needs >= 3 sensors with el0 and az0 each; got "
                         f"{len(el0)} and {len(az0)}")
    if n > MAX_SENSORS:
        raise InputError(f"{n} sensors: the subset count enumerates 2^n sets; at most "
                         f"{MAX_SENSORS} are supported")
    if not (np.isfinite(fault) and fault > 0):
        raise InputError(f"--fault must be > 0 (noise sigmas), got {fault}")
    if not (0 < alpha < 1):
        raise InputError(f"--alpha must lie in (0, 1), got {alpha}")
    H = axes(el0, az0)
    single, double = fault_sets(H, 1), fault_sets(H, 2)
    sub = subsets(H)
    det = detection_power(H, fault, alpha)

    def lst(sets):
        return [list(s) for s in sets]

    return {
        "name": name, "n_sensors": n, "directions": H.tolist(),
        "spans_3d": spans(H),
        "accuracy_gain": accuracy_gain(H),
        "HtH": (H.T @ H).tolist(),
        "collinear_groups": collinear_groups(H),
        "subsets": sub,
        "single_faults": {"tolerated": len(single["tolerated"]),
                          "detectable": len(single["detectable"]),
                          "isolable": len(single["isolable"]), "of": single["total"],
                          "not_isolable_pairs": [[F[0], G[0]] for F, G in single["confused"]]},
        "double_faults": {"tolerated": len(double["tolerated"]),
                          "detectable": len(double["detectable"]),
                          "isolable": len(double["isolable"]), "of": double["total"],
                          "not_tolerated": lst(s for s in itertools.combinations(range(n), 2)
                                               if s not in set(double["tolerated"])),
                          "not_isolable": [[list(F), list(G)] for F, G in double["confused"]]},
        "detection": {"fault_sigma": fault, "alpha": alpha, **det,
                      "min_power": min(p for p in det["per_sensor"] if p is not None)
                      if det["threshold"] is not None else None},
    }
