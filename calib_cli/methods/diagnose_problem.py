"""The data side of ``calib diagnose``: which samples, their true inputs
(the plan's attitudes and table motion), short time bins, and the noise floor.

A recording becomes a ``Problem``: per-sample kinematics of every usable
segment (static positions with a known attitude; rotating segments with the
table motion as recorded, else the plan's nominal rate), the measured outputs,
and a partition of the samples into short bins (``BIN_S`` seconds, never
crossing a segment). Every model is compared with the data through bin means
of the per-sample prediction, so the comparison is exact for any effect
while the fits stay small.

Noise floor: the per-sample white noise of each channel from the data's own
high-frequency content (second differences within segments, robust MAD),
so "explained down to the noise" is a number. A bin mean of n samples has
sigma / sqrt(n); residuals are reported in those units (CONTRACT.md
section 5). The within-segment scatter of the bin means of static segments
is reported beside it (``bin_scatter_ratio``): a ratio well above 1 says
the noise is not white (coloured or drifting), which the stochastic
candidates then test.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib_cli.data import Recording
from calib_cli.errors import EstimationError, InputError
from calib_cli.methods.method import Diagnose, Method, method_named, resolve, table
from calib_cli.methods.noise import difference_sigma
from calib_cli.methods.rimu import segment_kinematics
from calib_cli.model import kinematics as kn
from calib_cli.model.effects import Layout
from calib_cli.model.frames import attitude_to_rotation

BIN_S = 0.5  # s: bin length


@dataclass
class Problem:
    method: str
    sensors: tuple
    kin: kn.Kinematics  # per usable sample
    y: dict  # sensor -> (N, n) measured
    starts: np.ndarray  # (M,) first sample of each bin
    counts: np.ndarray  # (M,) samples per bin
    bin_seg: np.ndarray  # (M,) raw segment index of each bin
    bin_t: np.ndarray  # (M,) mean time of each bin
    sigma: dict  # sensor -> (n,) per-sample white-noise sigma
    ymean: dict  # sensor -> (M, n) bin means of the data
    seg_labels: list
    seg_kinds: list
    skipped: list
    units: dict
    layout: object
    scatter_ratio: dict  # sensor -> (n,) bin scatter / white prediction (static segments)
    g: float
    cycle_axes: np.ndarray | None = None  # (n_cycles, 3) table axis in body axes per cycle
    # positions of unknown attitude (accel "scalar" mode): gravity direction u_i (U, 3)
    # at the start, two unit vectors perpendicular to it (U, 2, 3), and per sample the
    # position it belongs to (N,), -1 for none
    tilt_u: np.ndarray | None = None
    tilt_basis: np.ndarray | None = None
    tilt_index: np.ndarray | None = None
    start: dict | None = None  # starting parameter values (scalar mode: ellipsoid fit)
    unit_scale: dict | None = None  # sensor -> data units per SI unit (1 for SI; counts: ~K)
    scatter_dof: int = 0
    noise_mode: str = "hf"
    # align: each used segment's attitude (raw segment index -> body-to-ENU matrix), so
    # the attitude nuisance is a rotation of the navigation frame common to all positions
    seg_rot: dict | None = None
    sigma_hf: dict | None = None  # the high-frequency estimate, before apply_noise
    how: Diagnose | None = None  # the method's diagnose description (the method table)

    def scale_of(self, key: str) -> float:
        """Factor on a parameter's typical size for this data's output units."""
        for s in ("accel", "gyro"):
            if key.startswith(s + "_") and self.unit_scale:
                return self.unit_scale.get(s, 1.0)
        return 1.0

    @property
    def raised(self) -> bool:
        """Whether some channel's sigma was raised above the high-frequency estimate."""
        return bool(self.sigma_hf) and any(
            np.any(np.asarray(self.sigma[s]) > np.asarray(self.sigma_hf[s])) for s in self.sensors
            if s in self.sigma_hf)

    @property
    def scalar(self) -> bool:
        return self.tilt_basis is not None

    @property
    def n_bins(self) -> int:
        return len(self.starts)

    def bin_mean(self, a: np.ndarray) -> np.ndarray:
        """Bin means of a per-sample array (N, ...)."""
        return np.add.reduceat(a, self.starts, axis=0) / self.counts.reshape(
            (-1,) + (1,) * (a.ndim - 1))

    def whitener(self, sensor: str, high_frequency: bool = False) -> np.ndarray:
        """(M, n) 1-sigma of each bin mean (high_frequency: from the data's
        high-frequency content alone, before any raise to the bins' scatter)."""
        sig = self.sigma[sensor]
        if high_frequency and self.sigma_hf and sensor in self.sigma_hf:
            sig = np.asarray(self.sigma_hf[sensor], float)
        return sig[None, :] / np.sqrt(self.counts)[:, None]

    # bin-level descriptors for the plots and signatures
    def rate_norm(self) -> np.ndarray:
        w = self.kin.w
        return self.bin_mean(np.linalg.norm(w, axis=1))

    def temp(self):
        return None if self.kin.temp is None else self.bin_mean(self.kin.temp)


