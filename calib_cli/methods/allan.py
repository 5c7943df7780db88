"""Overlapping Allan deviation, computed chunk by chunk, and the IEEE Std 952
noise terms read off the curve. Pure: arrays in, results out (docs/allan.md).

Streaming algorithm. The rate samples y_k (period tau0) are integrated to a
"phase" x_i = tau0 * sum_{k<i} (y_k - y_ref) (x_0 = 0, y_ref the mean of the
first chunk, removed only for numerical range; the Allan variance does not
see a constant). For a cluster of m samples

    AVAR(m tau0) = < (x_{k+2m} - 2 x_{k+m} + x_k)^2 > / (2 (m tau0)^2)

averaged over the start indices k. Clusters are octave spaced (m = 1, 2, 4,
...). For m <= STRIDE_DIV every k is used (the fully overlapping estimator,
identical to allantools.oadev); for larger m only k that are multiples of
s = m / STRIDE_DIV, which keeps 16 overlapping estimates per cluster length
(statistically as good as full overlap to within a few per cent) and means
each octave keeps only its last 2 m / s = 32 phase values between chunks.
Memory is O(chunk + 32 * n_octaves * n_channels): it does not grow with the
length of the recording.

Confidence. The number of independent (non-overlapping) clusters at m is
C = floor(N / m); the Allan variance is taken as chi-square with nu = C - 1
degrees of freedom (relative 1-sigma error of the deviation
1 / sqrt(2 (C - 1)), the IEEE 952 / El-Sheimy rule), which is conservative
for the overlapping estimator.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

STRIDE_DIV = 16  # overlapping estimates kept per cluster length (0: every k)
MIN_CLUSTERS = 3  # shortest usable: at least 3 independent clusters
CONFIDENCE = 0.95  # level of every interval reported
BI_FACTOR = 0.664  # flicker floor = sqrt(2 ln2 / pi) B (IEEE Std 952)
ARW_TAU = 1.0  # s, where the -1/2 line is read
RRW_TAU = 3.0  # s, where the +1/2 line is read
SLOPE_BAND = 0.2  # a point is on a +-1/2 line when its local slope is within this
# The lower interval limit of a slope-line reading removes this many times the
# variance the other terms add at the reading point: real (and simulated)
# flicker noise rises above its floor at short tau, so once is not enough.
OTHER_TERMS_MARGIN = 2.0
Q_MIN_SHARE = 0.1  # quantisation visible: >= 10 % of the Allan variance at the shortest tau
FLOOR_CLUSTERS = 10  # the minimum is looked for where the record is >= 10 x tau


# ---------------------------------------------------------------------------
# streaming overlapping Allan deviation


class OctaveAllan:
    """Accumulate overlapping Allan variances at octave cluster sizes.

    n_samples: total number of samples that will be fed (fixes the octaves);
    tau0: sample period, s; stride_div: STRIDE_DIV, or 0 for the exact fully
    overlapping estimator at every octave (what allantools.oadev computes).
    Feed (n, n_channels) chunks in order with ``feed``; ``result`` returns
    the curve.
    """

    def __init__(self, n_samples: int, n_channels: int, tau0: float,
                 stride_div: int = STRIDE_DIV):
        if n_samples < 2 * MIN_CLUSTERS:
            raise ValueError("too few samples for an Allan deviation")
        self.n, self.nch, self.tau0 = int(n_samples), int(n_channels), float(tau0)
        ms = []
        m = 1
        while n_samples // m >= MIN_CLUSTERS:
            ms.append(m)
            m *= 2
        self.m = np.array(ms, dtype=np.int64)
        self.stride = np.array([1 if not stride_div or mm <= stride_div else mm // stride_div
                                for mm in ms], dtype=np.int64)
        self.sums = np.zeros((len(ms), self.nch))
        self.counts = np.zeros(len(ms), dtype=np.int64)
        # per octave: decimated phase values not yet consumed (start with x_0 = 0)
        self.tails = [np.zeros((1, self.nch)) for _ in ms]
        self.pos = 0  # samples fed so far
        self.x_last = np.zeros(self.nch)
        self.y_ref = None

    def feed(self, y: np.ndarray) -> None:
        y = np.asarray(y, dtype=float)
        if y.ndim == 1:
            y = y[:, None]
        if len(y) == 0:
            return
        if self.pos + len(y) > self.n:
            raise ValueError("fed more samples than announced")
        if self.y_ref is None:
            self.y_ref = y.mean(axis=0)
        x = self.x_last + np.cumsum((y - self.y_ref) * self.tau0, axis=0)
        first = self.pos + 1  # global index of x[0]
        self.x_last = x[-1]
        self.pos += len(y)
        for j, (m, s) in enumerate(zip(self.m, self.stride, strict=True)):
            q = int(m // s)
            sel = x[(-first) % s::s]  # the phases whose global index is a multiple of s
            buf = np.concatenate([self.tails[j], sel]) if len(sel) else self.tails[j]
            if len(buf) > 2 * q:
                d = buf[2 * q:] - 2.0 * buf[q:-q] + buf[:-2 * q]
                self.sums[j] += np.einsum("ij,ij->j", d, d)
                self.counts[j] += len(d)
            self.tails[j] = buf[-2 * q:]

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(tau (n_tau,) s, adev (n_tau, n_ch), n_terms (n_tau,))."""
        if self.pos != self.n:
            raise ValueError(f"fed {self.pos} of {self.n} samples")
        tau = self.m * self.tau0
        ok = self.counts > 0
        avar = self.sums[ok] / (2.0 * tau[ok, None] ** 2 * self.counts[ok, None])
        return tau[ok], np.sqrt(avar), self.counts[ok]


def overlapping_adev(y: np.ndarray, tau0: float, stride_div: int = STRIDE_DIV,
                     chunk: int = 1 << 18):
    """In-memory convenience: (tau, adev, clusters) of rate samples y (N,) or (N, c)."""
    y = np.asarray(y, dtype=float)
    y2 = y[:, None] if y.ndim == 1 else y
    acc = OctaveAllan(len(y2), y2.shape[1], tau0, stride_div)
    for a in range(0, len(y2), chunk):
        acc.feed(y2[a:a + chunk])
    tau, adev, _ = acc.result()
    clusters = len(y2) // np.rint(tau / tau0).astype(np.int64)
    return tau, (adev[:, 0] if y.ndim == 1 else adev), clusters


# ---------------------------------------------------------------------------
# confidence intervals


def ci_factors(clusters, level: float = CONFIDENCE) -> tuple[np.ndarray, np.ndarray]:
    """Multipliers (lo, hi) of an Allan deviation estimate that bound the true
    deviation at ``level`` with C independent clusters (chi-square, C - 1 dof)."""
    from scipy.stats import chi2  # here: SciPy's stats take ~1 s to import (calib allan --help)

    nu = np.maximum(np.asarray(clusters, dtype=float) - 1.0, 1.0)
    a = (1.0 - level) / 2.0
    lo = np.sqrt(nu / chi2.ppf(1.0 - a, nu))
    hi = np.sqrt(nu / chi2.ppf(a, nu))
    return lo, hi


def rel_sigma(clusters) -> np.ndarray:
    """Relative 1-sigma error of an Allan deviation with C independent clusters."""
    return 1.0 / np.sqrt(2.0 * np.maximum(np.asarray(clusters, dtype=float) - 1.0, 1.0))


# ---------------------------------------------------------------------------
# the noise terms (IEEE Std 952 slope lines)