def build_problem(rec: Recording, method, bin_s: float = BIN_S,
                  noise: str = "auto") -> Problem:
    """The usable samples of a recording for the given method (its name or ``Method``),
    as its ``Diagnose`` description in the method table says (methods/method.py).

    noise: "hf" (white noise from the high-frequency content) or "auto" (the
    same, raised to the within-segment scatter of the bin means where that
    is significantly larger: coloured or drifting noise; see apply_noise)."""
    m = method if isinstance(method, Method) else method_named(method)
    how = m.diagnose
    if how is None or how.own:
        raise InputError(f"the {m.name} method has no base model for the diagnose engine "
                         "(its description in the method table has none)")
    extra = {}
    if how.prepare is not None:
        rec, extra = resolve(how.prepare)(rec)
    pb = _build(rec, m.name, how, bin_s)
    pb.how = how
    for k, v in extra.items():
        setattr(pb, k, v)
    pb.noise_mode = noise
    if noise == "auto":
        apply_noise(pb)
    return pb


def apply_noise(pb: Problem) -> None:
    """Raise each channel's sigma by its bin-scatter ratio where the ratio is
    significantly above 1 (3 sigma of its own sampling error)."""
    for s in pb.sensors:
        ratio = pb.scatter_ratio.get(s)
        if ratio is None or pb.scatter_dof <= 0:
            continue
        lim = 1.0 + 3.0 / np.sqrt(2.0 * pb.scatter_dof)
        pb.sigma[s] = pb.sigma[s] * np.where(np.isfinite(ratio) & (ratio > lim), ratio, 1.0)


def _wrong_layout(name: str, how: Diagnose) -> str:
    if how.wrong_layout:
        return how.wrong_layout
    if how.layout == "redundant":
        return f"--method {name} needs a redundant-unit recording"
    others = [n for n, m in table().items() if m.diagnose and m.diagnose.layout == "redundant"]
    return ("a redundant-unit recording: " + (f"use --method {' or '.join(others)}" if others
                                              else "no method diagnoses one"))


def _check_needs(how: Diagnose, use: list, scalar: bool) -> None:
    """The description's requirements on the segments used (exit 4 with its message)."""
    for need in how.needs:
        if need.attitudes == ("unknown" if not scalar else "known"):
            continue
        count = sum(need.kind in ("any", s.kind) for s in use)
        if count < need.n:
            raise EstimationError(need.message.format(count=count))