@dataclass(frozen=True)
class Term:
    """One noise term of one channel: the slope-line reading and its interval.

    value: the reading (NaN when the curve shows no such region); lo, hi:
    the CONFIDENCE interval. The statistical interval comes from the number
    of independent clusters at the reading point; because a slope-line
    reading also contains the other noise terms at that point, the lower
    bound is further extended to the reading with their (estimated)
    contributions removed. tau: where the curve was read, s; clusters: the
    independent clusters there.
    """

    value: float
    lo: float
    hi: float
    tau: float
    clusters: int

    @staticmethod
    def none() -> "Term":
        return Term(np.nan, np.nan, np.nan, np.nan, 0)


def local_slopes(tau: np.ndarray, adev: np.ndarray) -> np.ndarray:
    """d log(adev) / d log(tau) at each point (central where possible)."""
    lt, la = np.log(tau), np.log(np.maximum(adev, 1e-300))
    if len(tau) < 2:
        return np.zeros_like(tau)
    return np.gradient(la, lt)


def _term(value_fn, tau, adev, clusters, i, other_var):
    """Build a Term read at index i. value_fn(sig, tau) -> term value;
    other_var: variance the other terms add at tau[i] (for the lower bound)."""
    lo_f, hi_f = ci_factors(clusters[i])
    v = value_fn(adev[i], tau[i])
    clean = np.sqrt(max(adev[i] ** 2 - OTHER_TERMS_MARGIN * other_var, 0.0))
    lo = value_fn(min(clean, adev[i]) * lo_f, tau[i])
    return Term(float(v), float(lo), float(v * hi_f), float(tau[i]), int(clusters[i]))


def floor_index(adev: np.ndarray, clusters: np.ndarray) -> int:
    """Index of the Allan minimum, searched among the taus with at least
    FLOOR_CLUSTERS independent clusters (the record >= 10 x that tau): the
    last few octaves scatter so much that their dips are not a floor."""
    ok = np.flatnonzero(np.asarray(clusters) >= FLOOR_CLUSTERS)
    if not len(ok):
        return int(np.argmin(adev))
    return int(ok[np.argmin(np.asarray(adev)[ok])])


def quantization_fit(tau, adev, clusters, imin: int) -> dict | None:
    """Fit of the Allan variance left of the minimum (taus with >=
    FLOOR_CLUSTERS clusters) with a tau^-2 + b tau^-1 + c (quantisation,
    white noise, floor): non-negative least squares weighted by the
    chi-square error of each point (relative 1-sigma sqrt(2 / (C - 1))).
    Returns a, its 1-sigma sa (covariance scaled by chi2/dof when above 1),
    b, c, the first tau used and its clusters; None with fewer than 4 points."""
    from scipy.optimize import nnls

    idx = [i for i in range(min(imin, len(tau) - 1) + 1) if clusters[i] >= FLOOR_CLUSTERS]
    if len(idx) < 4:
        return None
    t, av = np.asarray(tau)[idx], np.asarray(adev)[idx] ** 2
    nu = np.maximum(np.asarray(clusters)[idx] - 1.0, 1.0)
    w = 1.0 / (av * np.sqrt(2.0 / nu))
    X = np.column_stack([t**-2.0, t**-1.0, np.ones_like(t)])
    cs = X[0].copy()  # columns scaled to unit size at the first point
    Xw = X / cs * w[:, None]
    coef, _ = nnls(Xw, av * w)
    act = coef > 0
    sa = np.inf
    if act[0]:
        J = Xw[:, act]
        r = Xw @ coef - av * w
        dof = max(len(t) - int(act.sum()), 1)
        cov = np.linalg.pinv(J.T @ J) * max(1.0, float(r @ r) / dof)
        sa = np.sqrt(cov[0, 0]) / cs[0]
    a, b, c = coef / cs
    return {"a": float(a), "sa": float(sa), "b": float(b), "c": float(c), "tau": float(t[0]),
            "clusters": int(np.asarray(clusters)[idx[0]])}