def _build(rec: Recording, method: str, how: Diagnose, bin_s: float) -> Problem:
    if rec.layout.redundant != (how.layout == "redundant"):
        raise EstimationError(_wrong_layout(method, how))
    sensors = tuple(how.sensors) + tuple(s for s in how.optional_sensors
                                         if getattr(rec, s) is not None)
    for s in how.sensors:
        if getattr(rec, s) is None:
            raise EstimationError(f"the recording has no {s} data ({method} needs "
                                  f"{'both sensors' if len(how.sensors) == 2 else 'it'})")
    use, skipped = [], []
    statics = [s for s in rec.segments if s.kind == "static" and s.n >= 3]
    scalar = how.unknown_attitudes and any(s.attitude is None for s in statics)
    for s in rec.segments:
        ok = (s.attitude is not None or scalar) and s.n >= 3
        ok = ok and ((s.kind == "static" and "static" in how.segments)
                     or (s.kind == "rotating" and "rotating" in how.segments
                         and s.table_axis_enu is not None))
        (use if ok else skipped).append(s)
    _check_needs(how, use, scalar)
    if scalar:
        return _scalar_problem(rec, method, use, skipped, bin_s)
    parts, ys = [], {s: [] for s in sensors}
    starts, counts, bin_seg, bounds = [], [], [], []
    fs = rec.sample_rate
    per_bin = max(int(round(bin_s * fs)), 1)
    n0 = 0
    cycle = 0
    axes = []
    for idx, s in zip([rec.segments.index(x) for x in use], use):
        k = segment_kinematics(rec, s)
        m = len(k)
        cyc = np.full(m, cycle if s.kind == "rotating" else -1)
        if s.kind == "rotating":
            cycle += 1
            axes.append(attitude_to_rotation(s.attitude).inv().apply(
                np.asarray(s.table_axis_enu, float) / np.linalg.norm(s.table_axis_enu)))
        k = k.with_(segment=np.full(m, idx), cycle=cyc,
                    temp=None if rec.temp is None else np.asarray(rec.temp[s.slice], float))
        parts.append(k)
        for sen in sensors:
            ys[sen].append(np.asarray((rec.accel if sen == "accel" else rec.gyro)[s.slice],
                                      float))
        nb = max(m // per_bin, 1)
        edges = np.linspace(0, m, nb + 1).round().astype(int)
        starts += list(n0 + edges[:-1])
        counts += list(np.diff(edges))
        bin_seg += [idx] * nb
        bounds.append((n0, n0 + m))
        n0 += m
    kin = kn.Kinematics.concatenate(parts)
    y = {sen: np.concatenate(v) for sen, v in ys.items()}
    starts = np.array(starts)
    counts = np.array(counts, float)
    sigma = {sen: difference_sigma(y[sen], 2, bounds) for sen in sensors}
    g = float(np.median(np.linalg.norm(kin.f, axis=1)))
    pb = Problem(method, sensors, kin, y, starts, counts, np.array(bin_seg),
                 np.zeros(len(starts)), sigma, {}, [s.label for s in rec.segments],
                 [s.kind for s in rec.segments], [s.label for s in skipped], dict(rec.units),
                 Layout(n_cycles=cycle) if not rec.layout.redundant else
                 Layout(rec.layout.n, rec.layout.el0, rec.layout.az0, cycle), {}, g)
    pb.cycle_axes = np.array(axes).reshape(-1, 3)
    pb.bin_t = pb.bin_mean(kin.t)
    pb.ymean = {sen: pb.bin_mean(y[sen]) for sen in sensors}
    _scatter(pb, rec)
    pb.unit_scale = _unit_scale(pb, rec)
    return pb


def _unit_scale(pb: Problem, rec: Recording) -> dict:
    out = {}
    for s in pb.sensors:
        if not rec.in_counts(s):
            out[s] = 1.0
        elif pb.start and s == "accel":
            out[s] = float(np.mean(np.abs(np.diag(pb.start["accel_K"]))))
        else:  # counts per SI unit from the spread of the bin means against the inputs
            x = pb.bin_mean(pb.kin.f if s == "accel" else pb.kin.w)
            y = pb.ymean[s]
            sx = np.linalg.norm(x - x.mean(axis=0), axis=1).mean()
            sy = np.linalg.norm(y - y.mean(axis=0), axis=1).mean()
            out[s] = float(sy / sx) if sx > 0 else 1.0
    return out


def _scatter(pb: Problem, rec: Recording) -> None:
    """Scatter of bin means about their segment mean (static segments) against white noise."""
    for sen in pb.sensors:
        y = pb.y
        ym, wh = pb.ymean[sen], pb.whitener(sen)
        acc, dof = 0.0, 0
        for idx in np.unique(pb.bin_seg):
            if rec.segments[idx].kind != "static":
                continue
            sel = pb.bin_seg == idx
            if sel.sum() < 2:
                continue
            zz = (ym[sel] - ym[sel].mean(axis=0)) / wh[sel]
            acc = acc + (zz ** 2).sum(axis=0)
            dof += sel.sum() - 1
        pb.scatter_ratio[sen] = np.sqrt(acc / dof) if dof > 0 else np.full(y[sen].shape[1],
                                                                            np.nan)
        pb.scatter_dof = int(dof)
    pb.sigma_hf = {s: v.copy() for s, v in pb.sigma.items()}


def _scalar_problem(rec: Recording, method: str, use, skipped, bin_s: float) -> Problem:
    """Static positions of unknown attitude: each position's gravity direction is a
    nuisance (two tilt angles), started from the ellipsoid fit of the position means
    (the scalar method's start, lower-triangular K)."""
    from scipy.spatial.transform import Rotation

    from calib_cli.methods.accel_lsq import ellipsoid_start

    g = rec.site.gravity
    means = np.array([np.asarray(rec.accel[s.slice], float).mean(axis=0) for s in use])
    b0, K0 = ellipsoid_start(means, g)
    u = np.linalg.solve(K0, (means - b0).T).T
    u /= np.linalg.norm(u, axis=1)[:, None]
    basis = []
    for v in u:
        a = np.eye(3)[int(np.argmin(np.abs(v)))]
        e1 = np.cross(v, a)
        e1 /= np.linalg.norm(e1)
        basis.append([e1, np.cross(v, e1)])
    parts, ys, starts, counts, bin_seg, bounds, tix = [], [], [], [], [], [], []
    per_bin = max(int(round(bin_s * rec.sample_rate)), 1)
    n0 = 0
    for j, s in enumerate(use):
        t = rec.time[s.slice]
        m = len(t)
        rot = Rotation.identity(m)
        k = kn.from_attitude(t, rot, rec.site)
        k = k.with_(f=np.tile(g * u[j], (m, 1)), w=np.zeros((m, 3)), dw=np.zeros((m, 3)),
                    segment=np.full(m, rec.segments.index(s)), cycle=np.full(m, -1),
                    temp=None if rec.temp is None else np.asarray(rec.temp[s.slice], float))
        parts.append(k)
        ys.append(np.asarray(rec.accel[s.slice], float))
        nb = max(m // per_bin, 1)
        edges = np.linspace(0, m, nb + 1).round().astype(int)
        starts += list(n0 + edges[:-1])
        counts += list(np.diff(edges))
        bin_seg += [rec.segments.index(s)] * nb
        bounds.append((n0, n0 + m))
        tix.append(np.full(m, j))
        n0 += m
    kin = kn.Kinematics.concatenate(parts)
    y = {"accel": np.concatenate(ys)}
    pb = Problem(method, ("accel",), kin, y, np.array(starts), np.array(counts, float),
                 np.array(bin_seg), np.zeros(len(starts)),
                 {"accel": difference_sigma(y["accel"], 2, bounds)}, {},
                 [s.label for s in rec.segments], [s.kind for s in rec.segments],
                 [s.label for s in skipped], dict(rec.units), Layout(), {}, g,
                 np.zeros((0, 3)), u, np.array(basis), np.concatenate(tix),
                 {"accel_bias": b0, "accel_K": K0})
    pb.bin_t = pb.bin_mean(kin.t)
    pb.ymean = {"accel": pb.bin_mean(y["accel"])}
    _scatter(pb, rec)
    pb.unit_scale = _unit_scale(pb, rec)
    return pb