def quantization_term(tau, adev, clusters, imin: int) -> Term:
    """Quantisation noise Q (IEEE Std 952: AVAR = 3 Q^2 / tau^2, slope -1).

    Quantised increments with the remainder carried give a white phase error,
    but it only looks white when the signal moves the phase by a fair part of
    a quantum per sample, and that motion is itself white rate noise of
    comparable size at tau0 (docs/allan.md): the curve rarely shows a whole
    octave of slope -1. So Q is not read off a slope line but from
    quantization_fit: Q = sqrt(a / 3), with the fit's CONFIDENCE interval
    of a; NaN (not visible) when a is not 2 sigma above zero. Read at: the
    first tau used. Also NaN when the quantisation makes less than Q_MIN_SHARE
    of the Allan variance at the shortest tau: below that, the fit cannot
    tell it from the shape of the other terms there (flicker noise is not
    flat at short tau)."""
    from scipy.stats import norm

    fit = quantization_fit(tau, adev, clusters, imin)
    if fit is None or not np.isfinite(fit["sa"]) or fit["a"] < 2.0 * fit["sa"]:
        return Term.none()
    if fit["a"] / fit["tau"] ** 2 < Q_MIN_SHARE * float(np.asarray(adev)[0]) ** 2:
        return Term.none()  # too small to tell from the other terms' shape at short tau
    a, sa = fit["a"], fit["sa"]
    z = norm.ppf(0.5 + CONFIDENCE / 2.0)
    return Term(float(np.sqrt(a / 3.0)), float(np.sqrt(max(a - z * sa, 0.0) / 3.0)),
                float(np.sqrt((a + z * sa) / 3.0)), fit["tau"], fit["clusters"])


def channel_terms(tau: np.ndarray, adev: np.ndarray, clusters: np.ndarray) -> dict[str, Term]:
    """IEEE 952 readings for one channel's curve.

    random_walk N (ARW for gyros, VRW for accelerometers; unit * sqrt(s)):
        the -1/2 slope line at tau = 1 s, i.e. adev * sqrt(tau) at the point
        of the -1/2 region with the most clusters (its left end).
    bias_instability B (unit): the flat minimum over 0.664 (the minimum over
        the taus with >= FLOOR_CLUSTERS clusters).
    quantization Q (unit * s: rad for gyros, m/s for accelerometers): the
        slope -1 line sqrt(3) Q / tau, from quantization_term (a fit of the
        short-tau part of the curve). NaN when not significant.
    rate_random_walk K (unit / sqrt(s)): the +1/2 slope line at tau = 3 s,
        adev * sqrt(3 / tau), read at the first point right of the minimum
        where the curve rises and has reached twice the minimum (else the
        rightmost point of slope +1/2 there). NaN when the record is too
        short to show it.
    """
    tau, adev, clusters = (np.asarray(a) for a in (tau, adev, clusters))
    slope = local_slopes(tau, adev)
    imin = floor_index(adev, clusters)
    # first readings (no correction), then intervals with the other terms removed
    wn = np.flatnonzero((np.abs(slope + 0.5) <= SLOPE_BAND) & (np.arange(len(tau)) <= imin))
    right = np.arange(len(tau)) > imin
    rk = np.flatnonzero((np.abs(slope - 0.5) <= SLOPE_BAND) & right)
    # the rate random walk dominates once the curve has risen to twice its floor
    # (the other terms then add at most a quarter of the variance); the local
    # slope there is noisy (few clusters), so only its sign is required
    risen = np.flatnonzero(right & (adev >= 2.0 * adev[imin]) & (slope > 0.5 - 2 * SLOPE_BAND))
    iN = int(wn[0]) if len(wn) else None
    q_term = quantization_term(tau, adev, clusters, imin)
    Q = q_term.value if np.isfinite(q_term.value) else 0.0
    iK = int(risen[0]) if len(risen) else (int(rk[-1]) if len(rk) else None)
    N = adev[iN] * np.sqrt(tau[iN] / ARW_TAU) if iN is not None else 0.0
    K = adev[iK] * np.sqrt(RRW_TAU / tau[iK]) if iK is not None else 0.0
    F = adev[imin]
    # a floor: the curve at its minimum lies significantly (2 sigma) above the
    # -1/2 line, i.e. it has left the white noise; without a -1/2 line, a
    # minimum inside the curve or a flat end
    if iN is not None and imin > iN:
        flat = adev[imin] >= N * np.sqrt(ARW_TAU / tau[imin]) * (1 + 2 * rel_sigma(clusters[imin]))
    else:
        flat = 0 < imin < len(tau) - 1 or abs(slope[imin]) <= SLOPE_BAND

    def var_n(t):
        return N**2 * ARW_TAU / t

    def var_q(t):
        return 3.0 * Q**2 / t**2

    def var_k(t):
        return K**2 * t / RRW_TAU

    out = {}
    out["random_walk"] = (_term(lambda s, t: s * np.sqrt(t / ARW_TAU), tau, adev, clusters, iN,
                                (F**2 if flat else 0.0) + var_k(tau[iN]) + var_q(tau[iN]))
                          if iN is not None else Term.none())
    out["quantization"] = q_term
    out["bias_instability"] = (_term(lambda s, t: s / BI_FACTOR, tau, adev, clusters, imin,
                                     var_n(tau[imin]) + var_k(tau[imin]) + var_q(tau[imin]))
                               if flat else Term.none())
    out["rate_random_walk"] = (_term(lambda s, t: s * np.sqrt(RRW_TAU / t), tau, adev,
                                     clusters, iK, F**2 + var_n(tau[iK]) + var_q(tau[iK]))
                               if iK is not None else Term.none())
    return out


def min_averaging_time(Q: float, N: float, F: float) -> float:
    """Recommended minimum averaging time per static position, s: where the
    quantisation line sqrt(3) Q / tau meets the rest of the noise of a mean,
    sqrt(N^2 / tau + F^2) (white noise N and floor F, the b and c of
    quantization_fit; NaN counts as 0). Shorter averages are dominated by the
    quantisation (their noise falls as 1/tau); NaN without a visible
    quantisation term. Closed form in u = 1 / tau: 3 Q^2 u^2 - N^2 u - F^2 = 0."""
    Q, N, F = (0.0 if not np.isfinite(v) else float(v) for v in (Q, N, F))
    if Q <= 0 or (N <= 0 and F <= 0):
        return float("nan")
    u = (N**2 + np.sqrt(N**4 + 12.0 * Q**2 * F**2)) / (6.0 * Q**2)
    return float(1.0 / u)


def averaging_time(tau: np.ndarray, adev: np.ndarray, target: float) -> float:
    """Shortest averaging time, s, at which the Allan deviation (the noise of
    a tau-long average, compared with the next one) is at or below ``target``:
    log-log interpolation between octaves; NaN when the curve never gets there."""
    below = np.flatnonzero(adev <= target)
    if not len(below) or not np.isfinite(target) or target <= 0:
        return float("nan")
    i = int(below[0])
    if i == 0:
        return float(tau[0])
    l0, l1 = np.log(adev[i - 1]), np.log(adev[i])
    f = (np.log(target) - l0) / (l1 - l0) if l1 != l0 else 1.0
    return float(np.exp(np.log(tau[i - 1]) + f * (np.log(tau[i]) - np.log(tau[i - 1]))))


# ---------------------------------------------------------------------------
# whole analysis


TERM_NAMES = ("quantization", "random_walk", "bias_instability", "rate_random_walk")


def term_units(unit: str) -> dict[str, str]:
    """Units of the three terms for a channel in ``unit`` (m/s^2, rad/s, count)."""
    return {"quantization": f"{unit}*s", "random_walk": f"{unit}*sqrt(s)",
            "bias_instability": unit,
            "rate_random_walk": f"{unit}/sqrt(s)"}


@dataclass(frozen=True)
class AllanResult:
    """Allan deviation of every channel with the noise terms.

    tau (n_tau,) s; adev (n_tau, n_ch); clusters (n_tau,) independent
    clusters; adev_lo/adev_hi: CONFIDENCE interval; terms[name] -> dict of
    arrays value/lo/hi/tau/clusters (n_ch,); tau_min (n_ch,) s at the minimum;
    averaging_time (n_ch,) s (NaN where the target is not reached);
    target (n_ch,) the target used, same unit as the channel;
    min_averaging_time (n_ch,) s, from the quantisation term
    (``min_averaging_time()``; NaN where no quantisation is visible).
    """

    channels: list
    units: list
    tau0: float
    n_samples: int
    tau: np.ndarray
    adev: np.ndarray
    clusters: np.ndarray
    adev_lo: np.ndarray
    adev_hi: np.ndarray
    terms: dict
    tau_min: np.ndarray
    averaging_time: np.ndarray
    target: np.ndarray
    stride_div: int = STRIDE_DIV
    meta: dict = field(default_factory=dict)
    min_averaging_time: np.ndarray | None = None

    def min_avg(self) -> np.ndarray:
        """min_averaging_time, NaN per channel when not computed (older files)."""
        if self.min_averaging_time is None:
            return np.full(len(self.channels), np.nan)
        return np.asarray(self.min_averaging_time, float)

    @property
    def duration(self) -> float:
        return self.n_samples * self.tau0


def analyse(tau: np.ndarray, adev: np.ndarray, tau0: float, n_samples: int, channels, units,
            targets, stride_div: int = STRIDE_DIV, meta=None) -> AllanResult:
    """Noise terms, intervals and averaging times from a computed curve."""
    tau, adev = np.asarray(tau, float), np.asarray(adev, float)
    if adev.ndim == 1:
        adev = adev[:, None]
    clusters = n_samples // np.rint(tau / tau0).astype(np.int64)
    lo_f, hi_f = ci_factors(clusters)
    terms = {k: {f: [] for f in ("value", "lo", "hi", "tau", "clusters")} for k in TERM_NAMES}
    t_min, t_avg = [], []
    targets = np.broadcast_to(np.asarray(targets, dtype=float), (adev.shape[1],))
    for c in range(adev.shape[1]):
        ct = channel_terms(tau, adev[:, c], clusters)
        for k in TERM_NAMES:
            for f in terms[k]:
                terms[k][f].append(getattr(ct[k], f))
        t_min.append(tau[floor_index(adev[:, c], clusters)])
        t_avg.append(averaging_time(tau, adev[:, c], targets[c]))
    terms = {k: {f: np.asarray(v) for f, v in d.items()} for k, d in terms.items()}
    t_q = []
    for c in range(adev.shape[1]):
        fit = quantization_fit(tau, adev[:, c], clusters, floor_index(adev[:, c], clusters))
        Q = terms["quantization"]["value"][c]
        t_q.append(min_averaging_time(Q, np.sqrt(fit["b"]), np.sqrt(fit["c"]))
                   if fit is not None and np.isfinite(Q) else float("nan"))
    return AllanResult(channels=list(channels), units=list(units), tau0=float(tau0),
                       n_samples=int(n_samples), tau=tau, adev=adev, clusters=clusters,
                       adev_lo=adev * lo_f[:, None], adev_hi=adev * hi_f[:, None], terms=terms,
                       tau_min=np.asarray(t_min), averaging_time=np.asarray(t_avg),
                       target=np.asarray(targets, dtype=float), stride_div=stride_div,
                       meta=dict(meta or {}), min_averaging_time=np.asarray(t_q, float))


def allan_of_chunks(chunks, n_samples: int, tau0: float, channels, units, targets,
                    stride_div: int = STRIDE_DIV, meta=None) -> AllanResult:
    """The whole analysis from an iterable of (n, n_ch) rate chunks (in order)."""
    acc = OctaveAllan(n_samples, len(channels), tau0, stride_div)
    for ch in chunks:
        acc.feed(ch)
    tau, adev, _ = acc.result()
    return analyse(tau, adev, tau0, n_samples, channels, units, targets, stride_div, meta)
